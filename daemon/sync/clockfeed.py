"""Feeding a :class:`~.clockmap.ClockMapper` a block of arrivals at once (one tick's profiles).

:meth:`ClockMapper.feed <wristscan.daemon.sync.clockmap.ClockMapper.feed>` costs several us per
arrival, most of it Python bookkeeping. A tick of a 5-10 kHz sensor brings 50-100 arrivals that
are almost always ordinary: device time increasing, no arrival below a trusted line, no pending
suspicion of a step back or a stopped clock. For those, :func:`feed_block` does what ``feed``
would do for each, with arrays:

* the gaps of the arrivals against the current line, all at once (the causality check);
* the bucket minima (lowest ``r - d * dx`` per ``bucket_ns``) of the block, pushed at once;
* the counters, the newest device time and the recent arrivals updated once.

The block is cut at the arrivals after which ``feed`` would refit (every ``refit_interval_ns``
of device time once locked, every bucket before), the refit is done there and the rest of the
block continues with the new line: the result is the one arrival-by-arrival feeding gives, up to
floating-point rounding (tested). Anything unusual (device time not increasing, an arrival below
a locked line by more than the re-anchor tolerance, a pending step-back suspicion, a stopped
clock, an epoch to open) goes through ``feed``, and the fast path is tried again after it (a
pending suspicion keeps the following arrivals on ``feed`` until it is settled).
:func:`feed_lists` is the same for a few arrivals given as lists (a tick's robot states).

With the compiled kernels in use (:mod:`wristscan.calib.jit_clock`, extra ``fast``) a segment's
arithmetic (its end, the causality check, each bucket's lowest point) is one call
(``feed_segment``: the steps and bits of :func:`_fast_segment`) for blocks of any size, a
tick's robot states included; without them, blocks of up to 48 arrivals take Python numbers
(:func:`_small_segment`) and larger ones the numpy steps.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import jit

if TYPE_CHECKING:
    from wristscan.daemon.sync.clockmap import ClockMapper

__all__ = ["feed_block", "feed_lists"]

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]

# Arrivals examined at once (a whole recording fed in one call is taken in slices of this).
_LOOKAHEAD = 4096
# Blocks of at most this many arrivals take the scalar path (:func:`_small_segment`): a few us
# of Python per arrival cost less there than the ~30 numpy calls of :func:`_fast_segment`.
_SMALL = 48
# Blocks spanning fewer buckets than this take their bucket minima one bucket at a time (a 10 ms
# tick spans one or two 10 ms buckets): fewer numpy calls than the segmented reductions.
_FEW_BUCKETS = 4


def feed_block(cm: ClockMapper, xs: IntArray, ys: IntArray) -> IntArray:
    """Feed arrivals ``(xs, ys)`` (int64 ns, in arrival order) to ``cm``; the epoch of each."""
    n = int(xs.shape[0])
    out = np.empty(n, dtype=np.int64)
    i = 0
    kern = jit.kernel("feed_segment")
    if kern is not None:  # the layout it was compiled for (strided views: one copy)
        xs, ys = np.ascontiguousarray(xs), np.ascontiguousarray(ys)
    lists = (xs.tolist(), ys.tolist()) if n <= _SMALL and kern is None else None
    while i < n:
        j = -1 if lists is None else _small_segment(cm, lists[0], lists[1], i)
        if j < 0:
            j = _fast_segment(cm, xs, ys, i) if kern is None else _compiled(cm, kern, xs, ys, i)
        if j > i:
            out[i:j] = cm.epoch
            i = j
            continue
        # Unusual: this arrival goes through feed(); the fast path is tried again after it.
        out[i] = cm.feed(int(xs[i]), int(ys[i]))
        i += 1
    return out


def feed_lists(cm: ClockMapper, xs: list[int], ys: list[int]) -> None:
    """:func:`feed_block` for arrivals given as lists of ints (a tick's robot states), without
    the epochs: a few arrivals take the scalar path with no array made (the same steps)."""
    if jit.kernel("feed_segment") is not None:  # compiled: no Python steps per arrival
        feed_block(cm, np.array(xs, dtype=np.int64), np.array(ys, dtype=np.int64))
        return
    n = len(xs)
    i = 0
    while i < n:
        j = _small_segment(cm, xs, ys, i) if n <= _SMALL else -1
        if j < 0:
            feed_block(cm, np.asarray(xs[i:], dtype=np.int64), np.asarray(ys[i:], dtype=np.int64))
            return
        if j == i:
            cm.feed(xs[i], ys[i])  # unusual: as feed_block does
            j += 1
        i = j


def _fast_segment(cm: ClockMapper, xs: IntArray, ys: IntArray, i: int) -> int:
    """Add the ordinary arrivals from ``i`` on, up to and including the next refit (done);
    returns the index after the last one added (``i`` if arrival ``i`` is unusual)."""
    cfg = cm.config
    line = cm._line
    if cm._n == 0 or cm._excess or cm._stuck_n or line is None:
        return i
    # Candidates: arrivals with device time increasing from the newest one.
    x = xs[i : i + _LOOKAHEAD]
    end = int(x.shape[0])
    if x[0] <= cm._x_last:
        return i
    if end > 1 and not (x[1:] > x[:-1]).all():
        end = int(np.argmin(x[1:] > x[:-1])) + 1
    # The arrival after which feed() would refit ends the segment (the line is fixed up to it).
    interval = cfg.refit_interval_ns if cm.locked else cfg.bucket_ns
    due = int(np.searchsorted(x[:end], cm._last_fit_x + interval))
    refit = due < end
    if refit:
        end = due + 1
    x = x[:end]
    y = ys[i : i + end]
    dxi = x - cm._x_ref
    dx = dxi.astype(np.float64)
    r = (y - cm._y_ref).astype(np.float64) - dx
    if cm._ever_locked:
        gap = r - (line.a + line.d * dx)
        # The tolerance is at least reanchor + 3 u0: exact test only when that is crossed.
        if float(gap.min()) < -(cfg.reanchor_tolerance_ns + 3.0 * line.u0):
            below = np.flatnonzero(gap < -(cfg.reanchor_tolerance_ns + 3.0 * line.uncertainty(dx)))
            if below.size:
                # Received before the line: feed() decides (re-anchor or jump) from there.
                end = int(below[0])
                refit = False
                if end == 0:
                    return i
                x, y, dxi, dx, r = x[:end], y[:end], dxi[:end], dx[:end], r[:end]
    _add_many(cm, x, y, dxi, dx, r)
    if refit:
        cm._refit()
    return i + end


def _compiled(cm: ClockMapper, kern: Callable[..., Any], xs: IntArray, ys: IntArray, i: int) -> int:
    """:func:`_fast_segment` with its arithmetic in one compiled call (``feed_segment``, the
    same steps and bits: :mod:`wristscan.calib.jit_clock`), the bookkeeping as there."""
    line = cm._line
    if cm._n == 0 or cm._excess or cm._stuck_n or line is None:
        return i
    cfg = cm.config
    interval = cfg.refit_interval_ns if cm.locked else cfg.bucket_ns
    tol = cfg.reanchor_tolerance_ns
    # Tuples (no arrays made) of the types the kernel was compiled for.
    params = (line.a, line.d, line.u0**2, line.u_slope, line.x_e, cfg.bucket_ns)
    stop = min(int(xs.shape[0]), i + _LOOKAHEAD)
    out_b, out_xr = np.empty(stop - i, dtype=np.int64), np.empty((stop - i, 2))
    end, refit, nb = kern(
        xs, ys, i, stop, int(cm._x_last), int(cm._last_fit_x + interval),
        (int(cm._x_ref), int(cm._y_ref)), tuple(map(float, params)), bool(cm._ever_locked),
        -(tol + 3.0 * line.u0), float(tol), out_b, out_xr,
    )  # fmt: skip
    if end == i:
        return i
    m = end - i
    cm.n_fed += m
    cm._n += m
    keep = max(i, end - (cm._recent.maxlen or m))
    cm._recent.extend(zip(xs[keep:end].tolist(), ys[keep:end].tolist(), strict=True))
    cm._x_last = int(xs[end - 1])
    bb = out_b[:nb].tolist()
    if bb[-1] - bb[0] < _FEW_BUCKETS:  # as _add_many decides: a few buckets one by one
        for b, (dx, r) in zip(bb, out_xr[:nb].tolist(), strict=True):
            _bucket_point(cm, b, dx, r, line.d)
    else:
        _merge_buckets(cm, bb, out_xr[:nb, 0], out_xr[:nb, 1], line.d)
    if refit:
        cm._refit()
    return end


def _small_segment(cm: ClockMapper, xs: list[int], ys: list[int], i: int) -> int:
    """:func:`_fast_segment` with Python scalars, for a small block (lists ``xs``, ``ys``): the
    same checks and the same floating-point steps, the arrivals then added one by one as
    ``ClockMapper._add`` does (without its refit). -1 when an arrival lies below the line by
    more than the quick tolerance (the exact test is :func:`_fast_segment`'s); nothing is
    changed then."""
    line = cm._line
    if cm._n == 0 or cm._excess or cm._stuck_n or line is None:
        return i
    cfg = cm.config
    n = len(xs)
    prev = cm._x_last
    if xs[i] <= prev:
        return i
    due = cm._last_fit_x + (cfg.refit_interval_ns if cm.locked else cfg.bucket_ns)
    x_ref, y_ref = cm._x_ref, cm._y_ref
    a, d = line.a, line.d
    lim = -(cfg.reanchor_tolerance_ns + 3.0 * line.u0) if cm._ever_locked else -math.inf
    pts: list[tuple[int, float, float]] = []
    refit = False
    end = i
    while end < n:
        x = xs[end]
        if x <= prev:
            break
        dxi = x - x_ref
        dx = float(dxi)
        r = float(ys[end] - y_ref) - dx
        if r - (a + d * dx) < lim:
            return -1
        pts.append((dxi, dx, r))
        end += 1
        prev = x
        if x >= due:
            refit = True
            break
    cm.n_fed += end - i
    cm._n += end - i
    cm._recent.extend(zip(xs[i:end], ys[i:end], strict=True))
    cm._x_last = prev
    bucket = cfg.bucket_ns
    # Each bucket's lowest point (the first of equals), then as _add does for one arrival.
    ob, ox, o_r, og = pts[0][0] // bucket, pts[0][1], pts[0][2], pts[0][2] - d * pts[0][1]
    for dxi, dx, r in pts[1:]:
        b, g = dxi // bucket, r - d * dx
        if b != ob:
            _bucket_point(cm, ob, ox, o_r, d)
            ob, ox, o_r, og = b, dx, r, g
        elif g < og:
            ox, o_r, og = dx, r, g
    _bucket_point(cm, ob, ox, o_r, d)
    if refit:
        cm._refit()
    return end


def _bucket_point(cm: ClockMapper, b: int, dx: float, r: float, d: float) -> None:
    """As ``ClockMapper._add`` keeps one point per bucket: the lowest against the drift ``d``
    in bucket ``b``; the bucket before it goes to the window when ``b`` starts a new one."""
    if b == cm._ob:
        if r - d * dx < cm._or - d * cm._ox:
            cm._ox, cm._or = dx, r
    else:
        if cm._ob >= 0:
            cm._push(cm._ox, cm._or)
        cm._ob, cm._ox, cm._or = b, dx, r


def _add_many(
    cm: ClockMapper, x: IntArray, y: IntArray, dxi: IntArray, dx: FloatArray, r: FloatArray
) -> None:
    """``ClockMapper._add`` for arrivals in increasing device time, without the refit."""
    m = int(x.shape[0])
    cm.n_fed += m
    cm._n += m
    keep = cm._recent.maxlen or m
    cm._recent.extend(zip(x[-keep:].tolist(), y[-keep:].tolist(), strict=True))
    cm._x_last = int(x[-1])
    line = cm._line
    d = line.d if line is not None else (cm._prior[0] if cm._prior else 0.0)
    bucket = cm.config.bucket_ns
    g = r - d * dx
    b_first, b_last = int(dxi[0]) // bucket, int(dxi[-1]) // bucket
    if b_last - b_first < _FEW_BUCKETS:
        # A tick spans one bucket or a few: the lowest point of each (the first of equals),
        # then as _add does for one arrival. (dxi increases: a bucket's arrivals are a run.)
        edges = [b * bucket for b in range(b_first + 1, b_last + 1)]
        cuts = [0, *np.searchsorted(dxi, edges).tolist(), m] if edges else [0, m]
        for bk, (s0, s1) in enumerate(itertools.pairwise(cuts), start=b_first):
            if s1 > s0:
                k = s0 + int(g[s0:s1].argmin())
                _bucket_point(cm, bk, float(dx[k]), float(r[k]), d)
        return
    b = dxi // bucket
    starts = np.flatnonzero(b[1:] != b[:-1]) + 1
    starts = np.concatenate(([0], starts))
    low = np.minimum.reduceat(g, starts)
    ends = np.append(starts[1:], m)
    pos = np.flatnonzero(g == np.repeat(low, ends - starts))
    first = pos[np.searchsorted(pos, starts)]
    _merge_buckets(cm, b[starts].tolist(), dx[first], r[first], d)


def _merge_buckets(
    cm: ClockMapper, bb: list[int], bx: FloatArray, br: FloatArray, d: float
) -> None:
    """Buckets ``bb`` (increasing) with their lowest points ``(bx, br)`` against the drift
    ``d``, after the open one: merged with it, the closed ones pushed to the window."""
    if bb[0] == cm._ob:
        # Continues the open bucket: keep the lower of the two (the open one on a tie).
        if not br[0] - d * bx[0] < cm._or - d * cm._ox:
            bx, br = bx.copy(), br.copy()
            bx[0], br[0] = cm._ox, cm._or
    elif cm._ob >= 0:
        bx = np.concatenate(([cm._ox], bx))
        br = np.concatenate(([cm._or], br))
    cm._ob = int(bb[-1])
    cm._ox, cm._or = float(bx[-1]), float(br[-1])
    if bx.shape[0] > 1:
        _push_many(cm, bx[:-1], br[:-1])


def _push_many(cm: ClockMapper, bx: FloatArray, br: FloatArray) -> None:
    """``ClockMapper._push`` for several closed buckets in order."""
    k = int(bx.shape[0])
    size = cm._bx.shape[0]
    lo = float(bx[-1]) - cm.config.window_ns
    if k > cm._cap:
        bx, br, k = bx[-cm._cap :], br[-cm._cap :], cm._cap
    if cm._b1 + k > size:
        n = cm._b1 - cm._b0
        keep = min(n, size - k)
        cm._bx[:keep] = cm._bx[cm._b1 - keep : cm._b1]
        cm._br[:keep] = cm._br[cm._b1 - keep : cm._b1]
        cm._b0, cm._b1 = 0, keep
    cm._bx[cm._b1 : cm._b1 + k] = bx
    cm._br[cm._b1 : cm._b1 + k] = br
    cm._b1 += k
    # Slide the window (and bound the memory).
    stored = cm._bx[cm._b0 : cm._b1]
    drop = int(np.searchsorted(stored, lo, side="left")) if stored[0] < lo else 0
    cm._b0 += max(drop, cm._b1 - cm._b0 - cm._cap)
