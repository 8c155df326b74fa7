"""The scan archive: finished scans kept in the daemon's state directory, bounded.

Layout: ``<root>/<job>/`` holds ``merged.ply`` (the merged cloud), ``report.json`` (the job
report) and ``manifest.json`` (job, creation time, file sizes). A job appears complete or not at
all: it is written into a hidden temporary folder, fsynced and renamed into place. After each
addition the oldest jobs go until at most ``keep`` jobs and ``max_bytes`` remain (the newest is
always kept). Job names are zenoh-key safe (``[A-Za-z0-9_.-]``), so a job is served as
``<prefix>/scans/<job>`` (:mod:`wristscan.daemon.cloud.scans`).

Its folder comes from ``[archive]`` (:mod:`wristscan.daemon.config.archive`).
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from wristscan.daemon.io.atomic import fsync_dir, process_umask

__all__ = [
    "ARCHIVED_FILES",
    "ArchiveError",
    "ScanArchive",
    "check_name",
    "job_name",
]

log = logging.getLogger(__name__)

ARCHIVED_FILES = ("merged.ply", "report.json")
"""What a finished scan leaves in the archive (the merged cloud and its job report)."""
_JOB = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")


class ArchiveError(ValueError):
    """A job or file name the archive does not hold (or could not hold)."""


def job_name(plan_name: str, when_s: float | None = None) -> str:
    """``<UTC time>-<plan name>``, key-safe: sorts by time, says what was scanned."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(time.time() if when_s is None else when_s))
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", plan_name).strip("._-")[:80] or "scan"
    return f"{stamp}-{safe}"


class ScanArchive:
    """The jobs under ``root``; see the module doc."""

    def __init__(self, root: Path, keep: int = 100, max_bytes: int = 2 * 1024**3) -> None:
        if keep < 1 or max_bytes < 1:
            raise ValueError("an archive keeps at least one job and one byte")
        self.root = Path(root)
        self.keep = keep
        self.max_bytes = max_bytes

    def add(self, job: str, files: dict[str, Path], info: dict[str, Any] | None = None) -> Path:
        """Copy ``files`` (archive name -> source path) in as ``job``; returns its folder."""
        self._check(job)
        for name in files:
            self._check(name)
        self.root.mkdir(parents=True, exist_ok=True)
        final = self.root / job
        if final.exists():
            raise ArchiveError(f"the archive already holds a job {job!r}")
        tmp = Path(tempfile.mkdtemp(prefix=f".{job}.", dir=self.root))
        try:
            sizes = {}
            for name, src in files.items():
                shutil.copyfile(src, tmp / name)
                with open(tmp / name, "rb+") as f:
                    os.fsync(f.fileno())
                sizes[name] = (tmp / name).stat().st_size
            manifest = {"job": job, "created_utc": time.time(), "files": sizes, **(info or {})}
            (tmp / "manifest.json").write_text(json.dumps(manifest, indent=1), encoding="utf-8")
            os.chmod(tmp, 0o755 & ~process_umask())
            fsync_dir(tmp)
            os.rename(tmp, final)
            fsync_dir(self.root)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        self.prune()
        return final

    def jobs(self) -> list[dict[str, Any]]:
        """The manifests of the jobs held, oldest first."""
        out: list[dict[str, Any]] = []
        if not self.root.is_dir():
            return out
        for d in sorted(self.root.iterdir()):
            if d.name.startswith(".") or not d.is_dir():
                continue
            try:
                out.append(json.loads((d / "manifest.json").read_text(encoding="utf-8")))
            except (OSError, ValueError):
                log.warning("scan archive: %s has no readable manifest; skipped", d)
        return out

    def manifest(self, job: str) -> dict[str, Any]:
        self._check(job)
        try:
            doc: dict[str, Any] = json.loads((self.root / job / "manifest.json").read_text())
        except (OSError, ValueError) as exc:
            raise ArchiveError(f"no scan {job!r} in the archive") from exc
        return doc

    def read(self, job: str, name: str) -> bytes:
        """The bytes of one archived file of ``job``."""
        if name not in self.manifest(job).get("files", {}):
            raise ArchiveError(f"scan {job!r} has no file {name!r}")
        return (self.root / job / name).read_bytes()

    def prune(self) -> list[str]:
        """Remove the oldest jobs beyond ``keep`` and ``max_bytes``; returns their names."""
        held = [(j["job"], sum(int(s) for s in j.get("files", {}).values())) for j in self.jobs()]
        total = sum(size for _, size in held)
        gone = []
        while len(held) > 1 and (len(held) > self.keep or total > self.max_bytes):
            job, size = held.pop(0)
            shutil.rmtree(self.root / job, ignore_errors=True)
            total -= size
            gone.append(job)
        if gone:
            log.info("scan archive: removed %d old scan(s): %s", len(gone), ", ".join(gone))
        return gone

    @staticmethod
    def _check(name: str) -> None:
        check_name(name)


def check_name(name: str) -> None:
    """Raise :class:`ArchiveError` unless ``name`` can be a job or file of the archive."""
    if not _JOB.match(name) or ".." in name:
        raise ArchiveError(f"not a scan archive name: {name!r}")
