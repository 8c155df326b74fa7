"""Configuration of a simulated profile sensor: its kind, optics, timing, transport and faults.

Its own module so that the sensor process (:mod:`.sensors`) and the wire formats it speaks
(:mod:`.sensor_protocols`, :mod:`.sensor_scip`) share it without depending on each other.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import se3
from wristscan.calib.dh import DHParams
from wristscan.drivers import lpf1
from wristscan.drivers.sim.laser import LaserModel

__all__ = [
    "DEFAULT_SENSOR2FLANGE_POSE",
    "KINDS",
    "FaultConfig",
    "SensorKind",
    "SensorSimConfig",
]

SensorKind = Literal[
    "lpf1-udp", "lpf1-tcp", "lpf1-serial", "rf627-udp", "scip-tcp", "scip-serial", "gocator"
]
KINDS: tuple[str, ...] = (
    "lpf1-udp",
    "lpf1-tcp",
    "lpf1-serial",
    "rf627-udp",
    "scip-tcp",
    "scip-serial",
    "gocator",
)

DEFAULT_SENSOR2FLANGE_POSE = (0.060, 0.010, 0.200, 0.020, -0.015, 0.010)
"""Ground-truth tool transformation as a UR pose (m, rotation vector in rad): near the paper's
TCP (60, 10, 200) mm with a small known rotation."""


@dataclass(frozen=True)
class FaultConfig:
    """Probabilities (0-1) applied to every wire unit the sensor sends."""

    drop: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    truncate: float = 0.0
    corrupt: float = 0.0

    def __post_init__(self) -> None:
        for k, v in asdict(self).items():
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"fault probability {k}={v} outside [0, 1]")

    @property
    def any(self) -> bool:
        return (self.drop + self.duplicate + self.reorder + self.truncate + self.corrupt) > 0


@dataclass(frozen=True)
class SensorSimConfig:
    """Everything a simulated sensor needs; SI units (m, rad, s), device times in ns."""

    kind: SensorKind = "lpf1-udp"
    rate_hz: float = 1000.0
    n_points: int = 2048
    half_width_m: float = 0.025
    z_min_m: float = 0.05
    z_max_m: float = 0.15
    noise_std_m: float = 20e-6
    noise_model: Literal["gaussian", "table"] = "table"
    """``"table"``: fast discretised Gaussian (truncated at 4.3 sigma), see :mod:`.laser`."""
    dropout_prob: float = 0.0
    outlier_prob: float = 0.0
    latency_s: float = 0.002
    """Exposure to send."""
    stamp_delay_s: float | None = None
    """Exposure to the device timestamp (None: ``latency_s``, the device stamps when it sends)."""
    send_late_s: tuple[float, float] = (0.0, 0.0)
    """A sender that cannot keep its timing (issue 21), e.g. ``(0.005, 0.05)``: it wakes every
    uniform(0, hi - lo) seconds and sends the profiles due at least ``lo`` before, so each
    leaves ``lo`` to ``hi`` late, in order, in bursts. ``(0, 0)``: on time."""
    send_late_spike_prob: float = 0.0
    """With ``send_late_s``: the share of the sender's wake-ups 100-300 ms later still."""
    clock_offset_ns: int = 0
    clock_drift_ppm: float = 0.0
    clock_jitter_ns: float = 0.0
    sensor_id: int = 1
    sensor2flange: tuple[float, ...] | tuple[tuple[float, ...], ...] = DEFAULT_SENSOR2FLANGE_POSE
    """Ground truth: a UR pose ``(x, y, z, rx, ry, rz)`` or a 4x4 matrix (nested tuples)."""
    robot_model: str | DHParams = "UR5e"
    """The arm's true model: a model name (its nominal table) or its DH parameters."""
    standalone_flange_pose: tuple[float, ...] | None = None
    """Flange pose (UR pose) without a robot ring; None: the sensor 0.1 m above the scene's
    ``"ball"`` primitive (or the base origin), looking down."""
    standalone_table_angle_rad: float = 0.0
    encoder: Literal["none", "table", "time"] = "none"
    """Encoder count source: the table angle, or a constant rate since start."""
    encoder_counts_per_rev: int = 36000
    encoder_counts_per_s: float = 1000.0
    intensity: bool = False
    host: str = "127.0.0.1"
    port: int = 0
    """TCP listening port (0: any free port); Gocator: the control channel's, the data channel
    on ``port + 6`` and the health channel on ``port + 4`` (0: three free ports)."""
    target: tuple[str, int] | None = None
    """UDP destination; None: ``(host, 50001)`` for RF627, ``(host, 50002)`` for LPF1."""
    max_datagram: int = lpf1.DEFAULT_MAX_MESSAGE
    lpf1_point_format: Literal["i16", "i32", "f32"] = "i16"
    lpf1_z_scale_nm: int = 2000
    lpf1_z_offset_um: int = 100_000
    serial_baud: int | None = None
    """Throttle a serial link to ``baud / 10`` bytes/s; None: as fast as the pty goes."""
    heartbeat_s: float = 1.0
    """LPF1 heartbeat period (0: none)."""
    scip_ares: int = 1440
    scip_range_min_m: float = 0.02
    scip_range_max_m: float = 30.0
    scip_model: str = "WRISTSCAN-SIM"
    gocator_uniform: bool = True
    """Gocator: send uniform profiles (the sensor's "uniform spacing"), else point clouds."""
    truth_wait_s: float = 0.05
    max_lag_s: float = 1.0
    """Exposures more than this late (an overloaded host) are skipped, leaving counter gaps."""
    batch_s: float = 0.001
    """Exposures are ray-cast together when they fall due within this window (at most a
    quarter of ``latency_s + precompute_s``, so that they are still sent on time)."""
    precompute_s: float = 0.003
    """Exposures are ray-cast up to this long before they happen, as soon as the truth rings
    cover them (the controller and the table write them ahead), and sent at their send time:
    a sensor process scheduled a little late still sends on time, as a real sensor does."""
    seed: int | None = None
    faults: FaultConfig = field(default_factory=FaultConfig)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown sensor kind {self.kind!r}; one of {', '.join(KINDS)}")
        if not 0 < self.rate_hz <= 100_000:
            raise ValueError("rate_hz must be in (0, 100000]")
        if self.n_points < 1:
            raise ValueError("n_points must be >= 1")
        if self.precompute_s < 0:
            raise ValueError("precompute_s must be >= 0")
        if self.latency_s < 0 or (self.stamp_delay_s is not None and self.stamp_delay_s < 0):
            raise ValueError("latency_s and stamp_delay_s must be >= 0")
        lo, hi = self.send_late_s
        if not 0.0 <= lo <= hi or not 0.0 <= self.send_late_spike_prob <= 1.0:
            raise ValueError("send_late_s must be 0 <= lo <= hi, send_late_spike_prob in [0, 1]")
        if self.is_scip and self.n_points > self.scip_ares:
            raise ValueError("a SCIP scan cannot have more steps (n_points) than ARES")
        if self.kind == "rf627-udp" and self.n_points > 16383:
            raise ValueError("RF627 carries at most 16383 points")
        self.sensor2flange_matrix()  # validates the shape

    @classmethod
    def for_kind(cls, kind: SensorKind, **overrides: Any) -> SensorSimConfig:
        """Defaults that suit ``kind`` (RF627: 648 points; SCIP: a 270-degree 1081-step scanner
        at 40 Hz; Gocator: the standard ports 3190/3196/3194), then ``overrides``."""
        base: dict[str, Any] = {"kind": kind}
        if kind == "rf627-udp":
            base.update(n_points=648)
        elif kind == "gocator":
            base.update(port=3190)
        elif kind.startswith("scip"):
            base.update(n_points=1081, scip_ares=1440, rate_hz=40.0, latency_s=0.001)
        base.update(overrides)
        return cls(**base)

    @property
    def is_scip(self) -> bool:
        return self.kind.startswith("scip")

    @property
    def transport(self) -> str:
        return "tcp" if self.kind == "gocator" else self.kind.split("-")[1]

    def sensor2flange_matrix(self) -> NDArray[np.float64]:
        a = np.asarray(self.sensor2flange, dtype=np.float64)
        if a.shape == (6,):
            return se3.pose_to_matrix(a)
        if a.shape == (4, 4):
            return se3.check_transform(a, "sensor2flange")
        raise ValueError("sensor2flange must be a UR pose (6,) or a 4x4 matrix")

    def scip_angles_rad(self) -> NDArray[np.float64]:
        front = (self.n_points - 1) // 2
        return 2.0 * np.pi * (np.arange(self.n_points) - front) / self.scip_ares

    def laser_model(self, rng: np.random.Generator | int | None = None) -> LaserModel:
        """The :class:`LaserModel` this sensor measures with."""
        if self.is_scip:
            return LaserModel(
                self.n_points,
                z_min_m=self.scip_range_min_m,
                z_max_m=self.scip_range_max_m,
                noise_std_m=self.noise_std_m,
                dropout_prob=self.dropout_prob,
                outlier_prob=self.outlier_prob,
                rng=rng,
                geometry="fan",
                angles_rad=self.scip_angles_rad(),
                noise_model=self.noise_model,
            )
        return LaserModel(
            self.n_points,
            self.half_width_m,
            self.z_min_m,
            self.z_max_m,
            self.noise_std_m,
            self.dropout_prob,
            self.outlier_prob,
            rng,
            noise_model=self.noise_model,
        )
