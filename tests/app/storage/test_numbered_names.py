"""The numbered-name series of app.storage.numbered: which names come, in which order, and
which one is the first free in a directory."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest

from trifuse.app.storage.numbered import backup_names, first_free, next_number, suffixed_names


def test_suffixed_names_start_with_the_stem_itself() -> None:
    assert list(suffixed_names("map", limit=4)) == ["map", "map-2", "map-3", "map-4"]
    assert list(suffixed_names("20261129-031500", ".mcap", 3)) == [
        "20261129-031500.mcap",
        "20261129-031500-2.mcap",
        "20261129-031500-3.mcap",
    ]
    endless = suffixed_names("v")
    assert list(itertools.islice(endless, 1000))[-1] == "v-1000"


def test_backup_names_are_gnu_cp_numbered_backups(tmp_path: Path) -> None:
    rig = tmp_path / "rig.yaml"
    got = list(itertools.islice(backup_names(rig), 3))
    assert got == [tmp_path / "rig.yaml.~1~", tmp_path / "rig.yaml.~2~", tmp_path / "rig.yaml.~3~"]


def test_first_free_skips_the_names_taken(tmp_path: Path) -> None:
    rig = tmp_path / "rig.yaml"
    assert first_free(backup_names(rig), Path.exists) == tmp_path / "rig.yaml.~1~"
    for n in (1, 2, 4):  # a gap: the first free is 3, not after the highest
        (tmp_path / f"rig.yaml.~{n}~").write_text("")
    assert first_free(backup_names(rig), Path.exists) == tmp_path / "rig.yaml.~3~"

    (tmp_path / "scan.map.npz").write_text("")
    (tmp_path / "scan-2.ply").write_text("")  # either file takes the name

    def taken(stem: str) -> bool:
        return (tmp_path / f"{stem}.map.npz").exists() or (tmp_path / f"{stem}.ply").exists()

    assert first_free(suffixed_names("scan"), taken) == "scan-3"


def test_a_finite_series_that_runs_out_raises() -> None:
    with pytest.raises(FileExistsError, match="every numbered name"):
        first_free(suffixed_names("x", limit=3), lambda name: True)


def test_next_number_is_one_more_than_the_highest() -> None:
    assert next_number([]) == 1
    assert next_number([3, 1]) == 4  # the gap at 2 is not reused
    assert next_number(iter([7])) == 8
