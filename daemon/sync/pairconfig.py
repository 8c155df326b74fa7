"""The settings of a :class:`~wristscan.daemon.sync.pairing.Pairer` (re-exported there)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from wristscan.calib import kinematics
from wristscan.daemon.sync.clockconfig import ClockConfig

__all__ = ["PairerConfig"]


@dataclass(frozen=True)
class PairerConfig:
    """Settings of a :class:`Pairer`. Times in ns, angles in rad."""

    mode: Literal["clock", "encoder"] = "clock"
    robot_model: str | kinematics.DHParams = "UR5e"
    interpolation: Literal["joint", "tcp"] = "joint"
    """``joint``: interpolate joints + forward kinematics; ``tcp``: interpolate the TCP pose."""
    tcp_offset: tuple[float, ...] = (0.0,) * 6
    """TCP configured on the controller (UR pose in the flange frame), for ``tcp`` mode."""
    sensor_latency_ns: int = 0
    """Exposure-to-timestamp latency of the sensors (measured by calib.latency). In encoder
    mode it is subtracted from the instant the count was reached: a trigger-to-exposure delay
    is a negative value."""
    robot_latency_ns: int = 0
    """Measurement-to-timestamp latency of the controller samples."""
    table_latency_ns: int = 0
    """Measurement-to-stamp latency of table readings (to receipt, if they carry no time)."""
    sensor_time_modulus_ns: int | None = None
    """Sensor timestamps wrap at this many ns (a 24-bit ms counter: ``2**24 * 10**6``)."""
    encoder_modulus: int | None = None
    """Encoder counts wrap at this value (``2**32`` for a 32-bit counter)."""
    max_wait_ns: int = 200_000_000
    """How long (host time after receipt) a profile may wait for the states it needs."""
    robot_max_gap_ns: int = 20_000_000
    """Largest spacing of two robot samples interpolated between (controller clock)."""
    robot_capacity: int = 8192
    use_table: bool = False
    table_max_gap_ns: int = 200_000_000
    table_period_rad: float | None = 2.0 * math.pi
    """Unwrap table angles with this period (None: the angle does not wrap)."""
    table_capacity: int = 4096
    encoder_max_gap_ns: int = 20_000_000
    encoder_capacity: int = 8192
    max_pending: int = 100_000
    """Profiles held at most; beyond, the oldest are dropped (bounded memory)."""
    max_batch_profiles: int = 512
    """Profiles per released batch at most (more ready at once are split). Only a backlog
    reaches it (5 kHz in 10 ms ticks makes 50): 512 x 2048 points keep a batch's arrays in
    the tens of MB, which the allocator reuses, where 4096 made 100 MB+ arrays that were
    mapped and page-faulted afresh for every batch just when the pipeline was behind."""
    sensor_clock: ClockConfig = field(default_factory=ClockConfig)
    robot_clock: ClockConfig = field(default_factory=ClockConfig)
    table_clock: ClockConfig = field(default_factory=ClockConfig)

    def __post_init__(self) -> None:
        if self.mode not in ("clock", "encoder"):
            raise ValueError(f"PairerConfig.mode must be 'clock' or 'encoder', not {self.mode!r}")
        if self.max_wait_ns <= 0 or self.max_pending < 1 or self.max_batch_profiles < 1:
            raise ValueError("PairerConfig: max_wait_ns, max_pending, max_batch_profiles > 0")
