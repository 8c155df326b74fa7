"""The arm's kinematic error in the hand-eye uncertainty (calib/handeye_kinematic.py): the
propagated effect of a known DH error against the shift of the solution when that error is
really applied to the flange poses (the sweeps' truth from calib.synthetic)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from wristscan.calib import handeye, kinematic_errors, kinematics, se3, synthetic
from wristscan.calib.dh import get_model, with_deltas
from wristscan.calib.handeye_kinematic import (
    KinematicPrior,
    flange_sensitivity,
    prior_sigma,
    sensitivity,
    sweep_joints,
)
from wristscan.calib.handeye_points import PointStack
from wristscan.calib.handeye_uncertainty import local_errors

R_BALL = 12.7e-3
C_BALL = np.array([0.45, -0.10, 0.12])
X_TRUE = se3.make(se3.rotvec_to_matrix([0.012, -0.018, 0.025]), [0.060, 0.010, 0.200])
R0 = se3.rot_x(np.pi) @ X_TRUE[:3, :3].T
NOMINAL = get_model("UR5e")
#: theta, a, d, alpha rows; joint column.
THETA, A_ROW, D_ROW = 0, 1, 2


def _sweeps() -> list[handeye.Sweep]:
    data = synthetic.make_ball_sweeps(
        X_TRUE, C_BALL, R_BALL, synthetic.fov_grid(), synthetic.tilt_orientations(R0), 0.0,
        2e-6, np.random.default_rng(3), sensor=synthetic.SensorModel(y_pitch_m=1e-3),
        sweep_step_m=1.5e-3, tilt_fov=synthetic.fov_grid()[[0, 2, 6, 8, 1, 7]],
    )  # fmt: skip
    return list(data.all)


def _delta_model(row: int, joint: int, value: float) -> object:
    d = np.zeros((4, 6))
    d[row, joint] = value
    return with_deltas(NOMINAL, d[0], d[1], d[2], d[3])


def _reported(sweeps: list[handeye.Sweep], true_model: object) -> list[handeye.Sweep]:
    """The sweeps as a controller computing with the nominal table reports them when the arm is
    ``true_model``: each sweep's flange moved by the error at its middle pose's joints."""
    out = []
    for s in sweeps:
        F = s.flange2base[s.n_poses // 2]
        q = kinematics.inverse_nearest(true_model, F, kinematics.inverse_nearest(NOMINAL, F, Q0))
        E = se3.invert(F) @ kinematics.forward(NOMINAL, q)
        out.append(handeye.Sweep(s.flange2base @ E, s.points_sensor, s.pose_index))
    return out


Q0 = np.array([0.0, -1.9, 1.9, -1.57, -1.57, 0.0])


@pytest.fixture(scope="module")
def clean() -> tuple[list[handeye.Sweep], handeye.HandEyeResult]:
    sw = _sweeps()
    two = handeye.two_step(sw[:9], sw[9:], R_BALL)
    return sw, handeye.refine(sw, two, R_BALL)


def test_prior_sigma_defaults() -> None:
    s = kinematic_errors.REALISTIC
    assert prior_sigma("none")[D_ROW, 5] == pytest.approx(s.d_m)
    assert prior_sigma("partial")[THETA, 1] == pytest.approx(0.15 * s.theta_rad)
    assert not np.any(prior_sigma("exact"))
    with pytest.raises(ValueError, match="factory calibration"):
        prior_sigma("half")
    with pytest.raises(ValueError, match="sigma"):
        KinematicPrior(NOMINAL, np.ones((3, 6)))


def test_flange_sensitivity_of_the_last_link_is_a_shift_along_the_tool_axis() -> None:
    q = np.array([[0.3, -1.7, 1.6, -1.2, -1.5, 0.4], [-0.5, -2.1, 2.0, -1.9, -1.3, -0.7]])
    G = flange_sensitivity(NOMINAL, q)
    assert G.shape == (2, 6, 24)
    np.testing.assert_allclose(G[:, :, 2 * 6 + 5], [[0, 0, 0, 0, 0, 1]] * 2, atol=1e-6)
    # Against the flange really moved by a finite DH error (0.1 mm on a2).
    dq = kinematics.forward(_delta_model(A_ROW, 1, 1e-4), q)
    D = se3.invert(kinematics.forward(NOMINAL, q)) @ dq
    np.testing.assert_allclose(G[:, 3:, 6 + 1] * 1e-4, D[:, :3, 3], atol=1e-8)


@pytest.mark.parametrize(
    ("row", "joint", "value"),
    [(A_ROW, 1, 0.1e-3), (THETA, 1, math.radians(0.01)), (D_ROW, 5, 0.1e-3)],
)
def test_propagated_shift_matches_the_applied_dh_error(
    clean: tuple[list[handeye.Sweep], handeye.HandEyeResult], row: int, joint: int, value: float
) -> None:
    sw, base = clean
    moved = handeye.refine(_reported(sw, _delta_model(row, joint, value)), base, R_BALL)
    actual = local_errors(moved.sensor2flange[None], base.sensor2flange)[0]
    prior = KinematicPrior(NOMINAL, np.zeros((4, 6)))
    G = flange_sensitivity(NOMINAL, sweep_joints(prior, sw))
    stack = PointStack.build(sw, base.inliers)
    predicted = sensitivity(stack, base, G)[:6, 6 * row + joint] * value
    # The truth moves by a few hundredths of a millimetre: the prediction within 5 % (measured:
    # under 1 %; a wrong sign or a lost sweep would be off by 100 %).
    assert np.linalg.norm(actual[3:]) > 5e-6
    assert np.linalg.norm(predicted[3:] - actual[3:]) <= 0.05 * np.linalg.norm(actual[3:])
    assert np.linalg.norm(predicted[:3] - actual[:3]) <= 0.05 * np.linalg.norm(actual[:3]) + 1e-7


def test_refine_adds_the_common_error_only_when_asked(
    clean: tuple[list[handeye.Sweep], handeye.HandEyeResult],
) -> None:
    sw, base = clean
    # A wrong last link length moves every pose alike along the tool axis: invisible in the
    # residuals, all of it in the prior's term.
    sig = np.zeros((4, 6))
    sig[D_ROW, 5] = 0.05e-3
    with_prior = handeye.refine(sw, base, R_BALL, kinematic_prior=KinematicPrior(NOMINAL, sig))
    without = handeye.refine(sw, base, R_BALL)
    np.testing.assert_allclose(without.cov, base.cov, rtol=1e-6, atol=1e-18)
    added = np.diag(with_prior.cov) - np.diag(without.cov)
    assert np.all(added >= -1e-18)
    moved = handeye.refine(_reported(sw, _delta_model(D_ROW, 5, 0.05e-3)), base, R_BALL)
    shift = local_errors(moved.sensor2flange[None], base.sensor2flange)[0]
    # The sensor origin's sigma along the tool axis grows by what the error really does.
    assert math.sqrt(added[5]) == pytest.approx(abs(shift[5]), rel=0.05)
    assert with_prior.point_sigma_m > without.point_sigma_m
