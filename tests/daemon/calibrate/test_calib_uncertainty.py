"""calibrate sensor's uncertainty: with a robot whose error is shared by all sweeps of a pose, the
solution's sigmas cover its error, the calibration file names them (each parameter's sigma, the
error model, the predicted point error, the jackknife) and the report explains them; a weakly
constrained pose set is solved with a warning instead of refused. Synthetic sweeps (ground truth
from calib.synthetic), solved as the procedure does."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from test_calib_sensor import BALL, R_BALL, X_TRUE, _recorded

from wristscan.calib import se3, synthetic
from wristscan.calib.handeye import Sweep
from wristscan.daemon.calibrate import sensor as cs
from wristscan.daemon.io.calibfile import RobotIdentity, SensorIdentity

POSE_SIGMA_M = 60e-6


def _session(tilt_deg: float, seed: int) -> list[cs.RecordedSweep]:
    """FOV sweeps and tilted sweeps, one pass each, whose reported flange poses are off by an
    error common to each orientation (``POSE_SIGMA_M`` per axis) plus 5 um per sweep."""
    rng = np.random.default_rng(seed)
    R0 = se3.rot_x(np.pi) @ X_TRUE[:3, :3].T
    grid = synthetic.fov_grid(3, 3, y_half_m=0.009, z_half_m=0.024)
    tilts = synthetic.tilt_orientations(R0, math.radians(tilt_deg))
    side = np.array([[0.009 * (-1) ** j, 0.0] for j in range(len(tilts))])
    run = synthetic.make_ball_sweeps(
        X_TRUE, BALL, R_BALL, grid, tilts, 5e-6, 15e-6, rng, tilt_fov=side,
        sweep_step_m=0.5e-3, sweep_margin_m=3e-3,
    )  # fmt: skip
    pose_error = rng.normal(0.0, POSE_SIGMA_M, (len(tilts) + 1, 3))
    out = []
    for k, s in enumerate(run.fov):
        out.append(_recorded(_off(s, pose_error[0]), "fov", 0, k, 1, 0.02))
    for j, s in enumerate(run.tilt):
        out.append(_recorded(_off(s, pose_error[j + 1]), "tilt", j + 1, 100 + j, 1, 0.02))
    return out


def _off(s: Sweep, d: np.ndarray) -> Sweep:
    """``s`` with its reported flange off by ``d`` (m, flange frame)."""
    return Sweep(s.flange2base @ se3.make(np.eye(3), d), s.points_sensor, s.pose_index)


def _result(sweeps: list[cs.RecordedSweep], loo: bool = True) -> cs.SensorCalibrationResult:
    two, joint = cs.solve(sweeps, R_BALL, robot_sigma_m=5e-6)
    return cs.SensorCalibrationResult(
        settings=cs.Settings(robot_sigma_m=5e-6),
        nominal=None,
        sweeps=tuple(sweeps),
        two_step=two,
        joint=joint,
        uncompensated=None,
        loo=cs.leave_one_out(sweeps, joint, R_BALL, max_points=600) if loo else None,
        check=None,
        check_sweeps=(),
        latency=None,
        orientations=(),
        fov_reference_flange2base=sweeps[0].sweep.flange2base[0],
        min_z_angle_deg=45.0,
        notes=(),
        configured_latency_s=0.0,
        manual=False,
        duration_s=1.0,
    )


def test_pose_error_is_in_the_sigmas_the_file_and_the_report(tmp_path: Path) -> None:
    result = _result(_session(50.0, seed=4))
    j = result.joint
    vc = j.components
    assert vc is not None and vc.pose_sigma_m > 20e-6  # found in the residuals
    e = np.concatenate(
        [se3.matrix_to_rotvec(X_TRUE[:3, :3].T @ j.sensor2flange[:3, :3]),
         j.sensor2flange[:3, 3] - X_TRUE[:3, 3]]
    )  # fmt: skip
    assert e @ np.linalg.solve(j.cov, e) < 27.9  # chi2(6), p = 1e-4
    assert np.linalg.norm(e[3:]) > 15e-6  # the pose error is felt: not a trivial pass

    params = cs.calibration_of(result, RobotIdentity("UR5e"), SensorIdentity("lpf1-udp", "1"))
    p = params.parameters
    sig = np.sqrt(np.diag(j.cov))
    for name, v in zip(cs.COVARIANCE_PARAMETERS, sig, strict=True):
        assert p[f"sigma_{name}"] == pytest.approx(v)
        assert p[f"jackknife_sigma_{name}"] >= 0.0
    assert p["robot_pose_sigma_m"] == pytest.approx(vc.pose_sigma_m)
    assert p["robot_sweep_sigma_m"] >= 5e-6  # never below the data sheet
    assert 0.0 < p["noise_sigma_m"] < 30e-6
    # The point error over the working volume: at least the origin's, at most a lever's worth.
    assert float(np.linalg.norm(sig[3:])) <= p["point_sigma_max_m"] < 1e-3
    assert p["point_sigma_rms_m"] <= p["point_sigma_max_m"]
    # The jackknife over the orientations agrees with the model about the origin.
    jk = np.array([p[f"jackknife_sigma_{n}"] for n in cs.COVARIANCE_PARAMETERS[3:]])
    ratio = float(np.linalg.norm(jk) / np.linalg.norm(sig[3:]))
    assert 0.3 < ratio < 3.0, ratio

    md = cs.build_report(result).write(tmp_path / "r.md").read_text()
    assert "per pose (orientation)" in md and "Predicted error of a measured point" in md


def test_a_weak_pose_set_is_solved_with_advice() -> None:
    """Tilts of 6 deg (the least the paper's two-step start takes): a unique solution whose
    sigma says how weak it is along the sensor Z axis, with advice."""
    result = _result(_session(6.0, seed=6), loo=False)
    j = result.joint
    assert 15.0 < j.condition < 1e4 and "sensor Z axis" in j.advice
    err_z = abs(j.sensor2flange[2, 3] - X_TRUE[2, 3])
    assert err_z < 4.0 * j.sigma_translation_m[2]
    assert j.sigma_translation_m[2] > 5.0 * j.sigma_translation_m[0]
