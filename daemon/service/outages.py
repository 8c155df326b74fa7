"""Device outages as the service sees them: a device whose link is not open, or that has
delivered nothing for ``after_s``, is out. Each outage is logged once at WARNING when it starts
and once, with its duration, when it ends; while it lasts, :meth:`OutageMonitor.degraded` names
it for systemd's STATUS and the daemon's status message ("no profiles for 3 s").

The monitor reads only the drivers' public state (``health().state`` and ``counters.received``)
from the service's main thread; the degraded texts are kept as one immutable tuple, so the
pipeline's worker may read them for its status message without a lock.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from wristscan.drivers.base import Device, LinkState

__all__ = ["RECORDS", "OutageMonitor"]

log = logging.getLogger(__name__)

RECORDS = {"sensor": "profiles", "robot": "robot states", "table": "table readings"}
"""What each device delivers, as the messages name it."""


@dataclass
class _Track:
    received: int
    last_change_ns: int
    out_since_ns: int | None = None
    reason: str = ""
    count: int = 0
    total_s: float = 0.0


def _seconds(ns: int) -> str:
    s = ns * 1e-9
    return f"{s:.0f} s" if s >= 10 else f"{s:.1f} s"


class OutageMonitor:
    """Watches the devices of one pipeline; call :meth:`check` a few times a second."""

    def __init__(self, devices: Mapping[str, Device[Any]], after_s: float = 1.0) -> None:
        now = time.monotonic_ns()
        self.devices = dict(devices)
        self.after_ns = round(after_s * 1e9)
        self._tracks = {k: _Track(d.counters.received, now) for k, d in self.devices.items()}
        self._degraded: tuple[str, ...] = ()

    def _reason(self, kind: str, d: Device[Any], now: int, t: _Track) -> str | None:
        """Why ``d`` is out now, or None when it delivers."""
        health = d.health()
        if health.state is not LinkState.OPEN:
            err = f": {health.last_error}" if health.last_error else ""
            return f"link {health.state.value}{err}"
        if now - t.last_change_ns >= self.after_ns:
            return f"no {RECORDS.get(kind, 'records')}"
        return None

    def check(self, now_ns: int | None = None) -> tuple[str, ...]:
        """Update every device's state, log outages that start or end; the degraded texts."""
        now = time.monotonic_ns() if now_ns is None else now_ns
        texts: list[str] = []
        for kind, d in self.devices.items():
            t = self._tracks[kind]
            received = d.counters.received
            if received != t.received:
                t.received, t.last_change_ns = received, now
            reason = self._reason(kind, d, now, t)
            if reason is not None and t.out_since_ns is None:
                t.out_since_ns = min(t.last_change_ns, now) if reason.startswith("no ") else now
                t.reason = reason
                t.count += 1
                log.warning("%s outage: %s for %s", kind, reason, _seconds(now - t.out_since_ns))
            elif reason is None and t.out_since_ns is not None:
                self._end(kind, t, now, "its " + RECORDS.get(kind, "records") + " flow again")
            if t.out_since_ns is not None:
                texts.append(self._text(kind, t, now))
        self._degraded = tuple(texts)
        return self._degraded

    @staticmethod
    def _text(kind: str, t: _Track, now: int) -> str:
        span = _seconds(now - (t.out_since_ns or now))
        if t.reason.startswith("no "):
            return f"{t.reason} for {span}"
        return f"{kind} {t.reason.removeprefix('link ')} for {span}"

    def _end(self, kind: str, t: _Track, now: int, why: str) -> None:
        assert t.out_since_ns is not None
        duration = (now - t.out_since_ns) * 1e-9
        t.total_s += duration
        t.out_since_ns = None
        log.warning("%s outage over after %.1f s: %s", kind, duration, why)

    def close(self, why: str) -> None:
        """End the outages still going on (``why``: a reload, the exit), logging each."""
        now = time.monotonic_ns()
        for kind, t in self._tracks.items():
            if t.out_since_ns is not None:
                self._end(kind, t, now, why)
        self._degraded = ()

    @property
    def degraded(self) -> tuple[str, ...]:
        """The outages going on at the last :meth:`check`, one text each."""
        return self._degraded

    def summary(self) -> dict[str, dict[str, float]]:
        """Per device: outages so far and their total duration (s), the current one included."""
        now = time.monotonic_ns()
        out: dict[str, dict[str, float]] = {}
        for kind, t in self._tracks.items():
            current = 0.0 if t.out_since_ns is None else (now - t.out_since_ns) * 1e-9
            out[kind] = {"count": t.count, "total_s": round(t.total_s + current, 3)}
        return out
