"""Offline jobs on a Ray cluster (issue 22): a head and two one-CPU worker nodes started
here (``ray.cluster_utils.Cluster``), two short simulated recordings fused and mapped in
pieces, the output compared byte for byte with the local run's; a worker killed in the
middle of a piece; a recording a node cannot read."""

from __future__ import annotations

import importlib
import ipaddress
import os
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import ray
from ray.cluster_utils import Cluster

from tests.support import ROOT, directory_bytes, poll_until, record_survey_archive
from trifuse.app.cli import main
from trifuse.app.procfs import child_pids
from trifuse.app.recording import jobs
from trifuse.app.recording.jobs import RayRunner, plan_fuse_job, run_fuse_job
from trifuse.fusion.compose import DisplaySettings

pytestmark = pytest.mark.slow  # a local Ray cluster: about 10 s to start, 25 s in all

CHUNK = ["--chunk-s", "1"]  # 3 pieces per 3 s recording


@pytest.fixture(scope="module")
def cluster() -> Iterator[Cluster]:
    """A head without CPUs for tasks and two worker nodes of one CPU each."""
    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 0})
    try:
        for _ in range(2):
            c.add_node(num_cpus=1)
        c.wait_for_nodes()
        ray.init(address=c.address, include_dashboard=False, log_to_driver=False)
        yield c
    finally:
        ray.shutdown()
        c.shutdown()


@pytest.fixture(scope="module")
def archive(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Two 3 s recordings of the simulated survey with the head's poses."""
    return record_survey_archive(tmp_path_factory.mktemp("archive"), (5, 6), 3.0)


@pytest.fixture(scope="module")
def local_fused(archive: list[Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The archive fused here (``trifuse fuse DIR --out OUT --chunk-s 1``)."""
    out = tmp_path_factory.mktemp("local") / "fused"
    assert main(["fuse", str(archive[0].parent), "--out", str(out), *CHUNK]) == 0
    return out


def test_fuse_and_map_on_the_cluster_write_the_local_bytes(
    cluster: Cluster,
    archive: list[Path],
    local_fused: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    capsys.readouterr()
    out = tmp_path / "fused"
    argv = ["fuse", str(archive[0].parent), "--out", str(out), *CHUNK, "--ray", cluster.address]
    assert main(argv) == 0
    printed = capsys.readouterr()
    assert f"6 pieces (1 s each; Ray at {cluster.address})" in printed.out
    total = sum(1 for _ in local_fused.rglob("*.jpg"))
    assert f"{total}/{total} frames" in printed.err  # one bar over the whole job
    got, want = directory_bytes(out), directory_bytes(local_fused)
    assert sorted(got) == sorted(want) and len(want) == total + 4  # + frames.csv, video
    assert got == want

    maps = {}
    for where in ("local", "ray"):
        ply = tmp_path / f"{where}.ply"
        extra = ["--ray", cluster.address] if where == "ray" else []
        assert main(["map", *map(str, archive), "--out", str(ply), *CHUNK, *extra]) == 0
        maps[where] = (ply.read_bytes(), ply.with_suffix(".map.npz").read_bytes())
    assert "Mapped 90 of 90 TOF frames" in capsys.readouterr().out
    assert maps["ray"] == maps["local"]


def test_a_worker_killed_in_a_piece_is_run_again_and_nothing_is_written_twice(
    cluster: Cluster,
    archive: list[Path],
    local_fused: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The second piece of the first recording kills its own worker process (SIGKILL, as
    the kernel's OOM killer would) after 5 pictures, once; Ray runs it again on a new
    worker. The driver takes each piece's results once and writes every file once (it
    never overwrites: a second write would raise), so the output is the local run's."""
    marker = tmp_path / "killed"
    victim = str(archive[0].resolve())
    fuse_task = jobs.fuse_task

    def dying(task: jobs.FuseTask, report):  # pickled by value to the workers
        first = False
        if task.piece.recording == victim and task.piece.number == 1:
            try:
                os.close(os.open(marker, os.O_CREAT | os.O_EXCL))
                first = True
            except FileExistsError:
                pass
        for n, item in enumerate(fuse_task(task, report)):
            if first and n == 5:
                os.kill(os.getpid(), signal.SIGKILL)
            yield item

    monkeypatch.setattr(jobs, "fuse_task", dying)
    workers: dict[int, set[int]] = {}
    out = tmp_path / "fused"
    dirs = [out / p.stem for p in archive]
    for d in dirs:
        d.mkdir(parents=True)
    settings = DisplaySettings()
    planned = plan_fuse_job(list(zip(archive, dirs, strict=True)), None, settings, 1, 1.0)
    seen = lambda k, _host, pid: workers.setdefault(k, set()).add(pid)  # noqa: E731
    with RayRunner(cluster.address, on_worker=seen) as runner:
        results = run_fuse_job(planned, settings, 1, runner)
    assert marker.exists()  # the worker was killed
    assert len(workers[1]) == 2  # piece 1 reported from a second worker: run again
    assert all(len(pids) == 1 for k, pids in workers.items() if k != 1)
    assert [r.frames for r in results] == [
        sum(1 for _ in (local_fused / p.stem).glob("*.jpg")) for p in archive
    ]
    assert directory_bytes(out) == directory_bytes(local_fused)


def test_a_recording_a_node_cannot_read_stops_the_job_saying_so(
    cluster: Cluster, archive: list[Path], tmp_path: Path
) -> None:
    gone = tmp_path / "gone.mcap"
    gone.write_bytes(archive[0].read_bytes())
    d = tmp_path / "out"
    d.mkdir()
    planned = plan_fuse_job([(gone, d)], None, DisplaySettings(), 1, 1.0)
    gone.unlink()  # planned here, not there where the pieces run
    with (
        RayRunner(cluster.address) as runner,
        pytest.raises(FileNotFoundError, match=r"cannot be read on .*at the same path"),
    ):
        run_fuse_job(planned, DisplaySettings(), 1, runner)
    assert list(d.iterdir()) == []  # nothing written, no video parts left


def test_a_damaged_recording_fuses_on_the_cluster_as_here(
    cluster: Cluster, archive: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A recording cut short (no index: one piece) comes back with its damage from the
    task: the same pictures and the same warning as here."""
    cut = tmp_path / "cut.mcap"
    data = archive[0].read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    printed = {}
    for where in ("local", "ray"):
        extra = ["--ray", cluster.address] if where == "ray" else []
        assert main(["fuse", str(cut), "--out", str(tmp_path / where), *extra]) == 0
        printed[where] = capsys.readouterr().err
        assert "warning: " in printed[where] and "recording damaged" in printed[where]
    warning = [line for line in printed["local"].splitlines() if "warning" in line]
    assert warning == [line for line in printed["ray"].splitlines() if "warning" in line]
    assert directory_bytes(tmp_path / "ray") == directory_bytes(tmp_path / "local")


# -- a private Ray instance listens on loopback only ------------------------------------------


def _tree(root: int) -> set[int]:
    """``root`` and every live process below it (children, their children, ...)."""
    found, todo = set(), [root]
    while todo:
        pid = todo.pop()
        found.add(pid)
        todo += [child for child in child_pids(pid) if child not in found]
    return found


def _listening(pid: int) -> set[tuple[str, int, str]]:
    """(address, port, process name) of every TCP socket the process ``pid`` listens on
    (its socket inodes in /proc; empty once it has ended)."""
    inodes = set()
    try:
        name = Path(f"/proc/{pid}/comm").read_text().strip()
        fds = list(Path(f"/proc/{pid}/fd").iterdir())
        tables = {v6: Path(f"/proc/{pid}/net/tcp{'6' if v6 else ''}").read_text() for v6 in (0, 1)}
    except OSError:  # ended meanwhile
        return set()
    for fd in fds:
        try:
            target = os.readlink(fd)
        except OSError:  # closed meanwhile
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    out = set()
    for v6, text in tables.items():
        for line in text.splitlines()[1:]:
            fields = line.split()
            if fields[3] == "0A" and fields[9] in inodes:  # 0A: LISTEN
                raw, port = fields[1].rsplit(":", 1)
                packed = bytes.fromhex(raw)
                if v6:  # four little-endian 32-bit words
                    words = [packed[i : i + 4][::-1] for i in range(0, 16, 4)]
                    address = socket.inet_ntop(socket.AF_INET6, b"".join(words))
                else:
                    address = socket.inet_ntop(socket.AF_INET, packed[::-1])
                out.add((address, int(port, 16), name))
    return out


def _loopback(address: str) -> bool:
    """127.0.0.0/8, ::1, or an IPv4 loopback address mapped into IPv6 (::ffff:127.0.0.1)."""
    ip = ipaddress.ip_address(address)
    mapped = ip.ipv4_mapped if isinstance(ip, ipaddress.IPv6Address) else None
    return ip.is_loopback or (mapped is not None and mapped.is_loopback)


def test_a_private_ray_instance_listens_on_loopback_only(
    archive: list[Path], tmp_path: Path
) -> None:
    """``trifuse fuse RECORDING --ray`` (no address) in a process of its own: every TCP
    socket that any of its processes (the driver, GCS, raylet, agents, workers) listens on
    while the job runs is on loopback, and the job fuses. (Before: the driver, GCS, raylet
    and workers listened on ``*``, every interface, and the runtime environment agent on
    the machine's address; ``ss -ltnp`` showed the same.)"""
    out, log = tmp_path / "fused", tmp_path / "stderr.txt"
    code = "import sys; from trifuse.app.cli import main; sys.exit(main(sys.argv[1:]))"
    with log.open("w") as stderr:  # (a file: a pipe nobody reads while polling can fill)
        job = subprocess.Popen(
            [sys.executable, "-c", code, "fuse", str(archive[0]), "--out", str(out), "--ray"],
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
            stderr=stderr,
        )
    seen: set[tuple[str, int, str]] = set()

    def ended() -> bool:
        for pid in _tree(job.pid):
            seen.update(_listening(pid))
        return job.poll() is not None

    try:
        poll_until(ended, 180, poll_s=0.2)
    finally:
        if job.poll() is None:  # past the deadline: SIGTERM, so that Ray is shut down
            job.terminate()
    assert job.wait(timeout=60) == 0, log.read_text()
    names = {name for _, _, name in seen}
    assert {"gcs_server", "raylet"} <= names and len(seen) >= 4, seen  # Ray ran, and was seen
    assert all(_loopback(address) for address, _, _ in seen), seen
    assert (out / "frames.csv").read_text().count("\n") > 1  # pictures were fused


def test_the_loopback_start_is_checked_and_leaves_ray_as_it_was() -> None:
    """Ray's single-node mode is on while the instance starts and put back after; an
    instance whose node took another address (a Ray that picks it otherwise) is shut down
    and refused, not used."""
    constants = importlib.import_module("ray._private.ray_constants")
    before = constants.ENABLE_RAY_CLUSTER
    calls: list[tuple] = []

    class FakeRay:
        address = "127.0.0.1"

        def init(self, **options: object) -> None:
            calls.append(("init", constants.ENABLE_RAY_CLUSTER, options))

        def nodes(self) -> list[dict[str, str]]:
            return [{"NodeManagerAddress": self.address}]

        def shutdown(self) -> None:
            calls.append(("shutdown",))

    fake = FakeRay()
    jobs._init_on_loopback(fake, num_cpus=1)
    assert calls == [("init", False, {"address": "local", "num_cpus": 1})]
    assert constants.ENABLE_RAY_CLUSTER == before
    fake.address = "192.0.2.2"
    with pytest.raises(RuntimeError, match=r"address \['192\.0\.2\.2'\], not 127\.0\.0\.1"):
        jobs._init_on_loopback(fake)
    assert calls[1:] == [("init", False, {"address": "local"}), ("shutdown",)]
    assert constants.ENABLE_RAY_CLUSTER == before
