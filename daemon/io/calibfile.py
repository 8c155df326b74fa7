"""Calibration files: versioned JSON, written atomically, refused when corrupt or foreign.

A file holds one calibration result::

    {
      "format": "wristscan-calibration",
      "version": 1,
      "kind": "sensor2flange",                      # or "table"
      "transform": {
        "name": "sensor2flange",                    # "base2table" for kind "table"
        "matrix_rows": [[r00, r01, r02, tx], ..., [0, 0, 0, 1]],   # 4x4, row-major, metres
        "ur_pose": [x, y, z, rx, ry, rz],           # metres, rotation vector in radians
        "ur_pose_text": "p[0.06000, 0.01000, 0.20000, 0.0100, -0.0200, 0.0000]"
      },
      "parameters": {"encoder_offset_rad": 0.01},   # named scalars (kind "table" needs this one)
      "covariance": {"parameters": ["x_m", "y_m", "z_m"], "matrix_rows": [[...], ...]},
      "residuals": {"rms_m": 1.2e-05, "max_m": 2.0e-05, "per_pose_m": [...]},
      "created_utc": "2026-05-09T07:35:25Z",
      "robot": {"model": "UR5e", "serial": "20235500001"},
      "sensor": {"driver": "lpf1-udp", "id": "1"},
      "method": "...",
      "software_version": "0.1.0",
      "notes": ""
    }

``ur_pose_text`` is what an integrator types into the robot's TCP settings (PolyScope shows
millimetres and radians or degrees: convert the metres). The matrix is authoritative; the pose
must agree with it. The covariance names its parameter order and units in ``parameters``.

:func:`write_calibration` replaces the file atomically (temp file in the same folder, fsync,
rename, fsync of the folder), so a crash or a full disk leaves either the old or the new file,
never a torn one. :func:`read_calibration` refuses a corrupt file or one made for another robot
or sensor with a :class:`CalibrationFileError` saying why. :class:`CalibrationStore` keeps the
calibration in force and swaps in a new one only when it reads cleanly.
"""

from __future__ import annotations

import json
import logging
import math
import os
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from types import MappingProxyType
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, Strict, ValidationError

from wristscan.calib import se3
from wristscan.daemon.config import format_validation_error
from wristscan.daemon.io.atomic import write_atomic
from wristscan.daemon.io.identity import (
    RobotIdentity,
    SensorIdentity,
    identities,
    identity_mismatch,
    robot_serial,
)
from wristscan.daemon.io.urpose import ur_pose_text

__all__ = [
    "FILE_FORMAT",
    "FILE_VERSION",
    "TRANSFORM_NAMES",
    "Calibration",
    "CalibrationFileError",
    "CalibrationKind",
    "CalibrationStore",
    "Residuals",
    "RobotIdentity",
    "SensorIdentity",
    "identities",
    "read_calibration",
    "robot_serial",
    "write_calibration",
]

log = logging.getLogger(__name__)

FILE_FORMAT = "wristscan-calibration"
FILE_VERSION = 1

CalibrationKind = Literal["sensor2flange", "table"]
TRANSFORM_NAMES: Mapping[str, str] = MappingProxyType(
    {"sensor2flange": "sensor2flange", "table": "base2table"}
)
"""The transform each kind of calibration stores (named ``a2b``, see DESIGN.md)."""

_REQUIRED_PARAMETERS: Mapping[str, tuple[str, ...]] = MappingProxyType(
    {"sensor2flange": (), "table": ("encoder_offset_rad",)}
)
_POSE_TOL_M = 1e-6
_POSE_TOL_RAD = 1e-6
_COV_SYM_TOL = 1e-9

FloatArray = NDArray[np.float64]


class CalibrationFileError(ValueError):
    """A calibration file that cannot be used (unreadable, corrupt, another version, or made for
    another robot or sensor); the message names the file and the reason."""

    def __init__(self, path: str | os.PathLike[str], message: str) -> None:
        self.path = str(path)
        self.reason = message
        super().__init__(f"{self.path}: {message}")


def _software_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("wristscan")
    except PackageNotFoundError:
        return "unknown"


@dataclass(frozen=True)
class Residuals:
    """How well the calibration explains its measurements (metres)."""

    rms_m: float
    per_pose_m: tuple[float, ...] = ()
    """Residual (norm) of each pose or table angle, in measurement order."""

    def __post_init__(self) -> None:
        values = (self.rms_m, *self.per_pose_m)
        if not all(math.isfinite(v) and v >= 0 for v in values):
            raise ValueError("residuals must be finite and >= 0")

    @classmethod
    def from_per_pose(cls, per_pose_m: ArrayLike) -> Residuals:
        """RMS over the per-pose residuals ``(n,)`` (norms) or ``(n, 3)`` (vectors)."""
        r = np.asarray(per_pose_m, dtype=np.float64)
        norms = np.linalg.norm(r, axis=-1) if r.ndim == 2 else r.reshape(-1)
        rms = float(np.sqrt(np.mean(norms**2))) if norms.size else 0.0
        return cls(rms, tuple(float(v) for v in norms))

    @property
    def max_m(self) -> float:
        return max(self.per_pose_m, default=self.rms_m)


def _frozen(a: ArrayLike) -> FloatArray:
    out = np.array(a, dtype=np.float64)
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class Calibration:
    """One calibration result; validated on construction (``ValueError`` when inconsistent)."""

    kind: CalibrationKind
    transform: FloatArray
    """4x4 rigid transform: ``sensor2flange`` (kind ``sensor2flange``) or ``base2table``
    (kind ``table``); metres."""
    robot: RobotIdentity
    sensor: SensorIdentity
    method: str
    """How it was obtained, e.g. ``"sphere-tcp-lstsq (Borangiu 2009)"``."""
    residuals: Residuals
    covariance: FloatArray | None = None
    """Covariance of the estimated parameters, in the order of ``covariance_parameters``."""
    covariance_parameters: tuple[str, ...] = ()
    """Names (with units) of the covariance rows, e.g. ``("x_m", "y_m", "z_m")``."""
    parameters: Mapping[str, float] = field(default_factory=dict)
    """Named scalar results with units in the names (``encoder_offset_rad`` for tables)."""
    created_utc: datetime = field(default_factory=lambda: datetime.now(UTC))
    software_version: str = field(default_factory=_software_version)
    notes: str = ""

    def __post_init__(self) -> None:
        if self.kind not in TRANSFORM_NAMES:
            raise ValueError(f"kind must be one of {', '.join(TRANSFORM_NAMES)}, not {self.kind!r}")
        T = se3.check_transform(self.transform, self.transform_name)
        if T.shape != (4, 4):
            raise ValueError(f"{self.transform_name}: expected one 4x4 transform, got {T.shape}")
        object.__setattr__(self, "transform", _frozen(T))
        if self.covariance is not None:
            cov = np.asarray(self.covariance, dtype=np.float64)
            _check_covariance(cov, self.covariance_parameters)
            object.__setattr__(self, "covariance", _frozen(cov))
        elif self.covariance_parameters:
            raise ValueError("covariance_parameters given without a covariance")
        params = {str(k): float(v) for k, v in self.parameters.items()}
        if not all(math.isfinite(v) for v in params.values()):
            raise ValueError("parameters must be finite numbers")
        missing = [k for k in _REQUIRED_PARAMETERS[self.kind] if k not in params]
        if missing:
            raise ValueError(f"a {self.kind} calibration needs parameters {', '.join(missing)}")
        object.__setattr__(self, "parameters", MappingProxyType(params))
        if self.created_utc.tzinfo is None:
            raise ValueError("created_utc must be timezone-aware (UTC)")
        object.__setattr__(self, "created_utc", self.created_utc.astimezone(UTC))
        if not self.method:
            raise ValueError("method must not be empty")

    @property
    def transform_name(self) -> str:
        return TRANSFORM_NAMES[self.kind]

    @property
    def ur_pose(self) -> FloatArray:
        """The transform as a UR pose ``[x, y, z, rx, ry, rz]`` (m, rotation vector in rad)."""
        return se3.matrix_to_pose(self.transform)

    @property
    def ur_pose_text(self) -> str:
        return ur_pose_text(self.ur_pose)

    def to_dict(self) -> dict[str, Any]:
        """The JSON document (plain Python types)."""
        cov = None
        if self.covariance is not None:
            cov = {
                "parameters": list(self.covariance_parameters),
                "matrix_rows": self.covariance.tolist(),
            }
        return {
            "format": FILE_FORMAT,
            "version": FILE_VERSION,
            "kind": self.kind,
            "transform": {
                "name": self.transform_name,
                "matrix_rows": self.transform.tolist(),
                "ur_pose": self.ur_pose.tolist(),
                "ur_pose_text": self.ur_pose_text,
            },
            "parameters": dict(self.parameters),
            "covariance": cov,
            "residuals": {
                "rms_m": self.residuals.rms_m,
                "max_m": self.residuals.max_m,
                "per_pose_m": list(self.residuals.per_pose_m),
            },
            "created_utc": self.created_utc.isoformat(timespec="microseconds").replace(
                "+00:00", "Z"
            ),
            "robot": {"model": self.robot.model, "serial": self.robot.serial},
            "sensor": {"driver": self.sensor.driver, "id": self.sensor.id},
            "method": self.method,
            "software_version": self.software_version,
            "notes": self.notes,
        }

    def to_json(self) -> str:
        """The file's text: indented, with every row of numbers on one line."""
        return _dumps(self.to_dict(), "") + "\n"


def _dumps(obj: Any, indent: str) -> str:
    inner = indent + "  "
    if isinstance(obj, dict) and obj:
        items = [f"{inner}{json.dumps(k)}: {_dumps(v, inner)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + indent + "}"
    if isinstance(obj, list) and any(isinstance(v, list | dict) for v in obj):
        items = [inner + _dumps(v, inner) for v in obj]
        return "[\n" + ",\n".join(items) + "\n" + indent + "]"
    return json.dumps(obj, allow_nan=False)


def _check_covariance(cov: FloatArray, names: Sequence[str]) -> None:
    k = len(names)
    if k == 0:
        raise ValueError("covariance needs its parameter names (order and units)")
    if len(set(names)) != k:
        raise ValueError("covariance parameter names must be distinct")
    if cov.shape != (k, k):
        raise ValueError(f"covariance must be {k}x{k} for {k} parameters, got shape {cov.shape}")
    if not np.all(np.isfinite(cov)):
        raise ValueError("covariance contains NaN or infinity")
    scale = max(float(np.abs(cov).max(initial=0.0)), 1e-300)
    if np.abs(cov - cov.T).max(initial=0.0) > _COV_SYM_TOL * scale:
        raise ValueError("covariance is not symmetric")
    if np.linalg.eigvalsh(cov).min(initial=0.0) < -1e-9 * scale:
        raise ValueError("covariance is not positive semi-definite")


# --------------------------------------------------------------------------------------------
# Writing


def write_calibration(path: str | os.PathLike[str], calib: Calibration) -> Path:
    """Write ``calib`` to ``path`` atomically and durably; returns the path.

    The document is built and checked as :func:`read_calibration` would check it before anything
    touches the disk (``CalibrationFileError`` or ``ValueError``); it goes to a temp file in the
    same folder, which is flushed, fsynced and renamed over ``path``; then the folder is fsynced.
    On any failure the temp file is removed and the old file stays as it was (the permissions
    follow :mod:`wristscan.daemon.io.atomic`'s one policy).
    """
    target = Path(path)
    text = calib.to_json()
    # Never write what read_calibration would refuse (guards against a Calibration altered after
    # construction): the check runs before anything touches the disk.
    _parse(target, text.encode("utf-8"))
    write_atomic(target, text)
    log.info("wrote %s calibration to %s", calib.kind, target)
    return target


# --------------------------------------------------------------------------------------------
# Reading

_Float = Annotated[float, Strict()]
_Row4 = Annotated[list[_Float], Field(min_length=4, max_length=4)]


class _Doc(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)


class _TransformDoc(_Doc):
    name: str
    matrix_rows: Annotated[list[_Row4], Field(min_length=4, max_length=4)]
    ur_pose: Annotated[list[_Float], Field(min_length=6, max_length=6)]
    ur_pose_text: str


class _CovarianceDoc(_Doc):
    parameters: Annotated[list[str], Field(min_length=1)]
    matrix_rows: list[list[_Float]]


class _ResidualsDoc(_Doc):
    rms_m: Annotated[_Float, Field(ge=0)]
    max_m: Annotated[_Float, Field(ge=0)]
    per_pose_m: list[Annotated[_Float, Field(ge=0)]]


class _RobotDoc(_Doc):
    model: Annotated[str, Field(min_length=1)]
    serial: str | None


class _SensorDoc(_Doc):
    driver: Annotated[str, Field(min_length=1)]
    id: str | None


class _FileDoc(_Doc):
    format: Literal["wristscan-calibration"]
    version: Literal[1]
    kind: CalibrationKind
    transform: _TransformDoc
    parameters: dict[str, _Float]
    covariance: _CovarianceDoc | None
    residuals: _ResidualsDoc
    created_utc: str
    robot: _RobotDoc
    sensor: _SensorDoc
    method: Annotated[str, Field(min_length=1)]
    software_version: str
    notes: str


def _parse(path: Path, raw: bytes) -> Calibration:
    try:
        data = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise CalibrationFileError(path, f"not UTF-8 text (byte {exc.start})") from None
    except json.JSONDecodeError as exc:
        raise CalibrationFileError(
            path, f"not valid JSON (line {exc.lineno}, column {exc.colno}): {exc.msg}"
        ) from None
    if not isinstance(data, dict):
        raise CalibrationFileError(path, "not a wristscan calibration (a JSON object expected)")
    if data.get("format") != FILE_FORMAT:
        raise CalibrationFileError(
            path,
            f"not a wristscan calibration (format is {data.get('format')!r}, "
            f'expected "{FILE_FORMAT}")',
        )
    if data.get("version") != FILE_VERSION:
        raise CalibrationFileError(
            path,
            f"calibration file version {data.get('version')!r} is not supported; this wristscan "
            f"reads version {FILE_VERSION}",
        )
    try:
        doc = _FileDoc.model_validate(data)
    except ValidationError as exc:
        lines = format_validation_error(exc, str(path), _FileDoc)
        reasons = [line.removeprefix(f"{path}: ") for line in lines]
        raise CalibrationFileError(path, "; ".join(reasons)) from None

    expected_name = TRANSFORM_NAMES[doc.kind]
    if doc.transform.name != expected_name:
        raise CalibrationFileError(
            path,
            f"transform.name: a {doc.kind} calibration stores {expected_name!r}, "
            f"not {doc.transform.name!r}",
        )
    T = np.asarray(doc.transform.matrix_rows, dtype=np.float64)
    try:
        se3.check_transform(T, "transform.matrix_rows")
    except ValueError as exc:
        raise CalibrationFileError(path, f"{exc} (not a rigid transform)") from None
    pose = np.asarray(doc.transform.ur_pose, dtype=np.float64)
    T_pose = se3.pose_to_matrix(pose)
    dt = float(np.abs(T_pose[:3, 3] - T[:3, 3]).max())
    dr = se3.rotation_angle(T_pose[:3, :3].T @ T[:3, :3])
    if dt > _POSE_TOL_M or float(dr) > _POSE_TOL_RAD:
        raise CalibrationFileError(
            path,
            f"transform.ur_pose disagrees with transform.matrix_rows (by {dt:.2e} m, "
            f"{float(dr):.2e} rad): the file was edited by hand or is corrupt",
        )
    try:
        created = datetime.fromisoformat(doc.created_utc)
    except ValueError:
        raise CalibrationFileError(
            path, f"created_utc: not an ISO 8601 time ({doc.created_utc!r})"
        ) from None
    if created.tzinfo is None:
        raise CalibrationFileError(path, "created_utc: the time zone is missing (use 'Z')")
    cov = doc.covariance
    try:
        return Calibration(
            kind=doc.kind,
            transform=T,
            robot=RobotIdentity(doc.robot.model, doc.robot.serial),
            sensor=SensorIdentity(doc.sensor.driver, doc.sensor.id),
            method=doc.method,
            residuals=Residuals(doc.residuals.rms_m, tuple(doc.residuals.per_pose_m)),
            covariance=None if cov is None else _cov_array(cov.matrix_rows),
            covariance_parameters=() if cov is None else tuple(cov.parameters),
            parameters=doc.parameters,
            created_utc=created,
            software_version=doc.software_version,
            notes=doc.notes,
        )
    except ValueError as exc:
        raise CalibrationFileError(path, str(exc)) from None


def _cov_array(rows: list[list[float]]) -> FloatArray:
    if len({len(r) for r in rows}) > 1:
        raise ValueError("covariance rows differ in length")
    return np.asarray(rows, dtype=np.float64)


def _check_identity(
    path: Path,
    calib: Calibration,
    expect_robot: RobotIdentity | None,
    expect_sensor: SensorIdentity | None,
) -> None:
    problem = identity_mismatch(calib.robot, calib.sensor, expect_robot, expect_sensor)
    if problem is not None:
        raise CalibrationFileError(path, problem)


def read_calibration(
    path: str | os.PathLike[str],
    expect_robot: RobotIdentity | None = None,
    expect_sensor: SensorIdentity | None = None,
    *,
    kind: CalibrationKind | None = None,
) -> Calibration:
    """Read and check a calibration file.

    Raises :class:`CalibrationFileError` when the file cannot be read, is not valid JSON, has
    another format or version, misses a field, holds a non-rigid transform or a pose that
    disagrees with it, is of another ``kind`` than asked for, or was made for another robot or
    sensor than ``expect_robot`` / ``expect_sensor`` (fields given as None are not compared).
    """
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise CalibrationFileError(p, f"cannot read: {exc.strerror or exc}") from None
    calib = _parse(p, raw)
    if kind is not None and calib.kind != kind:
        raise CalibrationFileError(p, f"a {calib.kind} calibration, but a {kind} one is needed")
    _check_identity(p, calib, expect_robot, expect_sensor)
    return calib


class CalibrationStore:
    """The calibration in force, replaced only by one that reads cleanly.

    :meth:`reload` reads the file again (at start-up and on SIGHUP): on success the new
    calibration is in force from the next :attr:`current` read on; on failure the last good one
    stays in force, the error is logged and returned. Safe to use from several threads.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        expect_robot: RobotIdentity | None = None,
        expect_sensor: SensorIdentity | None = None,
        *,
        kind: CalibrationKind = "sensor2flange",
    ) -> None:
        self.path = Path(path)
        self.expect_robot = expect_robot
        self.expect_sensor = expect_sensor
        self.kind: CalibrationKind = kind
        self._lock = threading.Lock()
        self._current: Calibration | None = None
        self._generation = 0
        self._last_error: CalibrationFileError | None = None

    @property
    def current(self) -> Calibration | None:
        """The calibration in force (None until one has loaded)."""
        return self._current

    @property
    def generation(self) -> int:
        """Counts the calibrations put in force (0: none yet); tells users when it changed."""
        return self._generation

    @property
    def last_error(self) -> CalibrationFileError | None:
        """Why the latest :meth:`reload` failed (None after a success)."""
        return self._last_error

    def reload(self) -> CalibrationFileError | None:
        """Read the file; returns None when the new calibration is in force, else the error."""
        with self._lock:
            try:
                calib = read_calibration(
                    self.path, self.expect_robot, self.expect_sensor, kind=self.kind
                )
            except CalibrationFileError as exc:
                self._last_error = exc
                kept = "the previous calibration stays in force" if self._current else "none"
                log.error("calibration not loaded: %s (%s)", exc, kept)
                return exc
            self._current = calib
            self._generation += 1
            self._last_error = None
            log.info(
                "calibration in force: %s %s from %s (rms %.1f um)",
                calib.kind,
                calib.ur_pose_text,
                self.path,
                calib.residuals.rms_m * 1e6,
            )
            return None
