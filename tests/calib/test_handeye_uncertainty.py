"""handeye_uncertainty: the robot's pose error in the joint solution's covariance (estimated from
the residuals), the jackknife over pose clusters, the predicted point error and the condition
check that warns on weak pose sets and refuses only non-unique ones. Ground truth from
calib.synthetic's ray-cast sweeps with robot errors applied here."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from test_handeye import BALL_C, BALL_R, GRID, R0, SENSOR, STEP_M, X_TRUE, errors, make

from wristscan.calib import handeye, se3, synthetic
from wristscan.calib import handeye_uncertainty as unc
from wristscan.calib.handeye import PoorlyConstrained, Sweep
from wristscan.calib.handeye_jackknife import with_jackknife


def _shifted(sweeps: list[Sweep], clusters: np.ndarray, offsets: np.ndarray) -> list[Sweep]:
    """The sweeps with the reported flange of each cluster off by its own flange-frame offset
    (translation, m, then rotation vector, rad): an error common to every sweep of a pose."""
    out = []
    for s, g in zip(sweeps, clusters, strict=True):
        E = se3.make(se3.rotvec_to_matrix(offsets[g, 3:]), offsets[g, :3])
        out.append(Sweep(s.flange2base @ E, s.points_sensor, s.pose_index))
    return out


def _mahalanobis2(res: handeye.HandEyeResult) -> float:
    w, t = errors(res.sensor2flange)
    e = np.concatenate([w, t])
    return float(e @ np.linalg.solve(res.cov, e))


def test_pose_clusters_group_the_fov_sweeps() -> None:
    data = make(np.random.default_rng(1))
    cl = unc.pose_clusters(data.all)
    assert list(cl) == [0] * 9 + [1, 2, 3, 4, 5, 6]


def test_error_shared_by_a_pose_is_estimated_and_covered() -> None:
    """80 um per axis shared by all sweeps of a pose: the plain covariance claims a few
    micrometres; the pose term finds the error's size and covers what it does."""
    rng = np.random.default_rng(5)
    data = make(rng, sensor=20e-6)
    cl = unc.pose_clusters(data.all)
    off = np.zeros((cl.max() + 1, 6))
    off[:, :3] = rng.normal(0.0, 80e-6, (cl.max() + 1, 3))
    sw = _shifted(data.all, cl, off)
    two = handeye.two_step(sw[:9], sw[9:], BALL_R)
    res = handeye.refine(sw, two, BALL_R)
    old = handeye.refine(sw, two, BALL_R, robot_model=False)
    assert res.components is not None
    # Its size per component (translation, rotation at the lever): the order of the 80 um (seven
    # clusters estimate it within a factor of 2-3).
    assert 20e-6 < res.components.pose_sigma_m < 160e-6
    assert res.components.sweep_sigma_m < 15e-6  # no error of its own per sweep
    assert np.all(res.sigma_translation_m > 5.0 * old.sigma_translation_m)
    assert _mahalanobis2(res) < 27.9  # chi2(6), p = 1e-4
    assert _mahalanobis2(old) > 27.9  # the plain covariance does not cover it


def _per_pose(rng: np.random.Generator, n: int = 15) -> tuple[list[Sweep], np.ndarray]:
    """One profile per pose at ``n`` orientations tilted 20-45 deg; the ball's centre in each."""
    ori = []
    for _ in range(n):
        phi = rng.uniform(0.0, 2.0 * np.pi)
        axis = np.array([np.cos(phi), np.sin(phi), 0.0]) * np.radians(rng.uniform(20.0, 45.0))
        ori.append(R0 @ se3.rotvec_to_matrix(axis) @ se3.rot_z(rng.uniform(-0.5, 0.5)))
    fov = np.column_stack([rng.uniform(-0.015, 0.015, n), rng.uniform(-0.01, 0.01, n)])
    data = synthetic.make_ball_sweeps(
        X_TRUE, BALL_C, BALL_R, np.zeros((0, 2)), np.stack(ori), 0.0, 20e-6, rng,
        sensor=SENSOR, sweep_step_m=STEP_M, tilt_fov=fov,
    )  # fmt: skip
    out = []
    for s in data.tilt:
        k = int(rng.integers(s.n_poses // 4, 3 * s.n_poses // 4))
        m = s.pose_index == k
        out.append(Sweep(s.flange2base[k : k + 1], s.points_sensor[m], np.zeros(int(m.sum()), int)))
    return out, np.arange(n)


def test_one_profile_per_pose_gets_the_pose_error_and_a_jackknife() -> None:
    rng = np.random.default_rng(8)
    poses, cl = _per_pose(rng)
    off = np.column_stack(
        [rng.normal(0.0, 100e-6, (len(poses), 3)), rng.normal(0.0, 3e-4, (len(poses), 3))]
    )
    sw = _shifted(poses, cl, off)
    start = handeye.HandEyeResult(
        X_TRUE @ se3.make(se3.rotvec_to_matrix([0.01, -0.01, 0.01]), [1e-3, 0.0, 5e-4]),
        BALL_C + 1e-3, BALL_R, np.eye(6), np.zeros(len(sw)), 0.0, 0, 0.0, "start",
        tuple(np.ones(s.n_points, dtype=bool) for s in sw),
    )  # fmt: skip
    res = with_jackknife(sw, handeye.refine(sw, start, BALL_R, robot_sigma_m=10e-6))
    old = handeye.refine(sw, res, BALL_R, robot_sigma_m=10e-6, robot_model=False)
    vc = res.components
    assert vc is not None and np.isnan(vc.sweep_sigma_estimated_m)  # one sweep per cluster
    assert vc.sweep_sigma_m == pytest.approx(10e-6)  # the data sheet's share
    assert 40e-6 < vc.pose_sigma_m < 250e-6
    assert _mahalanobis2(res) < 27.9
    assert np.all(res.sigma_translation_m > 3.0 * old.sigma_translation_m)
    # The jackknife over the poses agrees with the model within a factor of 2.5 per axis.
    jk = res.jackknife
    assert jk is not None and len(jk.left_out) >= 12
    ratio = jk.sigma / np.sqrt(np.diag(res.cov))
    assert np.all((ratio > 0.4) & (ratio < 2.5)), ratio
    # Predicted point error: at least the origin's, within the working volume's corners.
    assert (
        res.point_sigma_m
        >= res.point_sigma_rms_m
        >= float(np.linalg.norm(res.sigma_translation_m)) * 0.5
    )
    assert res.working_volume_m is not None


def test_point_error_grows_with_the_lever_of_a_rotation() -> None:
    C = np.diag([0.0, 0.0, 0.0, 1e-10, 1e-10, 1e-10])  # 10 um per axis, no rotation
    rms, top = unc.point_error(C, X_TRUE, (-0.03, 0.03), (-0.04, 0.04))
    assert rms == pytest.approx(np.sqrt(3) * 1e-5) and top == pytest.approx(np.sqrt(3) * 1e-5)
    C = np.diag([1e-8, 0.0, 0.0, 0.0, 0.0, 0.0])  # 0.1 mrad about the sensor X axis
    rms, top = unc.point_error(C, np.eye(4), (-0.03, 0.03), (0.0, 0.04))
    assert top == pytest.approx(1e-4 * np.hypot(0.03, 0.04))  # the farthest corner
    assert 0.0 < rms < top


def test_weakly_constrained_sets_warn_and_report_their_weakness(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Tilts of 1 deg: condition about 300, once refused; the solution is unique, so it is
    returned with a warning and advice, and its sigma along the weak axis covers its error."""
    rng = np.random.default_rng(2)
    data = make(rng, orientations=synthetic.tilt_orientations(R0, np.radians(1.0)),
                sensor=10e-6, robot=10e-6)  # fmt: skip
    with caplog.at_level(logging.WARNING, logger="wristscan.calib.handeye"):
        res = handeye.refine(data.all, X_TRUE, BALL_R, robot_sigma_m=10e-6)
    assert 100.0 < res.condition < handeye.COND_HARD
    assert "weakly constrained" in caplog.text and "sensor Z axis" in res.advice
    _, t = errors(res.sensor2flange)
    assert abs(t[2]) < 4.0 * res.sigma_translation_m[2]
    assert res.sigma_translation_m[2] > 10.0 * res.sigma_translation_m[0]  # and says it is weak


def test_a_null_direction_is_refused() -> None:
    """Tilts about the tool axis alone leave the origin along it unobserved: not unique."""
    ori = np.stack([R0 @ se3.rot_z(a) for a in np.radians([45.0, -45.0, 90.0])])
    data = make(np.random.default_rng(3), grid=GRID[[0, 2, 6]], orientations=ori, sensor=10e-6)
    with pytest.raises(PoorlyConstrained) as exc:
        handeye.refine(data.all, X_TRUE, BALL_R)
    assert exc.value.condition > handeye.COND_HARD
