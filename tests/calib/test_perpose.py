"""sensor2flange from one profile per pose (calib/perpose): the closed-form start, the side of the
laser plane, the joint refinement and the refusals.

The data are made here from the geometry alone: a ball of radius R at a known place, sensor
poses looking at it from tilted orientations, and each profile the arc where the laser plane
(sensor x = 0) cuts the ball, seen along the sensor's +Z rays, with Gaussian depth noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from wristscan.calib import perpose, se3
from wristscan.calib.handeye import PoorlyConstrained

R_BALL = 0.0127
NOISE = 20e-6
X_TRUE = se3.pose_to_matrix([0.060, 0.010, 0.200, 0.020, -0.015, 0.010])
C_TRUE = np.array([0.45, -0.20, 0.16])


@dataclass
class Data:
    flange2base: np.ndarray
    profiles: list[np.ndarray]
    circles: np.ndarray  # true (y, z, r) of each pose


def _data(
    seed: int = 0,
    n: int = 15,
    side: int | None = 1,
    heights: tuple[float, float] = (0.15, 0.85),
    tilt_deg: float = 50.0,
) -> Data:
    """``n`` stop-and-go poses; ``side`` None draws the side of each pose at random."""
    rng = np.random.default_rng(seed)
    F, profiles, circles = [], [], []
    y_grid = np.linspace(-0.025, 0.025, 512)
    for _ in range(n):
        tilt, az = rng.uniform(0, np.radians(tilt_deg)), rng.uniform(0, 2 * np.pi)
        axis = np.array([np.cos(az), np.sin(az), 0.0])
        Rs = se3.rotvec_to_matrix(axis * tilt) @ se3.rot_x(np.pi) @ se3.rot_z(rng.uniform(-3, 3))
        s = side if side is not None else rng.choice([-1, 1])
        x = s * R_BALL * rng.uniform(*heights)
        cs = np.array([x, rng.uniform(-0.01, 0.01), rng.uniform(0.08, 0.12)])
        F.append(se3.make(Rs, C_TRUE - Rs @ cs) @ se3.invert(X_TRUE))
        r = np.sqrt(R_BALL**2 - x**2)
        on = np.abs(y_grid - cs[1]) < r
        y = y_grid[on]
        z = cs[2] - np.sqrt(r**2 - (y - cs[1]) ** 2) + rng.normal(0, NOISE, y.size)
        profiles.append(np.column_stack([y, z]))
        circles.append([cs[1], cs[2], r])
    return Data(np.array(F), profiles, np.array(circles))


def _t_err(X: np.ndarray) -> float:
    return float(np.linalg.norm(X[:3, 3] - X_TRUE[:3, 3]))


def _r_err(X: np.ndarray) -> float:
    return float(se3.rotation_angle(X[:3, :3].T @ X_TRUE[:3, :3]))


def test_closed_form_needs_no_guess_and_tells_the_sides_apart() -> None:
    d = _data(seed=1)
    plus, minus = perpose.closed_form(d.flange2base, d.circles, R_BALL)
    # Exact circles: the right side's start is the truth to rounding; the other is 2 h away.
    assert _t_err(plus.sensor2flange) < 1e-9 and _r_err(plus.sensor2flange) < 1e-9
    np.testing.assert_allclose(plus.ball_centre_base, C_TRUE, atol=1e-9)
    assert plus.centre_rms_m < 1e-9 < 1e-3 < minus.centre_rms_m
    assert plus.handedness == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("side", [1, -1])
def test_profiles_calibrate_to_the_truth_from_either_side(side: int) -> None:
    d = _data(seed=2, side=side)
    res = perpose.calibrate_per_pose(d.flange2base, d.profiles, R_BALL)
    assert res.side == side and np.all(res.sides == side)
    # 15 profiles of ~200 points with 20 um noise: the reported sigma is ~1-4 um and ~0.003 deg
    # per axis; 10 um and 0.02 deg are more than 3 sigma of it.
    assert _t_err(res.sensor2flange) < 10e-6
    assert _r_err(res.sensor2flange) < np.radians(0.02)
    np.testing.assert_allclose(res.joint.ball_centre_base, C_TRUE, atol=10e-6)
    sig = res.joint.sigma_translation_m
    assert np.all(np.abs(res.sensor2flange[:3, 3] - X_TRUE[:3, 3]) < 4 * sig + 1e-6)
    w = se3.matrix_to_rotvec(res.sensor2flange[:3, :3].T @ X_TRUE[:3, :3])
    assert np.all(np.abs(w) < 4 * res.joint.sigma_rotation_rad + 1e-6)
    # The noise runs along the rays, the residual along the ball's normal: a part of the noise.
    assert 0.4 * NOISE < res.joint.rms < NOISE


def test_mixed_sides_are_found_pose_by_pose() -> None:
    d = _data(seed=3, side=None)
    res = perpose.calibrate_per_pose(d.flange2base, d.profiles, R_BALL)
    truth = np.sign(np.einsum("ki,ki->k", (d.flange2base @ X_TRUE)[:, :3, 0], C_TRUE - (
        d.flange2base @ X_TRUE)[:, :3, 3]))  # fmt: skip
    assert res.side == 0
    np.testing.assert_array_equal(res.sides, truth)
    assert _t_err(res.sensor2flange) < 10e-6


def test_one_height_of_the_cut_is_ambiguous_and_refused_unless_the_side_is_given() -> None:
    d = _data(seed=4, heights=(0.5, 0.5))
    with pytest.raises(perpose.AmbiguousSide, match="give the side"):
        perpose.calibrate_per_pose(d.flange2base, d.profiles, R_BALL)
    res = perpose.calibrate_per_pose(d.flange2base, d.profiles, R_BALL, side=1)
    assert _t_err(res.sensor2flange) < 10e-6


def test_circle_centres_alone_give_the_solution() -> None:
    d = _data(seed=5)
    fits = perpose.fit_pose_circles(d.profiles, R_BALL)
    C = np.array([[*c.centre_yz, c.radius] for c in fits])
    X, c, rms = perpose.calibrate_from_circles(d.flange2base, C, R_BALL, side=1)
    # The heights follow from the radii (dh = r/h dr): the centres carry ~20-50 um of noise.
    assert _t_err(X) < 0.1e-3 and _r_err(X) < np.radians(0.05)
    np.testing.assert_allclose(c, C_TRUE, atol=0.1e-3)
    assert rms < 0.1e-3


def test_jackknife_spread_agrees_with_the_reported_sigma() -> None:
    d = _data(seed=6)
    res = perpose.calibrate_per_pose(d.flange2base, d.profiles, R_BALL)
    jk = perpose.jackknife(res)
    assert jk.increments.shape == (15, 6) and jk.cov.shape == (6, 6)
    ratio = jk.sigma_translation_m / res.joint.sigma_translation_m
    assert np.all((ratio > 0.25) & (ratio < 4.0)), ratio


def test_orientations_that_never_change_are_refused() -> None:
    d = _data(seed=7)
    F = d.flange2base.copy()
    F[:, :3, :3] = F[0, :3, :3]  # the robot only translates
    with pytest.raises(PoorlyConstrained, match="do not determine"):
        perpose.closed_form(F, d.circles, R_BALL)


def test_too_few_poses_are_refused() -> None:
    d = _data(seed=8, n=5)
    with pytest.raises(perpose.PerPoseDataError, match=r"5 poses.*>= 6"):
        perpose.calibrate_per_pose(d.flange2base, d.profiles, R_BALL)


@pytest.mark.parametrize(
    ("factor", "message"), [(2.0, "radius, not the diameter"), (0.5, "ball radius right")]
)
def test_a_ball_radius_wrong_by_two_is_refused(factor: float, message: str) -> None:
    d = _data(seed=9)
    with pytest.raises(perpose.PerPoseDataError, match=message):
        perpose.calibrate_per_pose(d.flange2base, d.profiles, factor * R_BALL)
