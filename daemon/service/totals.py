"""Counters that stay cumulative across reloads.

A reload that changes devices or pipeline settings replaces the :class:`Pipeline` (and with it
the pairer and its counters). The service keeps the final counters of every pipeline it stopped
and adds them to the running one's, so ``stats`` and ``status`` count from the service's start
and ``received == published + sum(dropped) + pending`` keeps holding: the profiles a stopped
pipeline still held (none after a drain, normally) are counted as dropped for ``reload``.
Counters of the devices (``sensor``, ``robot``, ``table``, ``robot_states``) are carried only
for the devices that were replaced: a device kept open keeps counting on its own.
"""

from __future__ import annotations

import logging
from collections.abc import Collection, Mapping
from typing import Any

__all__ = ["CarriedCounters", "counters_line"]

log = logging.getLogger(__name__)

_SUMMED = ("received", "published", "published_points", "published_batches", "slow_ticks")
_SUMMED_MAPS = ("dropped", "read_errors", "gc_pauses_over_20ms", "worker_cpu_s")
_DEVICE = ("sensor", "robot", "table")


def _add_map(a: Mapping[str, Any], b: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(a)
    for k, v in b.items():
        if isinstance(v, int | float) and not isinstance(v, bool):
            out[k] = out.get(k, 0) + v
    return out


class CarriedCounters:
    """The counters of the pipelines (and devices) a service has stopped, by reload."""

    def __init__(self) -> None:
        self._base: dict[str, Any] = {}
        self.pipelines = 0

    def carry(self, final: Mapping[str, Any], replaced: Collection[str] = _DEVICE) -> None:
        """Keep the final ``stats()`` of a stopped pipeline, with the counters of the devices
        in ``replaced`` (``sensor``, ``robot``, ``table``: closed with it)."""
        b = self._base
        for k in _SUMMED:
            b[k] = b.get(k, 0) + int(final.get(k, 0))
        for k in _SUMMED_MAPS:
            b[k] = _add_map(b.get(k, {}), final.get(k) or {})
        pending = int(final.get("pending", 0))
        if pending:
            b["dropped"] = _add_map(b["dropped"], {"reload": pending})
        b["state_waited_s"] = b.get("state_waited_s", 0.0) + float(final.get("state_waited_s", 0))
        b["tick_ms_max"] = max(b.get("tick_ms_max", 0.0), float(final.get("tick_ms_max", 0)))
        if "robot" in replaced:
            b["robot_states"] = b.get("robot_states", 0) + int(final.get("robot_states", 0))
        # The pipeline's own count (its reader's queue), whatever happens to the robot.
        b["robot_states_dropped"] = b.get("robot_states_dropped", 0) + int(
            final.get("robot_states_dropped", 0)
        )
        for k in _DEVICE:
            if k in replaced and final.get(k):
                b[k] = _add_map(b.get(k) or {}, final[k])
        self.pipelines += 1

    def snapshot(self) -> dict[str, Any]:
        """The carried counters alone (no pipeline running): nothing pending."""
        b = self._base
        out: dict[str, Any] = {k: b.get(k, 0) for k in _SUMMED}
        out.update({k: dict(b.get(k, {})) for k in _SUMMED_MAPS})
        out.update(pending=0, state_waited_s=round(b.get("state_waited_s", 0.0), 4))
        out["tick_ms_max"] = b.get("tick_ms_max", 0.0)
        for k in ("robot_states", "robot_states_dropped", *_DEVICE):
            if k in b:
                out[k] = b[k]
        return out

    def merge(self, current: Mapping[str, Any]) -> dict[str, Any]:
        """``current`` (a running pipeline's ``stats()`` or ``status()``) plus what is carried;
        keys of ``current`` that are not counters pass unchanged."""
        out = dict(current)
        b = self._base
        if not b:
            return out
        for k in _SUMMED:
            if k in out:
                out[k] = int(out[k]) + b.get(k, 0)
        for k in _SUMMED_MAPS:
            if k in out and isinstance(out[k], Mapping):
                out[k] = _add_map(out[k], b.get(k, {}))
        if "state_waited_s" in out:
            out["state_waited_s"] = round(float(out["state_waited_s"]) + b["state_waited_s"], 4)
        if "tick_ms_max" in out:
            out["tick_ms_max"] = max(float(out["tick_ms_max"]), b["tick_ms_max"])
        for k in ("robot_states", "robot_states_dropped"):
            if k in out and k in b:
                out[k] = int(out[k]) + b[k]
        for k in _DEVICE:
            if isinstance(out.get(k), Mapping) and b.get(k):
                out[k] = _add_map(out[k], b[k])
        return out


def counters_line(st: Mapping[str, Any]) -> str:
    """``received R = published P + dropped D (reason n, ...) + pending N; B batches, M points``"""
    dropped = dict(st.get("dropped") or {})
    reasons = ", ".join(f"{k} {v}" for k, v in sorted(dropped.items()))
    return (
        f"received {st.get('received', 0)} = published {st.get('published', 0)} + dropped "
        f"{sum(dropped.values())}{f' ({reasons})' if reasons else ''} + pending "
        f"{st.get('pending', 0)}; {st.get('published_batches', 0)} batches, "
        f"{st.get('published_points', 0)} points"
    )
