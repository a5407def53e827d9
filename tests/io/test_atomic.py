"""Atomic outputs: a full disk or a refused folder leaves the earlier file and no partial."""

from __future__ import annotations

import errno
import io
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from fricjax.errors import FricjaxError, OutputFault
from fricjax.io import atomic
from fricjax.io.atomic import (
    check_outputs,
    clean_stale,
    partial_path,
    write_hdf5_atomic,
    write_text_atomic,
)


def _disk_full_after(n_bytes: int):
    """A writer that stores ``n_bytes`` then fails as a full disk does."""

    def write(fh: io.BufferedWriter, data: bytes) -> None:
        fh.write(data[:n_bytes])
        fh.flush()
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    return write


def test_full_disk_keeps_the_earlier_file_and_leaves_no_partial(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    target = tmp_path / "r.h5"
    write_hdf5_atomic(target, lambda f: f.create_dataset("x", data=np.arange(3.0)))
    before = target.read_bytes()
    monkeypatch.setattr(atomic, "_write_fully", _disk_full_after(100))
    with pytest.raises(OutputFault, match=r"r\.h5: cannot write \(No space left on device\)"):
        write_hdf5_atomic(target, lambda f: f.create_dataset("x", data=np.arange(1e5)))
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.h5"]


def test_hdf5_built_in_memory_reads_back_exactly(tmp_path: Path) -> None:
    x = np.random.default_rng(0).normal(size=1000)
    path = write_hdf5_atomic(tmp_path / "a.h5", lambda f: f.create_dataset("x", data=x))
    with h5py.File(path) as f:
        assert np.array_equal(f["x"][()], x)


def test_partial_files_of_dead_processes_are_cleaned_and_live_ones_kept(tmp_path: Path) -> None:
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        capture_output=True,
        text=True,
        check=True,
    )
    stale = tmp_path / f".r.h5{atomic.PARTIAL_TAG}{int(dead.stdout)}"
    live = tmp_path / f".s.h5{atomic.PARTIAL_TAG}{os.getppid()}"
    other = tmp_path / ".notes.txt"
    for p in (stale, live, other):
        p.write_text("x")
    write_text_atomic(tmp_path / "out.md", "hello\n")
    names = {p.name for p in tmp_path.iterdir()}
    assert stale.name not in names and {live.name, other.name, "out.md"} <= names
    assert clean_stale(tmp_path) == []  # nothing dead is left


def test_partial_name_says_what_it_is(tmp_path: Path) -> None:
    assert partial_path(tmp_path / "r.h5").name == f".r.h5.fricjax-partial-{os.getpid()}"


def test_an_existing_folder_or_a_file_in_the_path_is_the_users_mistake(tmp_path: Path) -> None:
    (tmp_path / "d").mkdir()
    (tmp_path / "f").write_text("x")
    with pytest.raises(FricjaxError, match="is a folder"):
        write_text_atomic(tmp_path / "d", "x")
    with pytest.raises(FricjaxError, match="is a file, not a folder"):
        write_text_atomic(tmp_path / "f" / "out.md", "x")


def test_an_output_equal_to_an_input_is_refused_through_links(tmp_path: Path) -> None:
    rec = tmp_path / "rec.h5"
    rec.write_bytes(b"data")
    (tmp_path / "link.h5").symlink_to(rec)
    os.link(rec, tmp_path / "hard.h5")
    for out in ("rec.h5", "link.h5", "hard.h5", "./sub/../rec.h5"):
        with pytest.raises(FricjaxError, match="--out would overwrite the input recording"):
            check_outputs([tmp_path / out], {"recording": rec, "--config": None}, "--out")
    check_outputs([tmp_path / "other.h5"], {"recording": rec}, "--out")  # a new file is fine
    assert rec.read_bytes() == b"data"


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_folder_is_the_machines_refusal(tmp_path: Path) -> None:
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        with pytest.raises(OutputFault, match="cannot write"):
            check_outputs([locked / "r.h5"], {}, "--out")
        with pytest.raises(OutputFault, match="cannot write"):
            write_text_atomic(locked / "r.md", "x")
    finally:
        locked.chmod(0o700)
