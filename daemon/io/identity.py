"""Whom a calibration belongs to: the robot (model and controller serial number) and the sensor
(driver and id), as a calibration file records them and as the cell reports them.

:func:`identities` reads the robot's serial number from its controller (the built-in UR driver:
the dashboard server's ``get serial number``, see
:func:`wristscan.drivers.ur.primary.read_serial_number`), so that a calibration made for another
arm of the same model is refused;
:func:`identity_mismatch` says why a file's identities do not fit (None when they do).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from wristscan.daemon.config import Config

__all__ = ["RobotIdentity", "SensorIdentity", "identities", "identity_mismatch", "robot_serial"]

log = logging.getLogger(__name__)

_HINT = "; recalibrate, or set calibration.check_identity = false to use it anyway"


@dataclass(frozen=True)
class RobotIdentity:
    """The robot a calibration belongs to."""

    model: str
    """UR model name (``UR5e``)."""
    serial: str | None = None
    """Controller serial number; None when unknown."""

    def describe(self) -> str:
        return self.model + (f" serial {self.serial}" if self.serial else "")


@dataclass(frozen=True)
class SensorIdentity:
    """The sensor a calibration belongs to."""

    driver: str
    """Driver name (``lpf1-udp``, ``rf627-udp``, ...)."""
    id: str | None = None
    """Sensor id or serial number as the device reports it; None when unknown."""

    def describe(self) -> str:
        return self.driver + (f" id {self.id}" if self.id else "")


def robot_serial(cfg: Config, timeout_s: float = 2.0) -> str | None:
    """The serial number the controller of ``cfg``'s robot reports (the built-in UR driver asks
    the dashboard server), or None when its driver has no way to tell, the controller's software
    predates the query or the controller does not answer (logged: the calibration files are then
    checked against the robot model only)."""
    r = cfg.robot
    if r.driver != "ur-rtde":
        return None
    from wristscan.drivers.base import DriverError
    from wristscan.drivers.ur.primary import DASHBOARD_PORT, read_serial_number

    try:
        return read_serial_number(r.host, DASHBOARD_PORT, timeout_s)
    except (DriverError, OSError) as exc:
        log.warning(
            "robot serial number not read from %s:%d (%s): calibration files are checked "
            "against the model %s only",
            r.host,
            DASHBOARD_PORT,
            exc,
            r.model,
        )
        return None


def identities(cfg: Config, *, ask_controller: bool = True) -> tuple[RobotIdentity, SensorIdentity]:
    """The robot and sensor of ``cfg`` as a calibration file records them: the robot model of
    the configuration with the serial number its controller reports (:func:`robot_serial`;
    ``ask_controller=False``: none, for work away from the cell), the sensor driver and id."""
    sid = cfg.sensor.sensor_id
    serial = robot_serial(cfg) if ask_controller else None
    return RobotIdentity(cfg.robot.model, serial), SensorIdentity(
        cfg.sensor.driver, None if sid is None else str(sid)
    )


def identity_mismatch(
    robot: RobotIdentity,
    sensor: SensorIdentity,
    expect_robot: RobotIdentity | None,
    expect_sensor: SensorIdentity | None,
) -> str | None:
    """Why a calibration made for ``robot`` and ``sensor`` does not fit the expected ones (None
    when it does; an expectation of None is not compared). A serial number or sensor id is
    compared when both sides know it: a file written without one (by an older wristscan, or
    away from the cell) is checked against the model or driver only."""
    if expect_robot is not None and (
        robot.model != expect_robot.model
        or (None not in (expect_robot.serial, robot.serial) and robot.serial != expect_robot.serial)
    ):
        return (
            f"made for robot {robot.describe()}, but this robot is {expect_robot.describe()}{_HINT}"
        )
    if expect_sensor is not None and (
        sensor.driver != expect_sensor.driver
        or (expect_sensor.id is not None and sensor.id != expect_sensor.id)
    ):
        return (
            f"made for sensor {sensor.describe()}, but this sensor is "
            f"{expect_sensor.describe()}{_HINT}"
        )
    return None
