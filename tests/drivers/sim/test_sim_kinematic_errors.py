"""A simulated arm as wrong as a real one (issue 17, item 1): its true kinematics differ from the
nominal DH table, its controller reports a factory calibration that is exact, partial or absent,
its encoders are noisy and its poses repeat only to the repeatability.

Truth comes from the simulator: the controller's ``state()`` (true joints, and the true TCP pose
computed by the arm's true model) and the models the cell reports in ``truth()``. What is checked
against it is what a client gets: the primary interface's KinematicsInfo (read by the UR driver's
reader, which the daemon uses with ``use_factory_kinematics``) and the RTDE stream.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import pytest
import rtde_receive
from pydantic import ValidationError
from support import UR5E_WORK_Q, ur5e_working_q

from wristscan.calib import kinematic_errors as kerr
from wristscan.calib import kinematics, se3
from wristscan.daemon.config import SimConfig
from wristscan.daemon.config.loading import parse_config
from wristscan.daemon.config.sim import SimControllerConfig
from wristscan.daemon.simcell.cell import cell_spec, dump_toml, free_sim_config
from wristscan.drivers.sim.cell import CellSpec, SimulatedCell
from wristscan.drivers.sim.truth import TruthRing
from wristscan.drivers.sim.ur.controller import ControllerConfig, SimulatedController
from wristscan.drivers.ur.primary import read_kinematics_info

pytestmark = pytest.mark.timeout(180)

UR5E = kinematics.get_model("UR5e")
# ------------------------------------------------------------------------------ the error model


def test_true_model_is_seeded_and_of_the_configured_size() -> None:
    a = ControllerConfig(kinematic_errors=kerr.REALISTIC, kinematic_seed=11)
    b = ControllerConfig(kinematic_errors=kerr.REALISTIC, kinematic_seed=11)
    c = ControllerConfig(kinematic_errors=kerr.REALISTIC, kinematic_seed=12)
    assert a.true_model == b.true_model  # reproducible
    assert a.true_model.d != c.true_model.d
    assert ControllerConfig().true_model == UR5E  # no errors unless asked for
    # The deviations have the configured spread (measured over many arms, not echoed).
    sizes = kerr.KinematicErrorSizes(
        theta_rad=math.radians(0.03), a_m=0.3e-3, d_m=0.2e-3, alpha_rad=math.radians(0.05)
    )
    dev = np.array(
        [np.subtract(kerr.true_model("UR5e", sizes, s).arrays(), UR5E.arrays()) for s in range(300)]
    )  # (seed, [d, a, alpha, theta], joint)
    spread = dev.std(axis=(0, 2))
    want = np.array([sizes.d_m, sizes.a_m, sizes.alpha_rad, sizes.theta_rad])
    assert np.all(np.abs(spread / want - 1.0) < 0.1), spread / want


def test_realistic_arm_misses_the_nominal_pose_by_a_real_arms_error() -> None:
    q = ur5e_working_q(400, seed=1)
    for seed in range(5):
        none = kerr.RobotErrorModel("UR5e", kerr.REALISTIC, seed, factory="none")
        partial = kerr.RobotErrorModel("UR5e", kerr.REALISTIC, seed, factory="partial")
        exact = kerr.RobotErrorModel("UR5e", kerr.REALISTIC, seed, factory="exact")
        e_none = none.flange_error(q)[0]
        rms = float(np.sqrt(np.mean(e_none**2)))
        assert 0.05e-3 < rms < 0.5e-3, (seed, rms)
        e_partial = partial.flange_error(q)[0]
        ratio = float(np.sqrt(np.mean(e_partial**2))) / rms
        assert 0.1 < ratio < 0.2, ratio  # 15 % of each deviation left
        assert exact.flange_error(q)[0].max() < 1e-12


def test_observe_applies_encoder_noise_and_repeatability_of_their_size() -> None:
    arm = kerr.RobotErrorModel(
        "UR5e", kerr.REALISTIC, 3, factory="exact", joint_noise_rad=2e-5, repeatability_m=5e-5
    )
    q = ur5e_working_q(4000, seed=2)
    obs = arm.observe(q, rng=9)
    noise = obs.q_reported - q
    assert noise.std() == pytest.approx(2e-5, rel=0.05)
    assert abs(noise.mean()) < 1e-6
    # Repeatability: the flange lands off the commanded pose by its RMS, in position only
    # (smallest joint change), independently from pose to pose.
    commanded = kinematics.forward(arm.true_model, q)
    off = obs.flange_true[:, :3, 3] - commanded[:, :3, 3]
    assert float(np.sqrt(np.mean(np.sum(off**2, axis=1)))) == pytest.approx(5e-5, rel=0.05)
    assert abs(np.corrcoef(off[:-1, 0], off[1:, 0])[0, 1]) < 0.1
    # Same seed, same draw.
    again = arm.observe(q, rng=9)
    assert np.array_equal(again.flange_true, obs.flange_true)
    # The samples of one sweep share their offset.
    sweeps = arm.observe(q[:6], rng=1, groups=[0, 0, 0, 1, 1, 1])
    off = sweeps.flange_true[:, :3, 3] - commanded[:6, :3, 3]
    assert np.allclose(off[:3], off[0], rtol=0, atol=1e-8)  # to first order
    assert np.allclose(off[3:], off[3], rtol=0, atol=1e-8)
    assert np.linalg.norm(off[0] - off[3]) > 1e-6


# ------------------------------------------------------------------------------ configuration


def test_sim_controller_section_builds_the_cell() -> None:
    with pytest.raises(ValidationError, match="realistic"):
        SimControllerConfig(kinematic_error_a_m=1e-4)  # sizes without errors switched on
    with pytest.raises(ValidationError):
        SimControllerConfig(factory_calibration="approximately")  # type: ignore[arg-type]
    doc = free_sim_config(
        {
            "sim.controller": {
                "kinematic_errors": "realistic",
                "kinematic_seed": 4,
                "kinematic_error_theta_deg": 0.02,
                "factory_calibration": "partial",
                "joint_noise_rad": 1e-5,
            }
        }
    )
    cfg = parse_config(dump_toml(doc))
    sizes = (cfg.sim or SimConfig()).controller.error_sizes()
    assert sizes == kerr.KinematicErrorSizes(theta_rad=math.radians(0.02))
    spec = cell_spec(cfg)
    assert spec.controller.kinematic_seed == 4
    assert spec.controller.joint_noise_rad == 1e-5
    true = kerr.true_model("UR5e", sizes, 4)
    # The sensor sees the scene from the true flange; the truth says which model that is.
    assert spec.sensor.robot_model == true
    truth = SimulatedCell(spec).truth()
    assert kerr.model_from_dict(truth["robot_model_true"]) == true
    reported = kerr.model_from_dict(truth["robot_model_reported"])
    assert reported == kerr.factory_model("UR5e", true, "partial")
    assert truth["robot_factory_calibration"] == "partial"
    # A cell built without the configuration gets the true model for its sensor as well.
    bare = SimulatedCell(
        CellSpec(
            controller=ControllerConfig(kinematic_errors=kerr.REALISTIC, kinematic_seed=2),
            table=None,
        )
    )
    assert bare.spec.sensor.robot_model == kerr.true_model("UR5e", kerr.REALISTIC, 2)
    # The true flange at an instant: the true model at the ring's true joints.
    bare.robot_ring = TruthRing.create(width=6, capacity=16)
    try:
        bare.robot_ring.append(1_000, UR5E_WORK_Q[0])
        bare.robot_ring.append(2_000, UR5E_WORK_Q[1])
        T = bare.true_flange2base([1_500, 5_000])
        mid = kinematics.forward(
            bare.spec.controller.true_model, (UR5E_WORK_Q[0] + UR5E_WORK_Q[1]) / 2
        )
        assert np.allclose(T[0], mid, rtol=0, atol=1e-12) and np.isnan(T[1, :3]).all()
    finally:
        bare.robot_ring.close()
        bare.robot_ring.unlink()
    # The default stays error-free: the existing suite's accuracy bounds rely on it.
    default = cell_spec(parse_config(dump_toml(free_sim_config())))
    assert default.controller.true_model == UR5E and default.sensor.robot_model == "UR5e"


# ------------------------------------------------------------------------------ the controller


@contextmanager
def controller(**overrides: Any) -> Iterator[SimulatedController]:
    cfg = ControllerConfig(primary_interface=True, initial_q=tuple(UR5E_WORK_Q[0]), **overrides)
    with SimulatedController.on_free_loopback(cfg) as sim:
        yield sim


def _states_at(sim: SimulatedController, qs: np.ndarray) -> list[dict[str, Any]]:
    """The controller's state after placing the arm at each of ``qs`` (true joints settled)."""
    out = []
    for q in qs:
        assert sim.set_joint_positions(q.tolist())
        t0 = sim.state()["timestamp"]
        deadline = time.monotonic() + 30.0
        while (s := sim.state())["timestamp"] < t0 + 0.02:  # past the motion look-ahead
            assert time.monotonic() < deadline
            time.sleep(0.005)
        assert np.allclose(s["q"], q, atol=0, rtol=0)
        out.append(s)
    return out


def _factory_pose_errors(sim: SimulatedController, qs: np.ndarray) -> np.ndarray:
    """How far the pose computed from the reported KinematicsInfo (as the UR driver reads it)
    at the true joints is from where the flange really is (the simulator's truth)."""
    model = read_kinematics_info(sim.host, timeout_s=10.0).model()
    errs = []
    for s in _states_at(sim, qs):
        T_true = se3.pose_to_matrix(np.asarray(s["tcp_pose_true"]))
        T_factory = kinematics.forward(model, np.asarray(s["q_true"]))
        errs.append(kerr.pose_errors(T_factory, T_true)[0])
    return np.array(errs)


def test_factory_calibration_none_partial_exact() -> None:
    qs = ur5e_working_q(8, seed=5)
    errors = {}
    for factory in ("none", "partial", "exact"):
        with controller(
            kinematic_errors=kerr.REALISTIC, kinematic_seed=3, factory_calibration=factory
        ) as sim:
            errors[factory] = _factory_pose_errors(sim, qs)
            if factory == "exact":
                # The RTDE pose (the controller's own, from the encoders) is the true one.
                r = rtde_receive.RTDEReceiveInterface(sim.host, -1.0, [])
                try:
                    pose = r.getActualTCPPose()
                finally:
                    r.disconnect()
                s = sim.state()
                dist, _ = kerr.pose_errors(
                    se3.pose_to_matrix(np.asarray(pose)),
                    se3.pose_to_matrix(np.asarray(s["tcp_pose_true"])),
                )
                assert float(dist) < 1e-6
    rms = {k: float(np.sqrt(np.mean(v**2))) for k, v in errors.items()}
    assert 0.05e-3 < rms["none"] < 0.5e-3, rms  # a real arm's error
    assert errors["exact"].max() < 1e-6, rms
    assert 0.05 * rms["none"] < rms["partial"] < 0.3 * rms["none"], rms


def test_encoder_noise_and_repeatability_have_their_sizes() -> None:
    with controller(
        kinematic_errors=kerr.REALISTIC,
        factory_calibration="exact",
        joint_noise_rad=3e-5,
        repeatability_m=1e-4,
        noise_seed=8,
    ) as sim:
        # Repeatability: each placement lands the true TCP off the commanded one, by ~1e-4 RMS.
        true_model = sim.config.true_model
        offsets = []
        for s in _states_at(sim, ur5e_working_q(40, seed=6)):
            T = kinematics.forward(true_model, np.asarray(s["q"]))
            offsets.append(np.asarray(s["tcp_pose_true"])[:3] - T[:3, 3])
        rms = float(np.sqrt(np.mean(np.sum(np.square(offsets), axis=1))))
        assert 0.6e-4 < rms < 1.4e-4, rms
        # Encoder noise: the reported joints of a still arm scatter by joint_noise_rad around the
        # controller's joints; target_q has none.
        q_ctrl = np.asarray(sim.state()["q"])
        r = rtde_receive.RTDEReceiveInterface(sim.host, -1.0, [])
        try:
            seen: dict[float, list[float]] = {}
            deadline = time.monotonic() + 30.0
            while len(seen) < 150:
                assert time.monotonic() < deadline
                seen[r.getTimestamp()] = r.getActualQ()
                assert np.array_equal(r.getTargetQ(), q_ctrl)
                time.sleep(0.002)
        finally:
            r.disconnect()
        noise = np.array(list(seen.values())) - q_ctrl
        assert noise.std() == pytest.approx(3e-5, rel=0.15)
        assert abs(noise.mean()) < 1e-5
