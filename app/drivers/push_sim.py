"""Example driver: push the simulated head to a console over the push ingest protocol.

    TRIFUSE_TOKEN=... python -m trifuse.app.drivers.push_sim \
        --url ws://127.0.0.1:8000/ingest [--rate 1.0]

Renders the inspection scenario with :class:`~app.sources.simulated.SimulatedHeadSource`
paced in real time (``--rate`` simulated seconds per second), encodes every frame
(:func:`~app.sources.push.encode.encode_frame`: colour JPEG, thermal and TOF 16-bit PNG) and
sends it; when the connection drops it reconnects every ``--retry`` seconds, the head
keeps moving meanwhile and only the newest frames are sent afterwards. Prints the first
frame of each sensor, then one line per second of what was sent; error replies of the
console go to stderr. Time stamps are the host clock when streaming starts plus the
simulated time. The console's token comes from ``--token`` or ``TRIFUSE_TOKEN``; a console
that refuses it ends the driver with exit status 2.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence

from websockets.exceptions import InvalidStatus, InvalidURI, WebSocketException

from trifuse.app.sources.push.clients import TOKEN_ENV, PushClient
from trifuse.app.sources.simulated import SimulatedHeadSource


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m trifuse.app.drivers.push_sim",
        description="Push the simulated sensor head to a trifuse console (push ingest).",
    )
    p.add_argument(
        "--url",
        default="ws://127.0.0.1:8000/ingest",
        help="the console's ingest WebSocket URL (default: %(default)s)",
    )
    p.add_argument(
        "--token",
        default=os.environ.get(TOKEN_ENV),
        help=f"the console's token (default: ${TOKEN_ENV}); none for a --no-token console",
    )
    p.add_argument(
        "--rate",
        type=_positive,
        default=1.0,
        help="simulated seconds per wall-clock second (default: %(default)s = real time)",
    )
    p.add_argument(
        "--render-hz",
        type=_positive,
        default=2.0,
        help="head poses rendered per simulated second (default: %(default)s)",
    )
    p.add_argument(
        "--sensors", default=None, help="comma-separated sensors to send (default: all five)"
    )
    p.add_argument("--jpeg-quality", type=int, default=85, help="colour JPEG quality (default 85)")
    p.add_argument(
        "--value-encoding",
        choices=("png16", "raw16", "raw32f"),
        default="png16",
        help="thermal and TOF encoding (default: %(default)s)",
    )
    p.add_argument(
        "--retry", type=_positive, default=1.0, help="seconds between reconnection attempts"
    )
    p.add_argument("--frames", type=int, default=None, help="stop after sending this many frames")
    p.add_argument(
        "--seconds",
        type=_positive,
        default=None,
        help="stop after streaming this many wall-clock seconds",
    )
    p.add_argument("--quiet", action="store_true", help="print only errors")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated scenario")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    sensors = None if args.sensors is None else [s for s in args.sensors.split(",") if s]

    def say(text: str) -> None:
        if not args.quiet:
            print(text, flush=True)

    def on_error(reply: dict) -> None:
        print(f"console rejected a frame: {reply.get('error')}", file=sys.stderr, flush=True)

    try:
        source = SimulatedHeadSource(
            sensors=sensors,
            realtime=True,
            speed=args.rate,
            render_hz=args.render_hz,
            start_ns=None,
            seed=args.seed,
        )
    except ValueError as exc:
        print(f"push_sim: {exc}", file=sys.stderr)
        return 2
    options = {"jpeg_quality": args.jpeg_quality, "value_encoding": args.value_encoding}
    say(f"rendering the first head pose of {', '.join(source.sensors)} ...")
    source.wait_ready()
    say(f"first pose rendered in {source.first_pose_s:.1f} s; streaming to {args.url}")
    frames = source.frames()
    start_wall = time.monotonic()
    sent_total = 0
    first_seen: set[str] = set()
    client: PushClient | None = None
    try:
        while True:
            try:
                if client is None:
                    client = PushClient(
                        args.url,
                        source.rig,
                        encode_options=options,
                        on_error=on_error,
                        token=args.token,
                    )
                    say(f"connected to {args.url}")
                counts: dict[str, int] = {}
                window_bytes = client.sent_bytes
                window_start = time.monotonic()
                for frame in frames:
                    before = client.sent_bytes
                    client.send(frame)
                    sent_total += 1
                    counts[frame.sensor] = counts.get(frame.sensor, 0) + 1
                    if frame.sensor not in first_seen:
                        first_seen.add(frame.sensor)
                        say(
                            f"sent {frame.sensor} stamp_ns={frame.stamp_ns} "
                            f"{frame.image.shape[1]}x{frame.image.shape[0]} "
                            f"({client.sent_bytes - before} bytes)"
                        )
                    now = time.monotonic()
                    if now - window_start >= 1.0:
                        rate = (client.sent_bytes - window_bytes) / (now - window_start) / 1e6
                        summary = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
                        say(f"sent {summary} in {now - window_start:.1f} s ({rate:.1f} MB/s)")
                        counts.clear()
                        window_bytes, window_start = client.sent_bytes, now
                    if args.frames is not None and sent_total >= args.frames:
                        say(f"sent {sent_total} frames; done")
                        return 0
                    if args.seconds is not None and now - start_wall >= args.seconds:
                        say(f"sent {sent_total} frames in {args.seconds:g} s; done")
                        return 0
                return 0  # the stream ended (source closed)
            except InvalidURI as exc:
                print(f"push_sim: --url: {exc}", file=sys.stderr)
                return 2
            except InvalidStatus as exc:
                if exc.response.status_code not in (401, 403):
                    raise
                what = "wrong --token" if args.token else "no --token (or TRIFUSE_TOKEN) given"
                print(
                    f"push_sim: {args.url} refused the connection "
                    f"(HTTP {exc.response.status_code}): {what}",
                    file=sys.stderr,
                )
                return 2
            except (OSError, WebSocketException) as exc:  # refused, timed out, closed
                print(
                    f"connection to {args.url}: {exc!r}; retrying in {args.retry:g} s",
                    file=sys.stderr,
                    flush=True,
                )
            if client is not None:
                try:
                    client.close()
                except Exception:
                    pass
                client = None
            time.sleep(args.retry)
            if args.seconds is not None and time.monotonic() - start_wall >= args.seconds:
                return 0
    except KeyboardInterrupt:
        say(f"interrupted after {sent_total} frames")
        return 0
    finally:
        if client is not None:
            try:
                client.close()
            except Exception:
                pass
        source.close()


if __name__ == "__main__":
    sys.exit(main())
