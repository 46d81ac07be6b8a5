"""Benchmark ``ray``: the offline jobs of issue 22 (``trifuse fuse``, ``trifuse map``,
:mod:`app.recording.jobs`) here and on a local Ray instance, in one run on the same
recordings: ``trifuse bench --only ray``.

It records (in a temporary directory, three ``trifuse record --source sim`` processes side
by side) two recordings of the inspection room and one of the survey at full resolution,
then measures:

1. Fusion throughput, frame sets composed and written per wall second (JPEGs, frames.csv
   and the joined video, as ``trifuse fuse`` does: :func:`~app.recording.jobs.
   plan_fuse_job` once, then :func:`~app.recording.jobs.run_fuse_job`) with
   :class:`~app.recording.jobs.LocalRunner` (the baseline) and
   :class:`~app.recording.jobs.RayRunner` on a new local instance of 1 and of 2 CPUs;
   every run uses the same plan, so every run's files must be the same bytes as the first
   one's: checked. Each Ray instance is started and shut down around its run; its start
   (``ray.init``) and its workers' start (an import of the jobs' modules on each) are timed
   apart and not counted in the throughput. Runs alternate the runners' order.
2. What a task costs besides its work: an empty Ray task's round trip, the progress
   actor each Ray job starts, and each piece's fixed cost (open, seek, warm-up replay).
3. Where a frame set's time goes, node by node, in small loops over the first recording
   with OpenCV on one thread: the implied bound per node for one core
   (:mod:`app.devtools.bench_ray_nodes`).
4. The map job (:func:`~app.recording.jobs.run_map_job`, poses from the recording)
   locally and on 2 CPUs: TOF frames per second, the PLY and the map's arrays compared.

It prints a table and returns the figures (``trifuse bench`` prints those after it).
A Ray step that fails or gives no answer in
:data:`~app.devtools.ray_instances.RAY_STEP_TIMEOUT_S` stops the benchmark with a
RuntimeError saying which step (the Ray instance shut down; :mod:`app.devtools.ray_instances`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

from trifuse.app.devtools.bench_ray_nodes import node_breakdown
from trifuse.app.devtools.benchmark import benchmark, check_repeat
from trifuse.app.devtools.ray_instances import (
    EMPTY_TASKS,
    ray_step,
    start_ray,
    task_overheads,
)

RECORDING_S = 3.0
"""Length of each recording fused, seconds (90 colour frame sets at 30 Hz)."""
SEEDS = (1, 2)
"""The fused recordings' simulator seeds (two recordings)."""
CHUNK_S = 1.5
"""``--chunk-s`` of the fusion: two pieces per recording."""
SPAN_SMOOTHING_S = 0.125
"""The display's span smoothing in the benchmark (the default is 1 s): a piece then warms up
over ``max(0.5 s, 4 x 0.125 s)`` = 15 frame sets, 17 % of a recording's 90, near the
default's share at the default ``--chunk-s`` (4 s of warm-up per 30 s piece, 13 %). With
the default smoothing the recordings would have to be minutes long to show it."""
SURVEY_S = 3.0
"""Length of the survey recording mapped (45 TOF frames at 15 Hz)."""
SURVEY_SEED = 3
MAP_CHUNK_S = 1.0
"""``--chunk-s`` of the map job: three pieces."""
MAP_VOXEL_M = 0.03
"""``trifuse map``'s default voxel."""
RECORD_TIMEOUT_S = 600.0
RUNNERS = ("local", "ray1", "ray2")
LABELS = {"local": "local (LocalRunner)", "ray1": "Ray, 1 CPU", "ray2": "Ray, 2 CPUs"}
CPUS = {"ray1": 1, "ray2": 2}


def _say(line: str = "") -> None:
    print(line, flush=True)


def _settings() -> Any:
    """The display settings of every fusion run (:data:`SPAN_SMOOTHING_S`)."""
    from trifuse.fusion.compose import DisplaySettings

    return DisplaySettings(span_smoothing_s=SPAN_SMOOTHING_S)


# -- the recordings -------------------------------------------------------------------------


def _record_all(tmp: Path) -> tuple[list[Path], Path, float]:
    """The two inspection recordings and the survey, recorded side by side by
    ``trifuse record`` processes; the wall time."""
    runs = [(tmp / f"inspection{s}.mcap", RECORDING_S, s, "inspection") for s in SEEDS]
    runs.append((tmp / "survey.mcap", SURVEY_S, SURVEY_SEED, "survey"))
    t0 = time.perf_counter()
    procs = []
    for path, seconds, seed, scenario in runs:
        argv = [sys.executable, "-m", "trifuse.app.cli", "record", "--source", "sim"]
        argv += ["--scenario", scenario, "--duration", f"{seconds:g}", "--seed", str(seed)]
        argv += ["--out", str(path)]
        procs.append(
            subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        )
    try:
        for (path, *_), proc in zip(runs, procs, strict=True):
            _, stderr = proc.communicate(timeout=RECORD_TIMEOUT_S)
            if proc.returncode != 0:
                raise RuntimeError(f"recording {path.name} failed: {stderr.strip()[-500:]}")
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    return [r[0] for r in runs[:2]], runs[2][0], time.perf_counter() - t0


# -- fusion runs ----------------------------------------------------------------------------


class TimedLocalRunner:
    """:class:`~app.recording.jobs.LocalRunner` that also times each piece: the time spent
    producing its results (opening, replay, fusion, JPEG and video), not the writer's."""

    name = "local"

    def __init__(self) -> None:
        from trifuse.app.recording.jobs import LocalRunner

        self.inner = LocalRunner()
        self.seconds: list[float] = []

    def run(
        self,
        fn: Callable[[Any, Callable[[int], None]], Iterable[Any]],
        tasks: Sequence[Any],
        expected: Sequence[int | None],
        progress: Callable[[int, int | None], None] | None = None,
    ) -> Iterator[Iterable[Any]]:
        self.seconds = [0.0] * len(tasks)
        for k, items in enumerate(self.inner.run(fn, tasks, expected, progress)):
            yield self._timed(k, items)

    def _timed(self, k: int, items: Iterable[Any]) -> Iterator[Any]:
        it = iter(items)
        while True:
            t0 = time.perf_counter()
            try:
                item = next(it)
            except StopIteration:
                self.seconds[k] += time.perf_counter() - t0
                return
            self.seconds[k] += time.perf_counter() - t0
            yield item


def _digests(directory: Path) -> dict[str, str]:
    """Every file under ``directory`` (relative path) -> its bytes' SHA-256."""
    return {
        str(p.relative_to(directory)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(directory.rglob("*"))
        if p.is_file()
    }


def _differences(got: dict[str, str], want: dict[str, str]) -> list[str]:
    missing = [f"{n} missing" for n in want if n not in got]
    extra = [f"{n} extra" for n in got if n not in want]
    differ = [f"{n} differs" for n in want if n in got and got[n] != want[n]]
    return missing + extra + differ


def _fuse_run(planned: list[Any], runner: Any, run_dir: Path) -> tuple[float, int]:
    """The planned job written under ``run_dir`` by ``runner``: (seconds, pictures)."""
    from trifuse.app.recording.jobs import run_fuse_job

    outputs = [dataclasses.replace(o, out_dir=run_dir / o.recording.stem) for o in planned]
    for o in outputs:
        o.out_dir.mkdir(parents=True)
    t0 = time.perf_counter()
    results = run_fuse_job(outputs, _settings(), 1, runner)
    return time.perf_counter() - t0, sum(r.frames for r in results)


def _unsplit_piece_s(recording: Path, threads: int | None = None) -> tuple[float, int]:
    """One piece of the whole recording (``--chunk-s 0``) fused here, results discarded,
    OpenCV on ``threads`` threads (None: as it is): (seconds, pictures)."""
    import cv2

    from trifuse.app.recording.fuse import FusedFrame
    from trifuse.app.recording.jobs import FuseTask, fuse_task, plan_fuse_job

    settings = _settings()
    (out,) = plan_fuse_job([(recording, recording.parent)], None, settings, 1, 0.0)
    task = FuseTask(out.pieces[0], out.rig, settings, 1)
    before = cv2.getNumThreads()
    if threads is not None:
        cv2.setNumThreads(threads)
    try:
        t0 = time.perf_counter()
        pictures = sum(isinstance(item, FusedFrame) for item in fuse_task(task, lambda _n: None))
        return time.perf_counter() - t0, pictures
    finally:
        cv2.setNumThreads(before)


# -- map runs -------------------------------------------------------------------------------


@dataclasses.dataclass
class MapOutcome:
    seconds: float
    tof_frames: int
    pieces: int
    pose_source: str
    ply: bytes
    arrays: dict[str, bytes]


def _map_run(survey: Path, runner: Any) -> MapOutcome:
    """``trifuse map SURVEY --pose recording --chunk-s MAP_CHUNK_S`` by ``runner``."""
    from trifuse.app.recording.jobs import run_map_job
    from trifuse.app.recording.map3d import MAX_IMAGE_AGE_S, open_recordings
    from trifuse.app.recording.pieces import plan_map
    from trifuse.app.storage.map_file import ply_bytes
    from trifuse.fusion.geometry import tof_sensor_name
    from trifuse.fusion.voxel_map import MapSettings

    sources, rig = open_recordings([survey], None)
    try:
        pieces = plan_map(sources, tof_sensor_name(rig), MAP_CHUNK_S, MAX_IMAGE_AGE_S, False)
        t0 = time.perf_counter()
        run = run_map_job(
            sources, rig, MapSettings(voxel_m=MAP_VOXEL_M), "recording", MAP_CHUNK_S, runner
        )
        seconds = time.perf_counter() - t0
    finally:
        for src in sources:
            src.close()
    arrays = {k: f"{a.dtype}{a.shape}".encode() + a.tobytes() for k, a in run.map.arrays().items()}
    return MapOutcome(
        seconds, run.integrated, len(pieces), run.pose_source, ply_bytes(run.map), arrays
    )


# -- the benchmark --------------------------------------------------------------------------


@benchmark(
    "ray",
    "offline jobs (issue 22) on 2 full-resolution recordings: fusion frame sets/s with "
    "LocalRunner vs a local Ray instance of 1 and 2 CPUs (outputs compared), Ray start-up "
    "and per-task overheads, each node's ms per frame set, the map job's TOF frames/s",
    baselines=(
        ("ray1_sets_per_s", "local_sets_per_s"),
        ("ray2_sets_per_s", "local_sets_per_s"),
        ("map_ray2_tof_per_s", "map_local_tof_per_s"),
    ),
    default_repeat=3,
)
def ray_jobs(repeat: int) -> dict[str, float]:
    """Figures (medians over ``repeat`` runs of each runner, the runners' order alternating;
    see the module docstring):

    - ``<runner>_sets_per_s``, ``<runner>_s``: pictures written per wall second, and the
      job's wall time, for ``local``, ``ray1`` (a local Ray instance of 1 CPU) and ``ray2``
      (2 CPUs); ``fuse_identical``: 1 if every run wrote the same files with the same
      bytes as the first, else 0; ``pictures``, ``pieces``, ``warmup_sets``: per run;
    - ``ray<n>_init_s``: ``ray.init`` (in :class:`RayRunner`); ``ray<n>_workers_s``: its
      workers' first tasks (each imports the jobs' modules); ``ray_shutdown_s``;
    - ``empty_task_ms``: an empty task's round trip (median of :data:`EMPTY_TASKS` per
      instance); ``progress_actor_ms``: the start of the actor every Ray job makes;
      ``ray1_minus_local_per_piece_ms``: (ray1 time - local time) / pieces;
    - ``piece_s`` of each piece (printed): the local runs' time producing its results
      (:class:`TimedLocalRunner`), median;
    - ``per_picture_ms``: (unsplit piece's time - the first piece's time) / (their
      pictures' difference), both from the recording's start without warm-up, fused here;
      ``unsplit_per_picture_ms``: the unsplit piece's time / its pictures, with OpenCV's
      threads here (``opencv_threads``) and on one (``unsplit_1thread_per_picture_ms``, as
      in a Ray task); ``piece_open_ms``: the first piece's time - its pictures x per
      picture (open, no seek, no warm-up); ``piece_fixed_ms``: median over the other
      pieces of their time - their pictures x per picture (open, seek, warm-up replay);
      ``warmup_set_ms``: median of (that - ``piece_open_ms``) / warm-up sets;
    - ``node_*_ms``: ms per frame set of each node (:func:`_node_breakdown`);
    - ``map_<runner>_tof_per_s``: TOF frames added per second by the map job locally and
      on 2 CPUs; ``map_identical``: 1 if every run's PLY and map arrays are the same bytes.
    """
    check_repeat(repeat)
    import cv2

    from trifuse.app.recording.jobs import import_ray, plan_fuse_job

    try:
        import_ray()
    except ImportError as exc:
        raise RuntimeError(str(exc)) from None

    with tempfile.TemporaryDirectory(prefix="trifuse-bench-ray-") as tmp_name:
        tmp = Path(tmp_name)
        _say(
            f"recording {len(SEEDS)} x {RECORDING_S:g} s of the inspection room and "
            f"{SURVEY_S:g} s of the survey (full resolution, side by side) ..."
        )
        recordings, survey, record_s = _record_all(tmp)
        sizes = sum(p.stat().st_size for p in [*recordings, survey]) / 1e6
        _say(f"  {record_s:.1f} s, {sizes:.0f} MB")
        planned = plan_fuse_job(
            [(p, tmp / "unused") for p in recordings], None, _settings(), 1, CHUNK_S
        )
        pieces = [p for o in planned for p in o.pieces]
        warm_sets = sum(p.start_set - p.first_set for p in pieces)
        threads = cv2.getNumThreads()
        _say(
            f"fusion: {len(pieces)} pieces ({', '.join(str(len(o.pieces)) for o in planned)} "
            f"per recording, --chunk-s {CHUNK_S:g}), {warm_sets} warm-up sets replayed; "
            f"OpenCV threads here: {threads} (in Ray tasks: 1)"
        )

        times: dict[str, list[float]] = {r: [] for r in RUNNERS}
        starts: dict[str, list[tuple[float, float]]] = {r: [] for r in CPUS}
        shutdowns: list[float] = []
        trips: list[float] = []
        actors: list[float] = []
        piece_s: list[list[float]] = []
        unsplit: list[tuple[float, int]] = []
        maps: dict[str, list[MapOutcome]] = {"local": [], "ray2": []}
        reference: dict[str, str] | None = None
        mismatches: list[str] = []
        pictures = 0
        runs = 0
        for r in range(repeat):
            order = RUNNERS if r % 2 == 0 else RUNNERS[::-1]
            for name in order:
                run_dir = tmp / f"run{r}-{name}"
                if name == "local":
                    runner = TimedLocalRunner()
                    seconds, pictures = _fuse_run(planned, runner, run_dir)
                    piece_s.append(runner.seconds)
                    unsplit.append(_unsplit_piece_s(recordings[0]))
                    maps["local"].append(_map_run(survey, runner.inner))
                    extra = ""
                else:
                    inst = start_ray(CPUS[name])
                    try:
                        starts[name].append((inst.init_s, inst.workers_s))
                        label = LABELS[name]
                        with ray_step(f"empty tasks on {label}", inst.logs):
                            t, a = task_overheads(inst.runner.ray)
                        trips += t
                        actors.append(a)
                        with ray_step(f"the fusion job on {label}", inst.logs):
                            seconds, pictures = _fuse_run(planned, inst.runner, run_dir)
                        if name == "ray2":
                            with ray_step(f"the map job on {label}", inst.logs):
                                maps["ray2"].append(_map_run(survey, inst.runner))
                    finally:
                        t0 = time.perf_counter()
                        inst.runner.close()
                        shutdowns.append(time.perf_counter() - t0)
                    extra = (
                        f" (start: ray.init {inst.init_s:.2f} s + {inst.workers} workers "
                        f"{inst.workers_s:.2f} s, not counted)"
                    )
                times[name].append(seconds)
                runs += 1
                got = _digests(run_dir)
                if reference is None:
                    reference = got
                else:
                    mismatches += [f"run {r + 1} {name}: {d}" for d in _differences(got, reference)]
                    shutil.rmtree(run_dir)
                _say(
                    f"  run {r + 1}/{repeat} {LABELS[name]}: {pictures} pictures in "
                    f"{seconds:.2f} s = {pictures / seconds:.2f} sets/s{extra}"
                )

        _say("per-node breakdown (OpenCV on 1 thread) ...")
        nodes = node_breakdown(recordings[0], repeat, tmp, _settings())
        one_thread = _unsplit_piece_s(recordings[0], 1)

    fig: dict[str, float] = {}
    for name in RUNNERS:
        med = statistics.median(times[name])
        fig[f"{name}_sets_per_s"] = pictures / med
        fig[f"{name}_s"] = med
    fig["fuse_identical"] = float(not mismatches)
    fig["opencv_threads"] = float(threads)
    fig["pictures"] = float(pictures)
    fig["pieces"] = float(len(pieces))
    fig["warmup_sets"] = float(warm_sets)
    for name in CPUS:
        fig[f"{name}_init_s"] = statistics.median(s[0] for s in starts[name])
        fig[f"{name}_workers_s"] = statistics.median(s[1] for s in starts[name])
    fig["ray_shutdown_s"] = statistics.median(shutdowns)
    fig["empty_task_ms"] = statistics.median(trips)
    fig["progress_actor_ms"] = statistics.median(actors)
    fig["ray1_minus_local_per_piece_ms"] = (fig["ray1_s"] - fig["local_s"]) / len(pieces) * 1e3

    # a piece's fixed cost: its time minus its pictures x the time per picture
    per_piece = [statistics.median(s[k] for s in piece_s) for k in range(len(pieces))]
    unsplit_s = statistics.median(u[0] for u in unsplit)
    unsplit_n = unsplit[0][1]
    first = planned[0].pieces[0]
    first_n = first.expected or 0
    per_picture = (unsplit_s - per_piece[0]) / (unsplit_n - first_n)
    fixed = [t - (p.expected or 0) * per_picture for t, p in zip(per_piece, pieces, strict=True)]
    opening = fixed[0]
    warm = [
        (f, p.start_set - p.first_set)
        for f, p in zip(fixed, pieces, strict=True)
        if p.start_set > p.first_set
    ]
    fig["per_picture_ms"] = per_picture * 1e3
    fig["unsplit_per_picture_ms"] = unsplit_s / unsplit_n * 1e3
    fig["unsplit_1thread_per_picture_ms"] = one_thread[0] / one_thread[1] * 1e3
    fig["piece_open_ms"] = opening * 1e3
    fig["piece_fixed_ms"] = statistics.median(f for f, _ in warm) * 1e3 if warm else 0.0
    fig["warmup_set_ms"] = (
        statistics.median((f - opening) / n for f, n in warm) * 1e3 if warm else 0.0
    )
    fig.update(nodes)
    node_names = [k for k in nodes if k.startswith("node_")]
    fig["node_sum_ms"] = sum(nodes[k] for k in node_names)

    map_ok = True
    ref_map = maps["local"][0]
    for outcome in maps["local"][1:] + maps["ray2"]:
        map_ok &= outcome.ply == ref_map.ply and outcome.arrays == ref_map.arrays
    for name in maps:
        fig[f"map_{name}_tof_per_s"] = ref_map.tof_frames / statistics.median(
            o.seconds for o in maps[name]
        )
    fig["map_identical"] = float(map_ok)
    fig["map_tof_frames"] = float(ref_map.tof_frames)

    _say()
    _say(_table(fig, times, starts, pieces, per_piece, fixed, planned, maps, runs, mismatches))
    return fig


def _table(
    fig: dict[str, float],
    times: dict[str, list[float]],
    starts: dict[str, list[tuple[float, float]]],
    pieces: list[Any],
    per_piece: list[float],
    fixed: list[float],
    planned: list[Any],
    maps: dict[str, list[MapOutcome]],
    runs: int,
    mismatches: list[str],
) -> str:
    """The report for people."""
    n = int(fig["pictures"])
    lines = [
        f"1. fusion throughput: {n} pictures from {len(planned)} recordings, "
        f"{len(pieces)} pieces, {int(fig['warmup_sets'])} warm-up sets (medians)",
        f"   {'runner':<20} {'sets/s':>7} {'x local':>8} {'job s':>6}   runs (s)"
        f"{'':<17}start-up, not counted",
    ]
    for name in RUNNERS:
        start = ""
        if name in starts:
            start = (
                f"ray.init {fig[f'{name}_init_s']:.2f} s + workers {fig[f'{name}_workers_s']:.2f} s"
            )
        ratio = fig[f"{name}_sets_per_s"] / fig["local_sets_per_s"]
        each = " ".join(f"{t:.2f}" for t in times[name])
        lines.append(
            f"   {LABELS[name]:<20} {fig[f'{name}_sets_per_s']:>7.2f} {ratio:>8.2f} "
            f"{fig[f'{name}_s']:>6.2f}   {each:<24}{start}".rstrip()
        )
    lines += (
        f"   ray1/local = {fig['ray1_sets_per_s'] / fig['local_sets_per_s']:.2f}, "
        f"ray2/local = {fig['ray2_sets_per_s'] / fig['local_sets_per_s']:.2f}; "
        f"Ray shutdown {fig['ray_shutdown_s']:.2f} s",
        f"   for reference, one piece per recording (--chunk-s 0), here, not written: "
        f"{1e3 / fig['unsplit_per_picture_ms']:.2f} sets/s (the split adds "
        f"{int(fig['warmup_sets'])} warm-up sets to {n} pictures)",
    )
    if mismatches:
        lines.append(f"   outputs: NOT identical: {len(mismatches)} differences, e.g.")
        lines += [f"     {m}" for m in mismatches[:10]]
    else:
        lines.append(
            f"   outputs: identical, every file byte for byte, in all {runs} runs "
            "(JPEGs, frames.csv, fused.mp4)"
        )
    lines += [
        "",
        "2. overheads",
        f"   empty Ray task round trip      {fig['empty_task_ms']:8.2f} ms (median of "
        f"{EMPTY_TASKS} per instance)",
        f"   progress actor, once per runner   {fig['progress_actor_ms']:8.1f} ms (a new process)",
        f"   (ray1 - local) per piece       {fig['ray1_minus_local_per_piece_ms']:8.1f} ms "
        "(Ray's cost per piece plus OpenCV on 1 thread instead of "
        f"{int(fig['opencv_threads'])})",
        f"   unsplit piece per picture      {fig['unsplit_per_picture_ms']:8.1f} ms with OpenCV "
        f"on {int(fig['opencv_threads'])} threads, "
        f"{fig['unsplit_1thread_per_picture_ms']:.1f} ms on 1 (as in a Ray task)",
        f"   per picture                    {fig['per_picture_ms']:8.1f} ms = (unsplit piece "
        f"- piece 0) / (their pictures' difference), local",
        f"   piece without warm-up (open)   {fig['piece_open_ms']:8.1f} ms = piece 0's time "
        "- its pictures x per picture",
        f"   piece with warm-up (median)    {fig['piece_fixed_ms']:8.1f} ms = open + seek + "
        "warm-up replay",
        f"   per warm-up set                {fig['warmup_set_ms']:8.1f} ms = (fixed - open) / "
        "warm-up sets",
        f"   {'piece':<14} {'warm-up sets':>12} {'pictures':>9} {'time s':>7} {'fixed s':>8}",
    ]
    k = 0
    for o in planned:
        for p in o.pieces:
            lines.append(
                f"   {o.recording.stem + ' ' + str(p.number):<14} "
                f"{p.start_set - p.first_set:>12} {p.expected or 0:>9} {per_piece[k]:>7.2f} "
                f"{fixed[k]:>8.2f}"
            )
            k += 1
    rows = [
        ("MCAP read + decompress", "node_read_ms"),
        ("decode colour JPEG x2", "node_decode_colour_ms"),
        ("decode thermal + TOF", "node_decode_thermal_tof_ms"),
        (f"TOF mapping update x{fig['tof_per_set']:.2f}", "node_tof_update_ms"),
        ("compose (radiometry+fusion)", "node_compose_ms"),
        ("JPEG encode", "node_jpeg_ms"),
        ("video write (mp4v)", "node_video_ms"),
        ("file write (driver)", "node_file_write_ms"),
        ("sum", "node_sum_ms"),
    ]
    lines += [
        "",
        "3. per frame set, by node (OpenCV on 1 thread; medians)",
        f"   {'node':<30} {'ms/set':>7} {'sets/s, 1 core':>15}",
    ]
    for label, key in rows:
        lines.append(f"   {label:<30} {fig[key]:>7.2f} {1e3 / fig[key]:>15.1f}")
    lines += [
        f"   (replay as a piece reads it: {fig['replay_ms']:.2f} ms/set = read + decode + "
        f"grouping; {fig['messages_per_set']:.1f} messages/set; measured per picture in the "
        f"job: {fig['per_picture_ms']:.2f} ms)",
        "",
        f"4. map job: {int(fig['map_tof_frames'])} TOF frames of the survey, poses from the "
        f"recording, {maps['local'][0].pieces} pieces (--chunk-s {MAP_CHUNK_S:g}), "
        f"{MAP_VOXEL_M:g} m voxels",
    ]
    for name in maps:
        each = " ".join(f"{o.seconds:.2f}" for o in maps[name])
        lines.append(
            f"   {LABELS[name]:<20} {fig[f'map_{name}_tof_per_s']:>7.1f} TOF frames/s   "
            f"runs (s) {each}"
        )
    same = "identical" if fig["map_identical"] else "NOT identical"
    lines.append(
        f"   ray2/local = {fig['map_ray2_tof_per_s'] / fig['map_local_tof_per_s']:.2f}; "
        f"PLY and map arrays: {same} in all runs (pose source: {maps['local'][0].pose_source})"
    )
    return "\n".join(lines)
