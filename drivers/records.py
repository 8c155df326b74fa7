"""The records every driver yields and every later stage consumes (DESIGN.md, "Records").

All units are SI: metres, radians, seconds for the controller timestamp, integer nanoseconds for
device and host timestamps.  Host times come from ``time.monotonic_ns()``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

__all__ = ["AlignedBatch", "Profile", "RobotState", "TableState"]


@dataclass(slots=True)
class Profile:
    """One laser profile in the sensor frame (laser plane = sensor Y-Z plane, X normal to it).

    ``y`` and ``z`` are float64 arrays in metres of equal length; ``valid`` marks points the
    sensor measured (invalid points keep their slot so indices stay stable). Drivers may hand
    out a read-only ``y`` shared by the profiles of a uniform lateral grid: copy before editing.
    """

    sensor_id: int
    frame_counter: int
    sensor_time_ns: int
    """Device clock at exposure as the device reports it, converted to ns (not host time)."""
    host_time_ns: int
    """Host monotonic clock at receipt (``time.monotonic_ns()``)."""
    y: NDArray[np.float64]
    z: NDArray[np.float64]
    valid: NDArray[np.bool_]
    intensity: NDArray[np.uint8] | None = None
    encoder: int | None = None

    def __post_init__(self) -> None:
        if self.y.shape != self.z.shape or self.valid.shape != self.y.shape:
            raise ValueError(
                f"profile arrays disagree: y {self.y.shape}, z {self.z.shape}, "
                f"valid {self.valid.shape}"
            )

    @property
    def n_points(self) -> int:
        return int(self.y.shape[0])


@dataclass(slots=True)
class RobotState:
    """One controller sample."""

    controller_time_s: float
    """RTDE ``timestamp``: seconds since the controller started."""
    host_time_ns: int
    q: NDArray[np.float64]
    """Actual joint positions (6,), radians."""
    tcp_pose: NDArray[np.float64]
    """Controller TCP pose ``[x, y, z, rx, ry, rz]`` (metres, rotation vector)."""
    protective_stop: bool = False
    program_running: bool = False
    qd: NDArray[np.float64] | None = None
    """Actual joint velocities (6,), rad/s, when the driver reads them."""


@dataclass(slots=True)
class TableState:
    """One rotary-table reading."""

    angle_rad: float
    device_time_ns: int | None
    host_time_ns: int


@dataclass(slots=True)
class AlignedBatch:
    """Points aligned into a named frame, several profiles at once."""

    frame_id: str
    """``"base"``, ``"table"`` or ``"part"``."""
    xyz: NDArray[np.float32]
    """(N, 3) metres."""
    profile_time_ns: NDArray[np.int64]
    """(P,) exposure instants of the profiles on the host clock (ns)."""
    sensor2frame: NDArray[np.float64]
    """(P, 4, 4) sensor pose of each profile in ``frame_id``."""
    profile_index: NDArray[np.uint32]
    """(N,) index into the batch's profiles for each point."""
    intensity: NDArray[np.uint8] | None = None
    seq: int = 0
    utc_offset_ns: int = field(default=0)
    """Add to host monotonic ns to get UTC ns (for the WSC1 header)."""
