"""The embedded default the two-process way: ``wristscan sim`` and ``wristscan run`` as separate
processes on the default configuration (on a loopback address of this run's own), a subscriber
counting the published points; and the robot's identity: the serial number the simulated
controller reports (set in ``[sim.controller]``) against the one a calibration file carries.

One simulated cell serves every test of the module. Ground truth (the true sensor2flange, the
ball) comes from ``wristscan sim --json``, the simulator's own report.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from wristscan.daemon.cloud.client import CloudClient
from wristscan.daemon.config import load_config
from wristscan.daemon.io.calibfile import (
    Calibration,
    Residuals,
    RobotIdentity,
    SensorIdentity,
    identities,
    write_calibration,
)
from wristscan.daemon.simcell.cell import dump_toml, free_sim_config
from wristscan.drivers.ur.primary import read_serial_number

SERIAL = "20235500042"
"""The simulated controller's serial number (the default's is another)."""
OTHER_SERIAL = "20235500777"
"""Another arm of the same model."""


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "wristscan.daemon.cli", *args]


@dataclass
class Cell:
    folder: Path
    doc: dict[str, Any]
    truth: dict[str, Any]

    def config(self, name: str, calibration_file: str | None) -> Path:
        """A configuration of this cell beside a calibration file (None: none)."""
        doc = dict(self.doc)
        if calibration_file is not None:
            doc["calibration"] = {**doc["calibration"], "file": calibration_file}
        path = self.folder / name
        path.write_text(dump_toml(doc))
        return path

    def calibration(self, name: str, serial: str | None) -> None:
        """The true sensor2flange as a calibration file for the robot ``serial``."""
        write_calibration(
            self.folder / name,
            Calibration(
                kind="sensor2flange",
                transform=np.array(self.truth["sensor2flange"]),
                robot=RobotIdentity("UR5e", serial),
                sensor=SensorIdentity("lpf1-udp", "1"),
                method="simulation truth",
                residuals=Residuals(rms_m=0.0),
            ),
        )


def _read_json(proc: subprocess.Popen[str], timeout: float) -> dict[str, Any]:
    """The JSON document ``wristscan sim --json`` prints once the cell runs."""
    assert proc.stdout is not None
    text = ""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        text += line
        if line.rstrip() == "}":
            return dict(json.loads(text))
    raise AssertionError(f"wristscan sim printed no JSON: {text!r} (exit {proc.poll()})")


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cell]:
    folder = tmp_path_factory.mktemp("default-cell")
    doc = free_sim_config({"sim.controller": {"serial_number": SERIAL}})
    path = folder / "sim.toml"
    path.write_text(dump_toml(doc))
    proc = subprocess.Popen(
        _cli("sim", "--config", str(path), "--json"),
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        info = _read_json(proc, 120.0)
        yield Cell(folder, doc, info["truth"])
    finally:
        proc.terminate()
        proc.wait(30)
        assert proc.stdout is not None
        proc.stdout.close()


def test_the_controller_reports_its_configured_serial(cell: Cell) -> None:
    host = cell.doc["robot"]["host"]
    assert read_serial_number(host) == SERIAL
    robot, _ = identities(load_config(cell.config("ids.toml", None)))
    assert robot == RobotIdentity("UR5e", SERIAL)
    robot, _ = identities(load_config(cell.config("ids.toml", None)), ask_controller=False)
    assert robot == RobotIdentity("UR5e", None)


def test_run_refuses_a_calibration_of_another_arm_of_the_same_model(cell: Cell) -> None:
    cell.calibration("foreign.json", OTHER_SERIAL)
    cfg = cell.config("foreign.toml", "foreign.json")
    out = subprocess.run(
        _cli("run", "--config", str(cfg)), capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 2, out.stderr
    refusal = [line for line in out.stderr.splitlines() if OTHER_SERIAL in line]
    assert refusal, out.stderr
    assert f"UR5e serial {OTHER_SERIAL}" in refusal[0]
    assert f"this robot is UR5e serial {SERIAL}" in refusal[0]
    assert "Traceback" not in out.stderr


def _points(endpoint: str, prefix: str, n_batches: int, timeout: float) -> list[Any]:
    """``n_batches`` batches with points (the first ones may come before the robot's states)."""
    got = []
    deadline = time.monotonic() + timeout
    with CloudClient(prefix, connect=[endpoint], capacity=64) as client:
        while len(got) < n_batches and time.monotonic() < deadline:
            cloud = client.recv(timeout=1.0)
            if cloud is not None and len(cloud.xyz):
                got.append(cloud)
    return got


def test_the_default_publishes_ball_points_from_the_start(cell: Cell) -> None:
    """The default arm pose puts the ball in the sensor's range: the daemon publishes points on
    the true ball at once (with the calibration of this arm: its serial is accepted)."""
    cell.calibration("own.json", SERIAL)
    cfg = cell.config("own.toml", "own.json")
    daemon = subprocess.Popen(
        _cli("run", "--config", str(cfg)),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        batches = _points(cell.doc["zenoh"]["listen"][0], "wristscan/sim", 20, 90.0)
    finally:
        daemon.terminate()
        _, err = daemon.communicate(timeout=60)
    assert len(batches) == 20, err[-2000:]
    xyz = np.concatenate([b.xyz for b in batches]).astype(np.float64)
    profiles = sum(b.n_profiles for b in batches)
    # The line (2048 points over 50 mm) crosses the 25.4 mm ball near its top: about half of
    # each profile lands on it (nothing else is in the 0.05-0.15 m range).
    assert len(xyz) / profiles > 600
    centre = np.array(cell.truth["ball_centre_base_m"])
    radius = cell.truth["ball_radius_m"]
    off = np.linalg.norm(xyz - centre, axis=1) - radius
    assert np.percentile(np.abs(off), 95) < 0.2e-3, np.percentile(np.abs(off), [50, 95, 100])
