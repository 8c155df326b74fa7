"""handeye: the paper's two-step tool transformation and the joint refinement, on ray-cast sweeps
with a known ground truth (calib.synthetic)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from wristscan.calib import handeye, se3, synthetic
from wristscan.calib.handeye import PoorlyConstrained, Sweep
from wristscan.calib.handeye_points import PointStack, right_jacobian

# Ground truth near the paper's simulated TCP (60, 10, 200) mm, with a small rotation.
X_TRUE = se3.make(se3.rotvec_to_matrix([0.012, -0.018, 0.025]), [0.060, 0.010, 0.200])
BALL_C = np.array([0.45, -0.10, 0.12])
BALL_R = 0.0127
R0 = se3.rot_x(np.pi) @ X_TRUE[:3, :3].T  # sensor Z looking down during the FOV sweeps
# Coarser sampling than a real sensor keeps the tests fast (about 25k points in all).
SENSOR = synthetic.SensorModel(y_pitch_m=0.5e-3)
STEP_M = 0.6e-3
GRID = synthetic.fov_grid()


def make(
    rng: np.random.Generator,
    *,
    grid: np.ndarray = GRID,
    orientations: np.ndarray | None = None,
    robot: float = 0.0,
    sensor: float = 0.0,
    **kw: object,
) -> synthetic.BallSweeps:
    ori = synthetic.tilt_orientations(R0) if orientations is None else orientations
    return synthetic.make_ball_sweeps(
        X_TRUE, BALL_C, BALL_R, grid, ori, robot, sensor, rng,
        sensor=SENSOR, sweep_step_m=STEP_M, **kw,  # type: ignore[arg-type]
    )  # fmt: skip


def errors(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rotation-vector error about the sensor axes (rad), translation error (m))."""
    d = se3.invert(X_TRUE) @ X
    return se3.matrix_to_rotvec(d[:3, :3]), X[:3, 3] - X_TRUE[:3, 3]


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


# ------------------------------------------------------------------------------------------
# generator


def test_synthetic_points_lie_on_the_ball_and_clutter_is_labelled(rng: np.random.Generator) -> None:
    data = make(rng, scene=synthetic.BallScene())
    for sw, on in zip(data.all, data.all_on_ball, strict=True):
        assert sw.points_sensor[:, 0].max() == 0.0  # laser plane
        d = np.linalg.norm(sw.points_base(X_TRUE) - BALL_C, axis=1) - BALL_R
        assert np.abs(d[on]).max() < 1e-12
        if (~on).any():
            assert np.abs(d[~on]).min() > -1e-12  # post and table lie outside the ball
    # The table shows in the shallower FOV sweeps and the post in the tilted ones.
    assert sum(bool((~on).any()) for on in data.fov_on_ball) == 6
    post = [np.abs(sw.points_base(X_TRUE)[~on, 2] - (BALL_C[2] - 0.03)) > 1e-9
            for sw, on in zip(data.tilt, data.tilt_on_ball, strict=True)]  # fmt: skip
    assert sum(int(p.sum()) for p in post) > 100


def test_sweep_validation() -> None:
    F = se3.identity((3,))
    with pytest.raises(ValueError, match="pose_index"):
        Sweep.from_yz(F, [0.0, 1.0], [0.0, 1.0], [0, 3])
    with pytest.raises(ValueError, match="points_sensor"):
        Sweep(F, np.zeros((4, 2)), np.zeros(4, dtype=int))
    with pytest.raises(ValueError, match="flange2base"):
        Sweep(np.eye(4), np.zeros((4, 3)), np.zeros(4, dtype=int))
    with pytest.raises(ValueError, match="NaN"):
        Sweep.from_yz(F, [np.nan], [0.0], [0])


# ------------------------------------------------------------------------------------------
# exact recovery


def test_noise_free_two_step_and_joint_recover_truth_exactly(rng: np.random.Generator) -> None:
    # The robot commands the sweeps along a nominal tool 1.3 deg and a few mm off the truth.
    nominal = X_TRUE @ se3.make(se3.rotvec_to_matrix([0.015, -0.01, 0.012]), [0.002, -0.001, 0.003])
    data = make(rng, sensor2flange_nominal=nominal)
    two = handeye.two_step(data.fov, data.tilt, BALL_R)
    w, t = errors(two.sensor2flange)
    assert np.abs(t).max() < 1e-9 and np.abs(w).max() < 1e-9
    np.testing.assert_allclose(two.ball_centre_base, BALL_C, atol=1e-9)
    assert two.method == "two-step" and two.rms < 1e-9 and two.advice == ""
    joint = handeye.refine(data.all, two, BALL_R)
    w, t = errors(joint.sensor2flange)
    assert np.abs(t).max() < 1e-9 and np.abs(w).max() < 1e-9
    assert joint.method == "joint" and joint.rms < 1e-9
    assert joint.n_points == sum(s.n_points for s in data.all)
    assert joint.per_sweep_rms.shape == (len(data.all),)
    assert joint.cov.shape == (6, 6) and joint.cov_full is not None
    assert joint.cov_full.shape == (9, 9)
    assert joint.condition < handeye.COND_SOFT


def test_joint_from_a_rough_guess_and_unknown_radius(rng: np.random.Generator) -> None:
    data = make(rng, sensor=5e-6)
    rough = X_TRUE @ se3.make(se3.rotvec_to_matrix([0.01, 0.01, -0.01]), [0.002, -0.002, 0.002])
    res = handeye.refine(data.all, rough, None, loss="soft_l1")  # robust loss: trf path
    w, t = errors(res.sensor2flange)
    assert np.abs(t).max() < 5e-6 and np.abs(w).max() < 5e-5
    assert res.ball_radius_m == pytest.approx(BALL_R, abs=5e-6)
    assert res.cov_full is not None and res.cov_full.shape == (10, 10)


def test_orientation_step_with_three_fov_locations(rng: np.random.Generator) -> None:
    data = make(rng, grid=GRID[[0, 2, 6]], orientations=np.zeros((0, 3, 3)))  # an L, not a line
    ori = handeye.solve_orientation(data.fov, BALL_R)
    assert se3.rotation_angle(ori.rotation.T @ X_TRUE[:3, :3]) < 1e-9
    assert ori.centres_sensor.shape == (3, 3) and ori.rms < 1e-9
    # A wrong sign of the commanded sweep axis is undone by the iteration with the estimate.
    flipped = handeye.solve_orientation(data.fov, BALL_R, sweep_direction_sensor=(-1.0, 0.0, 0.0))
    assert se3.rotation_angle(flipped.rotation.T @ X_TRUE[:3, :3]) < 1e-9
    assert flipped.iterations >= 2


def test_analytic_jacobian_matches_finite_differences(rng: np.random.Generator) -> None:
    data = make(rng, grid=GRID[:2], orientations=synthetic.tilt_orientations(R0)[:1])
    st = PointStack.build(data.all)
    Rb = X_TRUE[:3, :3]
    x = np.concatenate([[0.02, -0.01, 0.03], X_TRUE[:3, 3] + 1e-3, BALL_C - 2e-3, [BALL_R]])

    def fun(v: np.ndarray) -> np.ndarray:
        return st.residuals(Rb @ se3.rotvec_to_matrix(v[:3]), v[3:6], v[6:9], v[9])

    J = st.jacobian(Rb @ se3.rotvec_to_matrix(x[:3]), x[3:6], x[6:9], True,
                    right_jacobian(x[:3]))  # fmt: skip
    h = 1e-7
    Jn = np.stack([(fun(x + h * e) - fun(x - h * e)) / (2 * h) for e in np.eye(10)], axis=1)
    np.testing.assert_allclose(J, Jn, atol=1e-6)


# ------------------------------------------------------------------------------------------
# noise and covariance


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_noisy_errors_are_within_the_reported_covariance(seed: int) -> None:
    robot = 10e-6
    data = make(np.random.default_rng(seed), robot=robot, sensor=20e-6)
    two = handeye.two_step(data.fov, data.tilt, BALL_R)
    joint = handeye.refine(data.all, two, BALL_R, robot_sigma_m=robot)
    for res in (two, joint):
        w, t = errors(res.sensor2flange)
        e = np.concatenate([w, t])
        sig = np.sqrt(np.diag(res.cov))
        assert np.all(np.abs(e) < 4.5 * sig), (res.method, e / sig)
        assert e @ np.linalg.solve(res.cov, e) < 27.9  # chi2(6), p = 1e-4
    # Sanity of magnitudes: tens of micrometres, hundredths of a degree.
    w, t = errors(joint.sensor2flange)
    assert np.linalg.norm(t) < 60e-6 and np.degrees(np.linalg.norm(w)) < 0.06
    assert 15e-6 < joint.rms < 30e-6


def test_robot_noise_term_widens_the_covariance(rng: np.random.Generator) -> None:
    data = make(rng, robot=10e-6, sensor=20e-6)
    plain = handeye.refine(data.all, X_TRUE, BALL_R, robot_model=False)  # sensor noise alone
    wide = handeye.refine(data.all, plain, BALL_R, robot_sigma_m=10e-6, robot_model=False)
    found = handeye.refine(data.all, plain, BALL_R)  # the robot's error from the residuals
    np.testing.assert_allclose(wide.sensor2flange, plain.sensor2flange, atol=1e-10)
    np.testing.assert_allclose(found.sensor2flange, plain.sensor2flange, atol=1e-10)
    # Robot error is shared by a whole sweep: it dominates the points' sensor noise.
    assert np.all(wide.sigma_translation_m > 2.0 * plain.sigma_translation_m)
    assert np.all(found.sigma_translation_m > 2.0 * plain.sigma_translation_m)
    # The simulated 10 um per sweep, seen in the scatter of the FOV group's sweeps.
    assert found.components is not None
    assert 6e-6 < found.components.sweep_sigma_estimated_m < 14e-6
    assert 12e-6 < found.components.noise_sigma_m < 22e-6


# ------------------------------------------------------------------------------------------
# outliers


def test_post_and_table_points_are_excluded() -> None:
    data = make(np.random.default_rng(3), robot=5e-6, sensor=20e-6, scene=synthetic.BallScene())
    two = handeye.two_step(data.fov, data.tilt, BALL_R)
    rough = X_TRUE @ se3.make(se3.rotvec_to_matrix([0.01, -0.01, 0.01]), [0.001, 0.002, -0.001])
    n_ball = sum(int(on.sum()) for on in data.all_on_ball)
    for res in (
        two,
        handeye.refine(data.all, two, BALL_R, robot_sigma_m=5e-6),
        handeye.refine(data.all, rough, BALL_R, robot_sigma_m=5e-6),
    ):
        n_clutter = sum(int((~on).sum()) for on in data.all_on_ball)
        wrong = sum(
            int((m & ~on).sum()) for m, on in zip(res.inliers, data.all_on_ball, strict=True)
        )
        assert n_clutter > 20_000
        # Only post points right at the ball's equator may pass (they touch the sphere).
        assert wrong < 0.002 * n_clutter, res.method
        missed = sum(
            int((~m & on).sum()) for m, on in zip(res.inliers, data.all_on_ball, strict=True)
        )
        assert missed < 0.005 * n_ball, res.method
        w, t = errors(res.sensor2flange)
        assert np.linalg.norm(t) < 4 * np.linalg.norm(res.sigma_translation_m), res.method
        assert np.linalg.norm(w) < 4 * np.linalg.norm(res.sigma_rotation_rad), res.method
        assert res.rms < 30e-6


# ------------------------------------------------------------------------------------------
# identifiability


def test_tilts_about_one_axis_are_poorly_constrained(rng: np.random.Generator) -> None:
    ori = np.stack([R0 @ se3.rot_z(a) for a in np.radians([45.0, -45.0, 90.0])])
    data = make(rng, grid=GRID[[0, 2, 6]], orientations=ori, sensor=10e-6)
    with pytest.raises(PoorlyConstrained) as joint:
        handeye.refine(data.all, X_TRUE, BALL_R)
    assert "tilted about the sensor X or Y axis" in joint.value.advice
    assert joint.value.condition > handeye.COND_HARD
    with pytest.raises(PoorlyConstrained) as two:
        handeye.two_step(data.fov, data.tilt, BALL_R)
    assert "tilted about the sensor X and Y axes" in two.value.advice
    assert isinstance(two.value, ValueError)


def test_no_tilts_and_collinear_fov_give_advice(rng: np.random.Generator) -> None:
    data = make(rng, orientations=np.zeros((0, 3, 3)))
    with pytest.raises(PoorlyConstrained, match="two different axes"):
        handeye.refine(data.fov, X_TRUE, BALL_R)
    line = make(rng, grid=synthetic.fov_grid(3, 1), orientations=np.zeros((0, 3, 3)))
    with pytest.raises(PoorlyConstrained, match="more field-of-view locations"):
        handeye.solve_orientation(line.fov, BALL_R)
    with pytest.raises(PoorlyConstrained, match=">= 3 field-of-view"):
        handeye.solve_orientation(line.fov[:2], BALL_R)


def test_small_tilts_warn(rng: np.random.Generator, caplog: pytest.LogCaptureFixture) -> None:
    data = make(rng, orientations=synthetic.tilt_orientations(R0, np.radians(12.0)), sensor=10e-6)
    with caplog.at_level(logging.WARNING, logger="wristscan.calib.handeye"):
        res = handeye.refine(data.all, X_TRUE, BALL_R)
    assert handeye.COND_SOFT < res.condition < handeye.COND_HARD
    assert "weakly constrained" in caplog.text
    assert "sensor Z axis" in res.advice  # tilts about X and Y leave the depth least observed
    assert handeye.check_identifiability(data.all, X_TRUE, BALL_C).condition == pytest.approx(
        res.condition, rel=0.05
    )


def test_two_step_refuses_rotating_sweeps(rng: np.random.Generator) -> None:
    data = make(rng)
    s = data.tilt[0]
    F = s.flange2base.copy()
    F[-1, :3, :3] = F[-1, :3, :3] @ se3.rot_z(0.01)
    bad = Sweep(F, s.points_sensor, s.pose_index)
    with pytest.raises(ValueError, match="constant-orientation"):
        handeye.two_step(data.fov, [bad, *data.tilt[1:]], BALL_R)
    with pytest.raises(ValueError, match="ball_radius"):
        handeye.two_step(data.fov, data.tilt, -1.0)
