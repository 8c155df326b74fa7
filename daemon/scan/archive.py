"""Keep a finished scan in the cell's archive (``[archive]``, docs/plant.md).

The merged cloud and the job report go into :class:`~wristscan.daemon.io.archive.ScanArchive`
under ``<UTC time>-<plan name>``; the running daemon serves them on ``<prefix>/scans``. When the
job wrote no output folder, its outputs are written into a temporary one first. A failure to
archive (a full disk, a folder the user may not write) is logged and reported, never fails the
scan whose results are already in hand.
"""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from wristscan.calib.merge import MergeOptions, MergeResult, PassCloud
from wristscan.daemon.config import Config
from wristscan.daemon.io.archive import ARCHIVED_FILES, ScanArchive, job_name
from wristscan.daemon.scan.output import write_outputs

__all__ = ["keep_in_archive"]

log = logging.getLogger(__name__)


def keep_in_archive(
    cfg: Config,
    plan_name: str,
    files: Sequence[Path],
    clouds: Sequence[PassCloud],
    merge: MergeResult | None,
    opts: MergeOptions,
    report: dict[str, Any],
) -> Path | None:
    """Archive the job (its ``files`` when they hold the merged cloud and the report, else
    outputs written for it); returns the job's folder, or None (off, or failed: logged)."""
    if not cfg.archive.enabled:
        return None
    a = cfg.archive
    archive = ScanArchive(a.root, keep=a.keep, max_bytes=a.max_bytes)
    job = job_name(plan_name or "scan")
    passes = list(report.get("passes", []))
    info = {
        "plan": plan_name,
        "frame": report.get("frame"),
        "passes": len(passes),
        "points": sum(int(p.get("points", 0)) for p in passes),
    }
    try:
        by_name = {p.name: p for p in files}
        if all(n in by_name for n in ARCHIVED_FILES):
            folder = archive.add(job, {n: by_name[n] for n in ARCHIVED_FILES}, info)
        else:
            with tempfile.TemporaryDirectory(prefix="wristscan-archive-") as tmp:
                written = {p.name: p for p in write_outputs(Path(tmp), clouds, merge, opts, report)}
                folder = archive.add(job, {n: written[n] for n in ARCHIVED_FILES}, info)
    except (OSError, ValueError, KeyError) as exc:
        log.warning("the scan was not archived in %s: %s", a.root, exc)
        return None
    log.info("scan archived as %s", folder)
    return folder
