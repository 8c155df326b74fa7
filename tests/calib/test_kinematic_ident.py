"""The kinematic identification (``calib.kinematic_ident``) on sweeps of a simulated arm whose
true DH deviations are known (``calib.kinematic_errors``); the truth never comes from the
solver."""

from __future__ import annotations

import math

import numpy as np
import pytest
from support import ur5e_working_q

from wristscan.calib import kinematic_errors as kerr
from wristscan.calib import kinematic_ident as ki
from wristscan.calib import kinematic_ident_synthetic as ks
from wristscan.calib import kinematics, se3
from wristscan.calib.handeye_kinematic import prior_sigma

X_TRUE = se3.make(se3.rotvec_to_matrix([0.012, -0.018, 0.025]), [0.060, 0.010, 0.200])
R0 = se3.rot_x(np.pi) @ X_TRUE[:3, :3].T
PLACES = np.array([[-0.30, -0.23, 0.17], [-0.55, 0.07, 0.17], [-0.07, -0.23, 0.17]])
FOV = np.array([[-0.012, -0.012], [0.012, 0.012], [0.012, -0.012], [-0.012, 0.012]])
X0 = X_TRUE @ se3.make(se3.rotvec_to_matrix(np.radians([0.3, -0.3, 0.3])), [5e-4, -5e-4, 5e-4])


@pytest.fixture(scope="module")
def nominal_arm() -> tuple[ks.ArmSetup, list[ki.BallScan], ki.KinematicIdentification]:
    """An arm with realistic DH deviations, its controller on the nominal table (the largest
    error), 8 um repeatability per axis; sweeps at three ball places."""
    m = kerr.RobotErrorModel("UR5e", seed=3, factory="none")
    arm = ks.ArmSetup(m.true_model, m.reported_model, X_TRUE, PLACES, repeatability_axis_m=8e-6)
    ori = ks.orbit_orientations(R0, X_TRUE[:3, :3], (0.0, 25.0, 50.0), 8)[7:]
    scans = ks.make_scans(arm, [ori] * len(PLACES), FOV, np.random.default_rng(3))
    res = ki.identify(scans, arm.reported, X0, arm.radius_m, prior_sigma("none"))
    return arm, scans, res


def test_unobservable_parameters_are_named_and_fixed(
    nominal_arm: tuple[ks.ArmSetup, list[ki.BallScan], ki.KinematicIdentification],
) -> None:
    _, _, res = nominal_arm
    ident = res.ident
    # The base frame (free ball centres), the last link (sensor2flange) and two of the three
    # parallel offsets (only their sum shows).
    assert set(ident.fixed_names) == {"theta1", "d1", "theta6", "d6", "a6", "alpha6", "d3", "d4"}
    assert np.all(res.delta.reshape(-1)[list(ident.fixed)] == 0.0)
    text = dict(u.split(": ", 1) for u in ident.unobservable)
    assert "sensor2flange" in text["theta6"] and "ball centre" in text["d1"]
    assert text["d3"] == "indistinguishable from +1.00 d2"
    # The fixed parameters' sigma is the prior's (nothing learnt), the free ones shrink.
    prior = prior_sigma("none")
    assert res.sigma[2, 2] == pytest.approx(prior[2, 2])
    assert res.sigma[1, 1] < 0.5 * prior[1, 1]


def test_identified_deltas_match_the_truth_within_their_sigmas(
    nominal_arm: tuple[ks.ArmSetup, list[ki.BallScan], ki.KinematicIdentification],
) -> None:
    arm, _, res = nominal_arm
    n, t = arm.reported.arrays(), arm.true.arrays()
    true_dev = np.concatenate([t[3] - n[3], t[1] - n[1], t[0] - n[0], t[2] - n[2]])
    err = res.delta_vector - res.ident.equivalent @ true_dev
    free = list(res.ident.free)
    z = np.abs(err[free]) / res.sigma.reshape(-1)[free]
    assert np.mean(z <= 2.0) >= 0.8, z
    assert z.max() < 4.0, z
    # d2 carries the sum of the parallel offsets, which is observed well.
    d_sum = true_dev[13] + true_dev[14] + true_dev[15]
    assert res.delta[2, 1] == pytest.approx(d_sum, abs=max(3 * res.sigma[2, 1], 5e-6))


def test_identification_cuts_the_point_error_and_the_ball_scatter(
    nominal_arm: tuple[ks.ArmSetup, list[ki.BallScan], ki.KinematicIdentification],
) -> None:
    arm, scans, res = nominal_arm
    q = ur5e_working_q(200, seed=7)  # held-out poses
    before = ks.point_error((arm.reported, res.sensor2flange_before), (arm.true, X_TRUE), q)[1]
    after = ks.point_error((res.model, res.sensor2flange), (arm.true, X_TRUE), q)[1]
    assert after < before / 3.0, (before, after)
    s_before = ks.centre_scatter(scans, arm.reported, res.sensor2flange_before, arm.radius_m)
    s_after = ks.centre_scatter(scans, res.model, res.sensor2flange, arm.radius_m)
    assert s_after < s_before / 3.0, (s_before, s_after)
    assert res.rms_m < 0.5 * res.rms_before_m
    # sensor2flange: its rotation is seen; of its translation, the last link's deviations
    # (absorbed) stay, 0.1 mm per parameter here.
    ang = math.degrees(float(se3.rotation_angle(res.sensor2flange[:3, :3].T @ X_TRUE[:3, :3])))
    assert ang < 0.02


def test_fit_sensor2flange_is_the_solution_without_identification(
    nominal_arm: tuple[ks.ArmSetup, list[ki.BallScan], ki.KinematicIdentification],
) -> None:
    arm, scans, res = nominal_arm
    X, c, rms = ki.fit_sensor2flange(scans, arm.reported, X0, arm.radius_m)
    assert np.allclose(X, res.sensor2flange_before, atol=1e-7)
    assert rms == pytest.approx(res.rms_before_m, rel=0.05)
    assert c.shape == (len(PLACES), 3)


def test_path_joints_follow_the_flange_path() -> None:
    model = kerr.true_model("UR5e", kerr.REALISTIC, 5)
    q0 = np.array([0.2, -1.8, 1.8, -1.6, -1.5, 0.3])
    F0 = kinematics.forward(model, q0)
    F = np.stack([F0 @ se3.make(None, (s, 0.0, 0.0)) for s in np.linspace(-0.02, 0.02, 41)])
    q = ks.path_joints(model, F, q0)
    np.testing.assert_allclose(kinematics.forward(model, q), F, atol=1e-9)
    assert np.max(np.abs(q - q0)) < 0.2


def test_bad_input_is_one_clear_error() -> None:
    s = ks.make_scans(
        ks.ArmSetup(kinematics.get_model("UR5e"), kinematics.get_model("UR5e"), X_TRUE, PLACES[:1]),
        [R0[None]],
        FOV[:1],
        np.random.default_rng(0),
    )
    assert len(s) == 1
    with pytest.raises(ValueError, match="prior_sigma"):
        ki.identify(s, "UR5e", X0, 0.0127, np.zeros((4, 6)))
    with pytest.raises(ValueError, match="radius"):
        ki.identify(s, "UR5e", X0, -1.0, prior_sigma("none"))
    with pytest.raises(ValueError, match="joints"):
        ki.BallScan(s[0].sweep, s[0].joints[:-1])
    with pytest.raises(ValueError, match="numbered"):
        ki.identify([ki.BallScan(s[0].sweep, s[0].joints, 2)], "UR5e", X0, 0.0127,
                    prior_sigma("none"))  # fmt: skip
