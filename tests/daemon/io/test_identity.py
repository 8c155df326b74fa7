"""Whose calibration it is: the rules that compare a file's robot and sensor with the cell's, and
the serial number read from a controller's dashboard server (an older controller that does not
know the query, one that hangs up, one that never answers, none at all).

The cell that reports a serial and a daemon that refuses a foreign one run in
``tests/daemon/cli/test_default_cell.py``."""

from __future__ import annotations

import logging
import socket
import threading
from collections.abc import Iterator

import pytest
from support import own_loopback_host

from wristscan.daemon.config import Config, parse_config
from wristscan.daemon.io.identity import (
    RobotIdentity,
    SensorIdentity,
    identities,
    identity_mismatch,
)
from wristscan.drivers.base import DriverTimeout
from wristscan.drivers.sim.ur.controller import ControllerConfig, SimulatedController
from wristscan.drivers.ur.primary import PrimaryInterfaceError, read_serial_number

SENSOR = SensorIdentity("lpf1-udp", "1")


@pytest.mark.parametrize(
    ("file_robot", "cell_robot", "refused"),
    [
        (RobotIdentity("UR5e", "111"), RobotIdentity("UR5e", "111"), None),
        (RobotIdentity("UR5e", "111"), RobotIdentity("UR5e", "222"), "UR5e serial 111, but this robot is UR5e serial 222"),  # noqa: E501
        (RobotIdentity("UR5e", None), RobotIdentity("UR5e", "222"), None),
        (RobotIdentity("UR5e", "111"), RobotIdentity("UR5e", None), None),
        (RobotIdentity("UR10e", "111"), RobotIdentity("UR5e", "111"), "made for robot UR10e serial 111"),  # noqa: E501
        (RobotIdentity("UR10e", None), RobotIdentity("UR5e", None), "but this robot is UR5e;"),
    ],
    ids=["same", "another arm", "file without serial", "controller without serial", "model", "model only"],  # noqa: E501
)  # fmt: skip
def test_robot_rules(
    file_robot: RobotIdentity, cell_robot: RobotIdentity, refused: str | None
) -> None:
    problem = identity_mismatch(file_robot, SENSOR, cell_robot, SENSOR)
    if refused is None:
        assert problem is None
    else:
        assert problem is not None and refused in problem and "check_identity = false" in problem
    assert identity_mismatch(file_robot, SENSOR, None, None) is None  # check_identity off


def test_sensor_rules() -> None:
    robot = RobotIdentity("UR5e", "1")
    assert identity_mismatch(robot, SENSOR, robot, SensorIdentity("lpf1-udp", None)) is None
    problem = identity_mismatch(robot, SENSOR, robot, SensorIdentity("lpf1-udp", "2"))
    assert problem is not None and "made for sensor lpf1-udp id 1, but this sensor is" in problem
    assert identity_mismatch(robot, SENSOR, robot, SensorIdentity("rf627-udp")) is not None


def _config_for(host: str) -> Config:
    return parse_config(
        f'schema_version = 1\n[cell]\nname = "c"\n[robot]\nhost = "{host}"\nmodel = "UR5e"\n'
        '[sensor]\ndriver = "lpf1-udp"\n'
    )


def test_a_controller_before_polyscope_5_6_has_no_serial() -> None:
    with SimulatedController.on_free_loopback(ControllerConfig(version=(5, 4, 0, 0))) as sim:
        assert read_serial_number(sim.host) is None
        robot, _ = identities(_config_for(sim.host))
    assert robot == RobotIdentity("UR5e", None)


@pytest.fixture
def listener() -> Iterator[socket.socket]:
    """A TCP listener on the dashboard port of an address of this run's own."""
    with socket.create_server((own_loopback_host(), 29999)) as server:
        yield server


def test_a_dashboard_that_hangs_up_or_stays_silent(listener: socket.socket) -> None:
    host = listener.getsockname()[0]

    def serve(welcome: bool) -> None:
        conn, _ = listener.accept()
        with conn:
            if welcome:
                conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
                conn.recv(100)
                done.wait(5.0)

    done = threading.Event()
    t = threading.Thread(target=serve, args=(False,))
    t.start()
    with pytest.raises(PrimaryInterfaceError, match="closed the connection"):
        read_serial_number(host, timeout_s=5.0)
    t.join()
    t = threading.Thread(target=serve, args=(True,))
    t.start()
    with pytest.raises(DriverTimeout, match="no reply line in time"):
        read_serial_number(host, timeout_s=0.5)
    done.set()
    t.join()


def test_no_controller_no_serial_and_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    host = own_loopback_host()  # nothing listens there: refused at once
    with caplog.at_level(logging.WARNING, logger="wristscan.daemon.io.identity"):
        robot, sensor = identities(_config_for(host))
    assert robot == RobotIdentity("UR5e", None) and sensor == SensorIdentity("lpf1-udp", None)
    assert f"robot serial number not read from {host}:29999" in caplog.text
    assert "checked against the model UR5e only" in caplog.text
