"""How an offline job over recordings (``trifuse fuse``, ``trifuse map``) splits into pieces
that run anywhere: in this process, one after the other, or as Ray tasks on a cluster
(:mod:`app.recording.jobs`). The plan depends only on the recordings and the options, never
on where the pieces run, so a job gives the same bytes locally and on any cluster.

A recording is split by time ranges of ``chunk_s`` seconds, found from the MCAP message
index (the log times of one stream: :meth:`app.recording.reader.ReplaySource.log_times`;
nothing is decoded to plan). A piece is defined by positions in that stream, not by
stamps: it seeks to a log time and counts the stream's frames from there, so it knows the
number of every frame it reads whatever its stamps are. A file without a message index (one
that had to be scanned: cut short, or its summary damaged) is one piece.

* Fusion (:class:`FusePiece`): the stream is the left eye's colour frames, one frame set
  each. A piece composes the sets of its range and first replays ``warmup_s`` before it
  without writing, so that the automatic span and AGC table, smoothed over time, and the
  TOF mapping are settled when it starts. The span's remaining difference to an unsplit run
  is ``exp(-warmup / time constant)`` of its change at the warm-up's start; the AGC table,
  renormalised every frame, settles more slowly (a picture or two after a piece's start
  can differ by a grey level or two on average: ``tests/app/recording/test_jobs.py``).
* Map (:class:`MapPiece`): the stream is the TOF's distance frames. A piece adds the TOF
  frames of its range; it reads from ``2 * max_image_age`` before the first one, so that
  every TOF frame finds the same nearest thermal and colour images as in an unsplit run.
  With poses estimated from the TOF clouds (KISS-ICP), all recordings are one piece: the
  estimate runs through them in order.
"""

from __future__ import annotations

import itertools
import math
import socket
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from trifuse.app.recording.reader import ReplaySource

DEFAULT_CHUNK_S = 30.0
"""Seconds of recording per piece (``--chunk-s``)."""

MIN_WARMUP_S = 0.5
WARMUP_TIME_CONSTANTS = 4.0
"""A fusion piece replays ``max(MIN_WARMUP_S, WARMUP_TIME_CONSTANTS x span_smoothing_s)``
seconds before its range (``exp(-4)``: 2 % of the span's change is left; at least the
TOF frames and the other sensors' frames that the first sets need)."""


def warmup_s(span_smoothing_s: float) -> float:
    """The replay before a fusion piece's range, seconds (see :data:`WARMUP_TIME_CONSTANTS`)."""
    return max(MIN_WARMUP_S, WARMUP_TIME_CONSTANTS * span_smoothing_s)


@dataclass(frozen=True)
class FusePiece:
    """One piece of a fusion job: the frame sets ``[start_set, end_set)`` of one recording.

    Attributes:
        recording: the recording's absolute path.
        number: the piece's number within its recording (0, 1, ...).
        seek_ns: the log time to start reading at (None: the recording's start).
        first_set: the index of the first frame set read from there (warm-up included).
        start_set: the index of the first set this piece writes (sets before it warm up).
        end_set: one past the last set it writes (None: to the end of the recording).
        expected: pictures it considers (sets with ``index % every == 0``), None if unknown.
    """

    recording: str
    number: int
    seek_ns: int | None
    first_set: int
    start_set: int
    end_set: int | None
    expected: int | None


@dataclass(frozen=True)
class MapSpan:
    """A stretch of one recording a map piece adds.

    Attributes:
        recording: the recording's absolute path.
        seek_ns: the log time to start reading at (None: the start).
        skip_tof: TOF distance frames read from there only for context (not added).
        add_tof: TOF frames added after those (None: all to the end).
        end_ns: the log time of the last TOF frame added (None: the recording's end).
    """

    recording: str
    seek_ns: int | None
    skip_tof: int
    add_tof: int | None
    end_ns: int | None = None


@dataclass(frozen=True)
class MapPiece:
    """One piece of a map job: the spans one map builder adds in order (several only when
    poses are estimated: the estimate runs through all recordings).

    Attributes:
        spans: what to read.
        expected: TOF frames it adds, None if unknown.
    """

    spans: tuple[MapSpan, ...]
    expected: int | None


def ranges(times: np.ndarray, chunk_s: float) -> list[tuple[int, int]]:
    """Split sorted log times (ns) into ``[a, b)`` index ranges of ``chunk_s`` seconds each,
    counted from the first; ``chunk_s <= 0``: one range."""
    n = len(times)
    if n == 0 or chunk_s <= 0:
        return [(0, n)]
    span = int(times[-1] - times[0])
    chunk_ns = round(chunk_s * 1e9)
    edges = times[0] + chunk_ns * np.arange(1, span // chunk_ns + 1, dtype=np.int64)
    cuts = [0, *np.searchsorted(times, edges, side="left").tolist(), n]
    return [(a, b) for a, b in itertools.pairwise(cuts) if b > a]


def plan_fuse(
    source: ReplaySource, reference: str, chunk_s: float, warmup: float, every: int
) -> list[FusePiece]:
    """The pieces of one recording's fusion (see the module docstring); ``reference`` is the
    left eye's colour camera."""
    path = str(source.path.resolve())
    count = source.message_count(reference, "color")
    times = source.log_times(reference, "color") if chunk_s > 0 else None
    if times is None or len(times) == 0:
        expected = math.ceil(count / every) if count else None
        return [FusePiece(path, 0, None, 0, 0, None, expected)]
    pieces = []
    cuts = ranges(times, chunk_s)
    for k, (a, b) in enumerate(cuts):
        w = int(np.searchsorted(times, times[a] - round(warmup * 1e9), side="left")) if a else 0
        expected = len(range(a + (-a) % every, b, every))
        end = b if k < len(cuts) - 1 else None
        pieces.append(FusePiece(path, k, int(times[w]) if w else None, w, a, end, expected))
    return pieces


def plan_map(
    sources: Sequence[ReplaySource],
    tof: str,
    chunk_s: float,
    max_image_age_s: float,
    estimate: bool,
) -> list[MapPiece]:
    """The pieces of a map job over ``sources`` (in order; see the module docstring)."""
    counts = [src.message_count(tof, "tof_distance") for src in sources]
    if estimate:
        total = None if any(c is None for c in counts) else sum(counts)  # type: ignore[misc]
        spans = tuple(MapSpan(str(s.path.resolve()), None, 0, None) for s in sources)
        return [MapPiece(spans, total)]
    pieces = []
    margin_ns = round(2 * max_image_age_s * 1e9)
    for src, count in zip(sources, counts, strict=True):
        path = str(src.path.resolve())
        times = src.log_times(tof, "tof_distance") if chunk_s > 0 else None
        if times is None or len(times) == 0:
            pieces.append(MapPiece((MapSpan(path, None, 0, None),), count))
            continue
        cuts = ranges(times, chunk_s)
        for k, (a, b) in enumerate(cuts):
            seek = int(times[a]) - margin_ns if a else None
            first = int(np.searchsorted(times, seek, side="left")) if seek is not None else 0
            last = k == len(cuts) - 1
            span = MapSpan(
                path, seek, a - first, None if last else b - a, None if last else int(times[b - 1])
            )
            pieces.append(MapPiece((span,), b - a))
    return pieces


def open_task_recording(path: str) -> ReplaySource:
    """Open a piece's recording where the piece runs (as fast as it is read).

    Raises:
        FileNotFoundError: this machine cannot read ``path``, saying which machine: on a
            cluster every node must see the recordings at the same path.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(
            f"{path}: the recording cannot be read on {socket.gethostname()}: every machine "
            "that runs pieces must see the recordings at the same path (a shared file "
            "system, or an object store mounted there)"
        )
    return ReplaySource(p, realtime=False)
