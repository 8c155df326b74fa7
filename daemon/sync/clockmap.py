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

A sender that cannot keep its timing (issue 21) raises the floor instead: its first records are
the least late, so the line rests on them and never locks. Before the first lock the fit moves
to the newest part of the window that locks with its floor reached at its newest end
(:func:`~.envelope.newer_floor`, counted in ``status()["floor_moves"]``), and a floor that came
down since the last fit discards the split history of the points it left behind.

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
by :class:`~.counters.CounterUnwrapper` or :func:`~.counters.unwrap`. The settings are
:class:`~.clockconfig.ClockConfig`; the line and its slope search live in :mod:`.envelope`.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections import deque
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import jit
from wristscan.daemon.sync.clockconfig import ClockConfig
from wristscan.daemon.sync.clockfeed import feed_block
from wristscan.daemon.sync.envelope import EnvelopeLine, Fit, fit_window, newer_floor

logger = logging.getLogger(__name__)

__all__ = ["ClockMapper", "ClockUnlockedError"]

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]

# The uncertainty is the RMS of the split differences of this many recent refits.
_U_HISTORY = 16
# Recent arrivals an arrival below the line is compared with (jump or descending floor).
_RECENT = 8


class ClockUnlockedError(RuntimeError):
    """The mapper has no line for the requested epoch yet."""


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
        self.n_floor_moves = 0  # fits moved to a newer part of the window before a lock
        self.n_fed = 0
        self._old: dict[int, EnvelopeLine] = {}
        # Drift kept from the previous epoch: (drift, its uncertainty, span (ns) it was fitted on).
        self._prior: tuple[float, float, float] | None = None
        self._line: EnvelopeLine | None = None
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
        self._last_trial_x = -(1 << 62)  # newest device time of the last _newer_part trial
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
        """Feed arrays of arrivals in order (a tick's records); returns the epoch of each. Same
        result as :meth:`feed` per arrival, vectorised while nothing unusual happens
        (:func:`~.clockfeed.feed_block`)."""
        xs = np.asarray(device_ns, dtype=np.int64).reshape(-1)
        ys = np.asarray(host_ns, dtype=np.int64).reshape(-1)
        if xs.shape != ys.shape:
            raise ValueError("feed_many: device_ns and host_ns differ in length")
        return feed_block(self, xs, ys)

    def _straggler(self, x: int) -> bool:
        """Whether the arrival that went back (``_excess[0]``) was a reordered record: the next
        one (device time ``x``) continues from the newest device time before it, not from it.
        The record period is the median step of the recent arrivals."""
        xs = [px for px, _ in self._recent]
        steps = [b - a for a, b in itertools.pairwise(xs) if b > a]
        period = float(np.median(steps)) if steps else 0.0
        x_back = self._excess[0][0]
        return abs(x - self._back_from - period) <= abs(x - x_back - period)

    def _abrupt(self, line: EnvelopeLine, gap: float, tol: float) -> bool:
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
        kern = jit.kernel("prune_buckets")  # compiled: the same buckets kept
        if kern is not None:
            margin = float(self.config.prune_margin_ns)
            self._b1 = b0 + kern(bx, br, m, self._or + m * self._ox, margin)
            return
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

    def _fit(self, X: FloatArray, R: FloatArray, u_hist: deque[tuple[float, float]]) -> Fit:
        """``(d, a, x_e, u0, u_slope, span the slope rests on)`` of the points ``(X, R)``."""
        cfg = self.config
        n = X.shape[0]
        span = float(X.max() - X.min())
        # With a drift from the previous epoch, refit it only once this epoch has as much data
        # (up to half a window): a short baseline would give a worse slope than the old one.
        need = float(cfg.min_span_ns)
        if self._prior is not None:
            need = max(need, min(self._prior[2], 0.5 * cfg.window_ns))
        if span >= need and n >= 6:
            d, a, x_e, u0, u_slope = fit_window(X, R, span, cfg, self._line, self._prior, u_hist)
            return d, a, x_e, u0, u_slope, span
        d, u_prior, fit_span = (
            self._prior if self._prior is not None else (0.0, cfg.typical_drift, 0.0)
        )
        G = R - d * X
        i0 = int(np.argmin(G))
        # Offset only: the estimate sharpens quickly with every point, so no smoothing. (A
        # re-anchored fit starts from one point below a line that was good: no worse.)
        if n >= 2:
            u0 = abs(0.5 * float(G[0::2].min() - G[1::2].min()))
        elif self._ever_locked and self._line is not None:
            u0 = self._line.u0
        else:
            u0 = math.inf
        u_slope = u_prior if math.isfinite(u0) else cfg.max_drift
        return d, float(G[i0]), float(X[i0]), u0, u_slope, fit_span

    def _newer_part(self, X: FloatArray, R: FloatArray) -> Fit | None:
        """Before the first lock: the fit of the newest part of the window that locks with the
        floor reached at its newest end (:func:`~.envelope.newer_floor`); the older buckets are
        then dropped. None if there is none."""
        hists: list[deque[tuple[float, float]]] = []

        def fit_part(x: FloatArray, r: FloatArray) -> Fit:
            hists.append(deque(maxlen=_U_HISTORY))  # a fresh split history for each part
            return self._fit(x, r, hists[-1])

        dx_last = float(self._x_last - self._x_ref)
        got = newer_floor(X, R, dx_last, self.config, fit_part)
        if got is None:
            return None
        fit, x_cut = got
        hist = hists[-1]
        keep = self._bx[self._b0 : self._b1] >= x_cut
        k = int(np.count_nonzero(keep))
        self._bx[self._b0 : self._b0 + k] = self._bx[self._b0 : self._b1][keep]
        self._br[self._b0 : self._b0 + k] = self._br[self._b0 : self._b1][keep]
        self._b1 = self._b0 + k
        self._u_hist = hist
        self.n_floor_moves += 1
        logger.info(
            "%s: delay floor rose: fit moved to the newest %.3f s",
            self.name,
            (dx_last - x_cut) / 1e9,
        )
        return fit

    def _refit(self) -> None:
        cfg = self.config
        self._last_fit_x = self._x_last
        self._prune()
        X, R = self._points()
        span = float(X.max() - X.min())
        old = self._line
        if not self._ever_locked and old is not None and X.shape[0] > 1:
            # The floor came down by more than the prune margin since the last fit (a delay
            # that is falling, a lag that wanders): the split differences of the earlier fits
            # describe points that no longer hold the line, so they no longer count.
            if float((R - old.d * X).min()) < old.a - self.config.prune_margin_ns:
                self._u_hist.clear()
        fit = self._fit(X, R, self._u_hist)
        dx_last = float(self._x_last - self._x_ref)
        line = EnvelopeLine(self._x_ref, self._y_ref, *fit[:5], False)
        u_last = line.uncertainty1(dx_last)
        if self._ever_locked:
            # Hysteresis: a lock is not dropped for an uncertainty that wavers around the limit.
            locked = u_last <= cfg.unlock_factor * cfg.max_uncertainty_ns
        else:
            locked = (
                self._n >= cfg.min_points
                and span >= cfg.min_lock_span_ns
                and u_last <= cfg.max_uncertainty_ns
            )
            if (
                not locked
                and self._n >= cfg.min_points
                and span >= 2 * cfg.min_lock_span_ns
                and self._x_last - self._last_trial_x >= cfg.refit_interval_ns
            ):
                self._last_trial_x = self._x_last
                newer = self._newer_part(X, R)
                if newer is not None:
                    fit, locked = newer, True
                    line = EnvelopeLine(self._x_ref, self._y_ref, *fit[:5], False)
                    u_last = line.uncertainty1(dx_last)
        d, a, x_e, u0, u_slope, self._fit_span = fit
        self._line = EnvelopeLine(self._x_ref, self._y_ref, a, d, x_e, u0, u_slope, locked)
        if locked and not self._ever_locked:
            self._ever_locked = True
            logger.info(
                "%s: locked (epoch %d, drift %.2f ppm, uncertainty %.1f us)",
                self.name,
                self.epoch,
                d * 1e6,
                u_last / 1e3,
            )

    # ------------------------------------------------------------------ mapping

    def _get_line(self, epoch: int | None) -> EnvelopeLine:
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
            "floor_moves": self.n_floor_moves,
        }
