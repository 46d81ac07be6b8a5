"""``trifuse serve``: the console on one port, after the refusals (sources that exclude each
other, authentication, TLS, the port, the work directory) that come before anything starts."""

from __future__ import annotations

import argparse
import dataclasses
import os
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlsplit

from trifuse.app.cli.args import (
    EXIT_OK,
    PROG,
    Commands,
    UsageError,
    bounded_int,
    bounded_seconds,
    listen_port,
    port_number,
    share_of_a_core,
    sim_drift_arg,
)
from trifuse.app.cli.choices import SCENARIOS

if TYPE_CHECKING:
    import socket

    from trifuse.app.server.middleware.auth import AuthConfig
    from trifuse.app.server.runtime.serve import TLSFiles
    from trifuse.calib.board import Board


def add_parser(commands: Commands) -> argparse.ArgumentParser:
    """``serve [--replay FILE | --live CONFIG | --push] [--rig] [--scenario] ...``."""
    srv = commands.add_parser(
        "serve",
        help="start the console: fused stereo viewer, 3D scene, stream (one URL)",
        description=(
            "Start the console on one port: the operator's fused stereo viewer at /, the "
            "stream (/stream WebSocket, /stream.mjpg), the Viser 3D console at /console/ "
            "(rig frames, sensor frustums, live TOF point cloud) and the API under /api/ "
            "(OpenAPI at /docs). Without a source option it runs on the simulated head."
        ),
    )
    srv.add_argument("--replay", metavar="FILE", help="replay a recording (looping)")
    srv.add_argument(
        "--live",
        metavar="CONFIG",
        help="OpenCV cameras (docs/FORMATS.md 'Live camera configuration'; needs --rig)",
    )
    srv.add_argument(
        "--push",
        action="store_true",
        help="take frames pushed by an on-robot driver at /ingest "
        "(docs/FORMATS.md 'Push ingest protocol')",
    )
    srv.add_argument(
        "--ros2",
        metavar="TOPICS.yaml",
        help="a robot's live ROS 2 image topics over DDS, mapped onto sensors by a topic map "
        "(docs/FORMATS.md 'ROS 2 bags and topic maps', 'ROS 2 live'; needs --rig and the "
        "[ros2] extra; no ROS installation)",
    )
    srv.add_argument(
        "--ros2-domain",
        type=int,
        default=None,
        metavar="N",
        help="the DDS domain (default: ROS_DOMAIN_ID, else 0)",
    )
    srv.add_argument(
        "--ros2-max-mb",
        type=float,
        default=None,
        metavar="MB",
        help="refuse ROS 2 messages larger than this (default: 64; counted and worded per "
        "topic in the sensor health)",
    )
    srv.add_argument(
        "--ros2-reliable",
        action="store_true",
        help="read the topics with reliable QoS (default: best effort, which also matches "
        "reliable publishers)",
    )
    srv.add_argument(
        "--rig",
        metavar="RIG.yaml",
        help="the calibrated rig (default: the recording's or the simulated head's)",
    )
    srv.add_argument(
        "--scenario",
        choices=SCENARIOS,
        default="inspection",
        help="what the simulated head sees: the inspection room, the heated board "
        "held at --board-poses poses for a calibration session, or the survey of the room "
        "for the 3D map (pan and tilt, then a 3 m drive) (default: %(default)s)",
    )
    srv.add_argument(
        "--board-poses",
        type=bounded_int(1, 1000),
        default=40,
        metavar="N",
        help="calibration scenario: how many board poses it cycles through (default: "
        "%(default)s; each is rendered once, about 1.5 s of CPU)",
    )
    srv.add_argument(
        "--hold",
        type=bounded_seconds(0.5, 3600.0),
        default=3.0,
        metavar="S",
        help="calibration scenario: seconds the board is held at each pose (default: "
        "%(default)s; auto-capture needs it still for two searches)",
    )
    srv.add_argument(
        "--sim-drift",
        metavar="SENSOR:RX,RY,RZ[@AT_S]",
        help="simulated head (inspection or survey): one sensor moves during the run "
        "(calibration drift): from AT_S seconds on (default 0; it stays moved while the "
        "scene loops) it is rendered turned by the rotation vector RX,RY,RZ in degrees "
        "about its own axes, applied on the right of its pose; the console's rig stays the "
        "calibrated one, e.g. thermal_left:0,0.3,0@20",
    )
    srv.add_argument(
        "--workdir",
        metavar="DIR",
        default="trifuse-work",
        help="where the calibration session keeps its captures and saved rig versions "
        "(created if needed; reopened as it was on restart; default: ./%(default)s)",
    )
    srv.add_argument(
        "--board",
        metavar="BOARD.yaml",
        help="the calibration board: checkerboard, ChArUco or asymmetric circle grid "
        "(docs/FORMATS.md; the simulated calibration scenario holds it too; default: the "
        "simulated head's checkerboard, 9 x 6 inner corners, 60 mm squares)",
    )
    srv.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to bind (default: %(default)s; e.g. 0.0.0.0 for every interface, "
        "which needs a token)",
    )
    srv.add_argument(
        "--port",
        type=listen_port,
        default=8000,
        help="port, 1-65535, or 0 for any free port; the URL printed names the port bound "
        "(default: %(default)s)",
    )
    srv.add_argument(
        "--token",
        help="the secret that opens the console (at least 16 characters; default: "
        "$TRIFUSE_TOKEN, else a random one); printed in the console's URL, "
        "exchanged by the browser for a session cookie; scripts send "
        "'Authorization: token TOKEN'. Prefer TRIFUSE_TOKEN: arguments show in ps",
    )
    srv.add_argument(
        "--no-token",
        action="store_true",
        help="no authentication: only on a loopback --host, for a single-user machine",
    )
    srv.add_argument(
        "--allow-origin",
        action="append",
        default=[],
        metavar="URL",
        help="another origin (scheme://host[:port]) allowed to open WebSockets and send "
        "changes, besides the console's own (repeatable)",
    )
    srv.add_argument(
        "--console-bandwidth",
        choices=("full", "low"),
        default="full",
        help="what the 3D console (/console/) sends to each browser: full (every TOF "
        "point; about 6 Mbit/s) or low (a decimated cloud at 2 Hz, small images once a "
        "second; about 1 Mbit/s, for a radio link); changeable in its 3D scene folder and "
        "at /api/console/settings (default: %(default)s)",
    )
    srv.add_argument(
        "--map",
        action="store_true",
        help="build the thermal 3D map from the start (the 3D console's Thermal map folder "
        "and /api/map turn it on and off; maps are saved in WORKDIR/maps)",
    )
    srv.add_argument(
        "--drift-share",
        type=share_of_a_core,
        metavar="F",
        help="the share of one core the calibration health check (each camera's drift "
        "against the rig, measured on the live scene) may take (default: 0.1); "
        "more finds a drifted sensor sooner: four measures a camera pair are needed",
    )
    srv.add_argument(
        "--foxglove-port",
        type=port_number,
        metavar="N",
        help="also publish the live sensor images, the fused pair (H.264), the rig's "
        "transforms and calibrations, the TOF point cloud and the sensor health to Foxglove "
        "(foxglove-sdk's WebSocket server; the topics and schemas of a recording, "
        "docs/FORMATS.md 'Foxglove live') at ws://127.0.0.1:N. It has no authentication: "
        "the console's token does not guard it, so it always binds 127.0.0.1, whatever "
        "--host says; from another machine use an SSH tunnel (ssh -L N:127.0.0.1:N robot). "
        "Any local user or web page can read it (docs/SECURITY.md)",
    )
    srv.add_argument(
        "--rerun",
        nargs="?",
        const="",
        metavar="ADDRESS",
        help="also log the rig's cameras at their poses, the live images, the TOF's points "
        "coloured by temperature and the fused pair to a rerun viewer (the console connects "
        "to it; default: one on this machine, rerun+http://127.0.0.1:9876/proxy; from "
        "another machine its address, or ssh -R 9876:127.0.0.1:9876 robot). Only while the "
        "viewer answers; at most 5 frame sets a second. Needs the [rerun] extra",
    )
    srv.add_argument("--certfile", metavar="PEM", help="TLS certificate (chain): serve HTTPS/WSS")
    srv.add_argument("--keyfile", metavar="PEM", help="the certificate's private key")
    return srv


def load_board_arg(path: str | None) -> Board:
    """The board of ``--board`` (a board.yaml), else the simulated head's board."""
    if path is None:
        from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD

        return CALIBRATION_BOARD
    from trifuse.app.storage.capture import load_board_file

    return load_board_file(path)


def serve_auth(args: argparse.Namespace) -> AuthConfig:
    """The console's authentication from ``--token`` / ``TRIFUSE_TOKEN`` / ``--no-token``,
    ``--host``, ``--allow-origin`` and TLS; UsageError for an unsafe or unusable choice."""
    from trifuse.app.server.middleware.auth import AuthConfig, check_token, is_loopback, new_token
    from trifuse.app.sources.push.clients import TOKEN_ENV

    given = args.token if args.token is not None else os.environ.get(TOKEN_ENV)
    if args.no_token:
        if args.token is not None:
            raise UsageError(f"{PROG} serve: --token and --no-token exclude each other")
        if not is_loopback(args.host):
            raise UsageError(
                f"{PROG} serve: --host {args.host} --no-token: refusing to serve without a "
                "token on a non-loopback address (anyone on the network could watch the "
                "cameras and change the calibration); drop --no-token to use a token"
            )
        token = None
    else:
        try:
            network = not is_loopback(args.host)
            token = check_token(given, network) if given is not None else new_token()
        except ValueError as e:
            where = "--token" if args.token is not None else TOKEN_ENV
            raise UsageError(f"{PROG} serve: {where}: {e}") from None
    origins = set()
    for origin in args.allow_origin:
        parts = urlsplit(origin)
        if parts.scheme not in ("http", "https") or not parts.netloc or parts.path.strip("/"):
            raise UsageError(
                f"{PROG} serve: --allow-origin {origin!r}: expected scheme://host[:port], "
                "e.g. https://headset.local:8443"
            )
        origins.add(f"{parts.scheme}://{parts.netloc}".lower())
    return AuthConfig(token, args.port, args.certfile is not None, frozenset(origins))


def serve_tls(args: argparse.Namespace) -> TLSFiles | None:
    """``--certfile``/``--keyfile`` checked by loading them, or None."""
    from trifuse.app.server.runtime.serve import TLSFiles

    if (args.certfile is None) != (args.keyfile is None):
        raise UsageError(f"{PROG} serve: --certfile and --keyfile go together")
    if args.certfile is None:
        return None
    import ssl

    try:
        ssl.create_default_context(ssl.Purpose.CLIENT_AUTH).load_cert_chain(
            args.certfile, args.keyfile
        )
    except (OSError, ssl.SSLError) as e:
        raise UsageError(
            f"{PROG} serve: cannot use --certfile {args.certfile} --keyfile {args.keyfile}: {e}"
        ) from None
    return TLSFiles(Path(args.certfile), Path(args.keyfile))


def bound_auth(auth: AuthConfig, sock: socket.socket) -> AuthConfig:
    """``auth`` for the port ``sock`` is bound to: the one the system chose for ``--port 0``
    (the URL printed and the session cookie's name use it)."""
    port = int(sock.getsockname()[1])
    return auth if port == auth.port else dataclasses.replace(auth, port=port)


def run(args: argparse.Namespace) -> int:
    """Check everything, bind the port, lock the work directory, open the source, serve."""
    from trifuse.app.recording.open_source import open_source
    from trifuse.app.server.runtime.serve import bind_public_socket, serve
    from trifuse.app.storage.rigfile import load_rig
    from trifuse.app.storage.workdir_lock import WorkdirInUse, lock_workdir

    auth = serve_auth(args)
    tls = serve_tls(args)
    chosen = [x for x in (args.replay, args.live, args.push or None, args.ros2) if x]
    if len(chosen) > 1:
        raise UsageError(f"{PROG} serve: choose one of --replay, --live, --push, --ros2")
    ros2_options = (args.ros2_domain, args.ros2_max_mb, args.ros2_reliable or None)
    if args.ros2 is None and any(o is not None for o in ros2_options):
        raise UsageError(f"{PROG} serve: --ros2-domain, --ros2-max-mb and --ros2-reliable "
                         "are for --ros2")  # fmt: skip
    if args.ros2_max_mb is not None and not 0 < args.ros2_max_mb <= 1024:
        raise UsageError(f"{PROG} serve: --ros2-max-mb: expected 0 to 1024 MB, got "
                         f"{args.ros2_max_mb:g}")  # fmt: skip
    if args.scenario != "inspection" and chosen:
        raise UsageError(f"{PROG} serve: --scenario is for the simulated head only")
    if args.scenario != "calibration" and (args.board_poses, args.hold) != (40, 3.0):
        raise UsageError(f"{PROG} serve: --board-poses and --hold are for --scenario calibration")
    drift = None
    if args.sim_drift is not None:
        if chosen:
            raise UsageError(f"{PROG} serve: --sim-drift is for the simulated head only")
        if args.scenario == "calibration":
            raise UsageError(f"{PROG} serve: --sim-drift goes with --scenario inspection or survey")
        from trifuse.app.sources.sim.head import default_rig

        drift = sim_drift_arg(args.sim_drift, default_rig(), "serve", "--sim-drift")
    board = load_board_arg(args.board)
    try:  # the port and the work directory first: refusals come before anything starts
        sock = bind_public_socket(args.host, args.port)
    except OSError as e:
        raise UsageError(f"{PROG} serve: {e}") from None
    auth = bound_auth(auth, sock)
    try:
        if args.foxglove_port is not None:
            from trifuse.app.server.runtime.foxglove_live import check_foxglove_port

            try:
                check_foxglove_port(args.foxglove_port)
            except OSError as e:
                raise UsageError(f"{PROG} serve: {e}") from None
        if args.rerun is not None:
            from trifuse.app.recording.rerun_log import require_rerun
            from trifuse.app.server.runtime.rerun_live import viewer_endpoint

            try:
                require_rerun()
                viewer_endpoint(args.rerun or "rerun+http://127.0.0.1:9876/proxy")
            except (RuntimeError, ValueError) as e:
                raise UsageError(f"{PROG} serve: {e}") from None
        workdir = Path(args.workdir)
        try:
            lock = lock_workdir(workdir)
        except WorkdirInUse as e:
            raise UsageError(f"{PROG} serve: --workdir {e}") from None
        with lock:
            opened = open_source(
                args.replay,
                args.live,
                args.push,
                load_rig(args.rig) if args.rig else None,
                loop=True,
                keep_time=True,
                scenario=args.scenario,
                board_poses=args.board_poses,
                hold_s=args.hold,
                board=board,
                drift=drift,
                ros2=args.ros2,
                ros2_domain=args.ros2_domain,
                ros2_reliable=args.ros2_reliable,
                ros2_max_bytes=None if args.ros2_max_mb is None else round(args.ros2_max_mb * 1e6),
            )
            serve(
                opened,
                board,
                workdir,
                auth,
                args.host,
                tls,
                sock,
                args.console_bandwidth,
                build_map=args.map,
                foxglove_port=args.foxglove_port,
                drift_share=args.drift_share,
                rerun=args.rerun,
            )
    finally:
        sock.close()
    return EXIT_OK
