"""tests/prerender_support.py's jobs shared by pytest-xdist's workers: a job runs once in a
run, whichever worker asks first, and the others get its folder (or its failure)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from tests import prerender_support
from tests.prerender_support import _Background, _Store
from tests.support import wait_until


def _two_workers(base: Path, key: str) -> list[Path | BaseException]:
    """``run_here(key)`` by two workers of one run at once (threads standing for the
    processes: the claim is a file both see)."""
    results: list[Path | BaseException] = []

    def worker() -> None:
        try:
            results.append(_Store(base).run_here(key))
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
    assert _Store(tmp_path).run_here("fake") == tmp_path / "fake"  # a later test: no rerun
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
    with pytest.raises(pytest.fail.Exception, match="the simulator broke"):
        _Store(tmp_path).run_here("broken")  # a later test: the same failure, no rerun


def test_the_background_leaves_a_claimed_job_and_runs_the_rest(tmp_path: Path) -> None:
    """The background (in a subprocess, ``nice``) skips a job another process claimed,
    and a test's wait for one it runs gets its folder."""
    store = _Store(tmp_path)
    assert store.claim("calibration-frame-sets")  # another worker has it
    background = _Background(store, ["calibration-frame-sets", "fake-never"], after=[])
    try:
        wait_until(lambda: store.ended("fake-never"), "the background's job", 120)
    finally:
        background.stop(kill=True)
    assert not store.ended("calibration-frame-sets")  # left to its claimer
    with pytest.raises(pytest.fail.Exception, match="fake-never"):  # no such job there
        store.wait("fake-never")
