"""The kinematics calibration file: the arm's DH parameters identified with the probe
(``wristscan calibrate kinematics``), which ``[robot] kinematics_file`` names and the daemon then
computes every flange pose with (:func:`wristscan.daemon.devices.robot_model`).

Versioned JSON, written atomically::

    {
      "format": "wristscan-kinematics",
      "version": 1,
      "robot": {"model": "UR5e", "serial": "20235500001"},
      "model": {"name": ..., "theta": [6], "a": [6], "d": [6], "alpha": [6]},   # m, rad
      "base_model": {...},          # the model the flange poses were computed with before
      "delta": {"theta": [6], "a": [6], "d": [6], "alpha": [6]},     # model - base_model
      "sigma": {"theta": [6], ...},                                   # 1-sigma of each delta
      "fixed": ["theta1", ...],     # unobservable, kept at the base model's value
      "unobservable": ["theta1: indistinguishable from ...", ...],
      "weak": [...],                # weakly observed combinations (held by the prior)
      "sensor2flange": {"matrix_rows": [[...]], "ur_pose": [6]},
      "sensor2flange_before": {"matrix_rows": [[...]], "ur_pose": [6]},   # with base_model
      "figures": {"rms_before_m": ..., "rms_after_m": ..., "scatter_before_m": ...,
                  "scatter_after_m": ..., "n_scans": ..., "n_points": ...},
      "created_utc": "2026-11-26T09:00:00Z"
    }

The sensor2flange in the file is the one identified with the model: the two belong together
(the last link's deviations are part of it), so the sensor calibration is written with it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import se3
from wristscan.calib.dh import DHParams
from wristscan.calib.kinematic_errors import model_dict, model_from_dict
from wristscan.daemon.io.atomic import write_atomic
from wristscan.drivers.base import DriverInitError

__all__ = [
    "FILE_FORMAT",
    "FILE_VERSION",
    "KinematicsFile",
    "KinematicsFileError",
    "read_kinematics",
    "write_kinematics",
]

FILE_FORMAT = "wristscan-kinematics"
FILE_VERSION = 1

FloatArray = NDArray[np.float64]
_KEYS = ("theta", "a", "d", "alpha")


class KinematicsFileError(DriverInitError, ValueError):
    """A kinematics file that cannot be used; the message says which file and why (one line).
    A :class:`~wristscan.drivers.base.DriverInitError` too: the robot cannot be set up without
    it, and every command reports that as one line."""


@dataclass(frozen=True, eq=False)
class KinematicsFile:
    """The contents of a kinematics file (SI units; ``delta`` and ``sigma`` ``(4, 6)``: theta,
    a, d, alpha per joint)."""

    robot_model: str
    serial: str | None
    model: DHParams
    base_model: DHParams
    delta: FloatArray
    sigma: FloatArray
    fixed: tuple[str, ...]
    unobservable: tuple[str, ...]
    weak: tuple[str, ...]
    sensor2flange: FloatArray
    figures: dict[str, float]
    sensor2flange_before: FloatArray | None = None
    """The sensor calibration on the same sweeps with ``base_model`` (for comparison)."""
    created_utc: str = ""


def _rows(a: FloatArray) -> dict[str, list[float]]:
    return {k: [float(v) for v in a[i]] for i, k in enumerate(_KEYS)}


def _unrows(d: Any, what: str) -> FloatArray:
    try:
        a = np.array([[float(v) for v in d[k]] for k in _KEYS])
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{what}: expected theta, a, d, alpha lists of 6 numbers") from None
    if a.shape != (4, 6) or not np.all(np.isfinite(a)):
        raise ValueError(f"{what}: expected theta, a, d, alpha lists of 6 finite numbers")
    return a


def _transform(X: FloatArray) -> dict[str, Any]:
    return {
        "matrix_rows": [[float(v) for v in r] for r in X],
        "ur_pose": [float(v) for v in se3.matrix_to_pose(X)],
    }


def _untransform(d: Any, what: str) -> FloatArray:
    X = np.array(d["matrix_rows"], dtype=np.float64)
    return se3.check_transform(X, what)


def write_kinematics(path: str | Path, k: KinematicsFile) -> Path:
    """Write ``k`` to ``path`` atomically; returns the path."""
    data: dict[str, Any] = {
        "format": FILE_FORMAT,
        "version": FILE_VERSION,
        "robot": {"model": k.robot_model, "serial": k.serial},
        "model": model_dict(k.model),
        "base_model": model_dict(k.base_model),
        "delta": _rows(k.delta),
        "sigma": _rows(k.sigma),
        "fixed": list(k.fixed),
        "unobservable": list(k.unobservable),
        "weak": list(k.weak),
        "sensor2flange": _transform(k.sensor2flange),
        "figures": {key: float(v) for key, v in k.figures.items()},
        "created_utc": k.created_utc or datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }
    if k.sensor2flange_before is not None:
        data["sensor2flange_before"] = _transform(k.sensor2flange_before)
    p = Path(path)
    write_atomic(p, (json.dumps(data, indent=2) + "\n").encode())
    return p


def read_kinematics(path: str | Path, robot_model: str | None = None) -> KinematicsFile:
    """Read a kinematics file; ``robot_model``: the configured UR model it must be for.
    Raises :class:`KinematicsFileError` (one line naming the file) when it is missing, corrupt
    or made for another model."""
    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except FileNotFoundError:
        raise KinematicsFileError(f"kinematics file {p}: not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise KinematicsFileError(f"kinematics file {p}: cannot be read ({exc})") from None
    try:
        return _parse(data, robot_model)
    except (KeyError, TypeError, ValueError) as exc:
        raise KinematicsFileError(f"kinematics file {p}: {exc}") from None


def _parse(data: Any, robot_model: str | None) -> KinematicsFile:
    if not isinstance(data, dict) or data.get("format") != FILE_FORMAT:
        raise ValueError(f"not a {FILE_FORMAT} file")
    if data.get("version") != FILE_VERSION:
        raise ValueError(f"version {data.get('version')!r} is not {FILE_VERSION}")
    robot = data["robot"]
    model_name = str(robot["model"])
    if robot_model is not None and model_name.lower() != robot_model.lower():
        raise ValueError(f"made for a {model_name}, but [robot] model is {robot_model}")
    X = _untransform(data["sensor2flange"], "sensor2flange")
    before = data.get("sensor2flange_before")
    figures = {str(k): float(v) for k, v in data.get("figures", {}).items()}
    if not all(math.isfinite(v) for v in figures.values()):
        raise ValueError("figures: non-finite values")
    return KinematicsFile(
        robot_model=model_name,
        serial=None if robot.get("serial") is None else str(robot["serial"]),
        model=model_from_dict(data["model"]),
        base_model=model_from_dict(data["base_model"]),
        delta=_unrows(data["delta"], "delta"),
        sigma=_unrows(data["sigma"], "sigma"),
        fixed=tuple(str(v) for v in data.get("fixed", [])),
        unobservable=tuple(str(v) for v in data.get("unobservable", [])),
        weak=tuple(str(v) for v in data.get("weak", [])),
        sensor2flange=X,
        figures=figures,
        sensor2flange_before=None
        if before is None
        else _untransform(before, "sensor2flange_before"),
        created_utc=str(data.get("created_utc", "")),
    )
