"""`calibrate sensor`'s default prior of the arm's kinematic error
(daemon/calibrate/sensor/solve.py `kinematic_prior_for`), by the model the robot reports."""

from __future__ import annotations

import numpy as np
import pytest

from wristscan.calib import kinematic_errors
from wristscan.calib.dh import get_model
from wristscan.daemon.calibrate.sensor.solve import kinematic_prior_for

SIZES = kinematic_errors.REALISTIC


def test_a_factory_calibration_leaves_the_residual_of_a_real_arms_deviations() -> None:
    arm = kinematic_errors.RobotErrorModel("UR5e", seed=4, factory="partial")
    factory = arm.reported_model
    prior = kinematic_prior_for(factory, "UR5e")
    assert prior is not None and prior.model is factory
    np.testing.assert_allclose(prior.sigma[1], 0.15 * SIZES.a_m)
    np.testing.assert_allclose(prior.sigma[3], 0.15 * SIZES.alpha_rad)


def test_the_nominal_table_has_all_of_them_and_no_model_none() -> None:
    q = np.array([0.1, -1.5, 1.5, -1.6, -1.6, 0.2])
    for prior in (kinematic_prior_for(get_model("UR10e"), "UR10e", q),
                  kinematic_prior_for(None, "UR10e", q)):  # fmt: skip
        assert prior is not None and prior.model.a == get_model("UR10e").a
        np.testing.assert_allclose(prior.sigma[2], SIZES.d_m)
        assert prior.seed[0] == pytest.approx(0.1)
    assert kinematic_prior_for(None, None) is None
