"""Unwrapping device counters that wrap (SCIP 24-bit ms, 32-bit us, encoder counts, ...).

A wrapped counter must be unwrapped before its values reach a :class:`~.clockmap.ClockMapper`:
offline with :func:`unwrap`, online with :class:`CounterUnwrapper` (which also tells a wrap from
a counter reset using the host time elapsed), or against a known nearby value with
:func:`unwrap_nearest`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["CounterUnwrapper", "unwrap", "unwrap_nearest"]

IntArray = NDArray[np.int64]


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

    def many(self, raw: ArrayLike, host_ns: ArrayLike) -> IntArray:
        """:meth:`__call__` for arrays of values received in order at ``host_ns``: the same
        outputs and the same state, vectorised. Each stretch is unwrapped as a chain of steps and
        checked against the per-value rule (nearest to the newest so far, plausible for the host
        time elapsed); a value that fails the check (a reset) goes through :meth:`__call__`."""
        r = np.asarray(raw, dtype=np.int64) % np.int64(self.modulus)
        h = np.asarray(host_ns, dtype=np.int64)
        if r.shape != h.shape or r.ndim != 1:
            raise ValueError(f"CounterUnwrapper.many: raw {r.shape} and host {h.shape} differ")
        out = np.empty(r.shape[0], dtype=np.int64)
        i = 0
        while i < r.shape[0]:
            k = 0 if self._newest is None else self._run(r[i:], h[i:], out[i:])
            i += k
            if i < r.shape[0]:
                out[i] = self(int(r[i]), int(h[i])) // self.tick_ns
                i += 1
        return out * np.int64(self.tick_ns)

    def _run(self, r: IntArray, h: IntArray, out: IntArray) -> int:
        """Unwrap the longest prefix of ``r`` that needs no reset into ``out`` (ticks); returns
        its length and leaves the state as :meth:`__call__` would after it."""
        m = np.int64(self.modulus)
        newest0 = self._newest
        assert newest0 is not None
        first = r[0] + ((newest0 - r[0] + m // 2) // m) * m
        step = np.diff(r) % m
        step = np.where(step > m // 2, step - m, step)
        cand = first + np.concatenate([[0], np.cumsum(step)])
        # The newest value before each candidate, if every candidate is accepted.
        newest = np.maximum.accumulate(np.concatenate([[newest0], cand]))
        before = newest[:-1]
        ok = cand == r + ((before - r + m // 2) // m) * m
        is_new = cand > before
        # Host time of the newest value before each candidate (it moves with every new max).
        last = np.maximum.accumulate(np.where(is_new, np.arange(r.shape[0]), -1))
        src = np.concatenate([[-1], last[:-1]])
        h0 = self._newest_host
        host_before = np.where(src >= 0, h[np.maximum(src, 0)], 0 if h0 is None else h0)
        step_ns = (cand - before) * self.tick_ns
        bound = (h - host_before).astype(np.float64) * (1.0 + self.max_drift) + self.slack_ns
        plausible = (step_ns >= -self.slack_ns) & (step_ns <= bound)
        ok &= plausible if h0 is not None else plausible | (src < 0)
        k = r.shape[0] if ok.all() else int(np.argmin(ok))
        if k == 0:
            return 0
        out[:k] = cand[:k]
        top = int(newest[k])
        if top > newest0:
            self.n_wraps += top // self.modulus - newest0 // self.modulus
            self._newest = top
            self._newest_host = int(h[int(np.flatnonzero(is_new[:k])[-1])])
        return k

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
