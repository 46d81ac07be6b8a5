"""The benchmarks ``trifuse bench`` runs, in the order it runs and lists them.

A benchmark (:mod:`app.devtools.benchmark`) is a function ``run(repeat) -> {figure name:
value}`` that returns medians over ``repeat`` timings, with baselines measured in the same
run whose ratios the report gives. They live by subject in ``app/devtools/bench_*.py``;
:data:`REGISTRY` names them. Add one to a subject module with the decorator and list it in
:data:`BENCHMARKS`::

    @benchmark("fuse-remap", "median time of one fused eye vs cv2.remap",
               baselines=(("fuse_ms", "remap_ms"),))
    def fuse_remap(repeat: int) -> dict[str, float]: ...

The stream soak (``trifuse bench --soak``, app/devtools/bench_soak.py) is not in the
registry: it runs for minutes, has its own options and passes or fails.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Unpack

from trifuse.app.devtools import (
    bench_agc,
    bench_calib,
    bench_detect,
    bench_drift,
    bench_fusion,
    bench_idle,
    bench_link,
    bench_live,
    bench_map,
    bench_motion,
    bench_ray,
    bench_real_calib,
    bench_recording,
    bench_registration,
    bench_ros2,
    bench_sim,
    bench_stream,
)
from trifuse.app.devtools.benchmark import (
    BenchFn,
    Benchmark,
    BenchOptions,
    BenchResult,
    benchmark,
    run,
)

BENCHMARKS: tuple[Benchmark, ...] = (
    bench_sim.render,
    bench_calib.calibrate,
    bench_calib.calib_scale,
    bench_fusion.compose,
    bench_fusion.fuse,
    bench_fusion.fuse_accuracy,
    bench_registration.registration,
    bench_drift.drift,
    bench_agc.agc,
    bench_map.thermal_map,
    bench_recording.recording,
    bench_ray.ray_jobs,
    bench_stream.stream,
    bench_motion.sim_first_minute,
    bench_sim.sim_live,
    bench_detect.thermal_detect,
    bench_detect.real_12mp,
    bench_real_calib.real_calib,
    bench_idle.idle,
    bench_live.live,
    bench_link.link,
    bench_ros2.ros2,
)

REGISTRY: dict[str, Benchmark] = {}
"""Benchmark name -> benchmark, in the order ``trifuse bench`` runs them."""


def _add(bench: Benchmark) -> None:
    if bench.name in REGISTRY:
        raise ValueError(f"benchmark {bench.name!r}: registered twice")
    REGISTRY[bench.name] = bench


def register(
    name: str, description: str, **options: Unpack[BenchOptions]
) -> Callable[[BenchFn], BenchFn]:
    """Decorator: add ``fn`` to :data:`REGISTRY` under ``name``, after the listed ones;
    names are unique."""

    def deco(fn: BenchFn) -> BenchFn:
        _add(benchmark(name, description, **options)(fn))
        return fn

    return deco


for _bench in BENCHMARKS:
    _add(_bench)


def run_benchmark(name: str, repeat: int | None = None) -> BenchResult:
    """Run one registered benchmark; ValueError for an unknown name or a bad ``repeat``."""
    if name not in REGISTRY:
        raise ValueError(f"unknown benchmark {name!r} (known: {', '.join(sorted(REGISTRY))})")
    return run(REGISTRY[name], repeat)


def run_soak_command(soak_s: float, viewers: int) -> int:
    """``trifuse bench --soak``: ``viewers`` fast viewers plus slow readers on a console for
    ``soak_s`` seconds (app/devtools/bench_soak.py); prints the table, returns the exit code
    (1 if a criterion fails)."""
    from trifuse.app.devtools import bench_soak

    return bench_soak.run_soak_cli(bench_soak.SoakConfig(soak_s=soak_s, viewers=viewers))
