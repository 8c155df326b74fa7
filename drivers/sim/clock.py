"""A simulated device clock: offset, drift and stamping jitter against the host monotonic clock.

``device_ns(h) = offset_ns + (h - epoch_host_ns) * (1 + drift_ppm * 1e-6) + jitter``

* ``epoch_host_ns`` is the host time at which the device clock read ``offset_ns`` (power-on or the
  last :meth:`DeviceClock.reset`); it defaults to the construction time.
* ``drift_ppm`` > 0: the device clock runs fast.
* ``jitter`` is independent Gaussian noise (std ``jitter_ns``) on every stamp the device writes,
  not on the instants themselves; :meth:`ideal_ns` leaves it out.

Host times are ``time.monotonic_ns()`` values (CLOCK_MONOTONIC, shared by all processes).
"""

from __future__ import annotations

import time

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["DeviceClock"]


class DeviceClock:
    def __init__(
        self,
        offset_ns: int = 0,
        drift_ppm: float = 0.0,
        jitter_ns: float = 0.0,
        rng: np.random.Generator | int | None = None,
        epoch_host_ns: int | None = None,
    ) -> None:
        if jitter_ns < 0:
            raise ValueError("jitter_ns must be >= 0")
        self.offset_ns = int(offset_ns)
        self.drift_ppm = float(drift_ppm)
        self.jitter_ns = float(jitter_ns)
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        self.epoch_host_ns = time.monotonic_ns() if epoch_host_ns is None else int(epoch_host_ns)

    @property
    def rate(self) -> float:
        """Device seconds per host second."""
        return 1.0 + self.drift_ppm * 1e-6

    def ideal_ns(self, host_ns: ArrayLike) -> NDArray[np.int64]:
        """Device time at host time(s) ``host_ns``, without jitter (int64 ns)."""
        h = np.asarray(host_ns, dtype=np.int64)
        # Integer elapsed time first: float64 keeps ns exact for elapsed times below ~100 days.
        elapsed = (h - self.epoch_host_ns).astype(np.float64)
        return np.asarray(self.offset_ns + np.rint(elapsed * self.rate).astype(np.int64))

    def device_ns(self, host_ns: ArrayLike) -> NDArray[np.int64]:
        """Device stamps at host time(s) ``host_ns``: :meth:`ideal_ns` plus jitter."""
        ideal = self.ideal_ns(host_ns)
        if self.jitter_ns <= 0:
            return ideal
        noise = np.rint(self.rng.standard_normal(ideal.shape) * self.jitter_ns).astype(np.int64)
        return np.asarray(ideal + noise)

    def host_ns(self, device_ns: ArrayLike) -> NDArray[np.int64]:
        """Inverse of :meth:`ideal_ns`: the host time at which the device read ``device_ns``."""
        d = np.asarray(device_ns, dtype=np.int64)
        elapsed = (d - self.offset_ns).astype(np.float64) / self.rate
        return np.asarray(self.epoch_host_ns + np.rint(elapsed).astype(np.int64))

    def now_ns(self) -> int:
        """The device clock now (with jitter)."""
        return int(self.device_ns(time.monotonic_ns()))

    def reset(self, host_ns: int | None = None, offset_ns: int | None = None) -> None:
        """Restart the clock (a device reboot or a time-reset command): from ``host_ns``
        (default: now) it reads ``offset_ns`` (default: the configured offset)."""
        self.epoch_host_ns = time.monotonic_ns() if host_ns is None else int(host_ns)
        if offset_ns is not None:
            self.offset_ns = int(offset_ns)
