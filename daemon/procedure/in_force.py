"""What a procedure starts from: the calibrations in force and an open acquisition on the
configured devices with the points in the robot base frame."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Literal

from wristscan.daemon.config import Config
from wristscan.daemon.io.calibfile import (
    Calibration,
    CalibrationFileError,
    identities,
    read_calibration,
)
from wristscan.daemon.procedure.acquisition import Acquisition, open_retrying
from wristscan.daemon.procedure.errors import ProcedureError
from wristscan.daemon.procedure.motion import wait_until_pairing
from wristscan.drivers.base import DriverError

__all__ = [
    "calibration_in_force",
    "load_sensor_calibration",
    "procedure_acquisition",
    "procedure_config",
]


def calibration_in_force(
    cfg: Config,
    kind: Literal["sensor2flange", "table"],
    needed_for: str,
    error: type[ProcedureError] = ProcedureError,
) -> Calibration:
    """The calibration in force of ``kind`` (``[calibration] file`` or ``table_file``), checked
    against the robot (and, for the sensor calibration, the sensor) of ``cfg`` when
    ``check_identity`` is set. Raises ``error`` when the file is not set (``needed_for`` says
    what needs it) or cannot be used."""
    sensor = kind == "sensor2flange"
    path = cfg.calibration.file if sensor else cfg.calibration.table_file
    if path is None:
        key = "file" if sensor else "table_file"
        raise error(f"{cfg.source}: [calibration] {key} is not set: {needed_for}")
    robot_id, sensor_id = identities(cfg)
    check = cfg.calibration.check_identity
    try:
        return read_calibration(
            path,
            robot_id if check else None,
            sensor_id if check and sensor else None,
            kind=kind,
        )
    except CalibrationFileError as exc:
        raise error(f"{'sensor' if sensor else 'table'} calibration: {exc}") from None


def load_sensor_calibration(cfg: Config) -> Calibration:
    """The sensor2flange calibration of ``[calibration] file``; :class:`ProcedureError` when
    there is none or it cannot be used (the ball centres need it)."""
    return calibration_in_force(
        cfg,
        "sensor2flange",
        "this procedure needs the sensor calibration to put the ball in the robot base frame "
        "(run wristscan calibrate sensor first)",
    )


def procedure_config(cfg: Config) -> Config:
    """``cfg`` with the points in the base frame: the procedures read the table themselves (the
    table driver is not made for two threads at once)."""
    if cfg.pipeline.frame == "base":
        return cfg
    out = cfg.model_copy(update={"pipeline": cfg.pipeline.model_copy(update={"frame": "base"})})
    out._source = cfg.source
    return out


@contextlib.contextmanager
def procedure_acquisition(
    cfg: Config,
    acquisition: Acquisition | None = None,
    *,
    attempts: int = 1,
    open_error: type[ProcedureError] | None = None,
) -> Iterator[Acquisition]:
    """An open acquisition on the devices of ``cfg`` with the points in the base frame
    (:func:`procedure_config`), once profiles are being paired (:func:`wait_until_pairing`);
    closed when the block ends. ``acquisition``: an already built one (tests, benchmarks).
    ``attempts``: tries when a device does not answer in time. ``open_error``: what a device
    error while opening becomes (None: the driver's error goes on)."""
    try:
        if acquisition is not None:
            acq = acquisition.open()
        else:
            acq = open_retrying(lambda: Acquisition(procedure_config(cfg)), attempts)
    except DriverError as exc:
        if open_error is None:
            raise
        raise open_error(f"cannot open the devices: {exc}") from None
    with acq:
        wait_until_pairing(acq)
        yield acq
