"""Map a device clock (sensor, robot controller, table) onto the host monotonic clock.

Model
-----
A device stamps an event at device time ``x``; the host receives it at ``y``
(``time.monotonic_ns()``). With a device clock that runs at a constant rate relative to the host,

    y = x + a + d * x + delay,        delay >= 0,

where ``d`` is the drift (dimensionless, ``50e-6`` for 50 ppm) and ``a`` the offset. Receipt is
always after sending, so every point lies on or above the line ``x + a + d * x``: the line is the
*lower envelope* of the points (TICSync, Harrison & Newman 2011). The estimator takes, among the
lines that lie below every point of a sliding window, the one that is highest at a chosen
evaluation instant ``x_e`` (by default the middle of the window). That is a two-variable linear
programme whose optimum is the lower-convex-hull edge spanning ``x_e``; it is solved here by
bisection on the slope (the objective is concave in the slope), which needs no hull bookkeeping.
Delay spikes only ever lie *above* the envelope, so they are ignored by construction.

One-way arrivals cannot tell the offset from the smallest transport delay: the mapped time is the
host time at which the event *would have arrived with the smallest delay seen*. That constant, the
sensor's own exposure-to-timestamp latency and the robot's equivalent all end up in the configured
``latency_ns`` that :func:`wristscan.calib.latency.estimate_latency` measures.

To keep the fit cheap, points are reduced to one per ``bucket_ns`` of device time (the one lowest
above the current line): the lower envelope of a bucket is its lowest point up to ``d * bucket_ns``
(0.5 us for 50 ppm and 10 ms buckets).

A receiver short of CPU
-----------------------
A starved receiving process reads late: for a stall, nothing, then the queued records in a burst
(delays decreasing by about one record period each); under load, every record a few ms late,
for seconds; under overload, a backlog growing to a second. None of that moves the envelope, and
none of it restarts the fit: lateness alone is no evidence of a clock change. Three measures keep
the fit sound meanwhile:

* buckets that a later bucket makes irrelevant (higher by more than ``prune_margin_ns`` plus
  ``max_drift`` times their distance) are dropped, so a burst does not count as data span and
  does not pull ``x_e`` into a stretch where the envelope is undetermined (start-up backlog);
* when every arrival of a stretch reaching an end of the window is late (load longer than the
  rest of the window), the hull edges at the quartiles disagree; the slope then stays where it
  was instead of tilting towards the raised stretch;
* the fitted slope is combined with the prior drift (the previous epoch's, else 0 with
  ``typical_drift`` as its scale) by inverse-variance weights, so a short or noisy stretch
  counts for little; a locked epoch unlocks only beyond ``unlock_factor`` times the limit.

Discontinuities
---------------
Only a causality violation or a device-time discontinuity changes the fit:

* device time going back by more than ``reorder_tolerance_ns`` (a reboot, a counter reset):
  new epoch at once;
* an arrival further below a locked line than ``jump_tolerance_ns`` + 3 sigma, dropped there at
  once (by more than that below the lowest of the recent arrivals): the device clock jumped
  forward, new epoch at once;
* an arrival below a locked line by more than ``reanchor_tolerance_ns`` + 3 sigma but reached
  by steps (a backlog draining or a load ending onto a floor lower than the line): the fit had
  locked on a raised delay floor. It is *re-anchored*: refitted from there in the same epoch,
  drift and lock kept;
* device time going back by less than the reorder tolerance, the records after it continuing
  from there (not a reordered straggler), and arrivals then late by more than the jump
  tolerance for ``persist_ns``: the device clock stepped back; new epoch from those arrivals;
* device time not advancing for ``persist_ns`` of host time while records keep coming: the
  device clock stopped; new epoch.

Each restart opens a new *epoch*. Records keep the epoch they were fed in, and the last line of
an old epoch stays available, so records from before a reset are still mapped with their own
line. The drift survives a restart (same oscillator), so a new epoch locks on its offset alone
within a few tens of points.

Wrapping counters (SCIP 24-bit ms, 32-bit us, ...) are unwrapped before they reach the mapper,
by :class:`CounterUnwrapper` or :func:`unwrap`.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

logger = logging.getLogger(__name__)

__all__ = [
    "ClockConfig",
    "ClockMapper",
    "ClockUnlockedError",
    "CounterUnwrapper",
    "unwrap",
    "unwrap_nearest",
]

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]

# Slope bisection: 40 halvings of a +-1e-3 interval resolve the drift to ~2e-15, then the exact
# hull edge is taken from the two active points.
_BISECT_ITERATIONS = 40
_PRUNE_AFTER = 10
_CHECK_EVERY = 3
# A warm start brackets the previous slope by this much (2 ppm: successive fits of a window
# differ by far less; the edges at the quartiles by about that).
_WARM_HALF_WIDTH = 2e-6
# The uncertainty is the RMS of the split differences of this many recent refits.
_U_HISTORY = 16
# Recent arrivals an arrival below the line is compared with (jump or descending floor).
_RECENT = 8


class ClockUnlockedError(RuntimeError):
    """The mapper has no line for the requested epoch yet."""


@dataclass(frozen=True)
class ClockConfig:
    """Settings of one :class:`ClockMapper`; all durations in nanoseconds of device time."""

    window_ns: int = 30_000_000_000
    """Sliding window of the fit."""
    bucket_ns: int = 10_000_000
    """Points are reduced to the lowest one per bucket of this length."""
    refit_interval_ns: int = 50_000_000
    """Refit at most this often once locked (every bucket while unlocked)."""
    min_span_ns: int = 100_000_000
    """Device-time span needed before the drift is fitted from the data of an epoch."""
    min_points: int = 20
    """Points an epoch needs before it can lock."""
    min_lock_span_ns: int = 100_000_000
    """Device-time span an epoch needs before it can lock (after a reset the offset rests on
    the lowest delay seen since, which takes some arrivals to find)."""
    max_uncertainty_ns: float = 200_000.0
    """An epoch locks once the uncertainty at its newest point is below this."""
    unlock_factor: float = 10.0
    """A locked epoch unlocks only if its uncertainty exceeds this many ``max_uncertainty_ns``."""
    prune_margin_ns: int = 1_000_000
    """Buckets above a later one by more than this (plus ``max_drift`` times their distance)
    are dropped from the fit: they cannot touch the envelope (a backlog read in a burst)."""
    max_drift: float = 1e-3
    """Largest |drift| searched for (1e-3 = 1000 ppm); also the slope uncertainty before a fit."""
    typical_drift: float = 100e-6
    """Scale of a device clock's drift (crystals: tens of ppm): the prior of the first epoch's
    slope is 0 with this uncertainty, so a slope from little data is shrunk towards 0."""
    jump_tolerance_ns: int = 2_000_000
    """An arrival further below a locked line than this (plus 3 sigma) is a causality
    violation: a new epoch if it dropped there at once (clock jump), else a re-anchored fit."""
    reanchor_tolerance_ns: int = 500_000
    """An arrival further below a locked line than this (plus 3 sigma), short of a clock jump,
    means the fit locked on a raised delay floor: it is re-anchored (same epoch)."""
    persist_ns: int = 500_000_000
    """After device time went back (by less than ``reorder_tolerance_ns``), arrivals late by more
    than the jump tolerance for this long mean the device clock stepped back; device time not
    advancing for this long (host time) means it stopped. Either restarts the fit."""
    reorder_tolerance_ns: int = 50_000_000
    """Device time may go back by this much (reordered datagrams) without meaning a reset."""
    eval_fraction: float = 0.5
    """Where in the window the fitted line is tightest: 0 oldest, 1 newest point."""
    latency_ns: int = 0
    """Subtracted from every mapped time: event (exposure) to device timestamp, plus the transport
    delay floor (see the module docstring)."""
    keep_drift_on_reset: bool = True
    """Reuse the drift of the previous epoch after a restart."""
    max_epochs_kept: int = 4
    """Old epochs whose final line stays available to :meth:`ClockMapper.to_host`."""

    def __post_init__(self) -> None:
        for name in ("window_ns", "bucket_ns", "refit_interval_ns", "min_span_ns", "persist_ns"):
            if getattr(self, name) <= 0:
                raise ValueError(f"ClockConfig.{name} must be > 0")
        if not 0.0 <= self.eval_fraction <= 1.0:
            raise ValueError("ClockConfig.eval_fraction must be in [0, 1]")
        if not 0.0 < self.max_drift < 0.1:
            raise ValueError("ClockConfig.max_drift must be in (0, 0.1)")
        if not 0.0 < self.typical_drift <= self.max_drift:
            raise ValueError("ClockConfig.typical_drift must be in (0, max_drift]")
        if self.min_points < 2:
            raise ValueError("ClockConfig.min_points must be >= 2")
        if self.unlock_factor < 1.0 or self.prune_margin_ns < 0:
            raise ValueError("ClockConfig: unlock_factor must be >= 1, prune_margin_ns >= 0")


@dataclass(frozen=True, slots=True)
class _Line:
    """``host = y_ref + (x - x_ref) + a + d * (x - x_ref)``; ``x_e`` relative to ``x_ref``."""

    x_ref: int
    y_ref: int
    a: float
    d: float
    x_e: float
    u0: float
    u_slope: float
    locked: bool

    def rel(self, dx: float) -> float:
        return self.a + self.d * dx

    def uncertainty(self, dx: FloatArray) -> FloatArray:
        out: FloatArray = np.sqrt(self.u0**2 + (self.u_slope * (dx - self.x_e)) ** 2)
        return out

    def uncertainty1(self, dx: float) -> float:
        return math.hypot(self.u0, self.u_slope * (dx - self.x_e))


class ClockMapper:
    """Online offset + drift estimate of one device clock against the host monotonic clock.

    Feed every record's ``(device_ns, host_receive_ns)`` through :meth:`feed` (in arrival order);
    map with :meth:`to_host` / :meth:`to_device`. Not thread-safe: one owner feeds and maps.
    """

    def __init__(self, config: ClockConfig | None = None, name: str = "clock") -> None:
        self.config = config or ClockConfig()
        self.name = name
        cap = int(self.config.window_ns // self.config.bucket_ns) + 4
        self._cap = cap
        self._bx = np.empty(2 * cap)  # bucket minima, device time rel. x_ref (ns, float)
        self._br = np.empty(2 * cap)  # host - device rel. refs (ns, float)
        self._b0 = 0
        self._b1 = 0
        self.epoch = -1
        self.n_resets = 0
        self.n_reanchors = 0
        self.n_fed = 0
        self._old: dict[int, _Line] = {}
        # Drift kept from the previous epoch: (drift, its uncertainty, span (ns) it was fitted on).
        self._prior: tuple[float, float, float] | None = None
        self._line: _Line | None = None
        self._begin_state()

    # ------------------------------------------------------------------ state

    def _begin_state(self) -> None:
        self._n = 0  # points in this epoch
        self._x_ref = 0
        self._y_ref = 0
        self._x_last = 0
        self._x_first = 0
        self._b0 = self._b1 = 0
        self._ob = -1  # open bucket index (device time // bucket_ns)
        self._ox = 0.0
        self._or = 0.0
        self._last_fit_x = -(1 << 62)
        self._ever_locked = False
        self._fit_span = 0.0  # device-time span (ns) the current slope rests on
        # Arrivals late by more than the tolerance since device time went back (a step back?).
        self._excess: list[tuple[int, int]] = []
        self._back_from = 0  # newest device time before the first of them
        # Consecutive arrivals whose device time did not advance, and the host time of the first.
        self._stuck_n = 0
        self._stuck_y0 = 0
        self._recent: deque[tuple[int, int]] = deque(maxlen=_RECENT)
        # Recent half-differences of the split estimates: value at x_e (ns), slope.
        self._u_hist: deque[tuple[float, float]] = deque(maxlen=_U_HISTORY)

    def _keep_drift(self) -> None:
        """Remember the current line's drift for a fresh fit (same oscillator)."""
        line = self._line
        if line is None or not self._ever_locked or not self.config.keep_drift_on_reset:
            return
        self._prior = (line.d, line.u_slope, self._fit_span)

    def _start_epoch(self, x: int, y: int) -> None:
        if self._line is not None and self.epoch >= 0:
            self._old[self.epoch] = self._line
            while len(self._old) > self.config.max_epochs_kept:
                del self._old[min(self._old)]
        self._keep_drift()
        self.epoch += 1
        self._line = None
        self._begin_state()
        self._x_ref = x
        self._y_ref = y
        self._x_first = x

    def reset(self, reason: str = "requested") -> None:
        """Forget the current epoch's points (the drift is kept); the next feed opens a new
        epoch."""
        if self._n:
            logger.info("%s: clock fit restarted (%s)", self.name, reason)
            self.n_resets += 1
        self._n = 0

    # ------------------------------------------------------------------ feeding

    def feed(self, device_ns: int, host_ns: int) -> int:
        """Add one arrival; returns the epoch the record belongs to (map it with that epoch)."""
        x = int(device_ns)
        y = int(host_ns)
        self.n_fed += 1
        cfg = self.config
        if self._n == 0:
            self._start_epoch(x, y)
            self._add(x, y)
            return self.epoch
        if x < self._x_last - cfg.reorder_tolerance_ns:
            self._restart(x, y, f"device time went back by {(self._x_last - x) / 1e6:.3f} ms")
            return self.epoch
        back = x < self._x_last
        if x <= self._x_last:
            # Device time not advancing while records keep coming: the device clock stopped
            # (a stalled receiver delivers late records, but their device times still advance).
            if self._stuck_n == 0:
                self._stuck_y0 = y
            self._stuck_n += 1
            if self._stuck_n >= 5 and y - self._stuck_y0 >= cfg.persist_ns:
                self._restart(
                    x,
                    y,
                    f"device time did not advance for {(y - self._stuck_y0) / 1e9:.3f} s "
                    "(device clock stopped)",
                )
                return self.epoch
        else:
            self._stuck_n = 0
        line = self._line
        if line is not None:
            dx = float(x - self._x_ref)
            gap = float(y - self._y_ref) - dx - line.rel(dx)
            u3 = 3.0 * line.uncertainty1(dx)
            tol = cfg.jump_tolerance_ns + u3
            if gap < -(cfg.reanchor_tolerance_ns + u3) and self._ever_locked:
                # Received before it was sent, by a line that has been trusted: either the device
                # clock jumped forward, or the delay floor is lower than the line says.
                if gap < -tol and self._abrupt(line, gap, tol):
                    self._restart(
                        x,
                        y,
                        f"arrival {-gap / 1e6:.3f} ms before its send time (device clock "
                        "jumped forward)",
                    )
                    return self.epoch
                self._reanchor(x, y, gap)
                return self.epoch
            if self._excess and len(self._excess) == 1 and self._straggler(x):
                self._excess = []  # the one that went back was a reordered record
            if gap > tol and (self._excess or back):
                # Late by more than the tolerance ever since device time went back (and the
                # records after continued from there): the device clock stepped back, by less
                # than the reorder tolerance. Lateness alone is no evidence: a receiver starved
                # of CPU or under load delivers late records too.
                if not self._excess:
                    self._back_from = self._x_last
                self._excess.append((x, y))
                x0, y0 = self._excess[0]
                if len(self._excess) >= 5 and max(x - x0, y - y0) >= cfg.persist_ns:
                    pts = self._excess
                    self._restart(
                        x0,
                        y0,
                        f"device time went back and arrivals stayed late by > {tol / 1e6:.3f} ms "
                        f"for {cfg.persist_ns / 1e9:.3f} s (device clock stepped back)",
                    )
                    for px, py in pts[1:]:
                        self._add(px, py)
                    return self.epoch
            elif gap <= tol and self._excess:
                self._excess = []
        self._add(x, y)
        return self.epoch

    def feed_many(self, device_ns: ArrayLike, host_ns: ArrayLike) -> IntArray:
        """Feed arrays of arrivals in order; returns the epoch of each."""
        xs = np.asarray(device_ns, dtype=np.int64)
        ys = np.asarray(host_ns, dtype=np.int64)
        return np.fromiter(
            (self.feed(x, y) for x, y in zip(xs.tolist(), ys.tolist(), strict=True)),
            dtype=np.int64,
            count=xs.shape[0],
        )

    def _straggler(self, x: int) -> bool:
        """Whether the arrival that went back (``_excess[0]``) was a reordered record: the next
        one (device time ``x``) continues from the newest device time before it, not from it.
        The record period is the median step of the recent arrivals."""
        xs = [px for px, _ in self._recent]
        steps = [b - a for a, b in itertools.pairwise(xs) if b > a]
        period = float(np.median(steps)) if steps else 0.0
        x_back = self._excess[0][0]
        return abs(x - self._back_from - period) <= abs(x - x_back - period)

    def _abrupt(self, line: _Line, gap: float, tol: float) -> bool:
        """Whether an arrival ``gap`` below ``line`` dropped there at once: by more than ``tol``
        below the lowest of the recent arrivals. Arrivals in order can only come down by the
        device time between them, so a backlog draining or a load ending descends in steps of
        at most one record period; a clock jump drops by its size at once."""
        lowest = math.inf
        for px, py in self._recent:
            dx = float(px - self._x_ref)
            lowest = min(lowest, float(py - self._y_ref) - dx - line.rel(dx))
        return gap < lowest - tol

    def _restart(self, x: int, y: int, why: str) -> None:
        logger.warning("%s: clock fit restarted at epoch %d: %s", self.name, self.epoch + 1, why)
        self.n_resets += 1
        self._n = 0
        self._start_epoch(x, y)
        self._add(x, y)

    def _reanchor(self, x: int, y: int, gap: float) -> None:
        """The delay floor came down below a trusted line (the fit locked while every arrival
        was late, e.g. under load at start-up): refit from here in the same epoch, keeping the
        drift and the lock. Records of the epoch are then mapped with the lower line."""
        logger.info(
            "%s: delay floor %.3f ms below the line: fit re-anchored (epoch %d)",
            self.name,
            -gap / 1e6,
            self.epoch,
        )
        self.n_reanchors += 1
        self._keep_drift()
        self._b0 = self._b1 = 0
        self._ob = -1
        self._last_fit_x = -(1 << 62)
        self._excess = []
        self._u_hist.clear()
        self._add(x, y)

    def _add(self, x: int, y: int) -> None:
        cfg = self.config
        self._n += 1
        self._recent.append((x, y))
        if x > self._x_last or self._n == 1:
            self._x_last = x
        dxi = x - self._x_ref
        dx = float(dxi)
        r = float(y - self._y_ref) - dx
        b = dxi // cfg.bucket_ns
        d = self._line.d if self._line is not None else (self._prior[0] if self._prior else 0.0)
        if b == self._ob:
            if r - d * dx < self._or - d * self._ox:
                self._ox, self._or = dx, r
        elif b > self._ob:
            if self._ob >= 0:
                self._push(self._ox, self._or)
            self._ob, self._ox, self._or = b, dx, r
        # else: a reordered point of an already closed bucket; it arrived late, so it is not
        # a candidate for the lower envelope.
        interval = cfg.refit_interval_ns if self.locked else cfg.bucket_ns
        if x - self._last_fit_x >= interval or self._line is None:
            self._refit()

    def _push(self, bx: float, br: float) -> None:
        if self._b1 == self._bx.shape[0]:
            n = self._b1 - self._b0
            self._bx[:n] = self._bx[self._b0 : self._b1]
            self._br[:n] = self._br[self._b0 : self._b1]
            self._b0, self._b1 = 0, n
        self._bx[self._b1] = bx
        self._br[self._b1] = br
        self._b1 += 1
        # Slide the window (and bound the memory).
        lo = bx - self.config.window_ns
        while self._b0 < self._b1 and (self._bx[self._b0] < lo or self._b1 - self._b0 > self._cap):
            self._b0 += 1

    # ------------------------------------------------------------------ fitting

    def _prune(self) -> None:
        """Drop the stored buckets that a later bucket makes irrelevant.

        Bucket ``i`` can never touch a line of slope within ``+-max_drift`` that passes below a
        later bucket ``j`` once ``r_i >= r_j + max_drift * (x_j - x_i) + prune_margin_ns``, so
        dropping it leaves the fit unchanged. What it removes is a backlog read in a burst
        (device time advancing much faster than host time: each record lower than the one
        before), which would otherwise count towards the span of the data and pull the point
        where the line is evaluated into a stretch where the envelope is undetermined.
        """
        b0, b1 = self._b0, self._b1
        if b1 - b0 < 1 or self._ob < 0:
            return
        m = self.config.max_drift
        bx = self._bx[b0:b1]
        br = self._br[b0:b1]
        key = br + m * bx
        later = np.empty_like(key)
        later[-1] = self._or + m * self._ox
        if key.shape[0] > 1:
            later[:-1] = np.minimum.accumulate(key[:0:-1])[::-1]
            np.minimum(later[:-1], later[-1], out=later[:-1])
        keep = key < later + float(self.config.prune_margin_ns)
        if not keep.all():
            k = int(np.count_nonzero(keep))
            bx[:k] = bx[keep]
            br[:k] = br[keep]
            self._b1 = b0 + k

    def _points(self) -> tuple[FloatArray, FloatArray]:
        X = np.append(self._bx[self._b0 : self._b1], self._ox)
        R = np.append(self._br[self._b0 : self._b1], self._or)
        return X, R

    def _refit(self) -> None:
        cfg = self.config
        self._last_fit_x = self._x_last
        self._prune()
        X, R = self._points()
        n = X.shape[0]
        span = float(X.max() - X.min())
        # With a drift from the previous epoch, refit it only once this epoch has as much data
        # (up to half a window): a short baseline would give a worse slope than the old one.
        need = float(cfg.min_span_ns)
        if self._prior is not None:
            need = max(need, min(self._prior[2], 0.5 * cfg.window_ns))
        if span >= need and n >= 6:
            d, a, x_e, u0, u_slope = self._fit_slope(X, R, span)
            self._fit_span = span
        else:
            d, u_prior, self._fit_span = (
                self._prior if self._prior is not None else (0.0, cfg.typical_drift, 0.0)
            )
            G = R - d * X
            i0 = int(np.argmin(G))
            a = float(G[i0])
            x_e = float(X[i0])
            # Offset only: the estimate sharpens quickly with every point, so no smoothing. (A
            # re-anchored fit starts from one point below a line that was good: no worse.)
            if n >= 2:
                u0 = abs(0.5 * float(G[0::2].min() - G[1::2].min()))
            elif self._ever_locked and self._line is not None:
                u0 = self._line.u0
            else:
                u0 = math.inf
            u_slope = u_prior if math.isfinite(u0) else cfg.max_drift
        line = _Line(self._x_ref, self._y_ref, a, d, x_e, u0, u_slope, False)
        u_last = line.uncertainty1(float(self._x_last - self._x_ref))
        if self._ever_locked:
            # Hysteresis: a lock is not dropped for an uncertainty that wavers around the limit.
            locked = u_last <= cfg.unlock_factor * cfg.max_uncertainty_ns
        else:
            locked = (
                self._n >= cfg.min_points
                and span >= cfg.min_lock_span_ns
                and u_last <= cfg.max_uncertainty_ns
            )
        self._line = _Line(self._x_ref, self._y_ref, a, d, x_e, u0, u_slope, locked)
        if locked and not self._ever_locked:
            self._ever_locked = True
            logger.info(
                "%s: locked (epoch %d, drift %.2f ppm, uncertainty %.1f us)",
                self.name,
                self.epoch,
                d * 1e6,
                u_last / 1e3,
            )

    def _fit_slope(
        self, X: FloatArray, R: FloatArray, span: float
    ) -> tuple[float, float, float, float, float]:
        """Offset and drift from the window: ``(d, a, x_e, u0, u_slope)``."""
        cfg = self.config
        lo, hi = -cfg.max_drift, cfg.max_drift

        def clipped(v: float) -> bool:  # a slope at the end of the range: undetermined
            return abs(v) >= cfg.max_drift * (1.0 - 1e-9)

        f = cfg.eval_fraction
        x0 = float(X.min())
        x_e = x0 + f * span
        d = _support_slope(X, R, x_e, lo, hi, None if self._line is None else self._line.d)
        # Uncertainty: the same estimator on the even and on the odd buckets gives two
        # independent half-data estimates; half their difference is of the order of the full
        # estimate's error whatever the delay distribution. Windowed RMS: one split is a noisy
        # scale; old (early, poor) fits drop out.
        d1 = _support_slope(X[0::2], R[0::2], x_e, lo, hi, d)
        d2 = _support_slope(X[1::2], R[1::2], x_e, lo, hi, d)
        v1 = float((R[0::2] - d1 * X[0::2]).min()) + d1 * x_e
        v2 = float((R[1::2] - d2 * X[1::2]).min()) + d2 * x_e
        dv = 0.5 * (v1 - v2)
        dd = cfg.max_drift if clipped(d1) or clipped(d2) else 0.5 * (d1 - d2)
        self._u_hist.append((dv * dv, dd * dd))
        u0 = math.sqrt(sum(h[0] for h in self._u_hist) / len(self._u_hist))
        u_slope = math.sqrt(sum(h[1] for h in self._u_hist) / len(self._u_hist))
        # What was known before these data: the drift of the previous epoch or fit (same
        # oscillator), else 0 with the typical drift as its scale.
        if self._prior is not None:
            pd, pu = self._prior[0], self._prior[1]
        else:
            pd, pu = 0.0, cfg.typical_drift
        pu = max(pu, 0.01 * cfg.typical_drift)
        # The lower envelope is a straight line only where the delay floor is reached. When
        # every arrival of a stretch reaching one end of the window is late (sustained load
        # longer than the rest of the window), the hull edge spanning x_e tilts towards it.
        # The edges spanning the quartiles then disagree by more than the noise: the data do
        # not determine the drift, so it stays where it was (a clock's drift changes slowly).
        xq = (x0 + max(f - 0.25, 0.0) * span, x0 + min(f + 0.25, 1.0) * span)
        dq = (_support_slope(X, R, xq[0], lo, hi, d), _support_slope(X, R, xq[1], lo, hi, d))
        if abs(dq[0] - dq[1]) > max(6.0 * u_slope, 0.01 * cfg.typical_drift):
            ref = self._line.d if self._line is not None else pd
            G = R - ref * X
            i0 = int(np.argmin(G))
            u_ref = self._line.u_slope if self._line is not None else pu
            return ref, float(G[i0]), float(X[i0]), u0, u_ref
        # Combine with the prior (inverse-variance weights): a slope from a short or noisy
        # stretch then counts for little, and one at the end of the search range for nothing.
        us = cfg.max_drift if clipped(d) else u_slope
        w = pu * pu / (us * us + pu * pu)
        d = pd + w * (d - pd)
        u_slope = us * pu / math.sqrt(us * us + pu * pu)
        a = float((R - d * X).min())
        return d, a, x_e, u0, u_slope

    # ------------------------------------------------------------------ mapping

    def _get_line(self, epoch: int | None) -> _Line:
        if epoch is None or epoch == self.epoch:
            line = self._line
        else:
            line = self._old.get(epoch)
        if line is None:
            raise ClockUnlockedError(f"{self.name}: no clock line for epoch {epoch}")
        return line

    @property
    def locked(self) -> bool:
        """True once the current epoch mapped within ``max_uncertainty_ns``, and as long as it
        maps within ``unlock_factor`` times that."""
        return self._line is not None and self._line.locked and self._n > 0

    def is_locked(self, epoch: int | None = None) -> bool:
        """Whether ``epoch`` (default: the current one) can be mapped with confidence."""
        if epoch is None or epoch == self.epoch:
            return self.locked
        line = self._old.get(epoch)
        return line is not None and line.locked

    def to_host(self, device_ns: ArrayLike, epoch: int | None = None) -> IntArray:
        """Host monotonic ns of the *events* stamped ``device_ns`` (``latency_ns`` subtracted).

        ``epoch`` is the value :meth:`feed` returned for those records (default: current).
        Raises :class:`ClockUnlockedError` when that epoch has no line yet.
        """
        line = self._get_line(epoch)
        dx = np.asarray(device_ns, dtype=np.int64) - np.int64(line.x_ref)
        corr = np.rint(line.a + line.d * dx.astype(np.float64)).astype(np.int64)
        out: IntArray = dx + corr + np.int64(line.y_ref - self.config.latency_ns)
        return out

    def to_device(self, host_ns: ArrayLike, epoch: int | None = None) -> IntArray:
        """Inverse of :meth:`to_host`: device ns whose event happened at host time ``host_ns``."""
        line = self._get_line(epoch)
        h = (
            np.asarray(host_ns, dtype=np.int64)
            + np.int64(self.config.latency_ns)
            - np.int64(line.y_ref)
        ).astype(np.float64)
        dx = np.rint((h - line.a) / (1.0 + line.d)).astype(np.int64)
        out: IntArray = dx + np.int64(line.x_ref)
        return out

    def uncertainty_ns(self, device_ns: ArrayLike | None = None, epoch: int | None = None) -> Any:
        """Estimated 1-sigma error (ns) of :meth:`to_host` at ``device_ns`` (default: newest
        point), from the order statistics of the arrivals above the envelope. It is a scale, not
        a bound; ``inf`` before the epoch has two buckets."""
        line = self._get_line(epoch)
        if device_ns is None:
            return line.uncertainty1(float(self._x_last - line.x_ref))
        dx = (np.asarray(device_ns, dtype=np.int64) - np.int64(line.x_ref)).astype(np.float64)
        return line.uncertainty(dx)

    @property
    def drift(self) -> float:
        """Current drift estimate: host seconds per device second minus 1 (nan before a fit)."""
        return self._line.d if self._line is not None else math.nan

    def status(self) -> dict[str, float | int | bool | str]:
        """Health figures for the status topic."""
        line = self._line
        unc = float(self.uncertainty_ns()) if line is not None and self._n else math.inf
        span = float(self._x_last - self._x_first) / 1e9 if self._n else 0.0
        return {
            "name": self.name,
            "epoch": self.epoch,
            "locked": self.locked,
            "drift_ppm": self.drift * 1e6,
            "uncertainty_us": unc / 1e3,
            "points": self._n,
            "span_s": span,
            "resets": self.n_resets,
            "reanchors": self.n_reanchors,
        }


def _support_slope(
    X: FloatArray, R: FloatArray, x_e: float, lo: float, hi: float, guess: float | None = None
) -> float:
    """Slope of the highest line at ``x_e`` lying below all points ``(X, R)``.

    ``f(d) = min_i R_i + d (x_e - X_i)`` is concave; its supergradient at ``d`` is ``x_e - X_i*``
    of the active point, so bisection on its sign finds the maximiser: the lower-hull edge
    spanning ``x_e``. Slopes outside ``[lo, hi]`` are clipped to the range. ``guess``: a slope
    near the answer (the previous fit's); when ``guess +- _WARM_HALF_WIDTH`` brackets the
    answer, the search starts there with the points pruned at once (same edge, a third of the
    passes over the whole window).
    """
    span = float(X.max() - X.min())
    pruned = False
    if guess is not None:
        a, b = max(lo, guess - _WARM_HALF_WIDTH), min(hi, guess + _WARM_HALF_WIDTH)
        Ga = R - a * X
        ia = int(Ga.argmin())
        if a < b and X[ia] <= x_e and X[int((R - b * X).argmin())] > x_e:
            lo, hi = a, b
            keep = Ga - Ga[ia] <= (hi - lo) * span + 1.0  # as the pruning below, at slope lo
            X, R = X[keep], R[keep]
            pruned = True
    il = ir = -1  # active points at lo and hi once pruned
    for it in range(_BISECT_ITERATIONS):
        d = 0.5 * (lo + hi)
        G = R - d * X
        i = int(G.argmin())
        if X[i] > x_e:
            hi, ir = d, i
        else:
            lo, il = d, i
        if not pruned and it == _PRUNE_AFTER:
            # Only points within (hi - lo) * span of the envelope at slope d (an end of the new
            # interval) can be active anywhere in [lo, hi]: drop the rest, the remaining
            # halvings get cheap.
            keep = G - G[i] <= (hi - lo) * span + 1.0
            X, R = X[keep], R[keep]
            il = ir = -1
            pruned = True
        elif pruned and il >= 0 and ir >= 0 and it % _CHECK_EVERY == 0:
            # Done once the chord of the two active points is a supporting line: it touches the
            # envelope on both sides of x_e, so it is the edge the halvings converge to (they
            # take ~40 steps; the edge is usually isolated after ~15).
            s = float((R[ir] - R[il]) / (X[ir] - X[il]))
            if lo <= s <= hi and float((R - s * X).min()) >= float(R[il] - s * X[il]) - 1.0:
                return s
    # The two active points of the final interval give the edge exactly.
    il = int((R - lo * X).argmin())
    ir = int((R - hi * X).argmin())
    if X[ir] > X[il]:
        exact = float((R[ir] - R[il]) / (X[ir] - X[il]))
        if lo - 1e-12 <= exact <= hi + 1e-12:
            return exact
    return 0.5 * (lo + hi)


# ---------------------------------------------------------------------- counters


def unwrap(raw: ArrayLike, modulus: int, tick_ns: int = 1) -> IntArray:
    """Offline unwrapping of a counter that wraps at ``modulus`` ticks: monotonic ns.

    Each step is taken modulo ``modulus``; a step of more than half the modulus is read as going
    backwards (a reset), which the output keeps, so a :class:`ClockMapper` still sees the reset.
    """
    r = np.asarray(raw, dtype=np.int64)
    if r.ndim != 1:
        raise ValueError(f"unwrap: expected a 1-D array, got shape {r.shape}")
    if r.shape[0] == 0:
        return r.copy()
    m = np.int64(modulus)
    step = np.diff(r) % m
    step = np.where(step > m // 2, step - m, step)
    out: IntArray = (r[0] + np.concatenate([[0], np.cumsum(step)])) * np.int64(tick_ns)
    return out


def unwrap_nearest(raw: ArrayLike, reference: ArrayLike, modulus: int) -> IntArray:
    """The value congruent to ``raw`` modulo ``modulus`` that is nearest to ``reference``
    (an already unwrapped value of the same counter)."""
    r = np.asarray(raw, dtype=np.int64)
    ref = np.asarray(reference, dtype=np.int64)
    m = np.int64(modulus)
    k = np.floor_divide(ref - r + m // 2, m)
    out: IntArray = r + k * m
    return out


class CounterUnwrapper:
    """Online unwrapping of a device counter that wraps at ``modulus`` ticks of ``tick_ns``.

    ``unwrapper(raw, host_ns)`` returns ns on a monotonic scale: each raw value becomes the value
    congruent to it that is nearest to the newest one so far, so wraps and reordered records
    (slightly older values arriving late) both come out right. With host receive times, a step
    is accepted only when it is consistent with the host time elapsed: forward by at most
    ``elapsed * (1 + max_drift) + slack_ns``, backward by at most ``slack_ns``. Anything else is
    a counter reset: the raw value is then passed on without a wrap correction, so the output
    jumps and the clock mapper sees the discontinuity.
    """

    def __init__(
        self,
        modulus: int,
        tick_ns: int = 1,
        max_drift: float = 1e-3,
        slack_ns: int = 100_000_000,
    ) -> None:
        if modulus < 2 or tick_ns < 1:
            raise ValueError("CounterUnwrapper: modulus must be >= 2 and tick_ns >= 1")
        self.modulus = int(modulus)
        self.tick_ns = int(tick_ns)
        self.max_drift = float(max_drift)
        self.slack_ns = int(slack_ns)
        self.n_wraps = 0
        self.n_resets = 0
        self._newest: int | None = None  # newest unwrapped value (ticks)
        self._newest_host: int | None = None

    def __call__(self, raw: int, host_ns: int | None = None) -> int:
        m = self.modulus
        raw = int(raw) % m
        newest = self._newest
        if newest is None:
            self._newest, self._newest_host = raw, host_ns
            return raw * self.tick_ns
        out = raw + ((newest - raw + m // 2) // m) * m
        step_ns = (out - newest) * self.tick_ns
        plausible = True
        if host_ns is not None and self._newest_host is not None:
            elapsed = int(host_ns) - self._newest_host
            plausible = (
                -self.slack_ns <= step_ns <= elapsed * (1.0 + self.max_drift) + self.slack_ns
            )
        if not plausible:
            self.n_resets += 1
            out = raw + (newest // m) * m
            self._newest, self._newest_host = out, host_ns
        elif out > newest:
            self.n_wraps += out // m - newest // m
            self._newest, self._newest_host = out, host_ns
        return out * self.tick_ns
