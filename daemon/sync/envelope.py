"""The lower envelope of one-way arrivals: the fitted line, the search of its slope and the fit
of a window (offset, drift and their uncertainties).

The clock fit (:mod:`.clockmap`) takes, among the lines lying below every point of a window,
the one highest at an evaluation instant ``x_e``; that is the lower-convex-hull edge spanning
``x_e``, found here by bisection on the slope (the objective is concave in the slope), with a
warm start from the previous fit and an early stop once the chord of the two active points is a
supporting line. :class:`~.clockmap.ClockMapper` keeps the window and the epochs; this module
is the arithmetic on one window.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import jit
from wristscan.daemon.sync.clockconfig import ClockConfig

__all__ = ["EnvelopeLine", "fit_window", "newer_floor", "support_slope"]

FloatArray = NDArray[np.float64]

# Slope bisection: 40 halvings of a +-1e-3 interval resolve the drift to ~2e-15, then the exact
# hull edge is taken from the two active points.
_BISECT_ITERATIONS = 40
_PRUNE_AFTER = 10
_CHECK_EVERY = 3
# A warm start brackets the previous slope by this much (2 ppm: successive fits of a window
# differ by far less; the edges at the quartiles by about that).
_WARM_HALF_WIDTH = 2e-6
# Once pruned to this many points or fewer, the search goes on in Python floats.
_FEW_POINTS = 16


@dataclass(frozen=True, slots=True)
class EnvelopeLine:
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


def support_slope(
    X: FloatArray,
    R: FloatArray,
    x_e: float,
    lo: float,
    hi: float,
    guess: float | None = None,
    span: float | None = None,
    ends: tuple[FloatArray, FloatArray] | None = None,
) -> float:
    """Slope of the highest line at ``x_e`` lying below all points ``(X, R)``.

    ``f(d) = min_i R_i + d (x_e - X_i)`` is concave; its supergradient at ``d`` is ``x_e - X_i*``
    of the active point, so bisection on its sign finds the maximiser: the lower-hull edge
    spanning ``x_e``. Slopes outside ``[lo, hi]`` are clipped to the range. ``guess``: a slope
    near the answer (the previous fit's); when ``guess +- _WARM_HALF_WIDTH`` brackets the
    answer, the search starts there with the points pruned at once (same edge, a third of the
    passes over the whole window). ``span``: ``X.max() - X.min()`` when the caller has it.
    ``ends``: ``R - a X`` and ``R - b X`` at the ends ``a``, ``b`` of the warm bracket
    (:func:`warm_ends`) when the caller has them (several searches with one guess).
    """
    pruned = False
    if guess is not None:
        a, b = max(lo, guess - _WARM_HALF_WIDTH), min(hi, guess + _WARM_HALF_WIDTH)
        Ga, Gb = ends if ends is not None else (R - a * X, None)
        ia = int(Ga.argmin())
        if a < b and X[ia] <= x_e:
            Gb = R - b * X if Gb is None else Gb
            if X[int(Gb.argmin())] > x_e:
                lo, hi = a, b
                # A point higher than the active point ia by more than 1 ns at both ends is
                # higher than it all along (the difference of two lines is linear in the slope;
                # rounding is far below 1 ns): never the lowest at any slope evaluated from
                # here, so dropping it changes no result. Leaves ~40 % of a full window.
                keep = Ga <= Ga[ia] + 1.0
                keep |= Gb <= Gb[ia] + 1.0
                X, R = X[keep], R[keep]
                pruned = True
                if X.shape[0] <= _FEW_POINTS:
                    return _search_lists(X.tolist(), R.tolist(), x_e, lo, hi, 0)
    il = ir = -1  # active points at lo and hi once pruned
    G = np.empty_like(X)  # R - d X, computed in place (the same values, no allocation)
    for it in range(_BISECT_ITERATIONS):
        d = 0.5 * (lo + hi)
        np.subtract(R, np.multiply(X, d, out=G), out=G)
        i = int(G.argmin())
        if X[i] > x_e:
            hi, ir = d, i
        else:
            lo, il = d, i
        if not pruned and it == _PRUNE_AFTER:
            # Only points within (hi - lo) * span of the envelope at slope d (an end of the new
            # interval) can be active anywhere in [lo, hi]: drop the rest, the remaining
            # halvings get cheap.
            span = float(X.max() - X.min()) if span is None else span
            keep = G - G[i] <= (hi - lo) * span + 1.0
            X, R = X[keep], R[keep]
            if X.shape[0] <= _FEW_POINTS:
                return _search_lists(X.tolist(), R.tolist(), x_e, lo, hi, it + 1)
            G = np.empty_like(X)
            il = ir = -1
            pruned = True
        elif pruned and il >= 0 and ir >= 0 and it % _CHECK_EVERY == 0:
            # Done once the chord of the two active points is a supporting line: it touches the
            # envelope on both sides of x_e, so it is the edge the halvings converge to (they
            # take ~40 steps; the edge is usually isolated after ~15).
            xl, rl = float(X[il]), float(R[il])
            s = (float(R[ir]) - rl) / (float(X[ir]) - xl)
            if lo <= s <= hi:
                np.subtract(R, np.multiply(X, s, out=G), out=G)
                if float(G.min()) >= rl - s * xl - 1.0:
                    return s
    # The two active points of the final interval give the edge exactly.
    il = int((R - lo * X).argmin())
    ir = int((R - hi * X).argmin())
    if X[ir] > X[il]:
        exact = float((R[ir] - R[il]) / (X[ir] - X[il]))
        if lo - 1e-12 <= exact <= hi + 1e-12:
            return exact
    return 0.5 * (lo + hi)


def warm_ends(
    X: FloatArray, R: FloatArray, lo: float, hi: float, guess: float
) -> tuple[FloatArray, FloatArray]:
    """``R - a X`` and ``R - b X`` at the ends of :func:`support_slope`'s warm bracket around
    ``guess`` (its ``ends``; elementwise, so their even and odd halves are the halves')."""
    a, b = max(lo, guess - _WARM_HALF_WIDTH), min(hi, guess + _WARM_HALF_WIDTH)
    return R - a * X, R - b * X


def _lowest(X: list[float], R: list[float], d: float) -> tuple[int, float]:
    """The first index of the least ``R - d X`` and that value (``argmin`` in Python floats)."""
    i, gi = 0, R[0] - d * X[0]
    for k in range(1, len(X)):
        g = R[k] - d * X[k]
        if g < gi:
            i, gi = k, g
    return i, gi


def _search_lists(
    X: list[float], R: list[float], x_e: float, lo: float, hi: float, start: int
) -> float:
    """The rest of :func:`support_slope`'s search once pruned, from halving ``start`` on, when
    a few points are left: the same steps in Python floats (the same IEEE operations, the first
    of equal minima), cheaper than numpy calls on a handful of points."""
    il = ir = -1
    for it in range(start, _BISECT_ITERATIONS):
        d = 0.5 * (lo + hi)
        i = _lowest(X, R, d)[0]
        if X[i] > x_e:
            hi, ir = d, i
        else:
            lo, il = d, i
        if il >= 0 and ir >= 0 and it % _CHECK_EVERY == 0:
            xl, rl = X[il], R[il]
            s = (R[ir] - rl) / (X[ir] - xl)
            if lo <= s <= hi and _lowest(X, R, s)[1] >= rl - s * xl - 1.0:
                return s
    il = _lowest(X, R, lo)[0]
    ir = _lowest(X, R, hi)[0]
    if X[ir] > X[il]:
        exact = (R[ir] - R[il]) / (X[ir] - X[il])
        if lo - 1e-12 <= exact <= hi + 1e-12:
            return exact
    return 0.5 * (lo + hi)


def fit_window(
    X: FloatArray,
    R: FloatArray,
    span: float,
    cfg: ClockConfig,
    line: EnvelopeLine | None,
    prior: tuple[float, float, float] | None,
    u_hist: deque[tuple[float, float]],
) -> tuple[float, float, float, float, float]:
    """Offset and drift from the window's points ``(X, R)``: ``(d, a, x_e, u0, u_slope)``.

    ``line`` is the previous fit (its slope starts the search), ``prior`` the drift known before
    these data ``(drift, its uncertainty, span)``, and ``u_hist`` the recent split differences,
    to which this fit's is appended (the uncertainty is their windowed RMS).
    """
    lo, hi = -cfg.max_drift, cfg.max_drift

    def clipped(v: float) -> bool:  # a slope at the end of the range: undetermined
        return abs(v) >= cfg.max_drift * (1.0 - 1e-9)

    f = cfg.eval_fraction
    x0 = float(X.min())
    x_e = x0 + f * span
    xq = (x0 + max(f - 0.25, 0.0) * span, x0 + min(f + 0.25, 1.0) * span)
    # Uncertainty: the same estimator on the even and on the odd buckets gives two
    # independent half-data estimates; half their difference is of the order of the full
    # estimate's error whatever the delay distribution. Windowed RMS: one split is a noisy
    # scale; old (early, poor) fits drop out.
    d, d1, d2, v1, v2, dq = _searches(X, R, x_e, xq, lo, hi, line, span)
    dv = 0.5 * (v1 - v2)
    dd = cfg.max_drift if clipped(d1) or clipped(d2) else 0.5 * (d1 - d2)
    u_hist.append((dv * dv, dd * dd))
    u0 = math.sqrt(sum(h[0] for h in u_hist) / len(u_hist))
    u_slope = math.sqrt(sum(h[1] for h in u_hist) / len(u_hist))
    # What was known before these data: the drift of the previous epoch or fit (same
    # oscillator), else 0 with the typical drift as its scale.
    if prior is not None:
        pd, pu = prior[0], prior[1]
    else:
        pd, pu = 0.0, cfg.typical_drift
    pu = max(pu, 0.01 * cfg.typical_drift)
    # The lower envelope is a straight line only where the delay floor is reached. When
    # every arrival of a stretch reaching one end of the window is late (sustained load
    # longer than the rest of the window), the hull edge spanning x_e tilts towards it.
    # The edges spanning the quartiles then disagree by more than the noise: the data do
    # not determine the drift, so it stays where it was (a clock's drift changes slowly).
    if abs(dq[0] - dq[1]) > max(6.0 * u_slope, 0.01 * cfg.typical_drift):
        ref = line.d if line is not None else pd
        G = R - ref * X
        i0 = int(np.argmin(G))
        u_ref = line.u_slope if line is not None else pu
        return ref, float(G[i0]), float(X[i0]), u0, u_ref
    # Combine with the prior (inverse-variance weights): a slope from a short or noisy
    # stretch then counts for little, and one at the end of the search range for nothing.
    us = cfg.max_drift if clipped(d) else u_slope
    w = pu * pu / (us * us + pu * pu)
    d = pd + w * (d - pd)
    u_slope = us * pu / math.sqrt(us * us + pu * pu)
    a = float((R - d * X).min())
    return d, a, x_e, u0, u_slope


def _searches(
    X: FloatArray,
    R: FloatArray,
    x_e: float,
    xq: tuple[float, float],
    lo: float,
    hi: float,
    line: EnvelopeLine | None,
    span: float,
) -> tuple[float, float, float, float, float, tuple[float, float]]:
    """:func:`fit_window`'s five slope searches: at ``x_e`` (from the previous slope), of the
    even and of the odd points with their envelopes' values at ``x_e``, at the quartiles
    ``xq``. One compiled call when the kernels are in use (the same steps, the same bits:
    :mod:`wristscan.calib.jit_clock`), else :func:`support_slope` five times."""
    kern = jit.kernel("fit_slopes")
    guess = None if line is None else line.d
    if kern is not None and X.dtype == np.float64 and R.dtype == np.float64:
        g = 0.0 if guess is None else guess
        d, d1, d2, v1, v2, q0, q1 = kern(
            X, R, x_e, xq[0], xq[1], lo, hi, g, guess is not None, span
        )
        return d, d1, d2, v1, v2, (q0, q1)
    d = support_slope(X, R, x_e, lo, hi, guess, span)
    Ga, Gb = warm_ends(X, R, lo, hi, d)  # the four searches from d share their bracket
    d1 = support_slope(X[0::2], R[0::2], x_e, lo, hi, d, ends=(Ga[0::2], Gb[0::2]))
    d2 = support_slope(X[1::2], R[1::2], x_e, lo, hi, d, ends=(Ga[1::2], Gb[1::2]))
    v1 = float((R[0::2] - d1 * X[0::2]).min()) + d1 * x_e
    v2 = float((R[1::2] - d2 * X[1::2]).min()) + d2 * x_e
    dq = (
        support_slope(X, R, xq[0], lo, hi, d, span, (Ga, Gb)),
        support_slope(X, R, xq[1], lo, hi, d, span, (Ga, Gb)),
    )
    return d, d1, d2, v1, v2, dq


Fit = tuple[float, float, float, float, float, float]
"""``(d, a, x_e, u0, u_slope, span the slope rests on)``."""


def newer_floor(
    X: FloatArray,
    R: FloatArray,
    dx_last: float,
    cfg: ClockConfig,
    fit: Callable[[FloatArray, FloatArray], Fit],
) -> tuple[Fit, float] | None:
    """The fit of the longest newer part of the window (its newer half, quarter, ...: at least
    ``min_lock_span_ns``) that would lock with the floor reached at its newest end, and where
    that part starts; None if there is none. ``fit`` fits a part; ``dx_last``: the newest point.

    Used before an epoch's first lock. A delay floor that rose (a sender that became late,
    records held back behind a late one, a simulator that fell 1 s behind) leaves the older
    arrivals lower than every later one, often as lone minima: the line rests on them, tilts,
    and the split estimates disagree by the rise, so the epoch never locks (issue 21: nothing
    published). Nothing has been mapped yet, so the fit may follow the newer floor instead (a
    floor that comes down later re-anchors it). While the floor still rises (a lag growing),
    no part reaches its floor at its newest end, and the epoch stays unlocked.
    """
    x_max = float(X.max())
    part = 0.5 * float(x_max - X.min())
    while part >= cfg.min_lock_span_ns:
        newer = X >= x_max - part
        part *= 0.5
        if int(np.count_nonzero(newer)) < 6:
            continue
        Xn, Rn = X[newer], R[newer]
        got = fit(Xn, Rn)
        d, a, x_e, u0, u_slope = got[:5]
        if math.hypot(u0, u_slope * (dx_last - x_e)) > cfg.max_uncertainty_ns:
            continue
        end = Xn >= x_max - 0.25 * float(x_max - Xn.min())
        if float((Rn[end] - a - d * Xn[end]).min()) > cfg.jump_tolerance_ns:
            continue  # the newest points are all late: the floor is still rising
        return got, float(Xn.min())
    return None
