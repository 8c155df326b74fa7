"""Compiled kernels of the synchroniser's per-tick arithmetic (built by :mod:`.jit`, extra
``fast``): device times mapped through a clock line and located among a sample series in one
call; a clock's arrivals fed (the ordinary run of a tick, its buckets' lowest points); the slope
searches and the window pruning of a clock fit's lower envelope. Each repeats, element by
element, the IEEE operations of its numpy twin in ``wristscan.daemon.sync`` (no fast-math
licence, so no contraction into fused multiply-adds): the same bits, tested against those
twins.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

__all__ = ["exercise", "kernels"]

# Kernels that other kernels call are module globals, not closure cells: numba's on-disk cache
# takes a function calling a global dispatcher, not one whose closure holds one.
_dh_forward: Any = None
_lowest: Any = None
_support: Any = None

# The slope search's constants (``wristscan.daemon.sync.envelope``: the same values).
_ITERATIONS, _PRUNE_AFTER, _CHECK_EVERY, _WARM_HALF = 40, 10, 3, 2e-6


def kernels(numba: Any, njit: Callable[..., Any], dh_forward: Any) -> dict[str, Any]:
    """The kernels, jitted lazily by ``njit`` (:func:`wristscan.calib.jit._njit`);
    ``dh_forward``: the forward kinematics kernel, which ``map_locate`` ends with."""
    global _dh_forward
    _dh_forward = dh_forward
    exact = njit(numba, nogil=True, boundscheck=False)
    _search_kernels(exact)
    return {
        "map_locate": _mapping_kernel(exact),
        **_window_kernels(exact),
        "feed_segment": _feed_kernel(exact),
    }


def _mapping_kernel(exact: Callable[..., Any]) -> Any:
    @exact
    def map_locate(x, s_line, s_ints, r_line, r_ints, T, gap, expo, unc, rows, frac, Q, dh, F):  # type: ignore[no-untyped-def]
        """Device times ``x`` mapped onto the host clock and located among the samples ``T``
        of another device, whose clock maps back from the host clock.

        Tuples: ``s_line`` = (a, d, x_e, u0 squared, u_slope), ``s_ints`` = (x_ref,
        y_ref - latency):
        ``expo = dx + rint(a + d dx) + (y_ref - latency)`` with ``dx = x - x_ref`` and its
        uncertainty ``sqrt(u0^2 + (u_slope (dx - x_e))^2)`` (``ClockMapper.to_host`` and
        ``uncertainty_ns``); ``r_line`` = (a, 1 + d), ``r_ints`` = (latency - y_ref, x_ref):
        ``t = rint((expo + latency - y_ref - a) / (1 + d)) + x_ref``
        (``ClockMapper.to_device``); then ``rows`` and ``frac`` place ``t`` between
        ``T[rows]`` and ``T[rows + 1]`` (``SampleBuffer._locate``: ``T`` at least two
        samples). Returns (every ``t`` inside ``T`` with its samples at most ``gap``
        apart, the exposures non-decreasing); when the first is true, ``F`` (P, 4, 4) holds the
        poses at the joints interpolated there (``dh_forward`` of the samples ``Q`` (n, >= 6)
        with ``dh`` (5, 6): the DH constants ``off, cos alpha, sin alpha, a, d``)."""
        a, d, x_e, u0sq, u_slope = s_line[0], s_line[1], s_line[2], s_line[3], s_line[4]
        ra, rd1 = r_line[0], r_line[1]
        x_ref, c_host, c_dev, r_ref = s_ints[0], s_ints[1], r_ints[0], r_ints[1]
        n = T.shape[0]
        first, last = T[0], T[n - 1]
        ok = True
        ordered = True
        for k in range(x.shape[0]):
            dx = x[k] - x_ref
            fx = np.float64(dx)
            e = dx + np.int64(np.rint(a + d * fx)) + c_host
            expo[k] = e
            v = u_slope * (fx - x_e)
            unc[k] = math.sqrt(u0sq + v * v)
            if k and e < expo[k - 1]:
                ordered = False
            t = np.int64(np.rint((np.float64(e + c_dev) - ra) / rd1)) + r_ref
            lo, hi = 0, n  # searchsorted(T, t, side="right")
            while lo < hi:
                mid = (lo + hi) >> 1
                if T[mid] <= t:
                    lo = mid + 1
                else:
                    hi = mid
            i = max(min(lo - 1, n - 2), 0)
            t0 = T[i]
            dt = T[i + 1] - t0
            rows[k] = i
            frac[k] = np.float64(t - t0) / np.float64(dt)
            if dt > gap or t < first or t > last:
                ok = False
        if ok:
            _dh_forward(Q, rows, frac, True, dh[0], dh[1], dh[2], dh[3], dh[4], F)
        return ok, ordered

    return map_locate


def _search_kernels(exact: Callable[..., Any]) -> None:
    """The slope search (``_support``) and its argmin (``_lowest``), as module globals."""
    global _lowest, _support

    @exact
    def _lowest(X, R, n, d):  # type: ignore[no-untyped-def]
        """The first index of the least ``R - X d`` among the first ``n`` points, its value."""
        i, gi = 0, R[0] - X[0] * d
        for k in range(1, n):
            g = R[k] - X[k] * d
            if g < gi:
                i, gi = k, g
        return i, gi

    @exact
    def _support(X, R, x_e, lo, hi, guess, has_guess, span):  # type: ignore[no-untyped-def]
        """``envelope.support_slope`` (``span`` < 0: not given), step for step."""
        n = X.shape[0]
        Xw, Rw = X.copy(), R.copy()  # the points still in the search, first n
        pruned = False
        if has_guess:
            a, b = max(lo, guess - _WARM_HALF), min(hi, guess + _WARM_HALF)
            ia, ga = _lowest(Xw, Rw, n, a)
            if a < b and Xw[ia] <= x_e and Xw[_lowest(Xw, Rw, n, b)[0]] > x_e:
                lo, hi = a, b
                ta, tb = ga + 1.0, (Rw[ia] - b * Xw[ia]) + 1.0
                m = 0
                for k in range(n):
                    if Rw[k] - a * Xw[k] <= ta or Rw[k] - b * Xw[k] <= tb:
                        Xw[m], Rw[m] = Xw[k], Rw[k]
                        m += 1
                n, pruned = m, True
        il = ir = -1
        for it in range(_ITERATIONS):
            d = 0.5 * (lo + hi)
            i, gi = _lowest(Xw, Rw, n, d)
            if Xw[i] > x_e:
                hi, ir = d, i
            else:
                lo, il = d, i
            if not pruned and it == _PRUNE_AFTER:
                if span < 0.0:
                    span = Xw[:n].max() - Xw[:n].min()
                lim = (hi - lo) * span + 1.0
                m = 0
                for k in range(n):
                    if (Rw[k] - Xw[k] * d) - gi <= lim:
                        Xw[m], Rw[m] = Xw[k], Rw[k]
                        m += 1
                n, il, ir, pruned = m, -1, -1, True
            elif pruned and il >= 0 and ir >= 0 and it % _CHECK_EVERY == 0:
                xl, rl = Xw[il], Rw[il]
                s = (Rw[ir] - rl) / (Xw[ir] - xl)
                if lo <= s <= hi and _lowest(Xw, Rw, n, s)[1] >= rl - s * xl - 1.0:
                    return s
        il, ir = _lowest(Xw, Rw, n, lo)[0], _lowest(Xw, Rw, n, hi)[0]
        if Xw[ir] > Xw[il]:
            edge = (Rw[ir] - Rw[il]) / (Xw[ir] - Xw[il])
            if lo - 1e-12 <= edge <= hi + 1e-12:
                return edge
        return 0.5 * (lo + hi)


def _window_kernels(exact: Callable[..., Any]) -> dict[str, Any]:
    @exact
    def fit_slopes(X, R, x_e, xq0, xq1, lo, hi, guess, has_guess, span):  # type: ignore[no-untyped-def]
        """``envelope.fit_window``'s searches: the slope at ``x_e`` (from ``guess`` when
        ``has_guess``), those of the even and the odd points with their envelopes' values at
        ``x_e``, the slopes at ``xq0`` and ``xq1``: (d, d1, d2, v1, v2, dq0, dq1)."""
        d = _support(X, R, x_e, lo, hi, guess, has_guess, span)
        Xe, Re, Xo, Ro = X[0::2], R[0::2], X[1::2], R[1::2]
        d1 = _support(Xe, Re, x_e, lo, hi, d, True, -1.0)
        d2 = _support(Xo, Ro, x_e, lo, hi, d, True, -1.0)
        v1 = _lowest(Xe, Re, Xe.shape[0], d1)[1] + d1 * x_e
        v2 = _lowest(Xo, Ro, Xo.shape[0], d2)[1] + d2 * x_e
        dq0 = _support(X, R, xq0, lo, hi, d, True, span)
        dq1 = _support(X, R, xq1, lo, hi, d, True, span)
        return d, d1, d2, v1, v2, dq0, dq1

    @exact
    def prune_buckets(bx, br, m, last, margin):  # type: ignore[no-untyped-def]
        """``ClockMapper._prune``: the buckets ``(bx, br)`` whose key ``br + m bx`` is below
        the least key after them (and ``last``, the open bucket's) plus ``margin``, moved to
        the front in order; returns how many."""
        n = bx.shape[0]
        keep = np.empty(n, np.bool_)
        low = last
        for j in range(n - 1, -1, -1):
            key = br[j] + m * bx[j]
            keep[j] = key < low + margin
            low = min(low, key)
        k = 0
        for j in range(n):
            if keep[j]:
                bx[k], br[k] = bx[j], br[j]
                k += 1
        return k

    return {"fit_slopes": fit_slopes, "prune_buckets": prune_buckets}


def _feed_kernel(exact: Callable[..., Any]) -> Any:
    @exact
    def feed_segment(xs, ys, i, stop, x_last, due, ref, line, check, quick, tol, out_b, out_xr):  # type: ignore[no-untyped-def]
        """``clockfeed._fast_segment``'s arithmetic on arrivals ``xs[i:stop]``, ``ys``: the
        end of the ordinary run from ``i`` (device time increasing past ``x_last``, up to and
        including the first at or after ``due``, and, when ``check``, before the first
        arrival below the line by more than ``tol + 3 sigma``, looked for when one is below
        it by more than ``-quick``); ``ref`` = (x_ref, y_ref), ``line`` = (a, d, u0 squared,
        u_slope, x_e, bucket). Each bucket's lowest point against the drift ``d`` (the first
        of equals) into ``out_b`` (bucket) and ``out_xr`` (its dx, r). Returns (end, whether
        the end is the refit's, buckets written)."""
        if xs[i] <= x_last:
            return i, False, 0
        a, d, u0sq, u_slope, x_e = line[0], line[1], line[2], line[3], line[4]
        bucket = np.int64(line[5])
        end = i + 1
        while end < stop and xs[end] > xs[end - 1]:
            end += 1
        refit = False
        for k in range(i, end):
            if xs[k] >= due:
                end, refit = k + 1, True
                break
        if check:
            low = np.inf
            for k in range(i, end):
                dx = np.float64(xs[k] - ref[0])
                low = min(low, (np.float64(ys[k] - ref[1]) - dx) - (a + d * dx))
            if low < quick:
                for k in range(i, end):
                    dx = np.float64(xs[k] - ref[0])
                    gap = (np.float64(ys[k] - ref[1]) - dx) - (a + d * dx)
                    v = u_slope * (dx - x_e)
                    if gap < -(tol + 3.0 * math.sqrt(u0sq + v * v)):
                        end, refit = k, False
                        break
        nb = 0
        og = 0.0
        for k in range(i, end):
            dxi = xs[k] - ref[0]
            dx = np.float64(dxi)
            r = np.float64(ys[k] - ref[1]) - dx
            g = r - d * dx
            b = dxi // bucket
            if nb == 0 or b != out_b[nb - 1]:
                out_b[nb], out_xr[nb, 0], out_xr[nb, 1], og = b, dx, r, g
                nb += 1
            elif g < og:
                out_xr[nb - 1, 0], out_xr[nb - 1, 1], og = dx, r, g
        return end, refit, nb

    return feed_segment


def exercise(ks: dict[str, Callable[..., Any]]) -> None:
    """Each kernel called once on tiny inputs of the types the callers pass."""
    import numpy as np

    one, two = np.zeros(1, np.int64), np.arange(2, dtype=np.int64)
    ks["map_locate"](
        one, (0.0,) * 5, (0, 0), (0.0, 1.0), (0, 0), two, 1, np.empty(1, np.int64),
        np.empty(1), np.empty(1, np.int64), np.empty(1), np.zeros((2, 12)), np.zeros((5, 6)),
        np.empty((1, 4, 4)),
    )  # fmt: skip
    x = np.arange(8.0)
    ks["fit_slopes"](x, x, 4.0, 2.0, 6.0, -1e-3, 1e-3, 0.0, True, 7.0)
    ks["prune_buckets"](x.copy(), x.copy(), 1e-3, 9.0, 1.0)
    i8 = np.arange(8, dtype=np.int64)
    ks["feed_segment"](i8, i8, 0, 8, -1, 4, (0, 0), (1.0,) * 6, True, -1.0, 1.0,
                       np.empty(8, np.int64), np.empty((8, 2)))  # fmt: skip
