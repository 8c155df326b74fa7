"""The ``[sim]`` section: the simulated cell (``wristscan sim`` and the tests) and the ground
truth its calibrations are checked against."""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BeforeValidator, Field, field_validator, model_validator

from wristscan.calib import se3
from wristscan.calib.kinematic_errors import REALISTIC, KinematicErrorSizes
from wristscan.daemon.config.values import (
    Bool,
    Float,
    Host,
    Int,
    Joints6,
    NonNegFloat,
    Pose6,
    Probability,
    Str,
    StrictModel,
    URModelName,
    Vec3,
    cross_field,
    fixed_length,
)

__all__ = [
    "SimConfig",
    "SimControllerConfig",
    "SimSceneConfig",
    "SimSensorConfig",
    "SimTableConfig",
    "SimTruthConfig",
]

FloatArray = NDArray[np.float64]


_ERROR_KEYS = (
    "kinematic_error_theta_deg",
    "kinematic_error_a_m",
    "kinematic_error_d_m",
    "kinematic_error_alpha_deg",
)


class SimControllerConfig(StrictModel):
    host: Host = "127.0.0.2"
    """Loopback address the simulated controller listens on (ports 29999, 30003, 30004)."""
    model: URModelName = "UR5e"
    version: Annotated[
        tuple[Int, Int, Int, Int],
        BeforeValidator(fixed_length(4, "[major, minor, bugfix, build]")),
        Field(description="PolyScope version"),
    ] = (5, 15, 0, 0)
    serial_number: Str = "20235500001"
    kinematic_errors: Literal["none", "realistic"] = "none"
    """``realistic``: the true arm differs from the nominal DH table of ``model`` by seeded
    per-joint deviations of theta, a, d, alpha (1 sigma 0.01 deg and 0.1 mm unless the
    ``kinematic_error_*`` keys say otherwise), as a real arm does; ``none``: built to the table."""
    kinematic_seed: Int = 0
    kinematic_error_theta_deg: NonNegFloat | None = None
    kinematic_error_a_m: NonNegFloat | None = None
    kinematic_error_d_m: NonNegFloat | None = None
    kinematic_error_alpha_deg: NonNegFloat | None = None
    factory_calibration: Literal["exact", "partial", "none"] = "exact"
    """What the controller reports as KinematicsInfo and computes its poses with: the true model,
    the true model with ``factory_residual`` of each deviation left, or the nominal table."""
    factory_residual: Annotated[Float, Field(ge=0, le=1)] = 0.15
    joint_noise_rad: Annotated[Float, Field(ge=0, le=0.01)] = 0.0
    """Encoder noise on the reported joints (standard deviation)."""
    repeatability_m: Annotated[Float, Field(ge=0, le=0.01)] = 0.0
    noise_seed: Int | None = None
    """Seed of the repeatability and the encoder noise (leave out: different every run)."""
    initial_q_rad: Joints6 | None = None
    initial_q_deg: Joints6 | None = None
    """Start joint positions: give them in radians or degrees (not both)."""

    @field_validator("version")
    @classmethod
    def _version(cls, v: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
        if any(x < 0 for x in v):
            raise ValueError("version numbers must be >= 0")
        return v

    @model_validator(mode="after")
    def _one_q(self) -> SimControllerConfig:
        if self.initial_q_rad is not None and self.initial_q_deg is not None:
            raise cross_field("initial_q_deg", "give initial_q_rad or initial_q_deg, not both")
        return self

    @model_validator(mode="after")
    def _error_sizes(self) -> SimControllerConfig:
        if self.kinematic_errors == "none":
            for key in _ERROR_KEYS:
                if getattr(self, key) is not None:
                    raise cross_field(key, 'needs kinematic_errors = "realistic"')
        return self

    def error_sizes(self) -> KinematicErrorSizes | None:
        """The deviations of the true arm (None: ``kinematic_errors = "none"``)."""
        if self.kinematic_errors == "none":
            return None
        r = REALISTIC
        t, a, d, al = (getattr(self, key) for key in _ERROR_KEYS)
        return KinematicErrorSizes(
            theta_rad=r.theta_rad if t is None else math.radians(t),
            a_m=r.a_m if a is None else a,
            d_m=r.d_m if d is None else d,
            alpha_rad=r.alpha_rad if al is None else math.radians(al),
        )

    @property
    def q0_rad(self) -> tuple[float, ...] | None:
        """Start joint positions in radians (None: the simulator's default)."""
        if self.initial_q_deg is not None:
            return tuple(math.radians(a) for a in self.initial_q_deg)
        return self.initial_q_rad


SimSensorKind = Literal[
    "lpf1-udp", "lpf1-tcp", "lpf1-serial", "rf627-udp", "scip-tcp", "scip-serial", "gocator"
]

SIM_SCIP_ARES = 1440
"""Steps per revolution (ARES) of the simulated SCIP scanner: a scan has at most this many."""

SIM_KINDS_FOR_DRIVER: dict[str, tuple[str, ...]] = {
    "lpf1-udp": ("lpf1-udp",),
    "lpf1-tcp": ("lpf1-tcp",),
    "lpf1-serial": ("lpf1-serial",),
    "rf627-udp": ("rf627-udp",),
    "scip": ("scip-tcp", "scip-serial"),
    "gocator": ("gocator",),
}
"""The simulated sensors each built-in ``[sensor] driver`` reads (plug-in drivers: not known)."""


class SimSensorConfig(StrictModel):
    kind: SimSensorKind = "lpf1-udp"
    sensor_id: Annotated[Int, Field(ge=0, le=2**32 - 1)] = 1
    rate_hz: Annotated[Float, Field(gt=0, le=100_000)] = 1000.0
    n_points: Annotated[Int, Field(ge=1, le=16383)] = 2048
    fov_lateral_m: Annotated[Float, Field(gt=0, le=2.0)] = 0.05
    """Full width of the laser line (the points span ``y`` in ``[-fov/2, fov/2]``)."""
    depth_min_m: Annotated[Float, Field(ge=0)] = 0.05
    depth_max_m: Annotated[Float, Field(gt=0, le=50.0)] = 0.15
    noise_m: NonNegFloat = 20e-6
    """Standard deviation of the range noise."""
    dropout_prob: Probability = 0.0
    outlier_prob: Probability = 0.0
    latency_s: Annotated[Float, Field(ge=0, le=1.0)] = 0.002
    """Exposure to send (and to the device timestamp)."""
    clock_offset_s: Float = 0.0
    clock_drift_ppm: Annotated[Float, Field(ge=-1000, le=1000)] = 0.0
    clock_jitter_s: Annotated[Float, Field(ge=0, le=0.1)] = 0.0
    send_late_s: tuple[NonNegFloat, NonNegFloat] = (0.0, 0.0)
    """A sender that cannot keep its timing: it wakes every 0..(hi - lo) s and sends what is at
    least ``lo`` s overdue (``[0.005, 0.05]``: 5-50 ms late, in bursts); 0: on time."""
    send_late_spike_prob: Probability = 0.0
    """With ``send_late_s``: the share of the sender's wake-ups 100-300 ms later still."""
    encoder: Bool = False
    """The sensor reports the table's encoder count with every profile."""
    intensity: Bool = False
    seed: Int | None = None

    @model_validator(mode="after")
    def _depth(self) -> SimSensorConfig:
        if not self.depth_min_m < self.depth_max_m:
            raise cross_field("depth_max_m", "must be greater than depth_min_m")
        if self.kind.startswith("scip") and self.n_points > SIM_SCIP_ARES:
            raise cross_field(
                "n_points",
                f"a SCIP scan has at most {SIM_SCIP_ARES} steps (the simulated scanner's ARES); "
                f"kind = {self.kind!r} needs n_points <= {SIM_SCIP_ARES} (e.g. 1081)",
            )
        return self


class SimTableConfig(StrictModel):
    enabled: Bool = True
    transport: Literal["tcp", "rtu"] = "tcp"
    host: Host = "127.0.0.1"
    port: Annotated[Int, Field(ge=0, le=65535)] = 5020
    """Modbus TCP port (0: any free port)."""
    device_id: Annotated[Int, Field(ge=0, le=247)] = 1
    counts_per_rev: Annotated[Int, Field(ge=1, le=2**31)] = 3_600_000
    word_order: Literal["big", "little"] = "big"
    max_speed_deg_s: Annotated[Float, Field(gt=0, le=3600)] = 90.0
    accel_deg_s2: Annotated[Float, Field(gt=0, le=36000)] = 180.0
    initial_angle_rad: Float = 0.0


class SimSceneConfig(StrictModel):
    preset: Literal["demo"] = "demo"
    """``demo``: table top, tooling ball on a post, rotary table with a part."""
    with_part: Bool = True
    ball_radius_m: Annotated[Float, Field(gt=0, le=0.2)] = 0.0127
    ball_centre_m: Vec3 = (0.45, -0.20, 0.16)
    """Tooling ball centre in the robot base frame."""


class SimTruthConfig(StrictModel):
    """Ground truth the calibrations are checked against."""

    sensor2flange_pose: Pose6 = (0.060, 0.010, 0.200, 0.020, -0.015, 0.010)
    """The true tool transformation as a UR pose (m, rotation vector in rad)."""
    table_axis_point_m: Vec3 = (0.45, 0.25, 0.0)
    """A point of the rotary table's axis (base frame): the platter centre at the table top."""
    table_axis_direction: Vec3 = (0.0, -0.003490651415223732, 0.9999939076577904)
    """Direction of the table axis (base frame; normalised here). The default leans 0.2 deg."""

    @field_validator("table_axis_direction")
    @classmethod
    def _unit(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        n = math.sqrt(sum(x * x for x in v))
        if n < 1e-9:
            raise ValueError("must not be the zero vector")
        return (v[0] / n, v[1] / n, v[2] / n)

    def sensor2flange(self) -> FloatArray:
        """The true tool transformation, 4x4."""
        return se3.pose_to_matrix(np.asarray(self.sensor2flange_pose, dtype=np.float64))

    def table_zero2base(self) -> FloatArray:
        """The table frame at angle zero in the base frame: origin on the axis point, +Z along
        the axis, reached from the base axes by the smallest rotation."""
        z = np.array([0.0, 0.0, 1.0])
        d = np.asarray(self.table_axis_direction, dtype=np.float64)
        axis = np.cross(z, d)
        s = float(np.linalg.norm(axis))
        angle = math.atan2(s, float(z @ d))
        if s < 1e-12:
            # Parallel or anti-parallel to +Z: no unique axis, turn about X when anti-parallel.
            rotvec = np.array([angle, 0.0, 0.0])
        else:
            rotvec = axis / s * angle
        return se3.make(se3.rotvec_to_matrix(rotvec), np.asarray(self.table_axis_point_m))


class SimConfig(StrictModel):
    controller: SimControllerConfig = Field(default_factory=SimControllerConfig)
    sensor: SimSensorConfig = Field(default_factory=SimSensorConfig)
    table: SimTableConfig = Field(default_factory=SimTableConfig)
    scene: SimSceneConfig = Field(default_factory=SimSceneConfig)
    truth: SimTruthConfig = Field(default_factory=SimTruthConfig)
