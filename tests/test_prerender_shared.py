"""tests/prerender_support.py's jobs shared by pytest-xdist's workers: a job runs once in a
run, whichever worker asks first, and the others get its folder (or its failure)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from tests import prerender_support
from tests.prerender_support import _Shared


def _two_workers(base: Path, key: str) -> list[Path | BaseException]:
    """``run_here(key)`` by two workers of one run at once (threads standing for the
    processes: the claim is a file both see)."""
    results: list[Path | BaseException] = []

    def worker() -> None:
        try:
            results.append(_Shared(base).run_here(key))
        except BaseException as e:  # pytest.fail's exception is a BaseException
            results.append(e)

    threads = [threading.Thread(target=worker) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    return results


def test_a_job_runs_once_for_both_workers(tmp_path: Path, monkeypatch) -> None:
    runs: list[Path] = []

    def job(out: Path) -> None:
        runs.append(out)
        time.sleep(0.3)  # the other worker asks meanwhile
        out.mkdir()
        (out / "made").write_text("once")

    monkeypatch.setitem(prerender_support.JOBS, "fake", job)
    results = _two_workers(tmp_path, "fake")
    assert runs == [tmp_path / "fake"]
    assert results == [tmp_path / "fake"] * 2
    assert (tmp_path / "fake" / "made").read_text() == "once"
    assert _Shared(tmp_path).run_here("fake") == tmp_path / "fake"  # a later test: no rerun
    assert len(runs) == 1


def test_a_failed_job_fails_both_workers_with_its_error(tmp_path: Path, monkeypatch) -> None:
    def job(out: Path) -> None:
        time.sleep(0.3)
        raise RuntimeError("the simulator broke")

    monkeypatch.setitem(prerender_support.JOBS, "broken", job)
    results = _two_workers(tmp_path, "broken")
    assert len(results) == 2
    errors = sorted(type(r).__name__ for r in results)
    assert errors == sorted([pytest.fail.Exception.__name__, "RuntimeError"])
    failed = next(r for r in results if isinstance(r, pytest.fail.Exception))
    assert "the simulator broke" in str(failed)
