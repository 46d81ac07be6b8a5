"""``GET /api/threads``: the console's Python threads and the CPU seconds each has used
(:mod:`app.server.runtime.thread_cpu`; OpenAPI at /docs). Two readings a known time apart
give each thread's share of a core: ``trifuse bench --only live`` reports them per phase."""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel, Field

from trifuse.app.server.runtime.thread_cpu import thread_cpu


class ThreadFigures(BaseModel):
    """One thread."""

    name: str = Field(description="the Python thread's name, e.g. fusion, drift-check")
    native_id: int | None = Field(description="the kernel's thread id")
    cpu_s: float | None = Field(
        description="user + system CPU seconds since the thread started (null: unknown)"
    )


def make_threads_router() -> APIRouter:
    """The router of ``GET /api/threads``."""
    router = APIRouter(prefix="/api", tags=["status"])

    @router.get("/threads")
    def threads() -> list[ThreadFigures]:
        """The console's live Python threads with the CPU time each has used so far."""
        return [ThreadFigures(**vars(t)) for t in thread_cpu()]

    return router
