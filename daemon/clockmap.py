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

Discontinuities
---------------
* Device time going backwards by more than ``reorder_tolerance_ns`` (a reboot, a counter reset),
  or an arrival *before* the line by more than the jump tolerance (device clock stepped forward,
  or the transport delay floor dropped) restarts the fit immediately.
* Arrivals that stay above the line by more than the jump tolerance for ``persist_ns`` (device
  clock stepped back a little, or the delay floor rose) restart it from those points.
Each restart opens a new *epoch*. Records keep the epoch they were fed in, and the last line of
an old epoch stays available, so records from before a reset are still mapped with their own
line. The drift survives a restart (same oscillator), so a new epoch locks on its offset alone
within a few tens of points.

Wrapping counters (SCIP 24-bit ms, 32-bit us, ...) are unwrapped before they reach the mapper,
by :class:`CounterUnwrapper` or :func:`unwrap`.
"""

from __future__ import annotations

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
# The uncertainty is the RMS of the split differences of this many recent refits.
_U_HISTORY = 16


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
    """An epoch is locked while the uncertainty at its newest point stays below this."""
    max_drift: float = 1e-3
    """Largest |drift| searched for (1e-3 = 1000 ppm); also the slope uncertainty before a fit."""
    jump_tolerance_ns: int = 2_000_000
    """Arrivals further below the line than this (plus 3 sigma) restart the fit."""
    persist_ns: int = 500_000_000
    """Arrivals above the line by more than the jump tolerance for this long restart the fit."""
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
        if self.min_points < 2:
            raise ValueError("ClockConfig.min_points must be >= 2")


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
        self._excess: list[tuple[int, int]] = []
        # Recent half-differences of the split estimates: value at x_e (ns), slope.
        self._u_hist: deque[tuple[float, float]] = deque(maxlen=_U_HISTORY)

    def _start_epoch(self, x: int, y: int) -> None:
        if self._line is not None and self.epoch >= 0:
            self._old[self.epoch] = self._line
            while len(self._old) > self.config.max_epochs_kept:
                del self._old[min(self._old)]
        if self._line is not None and self.config.keep_drift_on_reset and self._line.locked:
            # Same oscillator after a restart: its drift is still known.
            span = float(self._x_last - self._x_first)
            if self._prior is not None and self._line.d == self._prior[0]:
                span = max(span, self._prior[2])  # the epoch never refitted the drift
            self._prior = (self._line.d, self._line.u_slope, span)
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
        line = self._line
        if line is not None:
            dx = float(x - self._x_ref)
            gap = float(y - self._y_ref) - dx - line.rel(dx)
            tol = cfg.jump_tolerance_ns + 3.0 * line.uncertainty1(dx)
            if gap < -tol:
                self._restart(
                    x, y, f"arrival {-gap / 1e6:.3f} ms before its send time (device clock jumped)"
                )
                return self.epoch
            if gap > tol:
                self._excess.append((x, y))
                x0, y0 = self._excess[0]
                # Host time too, so that a frozen device clock also ends here (and the list
                # stays bounded).
                if len(self._excess) >= 5 and max(x - x0, y - y0) >= cfg.persist_ns:
                    pts = self._excess
                    self._restart(
                        pts[0][0],
                        pts[0][1],
                        f"arrivals late by > {tol / 1e6:.3f} ms for {cfg.persist_ns / 1e9:.3f} s "
                        "(device clock stepped back or transport delay rose)",
                    )
                    for px, py in pts[1:]:
                        self._add(px, py)
                    return self.epoch
            elif self._excess:
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

    def _restart(self, x: int, y: int, why: str) -> None:
        logger.warning("%s: clock fit restarted at epoch %d: %s", self.name, self.epoch + 1, why)
        self.n_resets += 1
        self._n = 0
        self._start_epoch(x, y)
        self._add(x, y)

    def _add(self, x: int, y: int) -> None:
        cfg = self.config
        self._n += 1
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

    def _points(self) -> tuple[FloatArray, FloatArray]:
        X = np.append(self._bx[self._b0 : self._b1], self._ox)
        R = np.append(self._br[self._b0 : self._b1], self._or)
        return X, R

    def _refit(self) -> None:
        cfg = self.config
        self._last_fit_x = self._x_last
        X, R = self._points()
        n = X.shape[0]
        span = float(X.max() - X.min())
        # With a drift from the previous epoch, refit it only once this epoch has as much data
        # (up to half a window): a short baseline would give a worse slope than the old one.
        need = float(cfg.min_span_ns)
        if self._prior is not None:
            need = max(need, min(self._prior[2], 0.5 * cfg.window_ns))
        full = span >= need and n >= 6
        if full:
            x_e = float(X.min()) + cfg.eval_fraction * span
            lo, hi = -cfg.max_drift, cfg.max_drift
            d = _support_slope(X, R, x_e, lo, hi)
            a = float((R - d * X).min())
            # Uncertainty: the same estimator on the even and on the odd buckets gives two
            # independent half-data estimates; half their difference is of the order of the
            # full estimate's error whatever the delay distribution.
            d1 = _support_slope(X[0::2], R[0::2], x_e, lo, hi)
            d2 = _support_slope(X[1::2], R[1::2], x_e, lo, hi)
            v1 = float((R[0::2] - d1 * X[0::2]).min()) + d1 * x_e
            v2 = float((R[1::2] - d2 * X[1::2]).min()) + d2 * x_e
            dv, dd = 0.5 * (v1 - v2), 0.5 * (d1 - d2)
        else:
            d, u_prior, _ = self._prior if self._prior is not None else (0.0, cfg.max_drift, 0.0)
            G = R - d * X
            i0 = int(np.argmin(G))
            a = float(G[i0])
            x_e = float(X[i0])
            dv = 0.5 * float(G[0::2].min() - G[1::2].min()) if n >= 2 else math.inf
            dd = u_prior
        if not math.isfinite(dv):
            u0, u_slope = math.inf, cfg.max_drift
        elif not full:
            # Offset only: the estimate sharpens quickly with every point, so no smoothing.
            u0, u_slope = abs(dv), dd
        else:
            # Windowed RMS: one split is a noisy scale; old (early, poor) fits drop out.
            self._u_hist.append((dv * dv, dd * dd))
            u0 = math.sqrt(sum(h[0] for h in self._u_hist) / len(self._u_hist))
            u_slope = math.sqrt(sum(h[1] for h in self._u_hist) / len(self._u_hist))
        line = _Line(self._x_ref, self._y_ref, a, d, x_e, u0, u_slope, False)
        dx_last = float(self._x_last - self._x_ref)
        locked = (
            self._n >= cfg.min_points
            and self._x_last - self._x_first >= cfg.min_lock_span_ns
            and math.isfinite(u0)
            and line.uncertainty1(dx_last) <= cfg.max_uncertainty_ns
        )
        was_locked = self._line is not None and self._line.locked
        self._line = _Line(self._x_ref, self._y_ref, a, d, x_e, u0, u_slope, locked)
        if locked and not was_locked:
            logger.info(
                "%s: locked (epoch %d, drift %.2f ppm, uncertainty %.1f us)",
                self.name,
                self.epoch,
                d * 1e6,
                line.uncertainty1(dx_last) / 1e3,
            )

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
        """True while the current epoch maps within ``max_uncertainty_ns``."""
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
        }


def _support_slope(X: FloatArray, R: FloatArray, x_e: float, lo: float, hi: float) -> float:
    """Slope of the highest line at ``x_e`` lying below all points ``(X, R)``.

    ``f(d) = min_i R_i + d (x_e - X_i)`` is concave; its supergradient at ``d`` is ``x_e - X_i*``
    of the active point, so bisection on its sign finds the maximiser: the lower-hull edge
    spanning ``x_e``. Slopes outside ``[lo, hi]`` are clipped to the range.
    """
    span = float(X.max() - X.min())
    for it in range(_BISECT_ITERATIONS):
        d = 0.5 * (lo + hi)
        G = R - d * X
        i = int(G.argmin())
        if X[i] > x_e:
            hi = d
        else:
            lo = d
        if it == _PRUNE_AFTER:
            # Only points within (hi - lo) * span of the envelope at slope d (an end of the new
            # interval) can be active anywhere in [lo, hi]: drop the rest, the remaining
            # halvings get cheap.
            keep = G - G[i] <= (hi - lo) * span + 1.0
            X, R = X[keep], R[keep]
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
