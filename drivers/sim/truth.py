"""Ground truth shared between the simulated cell's processes.

The simulated controller, rotary table and sensors run as separate processes (ur_rtde holds the GIL
while it connects, so they cannot be threads of the test process). The sensors need the robot's
TRUE joint positions at each exposure instant, so the controller appends them to a ring in shared
memory and every sensor process reads it.

One writer, any number of readers, no locks: the writer fills a slot, then publishes it by bumping
a 64-bit counter; a reader copies the window it needs and re-reads the counter to discard slots
the writer may have overwritten meanwhile. Times are host ``time.monotonic_ns()`` values, which
all processes on the machine share (CLOCK_MONOTONIC).
"""

from __future__ import annotations

import logging
import secrets
import threading
from multiprocessing import resource_tracker, shared_memory

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["TruthRing"]

log = logging.getLogger(__name__)

_ATTACH_LOCK = threading.Lock()
_HEADER_BYTES = 64  # count (u64), width (u64), capacity (u64), padding


class TruthRing:
    """A shared-memory ring of timestamped float64 vectors."""

    def __init__(self, shm: shared_memory.SharedMemory, owner: bool) -> None:
        self._shm = shm
        self._owner = owner
        buf = shm.buf
        assert buf is not None  # an open segment always has a buffer
        header = np.ndarray((3,), dtype=np.uint64, buffer=buf[:24])
        self.width = int(header[1])
        self.capacity = int(header[2])
        self._count = np.ndarray((1,), dtype=np.uint64, buffer=buf[:8])
        t_bytes = 8 * self.capacity
        t_end = _HEADER_BYTES + t_bytes
        self._t = np.ndarray((self.capacity,), dtype=np.int64, buffer=buf[_HEADER_BYTES:t_end])
        self._v = np.ndarray(
            (self.capacity, self.width),
            dtype=np.float64,
            buffer=buf[t_end : t_end + t_bytes * self.width],
        )
        self._closed = False

    @property
    def name(self) -> str:
        return self._shm.name

    @classmethod
    def create(cls, width: int, capacity: int = 65536, name: str | None = None) -> TruthRing:
        """Create a ring of ``capacity`` samples of ``width`` float64 values each."""
        if width < 1 or capacity < 2:
            raise ValueError("TruthRing needs width >= 1 and capacity >= 2")
        size = _HEADER_BYTES + 8 * capacity * (1 + width)
        shm = shared_memory.SharedMemory(
            name=name or f"wsc_truth_{secrets.token_hex(6)}", create=True, size=size
        )
        assert shm.buf is not None
        header = np.ndarray((3,), dtype=np.uint64, buffer=shm.buf[:24])
        header[:] = (0, width, capacity)
        del header
        return cls(shm, owner=True)

    @classmethod
    def attach(cls, name: str) -> TruthRing:
        """Open an existing ring by name (from any process)."""
        # Python < 3.13 registers attached segments with the resource tracker, which unlinks
        # them when the tracker's processes exit (or complains when the creator unlinks after a
        # reader unregistered). Readers must not own the segment: skip registration.
        with _ATTACH_LOCK:
            register = resource_tracker.register
            resource_tracker.register = lambda *args, **kwargs: None
            try:
                shm = shared_memory.SharedMemory(name=name, create=False)
            finally:
                resource_tracker.register = register
        return cls(shm, owner=False)

    def append(self, t_ns: int, values: ArrayLike) -> None:
        """Publish one sample; times must not decrease."""
        n = int(self._count[0])
        slot = n % self.capacity
        self._t[slot] = t_ns
        self._v[slot] = np.asarray(values, dtype=np.float64)
        self._count[0] = n + 1

    def __len__(self) -> int:
        return min(int(self._count[0]), self.capacity)

    def latest(self) -> tuple[int, NDArray[np.float64]] | None:
        n = int(self._count[0])
        if n == 0:
            return None
        slot = (n - 1) % self.capacity
        return int(self._t[slot]), self._v[slot].copy()

    def sample(self, t_ns: ArrayLike) -> NDArray[np.float64]:
        """Linearly interpolated values at host times ``t_ns`` ``(M,)``; NaN rows outside the
        window the ring covers (never extrapolated).

        Searches the ring in place (its one or two sorted runs of slots) and copies only the
        bracketing samples: copying the whole ring per call cost a simulated sensor a third of
        its CPU."""
        tq = np.atleast_1d(np.asarray(t_ns, dtype=np.int64))
        out = np.full((tq.shape[0], self.width), np.nan)
        cap = self.capacity
        n1 = int(self._count[0])
        if n1 == 0:
            return out
        first = max(0, n1 - cap)
        count = n1 - first
        s0 = first % cap
        if count == 1:
            t_only = int(self._t[s0])
            out[tq == t_only] = self._v[s0]
            return out
        # The logical sequence first..n1-1 as one or two physical runs, each sorted.
        run_a = self._t[s0 : min(cap, s0 + count)]
        run_b = self._t[0 : max(0, s0 + count - cap)]
        t_first = int(run_a[0])
        t_last = int(run_b[-1]) if run_b.shape[0] else int(run_a[-1])
        inside = (tq >= t_first) & (tq <= t_last)
        if not inside.any():
            return out
        q = tq[inside]
        pos = np.searchsorted(run_a, q, side="left")
        if run_b.shape[0]:
            in_b = q > run_a[-1]
            pos[in_b] = run_a.shape[0] + np.searchsorted(run_b, q[in_b], side="left")
        hi = np.clip(pos, 1, count - 1)
        lo = hi - 1
        slot_lo, slot_hi = (first + lo) % cap, (first + hi) % cap
        t_lo, t_hi = self._t[slot_lo], self._t[slot_hi]
        v_lo, v_hi = self._v[slot_lo], self._v[slot_hi]
        # Slots the writer reused while we read are no longer trustworthy: leave those NaN.
        n2 = int(self._count[0])
        ok = first + lo >= n2 - cap
        dt = (t_hi - t_lo).astype(np.float64)
        w = np.where(dt > 0, (q - t_lo).astype(np.float64) / np.where(dt > 0, dt, 1.0), 0.0)
        vals = v_lo + (v_hi - v_lo) * w[:, None]
        vals[~ok] = np.nan
        out[inside] = vals
        return out

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        # Drop our views before closing the mapping (numpy views keep the buffer exported).
        del self._t, self._v, self._count
        self._shm.close()

    def unlink(self) -> None:
        """Remove the segment (creator only); readers that still hold it keep their mapping."""
        if self._owner:
            try:
                self._shm.unlink()
            except FileNotFoundError:
                pass

    def __enter__(self) -> TruthRing:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
        self.unlink()
