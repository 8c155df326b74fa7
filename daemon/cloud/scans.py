"""A cell's scan archive on the network: ``<prefix>/scans`` (``wristscan scans``, docs/plant.md).

The daemon answers queries on

| key | reply |
|---|---|
| ``<prefix>/scans`` | JSON list of the manifests held, oldest first (a wildcard: each cell) |
| ``<prefix>/scans/<job>`` | JSON manifest of one job (files and sizes, creation time, summary) |
| ``<prefix>/scans/<job>/<file>`` | the file's bytes (``merged.ply``, ``report.json``) |

and, for a zenohd storage that replicates the plant's scans centrally, *puts* every file of a
job that appears while it runs on ``<prefix>/scans/<job>/<file>`` (and its manifest on
``<prefix>/scans/<job>``), once. The archive itself (files, retention) is any object with the
methods of :class:`wristscan.daemon.io.archive.ScanArchive`; this module only speaks zenoh.
"""

from __future__ import annotations

import json
import logging
import threading
from typing import Any, Protocol

import zenoh

__all__ = ["ArchiveSource", "ScanServer", "fetch_file", "fetch_jobs", "fetch_manifest"]

log = logging.getLogger(__name__)
_JSON = zenoh.Encoding("application/json")
_BYTES = zenoh.Encoding("application/octet-stream")


class ArchiveSource(Protocol):
    def jobs(self) -> list[dict[str, Any]]: ...

    def manifest(self, job: str) -> dict[str, Any]: ...

    def read(self, job: str, name: str) -> bytes: ...


class ScanServer:
    """The queryable (and the puts for storages) of one daemon's archive."""

    def __init__(
        self, session: zenoh.Session, prefix: str, archive: ArchiveSource, poll_s: float = 2.0
    ) -> None:
        self.session = session
        self.base = f"{prefix.rstrip('/')}/scans"
        self.archive = archive
        self._known = {j["job"] for j in archive.jobs()}
        # ``<base>/**`` also matches ``<base>`` itself (``**`` is zero or more chunks)
        self._queryables = [session.declare_queryable(f"{self.base}/**", self._on_query)]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, args=(poll_s,), name="scan-archive")
        self._thread.daemon = True
        self._thread.start()

    def _on_query(self, query: zenoh.Query) -> None:
        key = str(query.key_expr)
        rest = key[len(self.base) :].strip("/")
        parts = rest.split("/") if rest else []
        try:
            if any(c in key for c in "*$?#") or not parts:
                # a plant-wide ``wristscan/*/scans``: each cell replies its list on its own key
                query.reply(self.base, json.dumps(self.archive.jobs()), encoding=_JSON)
            elif len(parts) == 1:
                body = json.dumps(self.archive.manifest(parts[0]))
                query.reply(key, body, encoding=_JSON)
            elif len(parts) == 2:
                query.reply(key, self.archive.read(parts[0], parts[1]), encoding=_BYTES)
            else:
                raise ValueError(f"no such scan key {key!r}")
        except (ValueError, OSError) as exc:
            query.reply_err(json.dumps({"error": str(exc)}))
        except Exception as exc:  # never let an archive fault kill zenoh's thread
            log.exception("scan archive query %s failed", key)
            query.reply_err(json.dumps({"error": str(exc)}))

    def _watch(self, poll_s: float) -> None:
        while not self._stop.wait(poll_s):
            try:
                self.announce_new()
            except Exception:
                log.exception("scan archive: announcing new scans failed")

    def announce_new(self) -> list[str]:
        """Put the files of the jobs that appeared since the last look; returns their names."""
        new = [j for j in self.archive.jobs() if j["job"] not in self._known]
        for manifest in new:
            job = manifest["job"]
            for name in manifest.get("files", {}):
                self.session.put(f"{self.base}/{job}/{name}", self.archive.read(job, name))
            self.session.put(f"{self.base}/{job}", json.dumps(manifest), encoding=_JSON)
            self._known.add(job)
            log.info("scan archive: %s published on %s/%s", job, self.base, job)
        return [m["job"] for m in new]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        for q in self._queryables:
            q.undeclare()


def _get(session: zenoh.Session, key: str, timeout_s: float) -> bytes:
    for reply in session.get(key, timeout=timeout_s):
        if reply.ok is not None:
            return bytes(reply.ok.payload.to_bytes())
        if reply.err is not None:
            try:
                msg = json.loads(reply.err.payload.to_string())["error"]
            except (ValueError, KeyError, TypeError):
                msg = reply.err.payload.to_string()
            raise LookupError(str(msg))
    raise TimeoutError(f"nobody answered on {key}")


def fetch_jobs(session: zenoh.Session, prefix: str, timeout_s: float = 5.0) -> list[Any]:
    """The manifests a daemon's archive holds; ``TimeoutError`` when no daemon answers."""
    doc = json.loads(_get(session, f"{prefix.rstrip('/')}/scans", timeout_s))
    return list(doc)


def fetch_manifest(
    session: zenoh.Session, prefix: str, job: str, timeout_s: float = 5.0
) -> dict[str, Any]:
    doc: dict[str, Any] = json.loads(_get(session, f"{prefix.rstrip('/')}/scans/{job}", timeout_s))
    return doc


def fetch_file(
    session: zenoh.Session, prefix: str, job: str, name: str, timeout_s: float = 30.0
) -> bytes:
    return _get(session, f"{prefix.rstrip('/')}/scans/{job}/{name}", timeout_s)
