"""``wristscan calibrate kinematics``: the kinematics file and ``[robot] kinematics_file`` (no
cell), and the whole command on the simulated cell with an arm as wrong as a real one (its truth
from the simulator's configuration, never from the solver)."""

from __future__ import annotations

import json
import re
import socket
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import typer
from support import TRUE_POSES_ONLY
from typer.testing import CliRunner

from wristscan.calib import kinematic_errors as kerr
from wristscan.calib import kinematics, se3
from wristscan.calib.kinematic_ident_synthetic import point_error
from wristscan.daemon.cli._calibrate_kinematics import kinematics as kinematics_command
from wristscan.daemon.config import Config, parse_config
from wristscan.daemon.devices import make_devices, robot_model
from wristscan.daemon.io.kinematics_file import (
    KinematicsFile,
    KinematicsFileError,
    read_kinematics,
    write_kinematics,
)

ROOT = Path(__file__).resolve().parents[3]


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _config(tmp: Path, extra_robot: str = "", motion: bool = True) -> Path:
    """config/sim.toml on free addresses, no rotary table, light profiles; the arm with
    realistic DH deviations and a controller on the nominal table."""
    from wristscan.drivers.sim.ur.controller import pick_free_loopback_host

    text = (ROOT / "config" / "sim.toml").read_text()
    text = text.replace('host = "127.0.0.2"', f'host = "{pick_free_loopback_host()}"')
    text = text.replace("port = 50002", f"port = {_free_udp_port()}")
    text = re.sub(r"\n\[table\]\n.*?\n(?=\[)", "\n", text, flags=re.S)
    text = text.replace("[sim.table]\nenabled = true", "[sim.table]\nenabled = false")
    text = text.replace("n_points = 2048", "n_points = 512")
    for key, value in (
        ("kinematic_errors", '"realistic"'),
        ("kinematic_seed", "4"),
        ("factory_calibration", '"none"'),
    ):
        text, n = re.subn(rf"^{key} = \S+", f"{key} = {value}", text, flags=re.M)
        assert n == 1, key
    text = text.replace("[robot]\n", f"[robot]\n{extra_robot}", 1)
    if not motion:
        text = text.replace("motion_enabled = true ", "motion_enabled = false")
    path = tmp / "cell.toml"
    path.write_text(text)
    return path


def _load(path: Path) -> Config:
    return parse_config(path.read_text(), str(path), path.parent)


def _cli(args: list[str]) -> Any:
    app = typer.Typer()
    app.command("kinematics")(kinematics_command)
    app.command("other")(lambda: None)  # a group, so the command is named as in wristscan
    return CliRunner().invoke(app, ["kinematics", *args], catch_exceptions=False)


def _sample_file(model: str = "UR5e") -> KinematicsFile:
    base = kinematics.get_model("UR5e")
    delta = np.zeros((4, 6))
    delta[1, 1] = 1e-4
    from wristscan.calib.kinematic_ident import apply_deltas

    return KinematicsFile(
        robot_model=model, serial="1", model=apply_deltas(base, delta, "identified"),
        base_model=base, delta=delta, sigma=np.full((4, 6), 1e-5), fixed=("theta1",),
        unobservable=("theta1: indistinguishable from sensor2flange or the ball centre(s)",),
        weak=(), sensor2flange=se3.make(None, (0.06, 0.01, 0.2)), figures={"rms_after_m": 2e-5},
    )  # fmt: skip


def test_kinematics_file_round_trip_and_one_line_errors(tmp_path: Path) -> None:
    k = _sample_file()
    path = write_kinematics(tmp_path / "k.json", k)
    back = read_kinematics(path, "ur5e")
    assert back.model.a == k.model.a and back.fixed == ("theta1",)
    np.testing.assert_allclose(back.delta, k.delta)
    np.testing.assert_allclose(back.sensor2flange, k.sensor2flange)
    with pytest.raises(
        KinematicsFileError, match="made for a UR5e, but \\[robot\\] model is UR10e"
    ):
        read_kinematics(path, "UR10e")
    with pytest.raises(KinematicsFileError, match="not found"):
        read_kinematics(tmp_path / "none.json")
    data = json.loads(path.read_text())
    data["delta"]["a"] = [0.0] * 5
    (tmp_path / "bad.json").write_text(json.dumps(data))
    with pytest.raises(KinematicsFileError, match="delta: expected"):
        read_kinematics(tmp_path / "bad.json")
    (tmp_path / "torn.json").write_text("{")
    with pytest.raises(KinematicsFileError, match="cannot be read"):
        read_kinematics(tmp_path / "torn.json")


def test_robot_model_uses_the_kinematics_file(tmp_path: Path) -> None:
    k = _sample_file()
    write_kinematics(tmp_path / "k.json", k)
    cfg = _load(_config(tmp_path, 'kinematics_file = "k.json"\n'))
    assert cfg.robot.kinematics_file == str(tmp_path / "k.json")  # relative to the config
    model = robot_model(cfg, make_devices(cfg))
    assert isinstance(model, kinematics.DHParams) and model.a == k.model.a
    cfg = _load(_config(tmp_path, 'kinematics_file = "missing.json"\n'))
    with pytest.raises(KinematicsFileError, match=r"missing\.json: not found"):
        robot_model(cfg, make_devices(cfg))


def test_usage_errors_move_nothing(tmp_path: Path) -> None:
    path = _config(tmp_path)
    res = _cli(["-c", str(path), "--grid", "1"])
    assert res.exit_code == 2 and "--grid" in res.output
    res = _cli(["-c", str(path), "-o", str(tmp_path / "no" / "k.json"), "--yes"])
    assert res.exit_code == 2 and "does not exist" in res.output
    off = _config(tmp_path, motion=False)
    res = _cli(["-c", str(off), "--yes"])
    assert res.exit_code == 2 and "motion_enabled" in res.output


def test_calibrate_kinematics_on_the_simulated_cell(tmp_path: Path) -> None:
    """A short run (2 x 2 places, 4 orientations, one lateral place, one way, 60 mm/s) with the
    controller on the nominal table: the identified kinematics put the ball's points closer to
    where the true arm puts them, and the daemon pairs with them afterwards."""
    from wristscan.daemon.simcell.cell import start_cell
    from wristscan.daemon.simcell.scenarios import jog_to_ball

    path = _config(tmp_path)
    cfg = _load(path)
    cell = start_cell(cfg, **TRUE_POSES_ONLY)
    try:
        jog_to_ball(cell)
        truth = np.array(cell.truth()["sensor2flange"])
        q_start = np.array(cell.controller.state()["q"])
        out = tmp_path / "kinematics.json"
        args = ["--grid", "2", "--orientations", "4", "--lateral-places", "1", "--one-way"]
        res = _cli(["-c", str(path), "-y", "-o", str(out), *args, "--speed-mm-s", "60", "-q"])
    finally:
        cell.stop()
    assert res.exit_code == 0, res.output
    assert "kinematics written to" in res.output
    k = read_kinematics(out, "UR5e")
    assert k.base_model.a == kinematics.get_model("UR5e").a  # paired with the nominal table
    assert {"theta1", "d1", "theta6", "d6", "a6", "alpha6"} <= set(k.fixed)
    # Without the truth: the ball-centre scatter across sweeps and the residuals shrink.
    f = k.figures
    assert f["scatter_after_m"] < 0.5 * f["scatter_before_m"], f
    assert f["rms_after_m"] < f["rms_before_m"], f
    # With the simulator's truth: over joints around the calibration's, the identified
    # kinematics and sensor2flange map the working volume closer to the true arm's.
    assert cfg.sim is not None
    sizes = cfg.sim.controller.error_sizes()
    assert sizes is not None
    true = kerr.true_model("UR5e", sizes, cfg.sim.controller.kinematic_seed)
    q = q_start + np.random.default_rng(0).normal(0.0, 0.15, (200, 6))
    nominal = kinematics.get_model("UR5e")
    assert k.sensor2flange_before is not None
    before = point_error((nominal, k.sensor2flange_before), (true, truth), q)[1]
    after = point_error((k.model, k.sensor2flange), (true, truth), q)[1]
    assert after < 0.5 * before, (before, after)
    cfg2 = _load(_config(tmp_path, f'kinematics_file = "{out}"\n'))
    assert robot_model(cfg2, make_devices(cfg2)) == k.model
