"""``trifuse bench``: the registered benchmarks' median timings, or the stream soak."""

from __future__ import annotations

import argparse

from trifuse.app.cli.args import EXIT_OK, PROG, Commands, UsageError, positive_int
from trifuse.app.cli.output import out


def _bench_names() -> str:
    """Every benchmark with its description, for ``--help`` (``%`` escaped for argparse)."""
    from trifuse.app.devtools.bench import REGISTRY

    return ", ".join(f"{n} ({b.description})" for n, b in REGISTRY.items()).replace("%", "%%")


def _viewer_counts(text: str) -> tuple[int, ...]:
    """``N,N,...`` viewers at once, each a positive integer."""
    try:
        counts = tuple(int(p) for p in text.split(","))
    except ValueError:
        counts = ()
    if not counts or min(counts) < 1:
        raise argparse.ArgumentTypeError(
            f"expected positive integers such as 1,10,50, got {text!r}"
        )
    return counts


def add_parser(commands: Commands) -> argparse.ArgumentParser:
    """``bench [--only NAME] [--repeat N]`` or ``bench --soak [--soak-seconds] [--viewers]
    [--video [N,N,...]]``."""
    bench = commands.add_parser(
        "bench",
        help="run the benchmarks and print median timings (and ratios to baselines)",
        description=(
            "Run the registered benchmarks and print the median of each figure over the "
            "repeats (after a warm-up), and for benchmarks with a baseline measured in the "
            "same run the ratio figure / baseline. Results are recorded in BENCHMARKS.md."
        ),
    )
    only = bench.add_argument("--only", metavar="NAME", help="run one benchmark only")

    def list_benchmarks() -> None:  # for --help only: the registry imports every benchmark
        only.help = f"run one benchmark only; known: {_bench_names()}"

    bench.late_help = list_benchmarks
    bench.add_argument(
        "--repeat",
        type=positive_int,
        metavar="N",
        help="timed repeats per benchmark (default: each benchmark's own, typically 10)",
    )
    bench.add_argument(
        "--soak",
        action="store_true",
        help="instead: the stream soak (BENCHMARKS.md 'Stream soak'): a console, a 1-viewer "
        "baseline, then --viewers viewers plus slow readers for --soak-seconds; frame "
        "rates and the server's memory; exit 1 if a criterion fails",
    )
    bench.add_argument(
        "--soak-seconds",
        type=positive_int,
        metavar="S",
        help="length of the soak phase (default: 600)",
    )
    bench.add_argument(
        "--viewers",
        type=positive_int,
        metavar="N",
        help="fast viewers during the soak, besides the slow readers (default: 10)",
    )
    bench.add_argument(
        "--video",
        nargs="?",
        const=(1, 10, 50),
        type=_viewer_counts,
        metavar="N,N,...",
        help="with --soak: viewers of the video stream instead (BENCHMARKS.md 'Video "
        "viewers'): N viewers at once for each N (default 1,10,50), --soak-seconds each "
        "(default 30), --repeat runs (default 1); their and the console's frame rates, "
        "/api/status answer times, the console's memory before, during and after",
    )
    return bench


def run(args: argparse.Namespace) -> int:
    """Run the soak, or each benchmark (all, or ``--only``) and print its figures."""
    from trifuse.app.devtools.bench import REGISTRY, run_benchmark, run_soak_command

    if args.video:
        if not args.soak or args.only or args.viewers:
            raise UsageError(f"{PROG} bench: --video goes with --soak (no --only, --viewers)")
        from trifuse.app.devtools import bench_soak

        return bench_soak.run_video_load_cli(
            bench_soak.VideoLoadConfig(
                counts=args.video, step_s=args.soak_seconds or 30.0, runs=args.repeat or 1
            )
        )
    if args.soak:
        if args.only or args.repeat:
            raise UsageError(f"{PROG} bench: --soak runs alone (no --only, --repeat)")
        return run_soak_command(args.soak_seconds or 600.0, args.viewers or 10)
    if args.soak_seconds or args.viewers:
        raise UsageError(f"{PROG} bench: --soak-seconds and --viewers go with --soak")

    names = [args.only] if args.only else list(REGISTRY)
    if args.only and args.only not in REGISTRY:
        raise UsageError(
            f"{PROG} bench: --only: unknown benchmark {args.only!r} (known: {', '.join(REGISTRY)})"
        )
    for name in names:
        out(f"running {name}: {REGISTRY[name].description} ...")
        result = run_benchmark(name, args.repeat)
        out(result.format())
    return EXIT_OK
