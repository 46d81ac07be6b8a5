"""What a benchmark is: a timed function with its figures' baselines, and how it is run.

A benchmark is a function ``run(repeat) -> {figure name: value}``; it times what it measures
``repeat`` times (after its own warm-up) and returns medians. Figure names carry their unit
(``render_ms``). A benchmark may name baselines, pairs ``(figure, baseline figure)`` measured
in the same run, and the report gives their ratio ``figure / baseline``: e.g. a fusion mode
against OpenCV's ``remap``, or our calibration against ``cv2.calibrateCamera``.

The modules ``app/devtools/bench_*.py`` declare theirs with :func:`benchmark`;
``app.devtools.bench`` lists them in the order ``trifuse bench`` runs them.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypedDict, Unpack

BenchFn = Callable[[int], dict[str, float]]


@dataclass(frozen=True)
class Benchmark:
    """A benchmark.

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


class BenchOptions(TypedDict, total=False):
    """What a benchmark may set besides its name and description (see :class:`Benchmark`)."""

    baselines: tuple[tuple[str, str], ...]
    default_repeat: int


def benchmark(
    name: str, description: str, **options: Unpack[BenchOptions]
) -> Callable[[BenchFn], Benchmark]:
    """Decorator: the function ``run(repeat)`` as the :class:`Benchmark` ``name``."""

    def deco(fn: BenchFn) -> Benchmark:
        return Benchmark(name, description, fn, **options)

    return deco


def check_repeat(repeat: int) -> None:
    """ValueError unless ``repeat`` is a positive number of repeats."""
    if repeat < 1:
        raise ValueError(f"repeat: expected a positive integer, got {repeat}")


def median_ms(fn: Callable[[int], object], repeat: int, warmup: int = 1) -> float:
    """Median wall time in milliseconds of ``fn(i)`` for i in 0..repeat-1.

    ``warmup`` calls (with i = -1, -2 ...) run first and are not counted.
    """
    check_repeat(repeat)
    for w in range(warmup):
        fn(-1 - w)
    times = []
    for i in range(repeat):
        t0 = time.perf_counter()
        fn(i)
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def run(bench: Benchmark, repeat: int | None = None) -> BenchResult:
    """Run ``bench`` ``repeat`` times (its default if None); ValueError for a bad ``repeat``."""
    n = bench.default_repeat if repeat is None else repeat
    check_repeat(n)
    figures = bench.run(n)
    ratios: dict[str, float] = {}
    for fig, base in bench.baselines:
        if fig in figures and base in figures and figures[base] != 0:
            ratios[f"{fig} / {base}"] = figures[fig] / figures[base]
    return BenchResult(bench.name, n, figures, ratios)
