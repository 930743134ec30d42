"""Atomic output: written files and folders get the modes a plain ``open()`` or ``mkdir()`` gives under the umask."""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from pathlib import Path

import pytest

from adaptdiffuser.io import atomic_dir, atomic_path, write_json

UMASKS = [0o022, 0o077, 0o002]


@pytest.fixture(params=UMASKS, ids=[f"umask{m:03o}" for m in UMASKS])
def umask(request: pytest.FixtureRequest) -> Iterator[int]:
    """Run the test under the given umask, restoring the previous one afterwards."""
    previous = os.umask(request.param)
    try:
        yield request.param
    finally:
        os.umask(previous)


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def plain_file_mode(folder: Path) -> int:
    """The mode ``open(path, "w")`` gives a new file in ``folder`` under the current umask."""
    path = folder / "plain.txt"
    with open(path, "w") as f:
        f.write("x")
    return mode(path)


def test_atomic_file_gets_the_mode_open_gives(tmp_path: Path, umask: int) -> None:
    expected = plain_file_mode(tmp_path)
    assert expected == 0o666 & ~umask
    write_json(tmp_path / "out" / "metrics.json", {"a": 1})
    assert mode(tmp_path / "out" / "metrics.json") == expected
    with atomic_path(tmp_path / "table.bin") as tmp:
        tmp.write_bytes(b"\0" * 8)
    assert mode(tmp_path / "table.bin") == expected


def test_replacing_a_file_gives_the_mode_open_gives(tmp_path: Path, umask: int) -> None:
    path = tmp_path / "metrics.json"
    path.write_text("{}")
    path.chmod(0o600)
    write_json(path, {"a": 2})
    assert mode(path) == plain_file_mode(tmp_path)


def test_writer_that_recreates_the_temporary_file_still_gets_the_mode_open_gives(tmp_path: Path, umask: int) -> None:
    path = tmp_path / "model.zip"
    with atomic_path(path) as tmp:
        tmp.unlink()  # as a library that writes through its own private temporary file and renames it
        os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    assert mode(path) == plain_file_mode(tmp_path)


def test_atomic_folder_gets_the_mode_mkdir_gives(tmp_path: Path, umask: int) -> None:
    (tmp_path / "plain").mkdir()
    with atomic_dir(tmp_path / "checkpoint") as tmp:
        (tmp / "weights.pt").write_bytes(b"w")
    assert mode(tmp_path / "checkpoint") == mode(tmp_path / "plain") == 0o777 & ~umask
    assert mode(tmp_path / "checkpoint" / "weights.pt") == plain_file_mode(tmp_path)


def test_failed_write_leaves_the_old_file_and_no_temporary(tmp_path: Path) -> None:
    path = tmp_path / "metrics.json"
    write_json(path, {"a": 1})
    with pytest.raises(RuntimeError), atomic_path(path) as tmp:
        tmp.write_text("half")
        raise RuntimeError("killed")
    assert path.read_text() == '{\n  "a": 1\n}\n'
    assert [p.name for p in tmp_path.iterdir()] == ["metrics.json"]


def test_temporary_names_do_not_collide(tmp_path: Path) -> None:
    with atomic_path(tmp_path / "a.txt") as first, atomic_path(tmp_path / "a.txt") as second:
        assert first != second and first.name.startswith(".a.txt.") and first.suffix == ".tmp"
        first.write_text("1")
        second.write_text("2")
    assert (tmp_path / "a.txt").read_text() == "1"  # the outer one renames last
