"""Graceful overload: admit profiles into the pairer at the rate the worker can process them.

When profiles arrive faster than the worker can pair, align and publish them, a worker that
takes everything falls further behind every tick: its latency grows without bound, the socket
buffer overflows and the kernel drops datagrams at random, uncounted by reason. Instead the
worker reads and decodes everything (cheap, and it keeps the socket drained), then admits at most
what it can process and sheds the rest as whole profiles, spread evenly over the tick's
profiles (the cloud stays uniformly sampled along the path), counted as ``overload``.

The admissible rate comes from the worker's own measured wall time per profile, in two parts:
reading and decoding (``c_read``, paid for every profile that arrives) and the rest (``c_keep``:
pairing, alignment, encoding, zenoh put, paid only for admitted ones). With ``u`` the share of
the worker's time to fill (``utilisation``) and ``rate_in`` the arrival rate, the worker keeps up
while ``rate_in * c_read + rate_keep * c_keep <= u``, so

    rate_keep = (u - rate_in * c_read) / c_keep.

A token bucket at that rate, holding ``burst_s`` worth of tokens, admits the profiles: below
capacity it never runs dry (a backlog after a pause of up to ``burst_s`` times the headroom goes
through whole); above it the worker publishes at ``u`` of its capacity; as soon as the rate drops
the bucket refills and nothing is shed. Wall time, not CPU time: a worker that waits for the GIL
or a CPU processes fewer profiles, and that is the capacity that matters.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from wristscan.drivers.records import ProfileBlock

__all__ = ["Shedder", "spread_rows", "take_rows"]


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
    """Token-bucket admission at the measured capacity (see the module docstring).

    Feed it the worker's measured costs (:meth:`note_read`, :meth:`note_kept`) and ask
    :meth:`admit` how many of the profiles that arrived may go on. Times in ns.
    """

    def __init__(
        self,
        utilisation: float = 0.9,
        burst_s: float = 0.25,
        smoothing: float = 0.1,
        min_profiles: int = 10,
    ) -> None:
        if not (0.0 < utilisation <= 1.0 and burst_s > 0.0 and 0.0 < smoothing <= 1.0):
            raise ValueError("Shedder: 0 < utilisation <= 1, burst_s > 0, 0 < smoothing <= 1")
        self.utilisation = utilisation
        self.burst_s = burst_s
        self.smoothing = smoothing
        self.min_profiles = min_profiles
        self.c_read_ns: float | None = None
        """Wall ns per profile read and decoded (smoothed)."""
        self.c_keep_ns: float | None = None
        """Wall ns per admitted profile: pairing, alignment, encoding, publishing (smoothed)."""
        self.rate_in = 0.0
        """Arrival rate (profiles/s, smoothed)."""
        self._tokens = math.inf
        self._last_ns: int | None = None
        self.shed = 0
        self.shedding = False
        """Whether the latest admission shed profiles."""

    def _smooth(self, old: float | None, new: float) -> float:
        return new if old is None else old + self.smoothing * (new - old)

    def note_read(self, n_profiles: int, wall_ns: int) -> None:
        """``n_profiles`` read and decoded in ``wall_ns``."""
        if n_profiles >= self.min_profiles:
            self.c_read_ns = self._smooth(self.c_read_ns, wall_ns / n_profiles)

    def note_kept(self, n_profiles: int, wall_ns: int) -> None:
        """``n_profiles`` admitted ones paired, aligned and published in ``wall_ns``."""
        if n_profiles >= self.min_profiles:
            self.c_keep_ns = self._smooth(self.c_keep_ns, wall_ns / n_profiles)

    @property
    def capacity_per_s(self) -> float:
        """Profiles per second the worker can admit now (inf before it has measured)."""
        if self.c_keep_ns is None:
            return math.inf
        spare = self.utilisation - self.rate_in * (self.c_read_ns or 0.0) * 1e-9
        # Never below a tenth of the worker's time: something always gets through.
        spare = max(spare, 0.1 * self.utilisation)
        return spare / (self.c_keep_ns * 1e-9)

    def admit(self, n_in: int, now_ns: int) -> int:
        """How many of the ``n_in`` profiles that arrived since the last call go on."""
        last, self._last_ns = self._last_ns, now_ns
        dt = 0.0 if last is None else max(0.0, (now_ns - last) * 1e-9)
        if dt > 0.0:
            # Smoothed over ~1/smoothing calls, weighted by their duration.
            w = min(1.0, self.smoothing * dt / 0.01)
            self.rate_in += w * (n_in / dt - self.rate_in)
        cap = self.capacity_per_s
        if math.isinf(cap):
            self.shedding = False
            return n_in
        full = max(cap * self.burst_s, float(self.min_profiles))
        self._tokens = min(full, self._tokens + cap * dt)
        keep = min(n_in, int(self._tokens))
        self._tokens -= keep
        self.shedding = keep < n_in
        self.shed += n_in - keep
        return keep

    def status(self) -> dict[str, float | bool | int | None]:
        """For ``stats``: the measured costs (us), arrival rate and capacity (profiles/s)."""
        cap = self.capacity_per_s
        return {
            "shedding": self.shedding,
            "shed": self.shed,
            "read_us_per_profile": None
            if self.c_read_ns is None
            else round(self.c_read_ns / 1e3, 2),
            "keep_us_per_profile": None
            if self.c_keep_ns is None
            else round(self.c_keep_ns / 1e3, 2),
            "rate_in_per_s": round(self.rate_in, 1),
            "capacity_per_s": None if math.isinf(cap) else round(cap, 1),
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
