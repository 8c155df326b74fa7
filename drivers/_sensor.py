"""Bookkeeping shared by the profile-sensor drivers (transport independent).

Every sensor driver decodes wire units into :class:`Profile` records and hands them to
:meth:`SensorCore._deliver`, which filters foreign sensor ids, books frame counters (lost,
duplicates, reordered, device restarts) and queues the profile for ``read``; a driver that
decodes many at once hands a :class:`~wristscan.drivers.records.ProfileBlock` to
:meth:`SensorCore._deliver_block`, which books it with the same counts (vectorised when its
counters simply continue, the usual case). Rejected input goes through
:meth:`SensorCore._reject`: counted as malformed and logged at debug level, rate-limited, with
a dump of the last raw frames.
"""

from __future__ import annotations

import logging
import time
from collections import Counter, deque
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import jit
from wristscan.drivers.base import ProfileSensor
from wristscan.drivers.records import Profile, ProfileBlock

__all__ = ["SensorCore"]

REORDER_WINDOW = 1024
"""A counter further than this behind the last delivered one means the device restarted (its
counters began again), not a late frame."""
RESTART_SILENCE_NS = 500_000_000
RESTART_MIN_BEHIND = 16
"""A counter more than this behind the last delivered one after ``RESTART_SILENCE_NS`` of silence
also means a restart (late datagrams arrive within milliseconds; a reboot takes longer; a sender
that repeats its last few frames after a reconnection is not a reboot)."""


_MAX_STEP = 1 << 30
"""Counter steps a block's vectorised bookkeeping takes (larger ones: profile by profile)."""
_MAX_STEP_U64 = np.uint64(_MAX_STEP)


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
        if not self._book(profile.sensor_id, profile.frame_counter, profile.host_time_ns, modulo):
            return False
        self._ready.append(profile)
        return True

    def _book(self, sensor_id: int, counter: int, host_time_ns: int, modulo: int) -> bool:
        """The frame-counter bookkeeping of one profile of this sensor (restarts, lost,
        duplicates, reordering). True if it is to be delivered."""
        last = self._last_counter
        if last is not None:
            behind = (last - counter) % modulo
            silence = host_time_ns - self._last_delivered_ns
            if 0 < behind <= modulo // 2 and (
                behind > REORDER_WINDOW
                or (behind > RESTART_MIN_BEHIND and silence > RESTART_SILENCE_NS)
            ):
                # Behind the last frame, far or after a silence: the device restarted and
                # counts from zero again.
                self._restart(f"frame counter went back from {last} to {counter}")
        if not self._account_counter(counter, modulo):
            return False
        self._last_delivered_ns = host_time_ns
        if self.expected_sensor_id is None:
            self.sensor_id = sensor_id
        return True

    def _deliver_block(self, block: ProfileBlock, modulo: int = 1 << 64) -> ProfileBlock | None:
        """:meth:`_deliver` for a block: the profiles to deliver (None if none), with the same
        counts as profile by profile. ``modulo`` is a power of two. When the counters simply
        continue from the last delivered one (the usual case) the bookkeeping is vectorised."""
        p = block.n_profiles
        if p == 0:
            return None
        ids = block.sensor_id
        own = None
        if self.expected_sensor_id is not None:
            mine = ids == self.expected_sensor_id
            if not mine.all():
                own = mine
        lost = None if own is not None else self._block_lost(block.frame_counter, modulo)
        if lost is not None:
            if lost:
                self._count_missing(lost)
            self._last_counter = int(block.frame_counter[-1]) % modulo
            self._last_delivered_ns = int(block.host_time_ns[-1])
            if self.expected_sensor_id is None:
                self.sensor_id = int(ids[-1])
            return block
        keep = np.zeros(p, dtype=bool)
        counters, stamps = block.frame_counter.tolist(), block.host_time_ns.tolist()
        for k, sid in enumerate(ids.tolist()):
            if own is not None and not own[k]:
                self.stats["foreign"] += 1
                continue
            keep[k] = self._book(sid, counters[k] % modulo, stamps[k], modulo)
        if keep.all():
            return block
        return block.take(np.flatnonzero(keep)) if keep.any() else None

    def _block_lost(self, counters: NDArray[np.int64], modulo: int) -> int | None:
        """The frames lost within a block that simply continues (each counter 1 to 2**30
        frames after the one before it, the first after the last delivered one when there is
        one); None when it does not."""
        c = counters.view(np.uint64)
        last = self._last_counter
        first = 1 if last is None else (int(c[0]) - last) % modulo
        if not 1 <= first <= _MAX_STEP:
            return None
        gaps = jit.kernel("counter_gaps")
        if gaps is not None:  # one compiled call for the numpy steps below
            missing = int(gaps(c, np.uint64(modulo - 1), _MAX_STEP_U64))
            return None if missing < 0 else first - 1 + missing
        steps = c[1:] - c[:-1]  # modulo 2**64 (arrays wrap without a warning)
        if modulo != 1 << 64:
            steps &= np.uint64(modulo - 1)
        # 1 <= step <= 2**30 in one comparison: a step of 0 wraps to the top.
        if not np.all(steps - np.uint64(1) < _MAX_STEP_U64):
            return None
        return first - 1 + int(steps.sum()) - int(steps.shape[0])

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
