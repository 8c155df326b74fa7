"""Bookkeeping shared by the profile-sensor drivers (transport independent).

Every sensor driver decodes wire units into :class:`Profile` records and hands them to
:meth:`SensorCore._deliver`, which filters foreign sensor ids, books frame counters (lost,
duplicates, reordered, device restarts) and queues the profile for ``read``. Rejected input goes
through :meth:`SensorCore._reject`: counted as malformed and logged at debug level, rate-limited,
with a dump of the last raw frames.
"""

from __future__ import annotations

import logging
import time
from collections import Counter, deque
from typing import Any

from wristscan.drivers.base import ProfileSensor
from wristscan.drivers.records import Profile

__all__ = ["SensorCore"]

REORDER_WINDOW = 1024
"""A counter further than this behind the last delivered one means the device restarted (its
counters began again), not a late frame."""
RESTART_SILENCE_NS = 500_000_000
RESTART_MIN_BEHIND = 16
"""A counter more than this behind the last delivered one after ``RESTART_SILENCE_NS`` of silence
also means a restart (late datagrams arrive within milliseconds; a reboot takes longer; a sender
that repeats its last few frames after a reconnection is not a reboot)."""


class SensorCore(ProfileSensor):
    """A :class:`ProfileSensor` with a queue of decoded profiles and shared bookkeeping.

    ``sensor_id=None`` accepts any sensor; otherwise profiles of other ids are skipped and
    counted in ``health().detail["foreign"]``.
    """

    reject_log_interval_s = 1.0
    """At most one debug message about rejected input per this many seconds."""

    def __init__(self, sensor_id: int | None) -> None:
        super().__init__(0 if sensor_id is None else int(sensor_id))
        self.expected_sensor_id = None if sensor_id is None else int(sensor_id)
        self._ready: deque[Profile] = deque()
        self.stats: Counter[str] = Counter()
        """Detail counters (foreign, heartbeats, hello, restarts, ...) for ``health().detail``."""
        self._last_delivered_ns = 0
        self._next_reject_log = 0.0
        self._rejects_unlogged = 0
        # Messages go to the concrete driver's module logger.
        self._log = logging.getLogger(type(self).__module__)

    # --- delivery ---------------------------------------------------------------------------
    def _deliver(self, profile: Profile, modulo: int = 1 << 64) -> bool:
        """Queue ``profile`` unless it is foreign, a duplicate or late. True if queued."""
        if self.expected_sensor_id is not None and profile.sensor_id != self.expected_sensor_id:
            self.stats["foreign"] += 1
            return False
        counter = profile.frame_counter
        last = self._last_counter
        if last is not None:
            behind = (last - counter) % modulo
            silence = profile.host_time_ns - self._last_delivered_ns
            if 0 < behind <= modulo // 2 and (
                behind > REORDER_WINDOW
                or (behind > RESTART_MIN_BEHIND and silence > RESTART_SILENCE_NS)
            ):
                # Behind the last frame, far or after a silence: the device restarted and
                # counts from zero again.
                self._restart(f"frame counter went back from {last} to {counter}")
        if not self._account_counter(counter, modulo):
            return False
        self._last_delivered_ns = profile.host_time_ns
        if self.expected_sensor_id is None:
            self.sensor_id = profile.sensor_id
        self._ready.append(profile)
        return True

    def _restart(self, why: str) -> None:
        """Forget the counter history: the device rebooted (no loss can be counted across)."""
        self.stats["restarts"] += 1
        self._log.info("%s: device restart detected (%s)", self.kind, why)
        self._last_counter = None

    def _pop(self) -> Profile | None:
        return self._ready.popleft() if self._ready else None

    # --- rejection --------------------------------------------------------------------------
    def _reject(self, reason: str) -> None:
        """Count a malformed frame; debug log (rate-limited) with the last raw frames."""
        self.counters.malformed += 1
        now = time.monotonic()
        if now < self._next_reject_log:
            self._rejects_unlogged += 1
            return
        self._next_reject_log = now + self.reject_log_interval_s
        if self._log.isEnabledFor(logging.DEBUG):
            self._log.debug(
                "%s: frame rejected: %s (%d more since the last message); last raw frames: %s",
                self.kind,
                reason,
                self._rejects_unlogged,
                self.raw_log.dump(),
            )
        self._rejects_unlogged = 0

    def _health_detail(self) -> dict[str, Any]:
        return dict(self.stats)
