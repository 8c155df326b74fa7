"""Configuration of a simulated UR controller, and the fixed ports it serves on.

Its own module so that every part of the controller (the parent-side handle in
:mod:`.controller`, the process in :mod:`.server` and the state under it) depends on it without
depending on each other.
"""

from __future__ import annotations

import math
import socket
from dataclasses import dataclass

from wristscan.calib import kinematic_errors as kerr
from wristscan.calib import kinematics
from wristscan.drivers.sim.ur.primary import PRIMARY_PORT

__all__ = [
    "CB3_MAJOR_VERSION",
    "DASHBOARD_PORT",
    "PRIMARY_PORT",
    "RTDE_PORT",
    "SCRIPT_PORT",
    "ControllerConfig",
]

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003
CB3_MAJOR_VERSION = 3


@dataclass(frozen=True)
class ControllerConfig:
    """Configuration of one simulated controller (SI units)."""

    host: str = "127.0.0.2"
    """Loopback address to listen on (ports 29999, 30003, 30004 are fixed, as on a robot)."""
    model: str | kinematics.DHParams = "UR5e"
    """Arm model: a key of :data:`wristscan.calib.kinematics.UR_MODELS`, or DH parameters (for
    example a calibrated arm), which the controller's own kinematics then uses."""
    version: tuple[int, int, int, int] = (5, 15, 0, 0)
    """Controller software version; major > 3 is e-Series (500 Hz), 3 is CB3 (125 Hz)."""
    serial_number: str = "20235500001"
    initial_q: tuple[float, ...] = (0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0)
    """Joint positions at start-up (rad)."""
    tcp_offset: tuple[float, ...] = (0.0,) * 6
    """TCP in the flange frame as a UR pose ``[x, y, z, rx, ry, rz]`` (m, rad); zero = flange."""
    max_joint_speed_rad_s: float = math.pi
    max_joint_accel_rad_s2: float = 40.0
    max_tool_speed_m_s: float = 3.0
    speed_slider: float = 1.0
    """Speed slider fraction (0..1]: scales the time of every motion."""
    kinematic_errors: kerr.KinematicErrorSizes | None = None
    """How far the TRUE arm is from ``model``: standard deviations of per-joint deviations of
    theta, a, d, alpha drawn from ``kinematic_seed``
    (:func:`wristscan.calib.kinematic_errors.true_model`;
    :data:`~wristscan.calib.kinematic_errors.REALISTIC` is a real arm's size). None: the arm is
    built exactly to ``model``. The arm moves by its true model (the truth ring holds its true
    joints, which the simulated sensor evaluates with :attr:`true_model`)."""
    kinematic_seed: int = 0
    factory_calibration: str = "exact"
    """The calibration the controller believes, reports as KinematicsInfo on the primary
    interface and computes ``actual_TCP_pose`` and its moves with (:attr:`reported_model`):
    ``"exact"`` the true model, ``"partial"`` with ``factory_residual`` of every deviation left,
    ``"none"`` the nominal ``model``."""
    factory_residual: float = kerr.DEFAULT_RESIDUAL
    joint_noise_rad: float = 0.0
    """Encoder noise: standard deviation (rad) of white noise on each reported ``actual_q`` (and
    so on ``actual_TCP_pose``); ``target_q`` and the true joints have none."""
    repeatability_m: float = 0.0
    """RMS distance (m) between the true and the reported TCP position (UR5e spec: 3e-5)."""
    noise_corr_rad: float = 0.5
    """Joint travel (rad, summed over joints) over which the repeatability offset decorrelates."""
    noise_seed: int | None = None
    """Seed of the repeatability and the encoder noise (None: different every run)."""
    powered_on: bool = True
    """Start with power on and brakes released (robot mode RUNNING); else POWER_OFF."""
    pstop_unlock_delay_s: float = 5.0
    """Time after a protective stop before the dashboard may unlock it (5 s on a real robot)."""
    protective_stop_decel_rad_s2: float = 10.0
    protective_stop_decel_m_s2: float = 5.0
    program_stop_decel_rad_s2: float = 4.0
    program_stop_decel_m_s2: float = 2.0
    truth_rate_hz: float = 1000.0
    """Internal simulation rate and truth-ring sample rate (must divide into the cycle)."""
    motion_lookahead_s: float = 0.004
    """The arm's motion is computed (and written to the truth ring) this far ahead of the cycle
    being reported; commands take effect after it. Simulated sensors then find the true pose of
    each exposure in the ring when they expose instead of waiting up to a cycle for it, which
    would delay every profile they send (a real sensor waits for nothing)."""
    payload_kg: float = 0.0
    primary_interface: bool = False
    """Also serve the primary interface on TCP 30001 (:mod:`.primary`: version message and
    ROBOT_STATE with KinematicsInfo reporting ``model``'s DH parameters)."""
    log_level: str = "WARNING"
    """Logging level set up in the controller process."""

    def __post_init__(self) -> None:
        kinematics.get_model(self.model)  # raises for an unknown model
        if len(self.version) != 4:
            raise ValueError(f"version must have 4 numbers, got {self.version}")
        if len(self.initial_q) != 6 or len(self.tcp_offset) != 6:
            raise ValueError("initial_q and tcp_offset need 6 values each")
        if not 0.0 < self.speed_slider <= 1.0:
            raise ValueError(f"speed_slider must be in (0, 1], got {self.speed_slider}")
        if self.repeatability_m < 0 or self.joint_noise_rad < 0:
            raise ValueError("repeatability_m and joint_noise_rad must be >= 0")
        kerr.factory_model(
            self.model,
            kinematics.get_model(self.model),
            self.factory_calibration,
            self.factory_residual,
        )  # raises for an unknown calibration or a residual outside [0, 1]
        if not 0.0 <= self.motion_lookahead_s <= 0.1:
            raise ValueError("motion_lookahead_s must be in [0, 0.1]")
        socket.inet_aton(self.host)  # a dotted IPv4 address
        if self.period_ns % self.tick_ns != 0:
            raise ValueError(
                f"truth_rate_hz {self.truth_rate_hz} does not divide the {self.period_ns} ns cycle"
            )

    @property
    def true_model(self) -> kinematics.DHParams:
        """The arm's true kinematics (``model`` itself without ``kinematic_errors``)."""
        if self.kinematic_errors is None:
            return kinematics.get_model(self.model)
        return kerr.true_model(self.model, self.kinematic_errors, self.kinematic_seed)

    @property
    def reported_model(self) -> kinematics.DHParams:
        """The factory calibration the controller reports and computes with."""
        if self.kinematic_errors is None:
            return kinematics.get_model(self.model)
        return kerr.factory_model(
            self.model, self.true_model, self.factory_calibration, self.factory_residual
        )

    @property
    def e_series(self) -> bool:
        return self.version[0] > CB3_MAJOR_VERSION

    @property
    def frequency_hz(self) -> float:
        """Controller cycle rate: 500 Hz e-Series, 125 Hz CB3."""
        return 500.0 if self.e_series else 125.0

    @property
    def period_ns(self) -> int:
        return 2_000_000 if self.e_series else 8_000_000

    @property
    def tick_ns(self) -> int:
        return round(1e9 / self.truth_rate_hz)

    @property
    def lookahead_ns(self) -> int:
        """``motion_lookahead_s`` rounded up to whole ticks."""
        return math.ceil(self.motion_lookahead_s * 1e9 / self.tick_ns) * self.tick_ns
