"""``trifuse serve``: a source, the fusion pipeline, Viser on loopback, FastAPI on one
public port (127.0.0.1 by default)."""

from __future__ import annotations

import errno
import signal
import socket
import threading
from dataclasses import dataclass
from pathlib import Path

import uvicorn

from trifuse.app.recording.open_source import OpenedSource, simulated_source
from trifuse.app.server.app_factory import create_app
from trifuse.app.server.middleware.auth import AuthConfig, is_loopback
from trifuse.app.server.middleware.connections import GuardedH11Protocol, quiet_repeated_logs
from trifuse.app.server.panels.calibration import CalibrationPanel
from trifuse.app.server.panels.display import Panels
from trifuse.app.server.panels.map_panel import MapPanel
from trifuse.app.server.panels.measurements import MeasurementsPanel
from trifuse.app.server.panels.precision import PrecisionPanel
from trifuse.app.server.panels.range import RangePanel
from trifuse.app.server.panels.rig_files import RigFilesPanel
from trifuse.app.server.panels.scene3d import Scene3D
from trifuse.app.server.panels.source import SourcePanel
from trifuse.app.server.routers.console_api import make_console_settings_router
from trifuse.app.server.routers.drift_api import make_drift_router
from trifuse.app.server.routers.map_api import make_map_router
from trifuse.app.server.routers.session_api import make_session_router
from trifuse.app.server.routers.viser_bridge import start_guarded_viser
from trifuse.app.server.runtime.board_watch import BoardWatch
from trifuse.app.server.runtime.context import ConsoleBandwidth, ConsoleContext
from trifuse.app.server.runtime.demand import ConsoleDemand, hold_while_connected
from trifuse.app.server.runtime.drift_watch import CPU_SHARE as DRIFT_CPU_SHARE
from trifuse.app.server.runtime.drift_watch import DriftWatch
from trifuse.app.server.runtime.foxglove_live import FoxgloveLive
from trifuse.app.server.runtime.map_worker import MapWorker
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.registration_watch import RegistrationWatch
from trifuse.app.server.runtime.source_control import SourceControl
from trifuse.app.server.runtime.source_tap import SourceTap
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.server.runtime.thermal_balance import ThermalBalancer
from trifuse.app.sources.capabilities import head_pose_of
from trifuse.app.workflows.calib_session import CalibrationSession
from trifuse.calib.board import Board


def warm_simulator_cache(scenarios: dict[str, dict], timeout_s: float = 1800.0) -> None:
    """Render every pose of each simulated scenario into the disk cache, all scenarios at
    once (one render thread or process each), and return when all are there.

    ``scenarios`` maps a scenario name to :func:`simulated_source`'s keyword arguments.
    Consoles started afterwards with the same arguments load every pose from disk instead
    of rendering beside their work (the test suite does this once per run).
    """
    import time

    sources = [simulated_source(name, **kw)[0] for name, kw in scenarios.items()]
    try:
        deadline = time.monotonic() + timeout_s
        for src in sources:
            while src.rendered_count < src.pose_count and src.render_thread_alive:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"the simulator's poses were not rendered in {timeout_s} s")
                time.sleep(0.2)
    finally:
        for src in sources:
            src.close()


def bind_public_socket(host: str, port: int) -> socket.socket:
    """The console's listening socket, bound before anything else starts (a port in use is
    then one line at once, not a traceback after the simulator has started).

    Raises:
        OSError: the address is in use, not local, or the port is not allowed; the message
            says which.
    """
    try:
        family, kind, proto, _, address = socket.getaddrinfo(
            host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )[0]
    except socket.gaierror as e:
        raise OSError(f"--host {host}: not an address of this machine ({e.strerror})") from None
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(2048)
    except OSError as e:
        sock.close()
        if e.errno == errno.EADDRINUSE:
            raise OSError(
                f"port {port} on {host} is in use (another console?); choose another --port"
            ) from None
        raise OSError(f"cannot listen on {host}:{port}: {e.strerror}") from None
    sock.set_inheritable(False)
    return sock


def _exit_on_sigterm(signum: int, _frame: object) -> None:
    raise SystemExit(128 + signum)


@dataclass(frozen=True)
class TLSFiles:
    """A PEM certificate (chain) and its private key, for HTTPS (a headset's WebXR needs a
    secure context)."""

    certfile: Path
    keyfile: Path


def console_url(host: str, port: int, auth: AuthConfig, path: str = "/") -> str:
    """The URL to open: scheme, a host a browser can reach, the token when there is one."""
    shown = "127.0.0.1" if host in ("0.0.0.0", "::") else host
    shown = f"[{shown}]" if ":" in shown else shown
    scheme = "https" if auth.secure else "http"
    query = f"?token={auth.token}" if auth.token else ""
    return f"{scheme}://{shown}:{port}{path}{query}"


def serve(
    opened: OpenedSource,
    board: Board,
    workdir: Path,
    auth: AuthConfig,
    host: str = "127.0.0.1",
    tls: TLSFiles | None = None,
    sock: socket.socket | None = None,
    console_bandwidth: str = "full",
    build_map: bool = False,
    foxglove_port: int | None = None,
    drift_share: float | None = None,
    rerun: str | None = None,
) -> None:
    """Run the console until interrupted; the calibration session lives in ``workdir``.
    ``auth`` (auth.py) guards every route and WebSocket; its port is the one served, on
    ``sock`` (:func:`bind_public_socket`) if given. ``console_bandwidth``: the 3D
    console's starting bandwidth mode (``full``, ``low``; context.py). ``build_map``:
    build the thermal 3D map from the start (map_worker.py; else the operator turns it
    on). ``foxglove_port``: also publish the live frames, transforms, calibrations, fused
    video, TOF cloud and health on foxglove-sdk's WebSocket server at 127.0.0.1:PORT
    (foxglove_live.py; OSError in one line if the port is taken). ``drift_share``: the
    share of one core the drift check may take (drift_watch.py; None: its default).
    ``rerun``: also log the live frames to the rerun viewer at that address ("": the one on
    this machine; rerun_live.py; None: not)."""
    port = auth.port
    source, rig = opened.source, opened.rig
    try:  # first: a work directory of another board or rig is refused before anything runs
        session = CalibrationSession(workdir, rig, board)
    except BaseException:
        source.close()
        raise
    demand = ConsoleDemand()  # who listens: the work is done only then (demand.py)
    hub = FrameHub(demand.fusion)  # each stream viewer holds it
    tap = SourceTap(source)  # per-sensor rates and recording (source_tap.py)
    pipeline = FusionPipeline(tap, rig, hub, demand=demand.fusion).start()
    server, viser_secret = start_guarded_viser()
    # A Viser client wants the GUI's updates, the fused depth and the balance (3D cloud,
    # Thermal panel) and the board search (Calibration panel, feeds, 3D board): Viser does
    # not tell which folder a browser has open.
    hold_while_connected(server, demand.gui, demand.fusion, demand.board, demand.balance)
    watch = BoardWatch(lambda: pipeline.latest_set, rig, board, demand=demand.board)
    # automatic unless the rig brings a balance; measured while demand.fusion is wanted
    balancer = ThermalBalancer(pipeline, listeners=demand.balance, auto=None)
    pipeline.balance_note = balancer.describe  # the viewer's overlay says which balance
    # each eye's registration sigma, every 2 s while the fusion is wanted (/api/status, the
    # registration display mode, the Fusion panel)
    registration = RegistrationWatch(pipeline)
    # the calibration's health: each camera's drift against the rig in use, measured at
    # most every 2 s within drift_share of a core (10 %) while the fusion is wanted
    # (/api/status, the Calibration panel's line, alert and Refine rig, the viewer's overlay)
    drift = DriftWatch(pipeline, cpu_share=drift_share or DRIFT_CPU_SHARE)
    ctx = ConsoleContext(
        server=server,
        source=source,
        description=opened.description,
        hub=hub,
        pipeline=pipeline,
        board=board,
        board_watch=watch,
        ground_truth_rig=opened.ground_truth_rig,
        balancer=balancer,
        save_rig=session.save_rig,
        demand=demand,
        bandwidth=ConsoleBandwidth(console_bandwidth),
        registration=registration,
        drift=drift,
    )
    control = SourceControl(pipeline, hub, opened.description, workdir)
    live = None
    if foxglove_port is not None:  # before the parts start: a refused port leaves nothing
        try:
            live = FoxgloveLive(control, foxglove_port)
        except BaseException:
            pipeline.stop()
            session.close()
            server.stop()
            raise
    mapper = MapWorker(pipeline, head_pose_of(source), workdir / "maps", enabled=build_map)
    if rerun is not None:
        from trifuse.app.server.runtime.rerun_live import RerunLive

        try:
            live_rerun = RerunLive(pipeline, hub, rerun or None, mapper=mapper)
        except BaseException:
            pipeline.stop()
            session.close()
            server.stop()
            raise
    panels = [
        SourcePanel(ctx, control),  # first: the Source panel tops the GUI
        CalibrationPanel(ctx, session),  # holds demand.board while auto-capture is on
        Scene3D(ctx),
        RangePanel(ctx, session),
        MapPanel(ctx, mapper),
        MeasurementsPanel(ctx),
        Panels(ctx),
    ]
    RigFilesPanel(ctx)  # the rig in robotics formats: export and import (no periodic work)
    for panel in panels:
        panel.demand = demand.gui  # updated only while a Viser client is connected
    parts = [
        *(panel.start() for panel in panels),
        watch.start(),
        balancer.start(),
        registration.start(),
        drift.start(),
        PrecisionPanel(ctx).start(),
        mapper.start(),
    ]
    if live is not None:
        parts.append(live.start())
    if rerun is not None:
        parts.append(live_rerun.start())
    from trifuse.app.recording.ros2_live import Ros2LiveSource

    if isinstance(source, Ros2LiveSource):  # the calibration and the fused pair back to ROS 2
        from trifuse.app.server.runtime.ros2_out import Ros2Out

        parts.append(Ros2Out(pipeline, hub, source.domain_id).start())
    parts.append(control)  # stopped first: a running recording is finished and kept
    app = create_app(
        hub,
        server.get_port(),
        pipeline,
        control,
        balancer,
        auth,
        viser_secret,
        registration,
        drift,
    )
    app.include_router(
        make_session_router(
            session,
            lambda: pipeline.latest_set,
            ctx.use_rig,
            lambda: pipeline.rig,
            pipeline.rig_with_radiometry,
        )
    )
    app.include_router(make_drift_router(drift, session.save_rig, ctx.use_rig))  # drift_api.py
    app.include_router(make_console_settings_router(ctx.bandwidth))  # /api/console/settings
    app.include_router(make_map_router(mapper))  # /api/map (map_api.py)
    ws_max = None
    from trifuse.app.sources.push.router import make_push_router, uvicorn_ws_max_size
    from trifuse.app.sources.push.source import PushSource

    if isinstance(source, PushSource):
        app.include_router(make_push_router(source))
        ws_max = uvicorn_ws_max_size(source)
    print(
        f"trifuse console on {opened.description}: {console_url(host, port, auth)}  "
        f"(3D console /console/, API /docs)",
        flush=True,
    )
    if auth.token is None:
        print("no token: anyone on this machine can use the console (--no-token)", flush=True)
    if live is not None:
        away = (
            ""
            if is_loopback(host)
            else f"; from another machine: ssh -L {live.port}:127.0.0.1:{live.port} this host"
        )
        print(
            f"Foxglove live on {live.url} (Foxglove: Open connection, Foxglove WebSocket; "
            f"127.0.0.1 only, not guarded by the token: docs/SECURITY.md{away})",
            flush=True,
        )
    if rerun is not None:
        print(
            f"rerun: logging to the viewer at {live_rerun.address} while it answers "
            "(start one with `rerun`)",
            flush=True,
        )
    config = uvicorn.Config(
        app,
        host=host,
        port=port,
        log_level="warning",
        http=GuardedH11Protocol,  # header-read timeout, connection caps per client and in all
        ws_per_message_deflate=False,  # JPEG does not deflate; it cost 13 ms a frame
        **({"ws_max_size": ws_max} if ws_max else {}),
        **({"ssl_certfile": tls.certfile, "ssl_keyfile": tls.keyfile} if tls else {}),
    )
    quiet_repeated_logs()  # after uvicorn's logging set-up
    if threading.current_thread() is threading.main_thread():
        # uvicorn re-raises a SIGTERM after its shutdown; by default that would end the
        # process before the clean-up below (a recording would be left unfinished)
        signal.signal(signal.SIGTERM, _exit_on_sigterm)
    try:
        uvicorn.Server(config).run(sockets=[sock] if sock is not None else None)
    finally:
        for part in reversed(parts):
            part.stop()
        pipeline.stop()
        session.close()
        server.stop()
