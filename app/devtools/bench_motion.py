"""Benchmark ``sim-first-minute``: how the picture of the simulated head moves in the
console's first minute, on an empty pose cache and on a full one."""

from __future__ import annotations

import itertools
import time
from pathlib import Path

from trifuse.app.devtools.benchmark import benchmark
from trifuse.app.devtools.browser_console import (
    BrowserConsole,
    headless_chromium,
    inspection_pose_count,
    rendered_poses,
    require_chromium,
    websocket_tap,
)

_PICTURE_PROBE = websocket_tap(
    "__trifuseMotion",
    "{ pictures: [] }",
    'if (typeof ev.data !== "string") rec.pictures.push([performance.now(), ev.data.size]);',
)
"""Injected into the viewer page: every binary stream message (one JPEG of the fused pair,
drawn by the viewer) as [performance.now() ms, size in bytes]. The pipeline publishes the
very same JPEG again while its inputs are unchanged, so equal consecutive sizes mean the
picture stood still."""

MOTION_MERGE_S = 0.15
"""Picture changes closer than this (seconds) count as one move: when the head's pose
changes, the colour, thermal and TOF images switch a few frames apart."""


def motion_figures(pictures: list[tuple[float, int]], t0_s: float, span_s: float) -> dict:
    """How the picture moved in ``[t0_s, t0_s + span_s)``: ``pictures`` are (time s, JPEG
    size) of the stream's pictures in arrival order; a size different from the previous
    picture's is a change (changes within :data:`MOTION_MERGE_S` are one move).

    Returns ``moves_per_s``, ``longest_still_s`` (the longest time between moves, the
    window's ends included), ``pictures_per_s`` and ``distinct`` (distinct pictures).
    """
    inside = [(t, s) for t, s in pictures if t0_s <= t < t0_s + span_s]
    moves: list[float] = []
    prev = None
    for t, size in inside:
        if prev is not None and size != prev and (not moves or t - moves[-1] > MOTION_MERGE_S):
            moves.append(t)
        prev = size
    edges = [t0_s, *moves, t0_s + span_s]
    return {
        "moves_per_s": len(moves) / span_s,
        "longest_still_s": max(b - a for a, b in itertools.pairwise(edges)),
        "pictures_per_s": len(inside) / span_s,
        "distinct": float(len({s for _, s in inside})),
    }


@benchmark(
    "sim-first-minute",
    "the console's first minute on the simulated head with an empty pose cache, against "
    "the same console once every pose is cached: picture moves per second and the longest "
    "time it stood still, in headless Chromium (minutes)",
    baselines=(
        ("first_longest_still_s", "full_longest_still_s"),
        ("first_moves_per_s", "full_moves_per_s"),
    ),
    default_repeat=1,
)
def sim_first_minute(repeat: int) -> dict[str, float]:
    """``trifuse serve`` (default: the inspection room) with its viewer page in headless
    Chromium, as in the ``stream`` benchmark, watched picture by picture.

    ``first_*``: a console on an empty disk cache (a temporary ``XDG_CACHE_HOME``), the
    ``SPAN_S`` seconds from the viewer's first picture (median over ``repeat`` consoles,
    each on a new empty cache). Then the last console's cache is left to fill (at most 600
    s; ``fill_s`` from its first picture, ``fill_poses_rendered`` of ``poses``) and
    ``full_*`` is a console restarted on that full cache, its first ``SPAN_S`` seconds:
    the baseline, how the picture moves once every pose is rendered.

    Per console: ``moves_per_s`` picture changes per second (:func:`motion_figures`: the
    JPEG the viewer receives changes), ``longest_still_s`` the longest time without one,
    ``pictures_per_s`` the pictures the viewer received per second, ``distinct`` distinct
    pictures, ``first_picture_s`` from the start of the server to the first picture.
    """
    import statistics
    import tempfile

    require_chromium("sim-first-minute")

    span_s = 60.0
    fill_max_s = 600.0
    poses = inspection_pose_count()

    def watch(console: BrowserConsole) -> tuple[dict[str, float], float]:
        console.page.add_init_script(_PICTURE_PROBE)
        console.page.reload()
        console.page.wait_for_function(
            "() => window.__trifuseMotion && window.__trifuseMotion.pictures.length > 0",
            timeout=300e3,
        )
        first_s = time.monotonic() - console.t_start
        js = "() => window.__trifuseMotion.pictures"
        t0 = console.page.evaluate(js)[0][0] / 1e3
        console.page.wait_for_timeout(span_s * 1e3)
        console.page.wait_for_function(
            f"() => performance.now() >= {(t0 + span_s) * 1e3 + 500}", timeout=60e3
        )
        pictures = [(t / 1e3, int(s)) for t, s in console.page.evaluate(js)]
        out = motion_figures(pictures, t0, span_s)
        out["first_picture_s"] = first_s
        return out, time.monotonic() - (first_s + console.t_start)

    figures: dict[str, float] = {"poses": float(poses)}
    with (
        tempfile.TemporaryDirectory(prefix="trifuse-bench-motion-") as tmp,
        headless_chromium() as b,
    ):
        firsts = []
        cache = Path(tmp) / "cache-0"
        for i in range(repeat):
            cache = Path(tmp) / f"cache-{i}"
            with BrowserConsole(b, cache, Path(tmp) / f"work-{i}") as console:
                first, elapsed = watch(console)
                firsts.append(first)
                if i == repeat - 1:  # let its cache fill, for the baseline
                    t_fill = time.monotonic() - elapsed
                    while rendered_poses(cache) < poses and time.monotonic() - t_fill < fill_max_s:
                        time.sleep(1.0)
                    figures["fill_s"] = time.monotonic() - t_fill
                    figures["fill_poses_rendered"] = float(rendered_poses(cache))
        for key in firsts[0]:
            figures[f"first_{key}"] = statistics.median(f[key] for f in firsts)
        with BrowserConsole(b, cache, Path(tmp) / "work-full") as console:
            full, _ = watch(console)
        figures.update({f"full_{k}": v for k, v in full.items()})
    return figures
