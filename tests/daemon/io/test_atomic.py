"""The one atomic writer: all of the new content or none of it, one mode policy."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from wristscan.daemon.io.atomic import atomic_writer, write_atomic


def test_atomic_writer_removes_temp_on_error(tmp_path: Path) -> None:
    target = tmp_path / "x.npz"
    target.write_bytes(b"old")
    with pytest.raises(OSError, match="disk full"):
        with atomic_writer(target) as f:
            f.write(b"partial")
            raise OSError("disk full")
    assert os.listdir(tmp_path) == ["x.npz"]
    assert target.read_bytes() == b"old"


def test_interrupt_leaves_the_old_file(tmp_path: Path) -> None:
    target = tmp_path / "plan.json"
    write_atomic(target, "{}\n")
    with pytest.raises(KeyboardInterrupt):
        with atomic_writer(target) as f:
            f.write(b'{"half": ')
            raise KeyboardInterrupt
    assert target.read_text() == "{}\n"
    assert os.listdir(tmp_path) == ["plan.json"]


def test_text_is_utf8_and_the_path_is_returned(tmp_path: Path) -> None:
    target = tmp_path / "r.md"
    assert write_atomic(target, "tilt 0.002 \u00b0\n") == target
    assert target.read_bytes() == "tilt 0.002 \u00b0\n".encode()


def test_mode_policy_new_file_umask_replaced_file_keeps_its_mode(tmp_path: Path) -> None:
    old = os.umask(0o027)
    try:
        write_atomic(tmp_path / "a", b"1")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a").stat().st_mode) == 0o640
    os.chmod(tmp_path / "a", 0o600)
    write_atomic(tmp_path / "a", b"2")
    assert stat.S_IMODE((tmp_path / "a").stat().st_mode) == 0o600
    assert (tmp_path / "a").read_bytes() == b"2"
