"""A simulated sensor that cannot keep its timing (issue 21): ``SensorSimConfig.send_late_s``.

Profiles are due at their send time (``t_k + latency_s``); a late sender wakes every
uniform(0, hi - lo) seconds (``send_late_spike_prob`` of its wake-ups 100-300 ms later still) and
sends the profiles due at least ``lo`` before. Each leaves ``lo`` to ``hi`` late (more after a
spike), in bursts, in order, as a sensor process descheduled by a busy host does.
"""

from __future__ import annotations

from collections import deque
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from wristscan.drivers.sim.sensor_config import SensorSimConfig

__all__ = ["LateSender"]


class LateSender:
    """Send times of a late sender, profile by profile in order (``send_times``)."""

    def __init__(self, cfg: SensorSimConfig, rng: np.random.Generator, start_ns: int) -> None:
        lo, hi = cfg.send_late_s
        self.lo_ns = round(lo * 1e9)
        self.span_ns = max(0.0, (hi - lo) * 1e9)
        self.spike_prob = cfg.send_late_spike_prob
        self.rng = rng
        self.wakes: deque[int] = deque([start_ns])
        """The coming wake-up times (the last one at or after the newest profile ready)."""

    def send_times(self, due: NDArray[np.int64]) -> NDArray[np.int64]:
        """When the profiles due at ``due`` (ns, increasing, after the previous call's) leave."""
        ready = due + self.lo_ns
        if self.span_ns <= 0.0 or ready.size == 0:
            return ready
        wakes = self.wakes
        last = int(ready[-1])
        while wakes[-1] < last:
            gap = self.rng.uniform(0.0, self.span_ns)
            if self.rng.random() < self.spike_prob:
                gap += self.rng.uniform(0.1e9, 0.3e9)
            wakes.append(wakes[-1] + int(gap))
        w = np.fromiter(wakes, dtype=np.int64, count=len(wakes))
        while wakes[0] < last:  # the last wake is >= last: one always stays
            wakes.popleft()
        out: NDArray[np.int64] = w[np.searchsorted(w, ready)]
        return out
