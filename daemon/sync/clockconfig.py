"""The settings of a :class:`~.clockmap.ClockMapper`, with what each one does.

Kept apart from the estimator so that the pairer and the device setup can build and pass
settings around; the model behind them is described in :mod:`.clockmap`.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["ClockConfig"]


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
    """An epoch locks once the uncertainty at its newest point is below this."""
    unlock_factor: float = 10.0
    """A locked epoch unlocks only if its uncertainty exceeds this many ``max_uncertainty_ns``."""
    prune_margin_ns: int = 1_000_000
    """Buckets above a later one by more than this (plus ``max_drift`` times their distance)
    are dropped from the fit: they cannot touch the envelope (a backlog read in a burst)."""
    max_drift: float = 1e-3
    """Largest |drift| searched for (1e-3 = 1000 ppm); also the slope uncertainty before a fit."""
    typical_drift: float = 100e-6
    """Scale of a device clock's drift (crystals: tens of ppm): the prior of the first epoch's
    slope is 0 with this uncertainty, so a slope from little data is shrunk towards 0."""
    jump_tolerance_ns: int = 2_000_000
    """An arrival further below a locked line than this (plus 3 sigma) is a causality
    violation: a new epoch if it dropped there at once (clock jump), else a re-anchored fit."""
    reanchor_tolerance_ns: int = 500_000
    """An arrival further below a locked line than this (plus 3 sigma), short of a clock jump,
    means the fit locked on a raised delay floor: it is re-anchored (same epoch)."""
    persist_ns: int = 500_000_000
    """After device time went back (by less than ``reorder_tolerance_ns``), arrivals late by more
    than the jump tolerance for this long mean the device clock stepped back; device time not
    advancing for this long (host time) means it stopped. Either restarts the fit."""
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
        if not 0.0 < self.typical_drift <= self.max_drift:
            raise ValueError("ClockConfig.typical_drift must be in (0, max_drift]")
        if self.min_points < 2:
            raise ValueError("ClockConfig.min_points must be >= 2")
        if self.unlock_factor < 1.0 or self.prune_margin_ns < 0:
            raise ValueError("ClockConfig: unlock_factor must be >= 1, prune_margin_ns >= 0")
