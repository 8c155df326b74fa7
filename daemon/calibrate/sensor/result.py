"""What the sensor calibration found (:class:`SensorCalibrationResult`) and the calibration file
made of it (:func:`calibration_of`): the joint solution with its covariance and residuals, and
the ball, the validation and the two-step figures as named parameters."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import handeye
from wristscan.calib.handeye_uncertainty import point_error
from wristscan.daemon.calibrate.sensor.plan import OrientationPlan, Settings, rotation_between
from wristscan.daemon.calibrate.sensor.solve import ApparentLatency
from wristscan.daemon.calibrate.sensor.sweeps import RecordedSweep
from wristscan.daemon.calibrate.sensor.validate import CheckScan, LeaveOneOut
from wristscan.daemon.io.calibfile import Calibration, Residuals, RobotIdentity, SensorIdentity

__all__ = [
    "COVARIANCE_PARAMETERS",
    "METHOD",
    "SensorCalibrationResult",
    "calibration_of",
    "joint_calibration",
    "predicted_point_error",
    "uncertainty_parameters",
    "working_volume",
]

FloatArray = NDArray[np.float64]

METHOD = "ball-matching+joint-refinement"
"""``method`` of the calibration files written here."""

COVARIANCE_PARAMETERS = (
    "rot_sensor_x_rad",
    "rot_sensor_y_rad",
    "rot_sensor_z_rad",
    "x_m",
    "y_m",
    "z_m",
)
"""Covariance order of the file: rotation increments about the sensor axes (right perturbation,
radians), then the sensor origin in the flange frame (metres)."""


@dataclass(frozen=True, eq=False)
class SensorCalibrationResult:
    """Everything the procedure found; :func:`calibration_of` and
    :func:`~.report.build_report` use it."""

    settings: Settings
    nominal: FloatArray | None
    sweeps: tuple[RecordedSweep, ...]
    """The solved sweeps, FOV first, in the order of the solutions' per-sweep figures."""
    two_step: handeye.HandEyeResult
    joint: handeye.HandEyeResult
    uncompensated: handeye.HandEyeResult | None
    """The joint refinement before the per-pair time offsets were removed (None: not done)."""
    loo: LeaveOneOut | None
    check: CheckScan | None
    check_sweeps: tuple[RecordedSweep, ...]
    latency: ApparentLatency | None
    orientations: tuple[OrientationPlan, ...]
    fov_reference_flange2base: FloatArray
    min_z_angle_deg: float
    """Smallest angle between the sensor Z axes of any two orientations used (degrees)."""
    notes: tuple[str, ...]
    configured_latency_s: float
    manual: bool
    duration_s: float
    robot_sigma_m: float = 0.0
    """Per-axis robot repeatability the covariance used (m): the larger of the data sheet's and
    the observed one."""
    observed_robot_sigma_m: float = 0.0
    """Per-axis scatter of the places' ball centres (m), see
    :func:`~.solve.observed_robot_sigma`."""
    robot_time_s: float = 0.0
    """Seconds from the start of the first motion to the end of the last (the check scan's
    included): how long the procedure keeps the robot."""
    motion_time_s: float = 0.0
    """Seconds the robot spent moving (sweeps and travel)."""

    @property
    def sensor2flange(self) -> FloatArray:
        return self.joint.sensor2flange


def working_volume(s: Settings) -> tuple[tuple[float, float], tuple[float, float]]:
    """The sensor's working volume in the laser plane: ``(y range), (z range)`` (m)."""
    return (-s.fov_width_m / 2, s.fov_width_m / 2), (s.depth_min_m, s.depth_max_m)


def predicted_point_error(result: SensorCalibrationResult) -> tuple[float, float]:
    """The calibration's predicted 1-sigma error of a measured point (3-D, m) over the sensor's
    working volume: ``(RMS, maximum)``."""
    j = result.joint
    return point_error(j.cov, j.sensor2flange, *working_volume(result.settings))


def uncertainty_parameters(result: SensorCalibrationResult) -> dict[str, float]:
    """The uncertainty as named parameters: the 1 sigma of each parameter, the error model's
    components (sensor noise, the robot's error per sweep and per pose), the predicted point
    error in the working volume and the jackknife's sigmas (when there is one)."""
    j = result.joint
    sig = np.sqrt(np.clip(np.diag(j.cov), 0.0, None))
    out = {f"sigma_{name}": float(v) for name, v in zip(COVARIANCE_PARAMETERS, sig, strict=True)}
    vc = j.components
    if vc is not None:
        out["noise_sigma_m"] = vc.noise_sigma_m
        out["robot_sweep_sigma_m"] = vc.sweep_sigma_m
        out["robot_sweep_sigma_estimated_m"] = vc.sweep_sigma_estimated_m
        out["robot_pose_sigma_m"] = vc.pose_sigma_m
    rms, top = predicted_point_error(result)
    out["point_sigma_rms_m"] = rms
    out["point_sigma_max_m"] = top
    if result.loo is not None:
        for name, v in zip(COVARIANCE_PARAMETERS, result.loo.sigma, strict=True):
            out[f"jackknife_sigma_{name}"] = float(v)
    return out


def joint_calibration(
    joint: handeye.HandEyeResult,
    ball_radius_m: float,
    parameters: dict[str, float],
    *,
    method: str,
    notes: str,
    robot: RobotIdentity,
    sensor: SensorIdentity,
) -> Calibration:
    """A calibration file of a joint solution (``calibrate sensor`` and ``calibrate import``):
    its transform, symmetrised covariance and per-sweep residuals; the ball and the solution's
    figures, then ``parameters``, as named parameters (those not finite left out)."""
    j = joint
    params: dict[str, float] = {
        "ball_radius_m": ball_radius_m,
        "ball_centre_x_m": float(j.ball_centre_base[0]),
        "ball_centre_y_m": float(j.ball_centre_base[1]),
        "ball_centre_z_m": float(j.ball_centre_base[2]),
        "condition_number": float(j.condition),
        "n_points": float(j.n_points),
        **parameters,
    }
    cov = np.asarray(j.cov, dtype=np.float64)
    per = np.nan_to_num(np.asarray(j.per_sweep_rms, dtype=np.float64))
    return Calibration(
        kind="sensor2flange",
        transform=j.sensor2flange,
        robot=robot,
        sensor=sensor,
        method=method,
        residuals=Residuals(float(j.rms), tuple(float(v) for v in per)),
        covariance=(cov + cov.T) / 2,
        covariance_parameters=COVARIANCE_PARAMETERS,
        parameters={k: v for k, v in params.items() if math.isfinite(v)},
        notes=notes,
    )


def calibration_of(
    result: SensorCalibrationResult, robot: RobotIdentity, sensor: SensorIdentity
) -> Calibration:
    """The calibration file's content: the joint solution with its covariance and residuals, the
    ball, the validation figures and the two-step figures as named parameters."""
    j, t = result.joint, result.two_step
    params: dict[str, float] = {
        "n_sweeps": float(len(result.sweeps)),
        "min_z_angle_deg": float(result.min_z_angle_deg),
        "robot_sigma_m": float(result.robot_sigma_m or result.settings.robot_sigma_m),
        "observed_robot_sigma_m": float(result.observed_robot_sigma_m),
        "two_step_rms_m": float(t.rms),
        "two_step_translation_diff_m": float(
            np.linalg.norm(t.sensor2flange[:3, 3] - j.sensor2flange[:3, 3])
        ),
        "two_step_rotation_diff_rad": rotation_between(t.sensor2flange, j.sensor2flange),
    }
    params.update(uncertainty_parameters(result))
    if result.loo is not None:
        params["loo_max_translation_m"] = result.loo.max_translation_dev_m
        params["loo_max_rotation_rad"] = result.loo.max_rotation_dev_rad
    if result.check is not None:
        params["check_centre_error_m"] = result.check.centre_error_m
        params["check_radius_error_m"] = result.check.radius_error_m
        params["check_rms_m"] = result.check.rms_m
    if result.latency is not None and math.isfinite(result.latency.offset_s):
        params["apparent_latency_offset_s"] = result.latency.offset_s
    notes = "; ".join(result.notes)
    return joint_calibration(
        j,
        result.settings.ball_radius_m,
        params,
        method=METHOD,
        notes=("manual mode; " if result.manual else "") + notes,
        robot=robot,
        sensor=sensor,
    )
