"""The live cells of a plant, as a zenoh consumer sees them (``wristscan cells``).

Each daemon declares the liveliness token ``<prefix>/alive`` while it runs, answers
``<prefix>/stats`` and publishes ``<prefix>/status`` (:mod:`.zenoh_io`). With one prefix per
cell under a common root (``wristscan/<cell>``, the default), the tokens under
``<root>/**/alive`` are the list of live cells: one liveliness query through the plant's router
finds them all, one query on ``<root>/**/stats`` fetches their counters, and their next status
messages say how each is doing. Nothing here needs a registry that could go stale: a cell that
stops (or whose link drops) loses its token at once.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass
from typing import Any

import zenoh

__all__ = ["Cell", "list_cells"]


@dataclass
class Cell:
    """One live daemon: its prefix, and what it answered within the wait (None if nothing)."""

    prefix: str
    stats: dict[str, Any] | None = None
    status: dict[str, Any] | None = None

    @property
    def state(self) -> str:
        """The daemon's own word for its state (``running``, ``degraded: ...``), else ``alive``."""
        st = self.status or {}
        state = str(st.get("state", "alive"))
        degraded = st.get("degraded")
        if degraded:
            state += ": " + "; ".join(str(d) for d in degraded)
        return state


def _prefix_of(key: str, leaf: str) -> str:
    return key[: -len(leaf) - 1] if key.endswith("/" + leaf) else key


def list_cells(
    session: zenoh.Session, root: str = "wristscan", timeout_s: float = 2.0, status_s: float = 1.5
) -> list[Cell]:
    """The cells whose token is under ``<root>/**/alive``, sorted by prefix, with their stats
    (one query) and, when one arrives within ``status_s``, their latest status message."""
    root = root.rstrip("/")
    statuses: dict[str, dict[str, Any]] = {}
    lock = threading.Lock()

    def on_status(sample: zenoh.Sample) -> None:
        try:
            doc = json.loads(sample.payload.to_string())
        except (ValueError, UnicodeDecodeError):
            return
        if isinstance(doc, dict):
            with lock:
                statuses[_prefix_of(str(sample.key_expr), "status")] = doc

    started = time.monotonic()
    sub = session.declare_subscriber(f"{root}/**/status", on_status)
    try:
        cells = {
            p: Cell(p)
            for p in (
                _prefix_of(str(r.ok.key_expr), "alive")
                for r in session.liveliness().get(f"{root}/**/alive", timeout=timeout_s)
                if r.ok is not None
            )
        }
        for reply in session.get(f"{root}/**/stats", timeout=timeout_s):
            if reply.ok is not None:
                cell = cells.get(_prefix_of(str(reply.ok.key_expr), "stats"))
                if cell is not None:
                    cell.stats = json.loads(reply.ok.payload.to_string())
        while time.monotonic() - started < status_s:
            with lock:
                if all(p in statuses for p in cells):
                    break
            time.sleep(0.05)
    finally:
        sub.undeclare()
    with lock:
        for prefix, cell in cells.items():
            cell.status = statuses.get(prefix)
    return [cells[p] for p in sorted(cells)]
