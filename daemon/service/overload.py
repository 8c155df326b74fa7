"""Graceful overload: admit profiles into the pairer at the rate the worker can process them.

When profiles arrive faster than the worker can pair, align and publish them, a worker that
takes everything falls further behind every tick: its latency grows without bound, the socket
buffer overflows and the kernel drops datagrams at random, uncounted by reason. Instead the
worker reads and decodes everything (cheap, and it keeps the socket drained), then admits at most
what it can process and sheds the rest as whole profiles, spread evenly over the tick's
profiles (the cloud stays uniformly sampled along the path), counted as ``overload``.

How much it can process is measured, not modelled (its cost per profile depends on its batch
sizes, on the CPU it gets, on the GIL, on a publisher that keeps it waiting): a tick processes
what it admits, so while the worker is behind and still takes everything, the profiles it
admits per second are its capacity. The trigger is the **lag**, the age of the oldest profile at
its admission: keeping up, it is one tick (10-12 ms); behind, it grows. When it exceeds
``max_lag_s`` (100 ms) at two steps running (a single late tick is a pause whose backlog goes
through whole), the admission rate is set to ``headroom`` times that capacity, and lowered by
the same factor at each step where the lag still rises; once the lag is below half of
``max_lag_s`` the rate is raised by ``increase`` every ``step_s`` (behind, the worker works in
bigger, cheaper batches than while catching up), and shedding stops when the rate is far above
the arrivals. A token bucket spreads the admitted rate over the ticks.

Shed profiles read and decoded cost the reading all the same: at twice the capacity that is
most of the worker's time (the 3-10 % of capacity docs/pipeline.md reports before this step).
So a sensor driver that can shed before reading (``ProfileSensor.set_admission``: the UDP
sensors' socket filter) is asked to let through only slightly more than the admission rate
(:class:`KernelAdmission`), and the token bucket sheds the remainder after reading; the frames
the kernel shed come back as frame-counter gaps, counted as ``overload`` too.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import NDArray

from wristscan.drivers.base import ProfileSensor
from wristscan.drivers.records import ProfileBlock

__all__ = ["KernelAdmission", "Shedder", "spread_rows", "take_rows"]

log = logging.getLogger(__name__)


def spread_rows(n_in: int, n_keep: int) -> NDArray[np.intp]:
    """``n_keep`` of ``range(n_in)`` spread evenly, in order (the first and the last kept)."""
    if n_keep >= n_in:
        return np.arange(n_in, dtype=np.intp)
    if n_keep <= 0:
        return np.zeros(0, dtype=np.intp)
    if n_keep == 1:
        return np.zeros(1, dtype=np.intp)
    return np.rint(np.linspace(0.0, n_in - 1, n_keep)).astype(np.intp)


class Shedder:
    """Lag-triggered admission at the measured throughput (see the module docstring). Times in
    ns, rates in profiles/s.

    Call :meth:`admit` once per tick with the number of profiles that arrived and the receipt
    time of the oldest of them; it returns how many go on (``spread_rows`` picks which).
    """

    def __init__(
        self,
        max_lag_s: float = 0.1,
        step_s: float = 0.1,
        headroom: float = 0.95,
        increase: float = 1.2,
        window_s: float = 1.0,
    ) -> None:
        if not (max_lag_s > 0 and step_s > 0 and 0 < headroom <= 1 < increase and window_s > 0):
            raise ValueError(
                "Shedder: max_lag_s, step_s and window_s > 0, 0 < headroom <= 1 < increase"
            )
        self.max_lag_s = max_lag_s
        self.step_s = step_s
        self.headroom = headroom
        self.increase = increase
        self.window_s = window_s
        self.limit = math.inf
        """The admission rate in force (inf: everything goes on)."""
        self.rate_in = 0.0
        """Arrival rate, smoothed over ``window_s``."""
        self.capacity = math.inf
        """What the worker processed per second, measured while it was behind taking all."""
        self.lag_s = 0.0
        self.shed = 0
        self.shedding = False
        """Whether the latest admission shed profiles."""
        self._tokens = 0.0
        self._last_ns: int | None = None
        self._step_ns = 0
        self._kept = 0
        self._arrived = 0
        self.admitted = 1.0
        """The fraction of the arrivals admitted over the last step."""
        self._lag_last = 0.0
        self._behind = 0

    def admit(
        self,
        n_in: int,
        now_ns: int,
        oldest_ns: int | None = None,
        available: int | None = None,
        period_s: float = 0.0,
    ) -> int:
        """How many of the ``n_in`` profiles that arrived since the last call go on;
        ``oldest_ns`` is the receipt (host monotonic) of the oldest of them, ``available`` how
        many of them are still there to go on (the others were shed before reading),
        ``period_s`` the caller's tick period (waiting for its tick is no lag)."""
        last, self._last_ns = self._last_ns, now_ns
        dt = 0.0 if last is None else max(0.0, (now_ns - last) * 1e-9)
        age = 0.0 if oldest_ns is None or not n_in else (now_ns - oldest_ns) * 1e-9
        self.lag_s = max(0.0, age - period_s)
        if now_ns - self._step_ns >= self.step_s * 1e9:
            self._step(now_ns)
        if math.isinf(self.limit):
            keep = n_in
        else:
            self._tokens = min(self.limit * self.step_s, self._tokens + self.limit * dt)
            keep = min(n_in, int(self._tokens))
        if available is not None:
            keep = min(keep, available)
        if math.isfinite(self.limit):
            self._tokens -= keep
        if dt > 0.0:
            self.rate_in += min(1.0, dt / self.window_s) * (n_in / dt - self.rate_in)
        self._kept += keep
        self._arrived += n_in
        self.shedding = keep < n_in
        self.shed += n_in - keep
        return keep

    def _step(self, now_ns: int) -> None:
        """Every ``step_s``: set the admission rate from the lag and the throughput."""
        wall_s = (now_ns - self._step_ns) * 1e-9
        # A tick processes what it admits: profiles admitted per second are its throughput.
        throughput = self._kept / wall_s if self._step_ns and wall_s > 0 else 0.0
        rising = self.lag_s > self._lag_last
        self.admitted = self._kept / self._arrived if self._arrived else 1.0
        self._step_ns, self._kept, self._arrived, self._lag_last = now_ns, 0, 0, self.lag_s
        # Behind at two steps running: one late tick is a pause (the worker stopped, starved
        # for a moment), whose backlog it works off in one big batch.
        self._behind = self._behind + 1 if self.lag_s > self.max_lag_s else 0
        if self._behind >= 2:
            if math.isinf(self.limit):  # taking everything: its throughput is its capacity
                self.capacity = max(1.0, throughput)
                self.limit = self.headroom * self.capacity
                self._tokens = min(self._tokens, self.limit * self.step_s)
            elif rising:  # still falling behind at that rate
                self.limit = max(1.0, self.limit * self.headroom)
        elif math.isfinite(self.limit) and self.lag_s < 0.5 * self.max_lag_s:
            # Caught up: probe upwards (behind, the worker works in bigger, cheaper batches than
            # while catching up), and stop shedding once far above the arrivals.
            self.limit *= self.increase
            if self.limit > 1.5 * self.rate_in:
                self.limit = math.inf

    @property
    def limiting(self) -> bool:
        """An admission rate is in force (shedding, or probing upwards after it)."""
        return math.isfinite(self.limit)

    def status(self) -> dict[str, float | bool | int | None]:
        """For ``stats``: shedding, the lag (s), the rates (profiles/s)."""
        return {
            "shedding": self.shedding,
            "shed": self.shed,
            "lag_s": round(self.lag_s, 4),
            "limit_per_s": None if math.isinf(self.limit) else round(self.limit, 1),
            "capacity_per_s": None if math.isinf(self.capacity) else round(self.capacity, 1),
            "rate_in_per_s": round(self.rate_in, 1),
        }


def take_rows(blocks: list[ProfileBlock], rows: NDArray[np.intp]) -> list[ProfileBlock]:
    """The profiles ``rows`` (sorted indices over the blocks' profiles in order), as blocks."""
    out: list[ProfileBlock] = []
    start = 0
    for b in blocks:
        end = start + b.n_profiles
        lo, hi = np.searchsorted(rows, [start, end])
        if hi > lo:
            out.append(b if hi - lo == b.n_profiles else b.take(rows[lo:hi] - start))
        start = end
    return out


class KernelAdmission:
    """Steers a sensor's shedding before reading from what a :class:`Shedder` admits: the
    sensor lets ``slack`` times the larger of the fraction admitted over the last step and half
    the rate in force over the arrivals through (the token bucket sheds the remainder after
    reading), everything once the shedder stops. A driver that cannot shed before reading is
    not asked again."""

    slack = 1.1
    change = 0.02
    """Relative change of the fraction below which the filter is left as it is."""

    def __init__(self, sensor: ProfileSensor, enabled: bool) -> None:
        self.sensor = sensor
        self.enabled = enabled
        self._seen = sensor.counters.shed

    @property
    def fraction(self) -> float | None:
        """The fraction in force (None: everything passes); the sensor's own (a reopened
        socket has no filter)."""
        return self.sensor.admission

    def shed_since(self) -> int:
        """Profiles the sensor shed before reading since the last call."""
        now = self.sensor.counters.shed
        n = now - self._seen if now >= self._seen else now  # counters restarted
        self._seen = now
        return n

    def steer(self, shedder: Shedder) -> None:
        """Set the sensor's admission for the shedder's rate in force and arrival rate."""
        if not self.enabled:
            return
        f: float | None = None
        if shedder.limiting and shedder.rate_in > 0:
            # What was admitted (less than the rate in force when late ticks met the bucket's
            # cap); while the filter is what limits, that is the filter's own fraction, which
            # thus grows by ``slack`` a step. Never far below the rate in force: a step that
            # admitted next to nothing must not close the filter.
            f = self.slack * max(shedder.admitted, 0.5 * shedder.limit / shedder.rate_in)
            f = None if f >= 1.0 else f
        old = self.fraction
        if (f is None and old is None) or (
            f is not None and old is not None and abs(f - old) <= self.change * old
        ):
            return
        if not self.sensor.set_admission(f) and f is not None:
            self.enabled = False
            log.info("%s cannot shed before reading: shedding after reading", self.sensor.kind)
