"""A recording's frame sets through the stereo step, as ``trifuse fuse``, ``measure`` and
``fuse --rerun`` read them: every ``every``-th set that makes a picture under the step's
policy (:data:`fusion.stereo_step.OFFLINE`: both eyes' colour and thermal frames after the
first depth)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from trifuse.app.recording.player import MessageReplay
from trifuse.app.sources.base import frame_sets
from trifuse.app.sources.frames import FrameSet
from trifuse.fusion.stereo_step import Skip, StereoStep


def pictured_sets(
    source: MessageReplay, step: StereoStep, every: int = 1
) -> Iterator[tuple[FrameSet, np.ndarray]]:
    """(frame set, its picture: the step's buffer, overwritten by the next) of every
    ``every``-th set of ``source`` (read as fast as possible, frames of another size than
    the step's rig skipped) that makes a picture; each TOF frame updates the mapping first.
    ValueError for ``every`` below 1."""
    if every < 1:
        raise ValueError(f"every: expected a positive integer, got {every}")
    source.realtime = False
    source.expect(step.rig)
    for i, fs in enumerate(frame_sets(source, step.sensors)):  # the left colour opens sets
        step.note(fs)
        step.update_depth()
        if i % every:
            continue
        inputs = step.inputs(fs)
        if not isinstance(inputs, Skip):
            yield fs, step.render(inputs)
