"""What the acquisition pipeline measures about itself: per-stage latency percentiles
(:class:`LatencyWindow`, in ``stats``) and the worker's CPU time by step (:class:`StepCpu`).

Both sit on the worker's path: they allocate nothing per profile and take no lock per step.
"""

from __future__ import annotations

import threading
import time

import numpy as np
from numpy.typing import NDArray

__all__ = ["STEPS", "LatencyWindow", "StepCpu"]


class LatencyWindow:
    """The latest ``size`` per-profile latencies of each stage (ns), for percentiles in ``stats``.

    Stages: ``transport`` (estimated exposure to the driver's receipt: sensor latency plus the
    link), ``wait`` (receipt to the worker's tick that paired it: batching and waiting for the
    robot state after the exposure), ``process`` (that tick to the publish call returning:
    pairing, alignment, encoding, zenoh put) and ``total`` (exposure to published).
    """

    STAGES = ("transport", "wait", "process", "total")

    def __init__(self, size: int = 20000) -> None:
        self.size = size
        self._buf = np.zeros((len(self.STAGES), size), dtype=np.int64)
        self._n = 0
        self._lock = threading.Lock()

    def add(self, exposure_ns: NDArray[np.int64], arrival_ns: NDArray[np.int64], tick_ns: int,
            done_ns: int) -> None:  # fmt: skip
        k = min(int(exposure_ns.shape[0]), self.size)
        if k == 0:
            return
        e, a = exposure_ns[-k:], arrival_ns[-k:]
        rows = np.stack([a - e, tick_ns - a, np.full(k, done_ns - tick_ns), done_ns - e])
        with self._lock:
            start = self._n % self.size
            first = min(k, self.size - start)
            self._buf[:, start : start + first] = rows[:, :first]
            self._buf[:, : k - first] = rows[:, first:]
            self._n += k

    def summary(self) -> dict[str, dict[str, float]]:
        """p50, p99 and max of each stage in ms over the window (empty before any batch)."""
        with self._lock:
            data = self._buf[:, : min(self._n, self.size)].astype(np.float64) * 1e-6
        if data.shape[1] == 0:
            return {}
        p50, p99 = np.percentile(data, [50.0, 99.0], axis=1)
        mx = data.max(axis=1)
        return {
            st: {
                "p50": round(float(p50[i]), 3),
                "p99": round(float(p99[i]), 3),
                "max": round(float(mx[i]), 3),
            }
            for i, st in enumerate(self.STAGES)
        }


class StepCpu:
    """Adds the calling thread's CPU time inside ``with`` to one step's total (ns). One object
    per step, reused: no allocation on the worker's path; steps do not nest."""

    __slots__ = ("_t0", "ns")

    def __init__(self) -> None:
        self.ns = 0
        self._t0 = 0

    def __enter__(self) -> None:
        self._t0 = time.thread_time_ns()

    def __exit__(self, *exc: object) -> None:
        self.ns += time.thread_time_ns() - self._t0


STEPS = ("read", "pair", "align", "publish")
"""The worker's steps, each with a :class:`StepCpu`."""
