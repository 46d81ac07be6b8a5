"""The progress of an offline job's Ray tasks (:class:`app.recording.jobs.RayRunner`), kept
by a Ray actor. A module of its own with nothing but the standard library, so that the
actor's process starts without importing OpenCV, PyAV and the fusion."""

from __future__ import annotations


class JobTracker:
    """Each task's latest progress and the worker processes (host, pid) that ran it, by
    task number."""

    def __init__(self) -> None:
        self.done: dict[int, int] = {}
        self.workers: dict[int, list[tuple[str, int]]] = {}

    def reset(self) -> None:
        """A new job."""
        self.done.clear()
        self.workers.clear()

    def report(self, task: int, done: int, host: str, pid: int) -> None:
        self.done[task] = done
        ran = self.workers.setdefault(task, [])
        if (host, pid) not in ran:
            ran.append((host, pid))

    def snapshot(self) -> tuple[dict[int, int], dict[int, list[tuple[str, int]]]]:
        return dict(self.done), {k: list(v) for k, v in self.workers.items()}
