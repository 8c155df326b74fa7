"""The scan archive on disk: complete jobs only, bounded by count and bytes, safe names."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from wristscan.daemon.config.archive import default_archive_root
from wristscan.daemon.io.archive import ArchiveError, ScanArchive, job_name


def _files(tmp: Path, tag: str, size: int = 100) -> dict[str, Path]:
    src = tmp / f"src-{tag}"
    src.mkdir()
    (src / "merged.ply").write_bytes(tag.encode() * (size // len(tag)))
    (src / "report.json").write_text(json.dumps({"tag": tag}))
    return {"merged.ply": src / "merged.ply", "report.json": src / "report.json"}


def test_jobs_are_kept_whole_and_the_oldest_go(tmp_path: Path) -> None:
    arch = ScanArchive(tmp_path / "scans", keep=3, max_bytes=10**6)
    for k in range(5):
        arch.add(f"2026112{k}T000000Z-part", _files(tmp_path, f"j{k}"), {"points": k})
    jobs = arch.jobs()
    assert [j["job"] for j in jobs] == [f"2026112{k}T000000Z-part" for k in (2, 3, 4)]
    assert jobs[-1]["points"] == 4 and jobs[-1]["files"]["merged.ply"] == 100
    assert arch.read("20261124T000000Z-part", "merged.ply") == b"j4" * 50
    assert json.loads(arch.read("20261124T000000Z-part", "report.json")) == {"tag": "j4"}
    assert sorted(os.listdir(tmp_path / "scans")) == [j["job"] for j in jobs]  # no temp left
    with pytest.raises(ArchiveError, match="already holds"):
        arch.add("20261124T000000Z-part", _files(tmp_path, "again"))


def test_the_byte_bound_keeps_at_least_the_newest(tmp_path: Path) -> None:
    arch = ScanArchive(tmp_path / "scans", keep=100, max_bytes=200)
    arch.add("a1", _files(tmp_path, "a", 100))
    arch.add("a2", _files(tmp_path, "b", 100))
    assert [j["job"] for j in arch.jobs()] == ["a2"]  # 2 x (100 + report) > 200
    arch.add("a3", _files(tmp_path, "c", 1000))
    assert [j["job"] for j in arch.jobs()] == ["a3"]  # bigger than the bound alone: kept


def test_a_failed_copy_leaves_nothing(tmp_path: Path) -> None:
    arch = ScanArchive(tmp_path / "scans")
    files = _files(tmp_path, "x")
    files["missing.ply"] = tmp_path / "nope.ply"
    with pytest.raises(FileNotFoundError):
        arch.add("broken", files)
    assert os.listdir(tmp_path / "scans") == [] and arch.jobs() == []


@pytest.mark.parametrize("bad", ["../etc", "a/b", ".hidden", "", "x" * 200, "a*b", "a b"])
def test_names_that_cannot_be_keys_or_paths_are_refused(tmp_path: Path, bad: str) -> None:
    arch = ScanArchive(tmp_path / "scans")
    with pytest.raises(ArchiveError, match="not a scan archive name"):
        arch.manifest(bad)
    with pytest.raises(ArchiveError):
        arch.add(bad, {})


def test_job_names_sort_by_time_and_defaults(monkeypatch: pytest.MonkeyPatch) -> None:
    assert job_name("part 7 / left", 0.0) == "19700101T000000Z-part_7_left"
    assert job_name("***", 86400.0) == "19700102T000000Z-scan"
    monkeypatch.setenv("STATE_DIRECTORY", "/var/lib/wristscan")
    assert default_archive_root() == Path("/var/lib/wristscan/scans")
