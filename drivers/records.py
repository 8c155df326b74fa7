"""The records every driver yields and every later stage consumes (DESIGN.md, "Records").

All units are SI: metres, radians, seconds for the controller timestamp, integer nanoseconds for
device and host timestamps.  Host times come from ``time.monotonic_ns()``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "AlignedBatch",
    "PointCodes",
    "Profile",
    "ProfileBlock",
    "RobotState",
    "TableState",
    "codes_to_metres",
]


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


@dataclass(frozen=True, slots=True)
class PointCodes:
    """Points as the sensor coded them: ``z = codes * scale_m + offset_m`` metres (float64,
    multiply then add), invalid where ``codes == sentinel``. The hot path aligns them as they
    are (the scale folded into the transform's input); ``decode`` gives the float64 z."""

    codes: NDArray[np.signedinteger]
    """(P, N) int16 or int32, C-contiguous (a copy: the receive buffer is reused)."""
    scale_m: float
    offset_m: float
    sentinel: int

    def take(self, rows: NDArray[np.integer] | slice) -> PointCodes:
        return PointCodes(self.codes[rows], self.scale_m, self.offset_m, self.sentinel)

    def decode(self) -> NDArray[np.float64]:
        """z (P, N) float64 metres, NaN where invalid (``lpf1.decode_profile``'s values)."""
        z, invalid = codes_to_metres(self.codes, self.scale_m, self.offset_m, self.sentinel)
        # Invalid points are few: their indices, then NaN there (a masked copy of every point
        # costs twice as much).
        bad = np.flatnonzero(invalid)
        if bad.size:
            z.reshape(-1)[bad] = np.nan
        return z


def codes_to_metres(
    codes: NDArray[np.signedinteger], scale_m: float, offset_m: float, sentinel: int
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Integer point codes in metres, ``float64(code) * scale_m + offset_m`` (multiply then
    add: the LPF1 decoders' values, bit for bit), and where a code is ``sentinel`` (invalid;
    z is left as computed there)."""
    invalid = codes == sentinel
    z = codes.astype(np.float64)  # exact; then in place (a casting multiply is slower)
    z *= scale_m
    z += offset_m
    return z, invalid


@dataclass(slots=True, init=False)
class ProfileBlock:
    """P profiles of N points each, as arrays: what the hot path moves instead of P records.

    Per profile ``(P,)`` int64: ``sensor_id``, ``frame_counter``, ``sensor_time_ns`` (device
    clock, as :attr:`Profile.sensor_time_ns`), ``host_time_ns`` (receipt, monotonic) and
    ``encoder`` with ``encoder_valid`` (None when no profile carries a count). Per point:
    ``y`` (N,) when every profile shares one lateral grid (read-only, shared) or (P, N);
    ``z`` (P, N) float64 metres, NaN where invalid; ``valid`` (P, N); ``intensity`` (P, N) or
    None. Rows are in arrival order. A block made with ``codes`` (:class:`PointCodes`) instead
    of ``z`` decodes z when it is first read.
    """

    sensor_id: NDArray[np.int64]
    frame_counter: NDArray[np.int64]
    sensor_time_ns: NDArray[np.int64]
    host_time_ns: NDArray[np.int64]
    y: NDArray[np.float64]
    _z: NDArray[np.float64] | None
    valid: NDArray[np.bool_]
    intensity: NDArray[np.uint8] | None
    encoder: NDArray[np.int64] | None
    encoder_valid: NDArray[np.bool_] | None
    codes: PointCodes | None

    def __init__(
        self,
        sensor_id: NDArray[np.int64],
        frame_counter: NDArray[np.int64],
        sensor_time_ns: NDArray[np.int64],
        host_time_ns: NDArray[np.int64],
        y: NDArray[np.float64],
        z: NDArray[np.float64] | None,
        valid: NDArray[np.bool_],
        intensity: NDArray[np.uint8] | None = None,
        encoder: NDArray[np.int64] | None = None,
        encoder_valid: NDArray[np.bool_] | None = None,
        codes: PointCodes | None = None,
    ) -> None:
        if z is None and codes is None:
            raise ValueError("profile block: give z or codes")
        self.sensor_id, self.frame_counter = sensor_id, frame_counter
        self.sensor_time_ns, self.host_time_ns = sensor_time_ns, host_time_ns
        self.y, self._z, self.valid, self.intensity = y, z, valid, intensity
        self.encoder, self.encoder_valid, self.codes = encoder, encoder_valid, codes
        self.__post_init__()

    @property
    def z(self) -> NDArray[np.float64]:
        if self._z is None:
            assert self.codes is not None
            self._z = self.codes.decode()
        return self._z

    @property
    def coded(self) -> bool:
        """The points are still only :attr:`codes` (z not decoded yet)."""
        return self._z is None

    def __post_init__(self) -> None:
        p = self.sensor_time_ns.shape[0]
        zs = self._z.shape if self._z is not None else self.codes.codes.shape  # type: ignore[union-attr]
        if len(zs) != 2 or zs[0] != p or self.valid.shape != zs:
            raise ValueError(
                f"profile block arrays disagree: {p} profiles, z {zs}, valid {self.valid.shape}"
            )
        if self.y.shape not in ((zs[1],), zs):
            raise ValueError(f"profile block: y {self.y.shape} for z {zs}")
        for name in ("sensor_id", "frame_counter", "host_time_ns"):
            if getattr(self, name).shape != (p,):
                raise ValueError(
                    f"profile block: {name} {getattr(self, name).shape}, ({p},) expected"
                )

    @property
    def n_profiles(self) -> int:
        return int(self.valid.shape[0])

    @property
    def n_points(self) -> int:
        """Points per profile."""
        return int(self.valid.shape[1])

    def y_rows(self) -> NDArray[np.float64]:
        """``y`` as (P, N) (a broadcast read-only view for a shared grid)."""
        return np.broadcast_to(self.y, self.valid.shape) if self.y.ndim == 1 else self.y

    def take(self, rows: NDArray[np.integer] | slice) -> ProfileBlock:
        """The block of the profiles ``rows`` (copies for an index array, views for a slice)."""
        y = self.y if self.y.ndim == 1 else self.y[rows]
        enc = None if self.encoder is None else self.encoder[rows]
        ev = None if self.encoder_valid is None else self.encoder_valid[rows]
        return ProfileBlock(
            self.sensor_id[rows],
            self.frame_counter[rows],
            self.sensor_time_ns[rows],
            self.host_time_ns[rows],
            y,
            None if self._z is None else self._z[rows],
            self.valid[rows],
            None if self.intensity is None else self.intensity[rows],
            enc,
            ev,
            None if self.codes is None else self.codes.take(rows),
        )

    def profile(self, k: int) -> Profile:
        """Profile ``k`` as a record (for consumers that want records; not the hot path)."""
        enc = None
        if self.encoder is not None and self.encoder_valid is not None and self.encoder_valid[k]:
            enc = int(self.encoder[k])
        return Profile(
            int(self.sensor_id[k]),
            int(self.frame_counter[k]),
            int(self.sensor_time_ns[k]),
            int(self.host_time_ns[k]),
            self.y if self.y.ndim == 1 else self.y[k],
            self.z[k],
            self.valid[k],
            None if self.intensity is None else self.intensity[k],
            enc,
        )

    @staticmethod
    def from_profiles(profiles: list[Profile]) -> list[ProfileBlock]:
        """Blocks of consecutive profiles of equal length, in order (records from drivers that
        deliver one at a time). A lateral grid shared by the whole run stays shared."""
        out: list[ProfileBlock] = []
        a = 0
        while a < len(profiles):
            n = profiles[a].n_points
            b = a + 1
            while b < len(profiles) and profiles[b].n_points == n:
                b += 1
            out.append(_stack(profiles[a:b]))
            a = b
        return out


def _stack(run: list[Profile]) -> ProfileBlock:
    """One block of profiles of equal length."""
    p = len(run)
    y0 = run[0].y
    shared = all(r.y is y0 for r in run)
    has_i = all(r.intensity is not None for r in run)
    has_e = any(r.encoder is not None for r in run)
    return ProfileBlock(
        sensor_id=np.fromiter((r.sensor_id for r in run), np.int64, p),
        frame_counter=np.fromiter((r.frame_counter for r in run), np.int64, p),
        sensor_time_ns=np.fromiter((r.sensor_time_ns for r in run), np.int64, p),
        host_time_ns=np.fromiter((r.host_time_ns for r in run), np.int64, p),
        y=y0 if shared else np.stack([r.y for r in run]),
        z=np.stack([r.z for r in run]),
        valid=np.stack([r.valid for r in run]),
        intensity=np.stack([r.intensity for r in run]) if has_i else None,  # type: ignore[misc]
        encoder=(np.fromiter((r.encoder or 0 for r in run), np.int64, p) if has_e else None),
        encoder_valid=(
            np.fromiter((r.encoder is not None for r in run), np.bool_, p) if has_e else None
        ),
    )


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
