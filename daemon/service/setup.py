"""What ``wristscan run`` starts from: the alignment in force (:func:`load_setup`), the ROS 2
publisher class when ``[ros2]`` is enabled, the daemon's zenoh session, and errors on one line.
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np
import zenoh

from wristscan.daemon.cloud.zenoh_io import open_session
from wristscan.daemon.config import Config
from wristscan.daemon.io.calibfile import (
    Calibration,
    RobotIdentity,
    SensorIdentity,
    identities,
    read_calibration,
)
from wristscan.daemon.service.pipeline import AlignmentSetup
from wristscan.drivers.base import DriverError

__all__ = [
    "SETUP_ERRORS",
    "StartupError",
    "load_setup",
    "one_line",
    "open_daemon_session",
    "ros2_class",
]

_RUST_AT = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")

SETUP_ERRORS: tuple[type[BaseException], ...] = (zenoh.ZError, RuntimeError, OSError, DriverError)
"""What opening zenoh and the devices may raise for a reason outside the program (an endpoint
taken, a device absent, a file unreadable): one line in the log, never a traceback."""


class StartupError(RuntimeError):
    """The service cannot start with this configuration (message says why)."""


def one_line(exc: BaseException) -> str:
    """An error's message on one line (zenoh's Rust source locations removed)."""
    return " ".join(_RUST_AT.sub("", str(exc)).split()) or type(exc).__name__


def _identities(
    cfg: Config, ask_controller: bool
) -> tuple[RobotIdentity | None, SensorIdentity | None]:
    """The identities a calibration file must match, or (None, None) when the configuration
    does not check them."""
    if not cfg.calibration.check_identity:
        return None, None
    return identities(cfg, ask_controller=ask_controller)


def load_setup(
    cfg: Config, uncalibrated: bool = False, ask_controller: bool = True
) -> AlignmentSetup:
    """The alignment the configuration asks for; raises ``CalibrationFileError`` or
    ``StartupError`` with a message for the operator. ``ask_controller`` False: the robot's
    serial number is not asked for (before the devices are open; checked again once they are)."""
    robot_id, sensor_id = _identities(cfg, ask_controller)
    c = cfg.calibration
    frame = cfg.pipeline.frame
    if c.file is None:
        if not uncalibrated:
            raise StartupError(
                "no calibration in force: set [calibration] file (wristscan calibrate sensor "
                "writes one), or start with --uncalibrated to publish with the sensor at the flange"
            )
        sensor2flange = np.eye(4)
        desc: dict[str, Any] = {"kind": "sensor2flange", "uncalibrated": True}
    else:
        calib = read_calibration(c.file, robot_id, sensor_id, kind="sensor2flange")
        sensor2flange = np.asarray(calib.transform, dtype=np.float64)
        desc = calib.to_dict()
    base2table = None
    offset = 0.0
    if frame != "base":
        if c.table_file is None:
            raise StartupError(f'pipeline.frame = "{frame}" needs [calibration] table_file')
        tcal: Calibration = read_calibration(c.table_file, robot_id, None, kind="table")
        base2table = np.asarray(tcal.transform, dtype=np.float64)
        offset = float(tcal.parameters.get("encoder_offset_rad", 0.0))
        desc = {"sensor2flange": desc, "table": tcal.to_dict()}
    return AlignmentSetup(
        sensor2flange=sensor2flange,
        frame=frame,
        base2table=base2table,
        encoder_offset_rad=offset,
        calibrated=c.file is not None,
        description=desc,
    )


def ros2_class(cfg: Config) -> Any:
    """The ``[ros2]`` publisher class when enabled, else None; checked before anything opens."""
    if not cfg.ros2.enabled:
        return None
    try:
        from wristscan.daemon.cloud.ros2pub import Ros2Publisher
    except ImportError as exc:
        raise StartupError(
            f"[ros2] enabled needs the extra: pip install 'wristscan[ros2]' ({exc})"
        ) from exc
    return Ros2Publisher


def open_daemon_session(cfg: Config) -> Any:
    """The daemon's zenoh session; raises a ``RuntimeError`` (``ZenohSetupError``) or
    ``zenoh.ZError`` naming what could not be set up."""
    z = cfg.zenoh
    return open_session(
        z.mode,
        z.connect,
        z.listen,
        z.multicast_scouting,
        config_file=z.config_file,
        shared_memory=z.shared_memory,
    )
