"""Benchmarks: a tiny registry that ``trifuse bench`` runs.

A benchmark is a function ``run(repeat) -> {figure name: value}``; it times what it measures
``repeat`` times (after its own warm-up) and returns medians. Figure names carry their unit
(``render_ms``). A benchmark may name baselines, pairs ``(figure, baseline figure)`` measured
in the same run, and the CLI prints their ratio ``figure / baseline``: e.g. a fusion mode
against OpenCV's ``remap``, or our calibration against ``cv2.calibrateCamera``.

Add one with the decorator; the CLI lists and runs whatever is registered::

    @register("fuse-remap", "median time of one fused eye vs cv2.remap",
              baselines=(("fuse_ms", "remap_ms"),))
    def _fuse(repeat: int) -> dict[str, float]: ...
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

BenchFn = Callable[[int], dict[str, float]]


@dataclass(frozen=True)
class Benchmark:
    """A registered benchmark.

    Attributes:
        name: what ``--only`` selects.
        description: one line for ``trifuse bench --help`` and the report.
        run: ``run(repeat)`` -> figures (name with unit suffix -> median value).
        baselines: pairs (figure, baseline figure) whose ratio is reported.
        default_repeat: repeats when the user gives none.
    """

    name: str
    description: str
    run: BenchFn
    baselines: tuple[tuple[str, str], ...] = ()
    default_repeat: int = 10


@dataclass(frozen=True)
class BenchResult:
    """Figures of one benchmark run and the ratios against its baselines."""

    name: str
    repeat: int
    figures: dict[str, float]
    ratios: dict[str, float]

    def format(self) -> str:
        """Lines for people: ``name: figure = value`` and ``figure / baseline = ratio``."""
        lines = [f"{self.name} (median of {self.repeat}):"]
        lines += [f"  {k} = {v:.3f}" for k, v in self.figures.items()]
        lines += [f"  {k} = {v:.3f}" for k, v in self.ratios.items()]
        return "\n".join(lines)


REGISTRY: dict[str, Benchmark] = {}


def register(
    name: str,
    description: str,
    *,
    baselines: tuple[tuple[str, str], ...] = (),
    default_repeat: int = 10,
) -> Callable[[BenchFn], BenchFn]:
    """Decorator: add ``fn`` to :data:`REGISTRY` under ``name``; names are unique."""

    def deco(fn: BenchFn) -> BenchFn:
        if name in REGISTRY:
            raise ValueError(f"benchmark {name!r}: registered twice")
        REGISTRY[name] = Benchmark(name, description, fn, baselines, default_repeat)
        return fn

    return deco


def median_ms(fn: Callable[[int], object], repeat: int, warmup: int = 1) -> float:
    """Median wall time in milliseconds of ``fn(i)`` for i in 0..repeat-1.

    ``warmup`` calls (with i = -1, -2 ...) run first and are not counted.
    """
    if repeat < 1:
        raise ValueError(f"repeat: expected a positive integer, got {repeat}")
    for w in range(warmup):
        fn(-1 - w)
    times = []
    for i in range(repeat):
        t0 = time.perf_counter()
        fn(i)
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def run_benchmark(name: str, repeat: int | None = None) -> BenchResult:
    """Run one registered benchmark; ValueError for an unknown name or a bad ``repeat``."""
    if name not in REGISTRY:
        raise ValueError(f"unknown benchmark {name!r} (known: {', '.join(sorted(REGISTRY))})")
    bench = REGISTRY[name]
    n = bench.default_repeat if repeat is None else repeat
    if n < 1:
        raise ValueError(f"repeat: expected a positive integer, got {n}")
    figures = bench.run(n)
    ratios: dict[str, float] = {}
    for fig, base in bench.baselines:
        if fig in figures and base in figures and figures[base] != 0:
            ratios[f"{fig} / {base}"] = figures[fig] / figures[base]
    return BenchResult(name, n, figures, ratios)


# -- the benchmarks -------------------------------------------------------------------------


@register(
    "render",
    "simulator: five-sensor frame sets (calibration view, inspection frame, per sensor) (ms)",
    default_repeat=5,
)
def _render(repeat: int) -> dict[str, float]:
    """Medians over ``repeat`` renders of the simulated head.

    ``calibration_view_ms``: one view in a stream of ``calibration_views`` (what
    ``trifuse simulate calibration`` pays per view, without writing the PNGs);
    ``inspection_frame_ms``: one five-sensor frame set of the inspection room;
    ``<sensor>_ms``: one sensor of that room alone; ``setup_ms``: a new renderer's first
    frame set (ray grids of all sensors, with undistortion, are built then).
    """
    from app.sources.sim.scenarios import InspectionScenario, calibration_views

    stream = calibration_views(repeat + 1, seed=1000)
    figures = {"calibration_view_ms": median_ms(lambda _i: next(stream), repeat)}
    scenario = InspectionScenario(seed=0)
    figures["inspection_frame_ms"] = median_ms(lambda i: scenario.render(0.1 * i), repeat)
    for name in scenario.rig.names:
        figures[f"{name}_ms"] = median_ms(lambda i, n=name: scenario.render(0.1 * i, [n]), repeat)
    figures["setup_ms"] = median_ms(lambda i: InspectionScenario(seed=0).render(0.0), repeat)
    return figures
