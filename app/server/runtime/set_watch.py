"""The plumbing the console's background checks of the live frame sets share
(:mod:`app.server.runtime.registration_watch`, :mod:`app.server.runtime.drift_watch`).

A :class:`SetWatch` listens to every frame set of a
:class:`~app.server.runtime.pipeline.FusionPipeline` (``_on_set``, in the fusion thread:
it decides what to hand on) and works in its own thread (a
:class:`~app.latest_worker.LatestWorker` keeping the newest job); a job that raises is
worded (:func:`app.errors.describe_error`) in :attr:`error` and counted.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Generic, Self, TypeVar

from trifuse.app.errors import describe_error
from trifuse.app.latest_worker import LatestWorker
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.sources.frames import FrameSet

J = TypeVar("J")


class SetWatch(ABC, Generic[J]):
    """A frame-set listener of ``pipeline`` with a worker thread ``name`` running
    ``process`` on the jobs the listener submits (module docstring)."""

    def __init__(self, pipeline: FusionPipeline, name: str, process: Callable[[J], None]) -> None:
        self.pipeline = pipeline
        self.error: str | None = None
        self.error_count = 0
        self._worker: LatestWorker[J] = LatestWorker(process, name=name, on_error=self._failed)

    def _listen(self) -> None:
        """Start listening: the last step of a subclass's ``__init__``, once ``_on_set`` has
        every attribute it reads (the fusion thread may call it at once)."""
        self.pipeline.set_listeners.append(self._on_set)

    @abstractmethod
    def _on_set(self, fs: FrameSet) -> None:
        """A frame set arrived (the fusion thread)."""

    def start(self) -> Self:
        self._worker.start()
        return self

    def stop(self, timeout_s: float = 2.0) -> None:
        """No more jobs; waits up to ``timeout_s`` for one under way."""
        try:
            self.pipeline.set_listeners.remove(self._on_set)
        except ValueError:
            pass
        self._worker.stop(timeout_s)

    @property
    def busy(self) -> bool:
        """A job is waiting or under way."""
        return self._worker.busy

    def _failed(self, exc: Exception) -> None:
        self.error = describe_error(exc)
        self.error_count += 1
