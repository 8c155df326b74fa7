"""``wristscan calibrate import``: sensor2flange from a stop-and-go data set on disk.

A data set is a folder (docs/calibration_import.md)::

    poses.csv              pose,x,y,z,<orientation columns of the convention>
    profiles/<pose>.csv    y,z[,valid]   one row per point of the profile taken at that pose

:func:`read_dataset` reads and checks it: every problem is a :class:`DatasetError` naming the
file and the line. :func:`calibrate_dataset` runs the per-pose calibration
(:func:`wristscan.calib.perpose.calibrate_per_pose`: circles, closed form, side, joint
refinement) and the jackknife over poses; :func:`calibration_of` makes the calibration file
(the same format and covariance order as ``calibrate sensor``'s) and :func:`run` ties it
together, writing the file and the report (:mod:`.imported_report`).
"""

from __future__ import annotations

import csv
import math
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import perpose
from wristscan.calib import pose_conventions as pc
from wristscan.calib.handeye import PoorlyConstrained
from wristscan.daemon.calibrate.sensor.result import joint_calibration
from wristscan.daemon.io.calibfile import (
    Calibration,
    RobotIdentity,
    SensorIdentity,
    write_calibration,
)

__all__ = [
    "DEFAULT_ROBOT_SIGMA_M",
    "METHOD",
    "UNITS",
    "DatasetError",
    "ImportFailed",
    "ImportResult",
    "ImportedDataset",
    "calibrate_dataset",
    "calibration_of",
    "parse_length",
    "read_dataset",
    "run",
]

FloatArray = NDArray[np.float64]
Units = Literal["mm", "m"]

UNITS: dict[str, float] = {"mm": 1e-3, "m": 1.0}
"""Length units of a data set's positions and profile points, in metres."""
DEFAULT_ROBOT_SIGMA_M = 20e-6
"""Per-axis flange position error of a pose assumed from a data sheet (a +-0.05 mm ISO 9283
repeatability is about 14 um per axis; 20 um leaves room for a little kinematic error): the floor
of the one estimated from the residuals."""
METHOD = "stop-and-go-import+joint-refinement"
"""``method`` of the calibration files written here."""

_VALID_TRUE = {"1", "true", "yes"}
_VALID_FALSE = {"0", "false", "no"}
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


class DatasetError(ValueError):
    """A data set that cannot be used: ``path`` the file, ``line`` its 1-based line (or None)."""

    def __init__(self, path: Path, message: str, line: int | None = None) -> None:
        self.path = path
        self.line = line
        self.reason = message
        where = f"{path}, line {line}" if line is not None else str(path)
        super().__init__(f"{where}: {message}")


class ImportFailed(RuntimeError):
    """The data were read but do not give a calibration (ambiguous, poorly constrained)."""


@dataclass(frozen=True, eq=False)
class ImportedDataset:
    """A data set in SI units: pose names, ``flange2base`` (K, 4, 4) and the valid ``(y, z)``
    points (N_k, 2) of each pose's profile."""

    folder: Path
    convention: str
    units: str
    names: tuple[str, ...]
    flange2base: FloatArray
    profiles: tuple[FloatArray, ...]

    def profile_path(self, k: int) -> Path:
        return self.folder / "profiles" / f"{self.names[k]}.csv"


# --------------------------------------------------------------------------------------------
# Reading


def parse_length(text: str, default_units: str = "mm") -> float:
    """A length such as ``40mm``, ``0.04 m`` or ``40`` (in ``default_units``) in metres."""
    m = re.fullmatch(r"\s*([-+0-9.eE]+)\s*(mm|m)?\s*", text)
    try:
        value = float(m.group(1)) if m else math.nan
    except ValueError:
        value = math.nan
    if m is None or not math.isfinite(value) or value <= 0.0:
        raise ValueError(f"{text!r} is not a positive length such as 40mm or 0.04m")
    return value * UNITS[m.group(2) or default_units]


def _rows(path: Path) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """Header (lower case, stripped) and the data rows with their line numbers; blank lines and
    lines starting with ``#`` are skipped."""
    if not path.is_file():
        raise DatasetError(path, "missing")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(path, f"cannot read: {exc}") from None
    header: list[str] | None = None
    rows: list[tuple[int, list[str]]] = []
    for n, cells in enumerate(csv.reader(text.splitlines()), start=1):
        if not cells or not "".join(cells).strip() or cells[0].lstrip().startswith("#"):
            continue
        if header is None:
            header = [c.strip().lower() for c in cells]
        else:
            rows.append((n, [c.strip() for c in cells]))
    if header is None:
        raise DatasetError(path, "empty: expected a header row and data rows")
    return header, rows


def _columns(path: Path, header: list[str], need: Sequence[str], what: str) -> list[int]:
    missing = [c for c in need if c not in header]
    if missing:
        hint = ""
        for conv in pc.CONVENTIONS:
            if all(c in header for c in pc.columns(conv)):
                hint = f"; these columns are those of --poses {conv}"
        raise DatasetError(
            path,
            f"no column {', '.join(missing)} (the header has {', '.join(header) or 'nothing'}; "
            f"{what} needs {', '.join(need)}){hint}",
            None,
        )
    return [header.index(c) for c in need]


def _number(path: Path, line: int, cells: list[str], idx: int, name: str) -> float:
    text = cells[idx] if idx < len(cells) else ""
    try:
        v = float(text)
    except ValueError:
        raise DatasetError(path, f"{name} = {text!r} is not a number", line) from None
    if not math.isfinite(v):
        raise DatasetError(path, f"{name} = {text!r} is not a finite number", line)
    return v


def _read_poses(folder: Path, convention: str, scale: float) -> tuple[list[str], FloatArray]:
    path = folder / "poses.csv"
    header, rows = _rows(path)
    cols = pc.columns(convention)
    idx = _columns(path, header, ("pose", *cols), f"--poses {convention}")
    names: list[str] = []
    values = np.empty((len(rows), len(cols)))
    for k, (line, cells) in enumerate(rows):
        name = cells[idx[0]] if idx[0] < len(cells) else ""
        if not _NAME.match(name):
            raise DatasetError(
                path, f"pose {name!r}: a name of letters, digits, '.', '_', '-' is needed", line
            )
        if name in names:
            raise DatasetError(path, f"pose {name!r} appears twice", line)
        names.append(name)
        values[k] = [_number(path, line, cells, i, c) for i, c in zip(idx[1:], cols, strict=True)]
    if len(names) < perpose.MIN_POSES:
        raise DatasetError(
            path,
            f"{len(names)} poses; the calibration needs >= {perpose.MIN_POSES} "
            "(12 or more recommended)",
        )
    values[:, :3] *= scale
    try:
        F = pc.to_matrix(convention, values)
    except pc.PoseRowError as exc:
        raise DatasetError(path, f"pose {names[exc.row]}: {exc}", rows[exc.row][0]) from None
    return names, F


def _valid(path: Path, line: int, text: str) -> bool:
    t = text.lower()
    if t in _VALID_TRUE:
        return True
    if t in _VALID_FALSE:
        return False
    raise DatasetError(path, f"valid = {text!r}: expected 1 or 0", line)


def _read_profile(path: Path, scale: float) -> FloatArray:
    header, rows = _rows(path)
    iy, iz = _columns(path, header, ("y", "z"), "a profile")
    iv = header.index("valid") if "valid" in header else None
    pts = []
    for line, cells in rows:
        if iv is not None and not _valid(path, line, cells[iv] if iv < len(cells) else ""):
            continue
        pts.append((_number(path, line, cells, iy, "y"), _number(path, line, cells, iz, "z")))
    if not pts:
        raise DatasetError(path, "no valid points")
    return np.asarray(pts, dtype=np.float64) * scale


def read_dataset(folder: Path, convention: str, units: str = "mm") -> ImportedDataset:
    """Read and check a data set folder (see the module doc); positions and profile points in
    ``units`` ("mm" or "m"). Raises :class:`DatasetError` naming the file and the line."""
    if units not in UNITS:
        raise ValueError(f"units must be one of {', '.join(UNITS)}, not {units!r}")
    pc.columns(convention)  # ValueError naming the known conventions
    if not folder.is_dir():
        raise DatasetError(folder, "no such folder")
    scale = UNITS[units]
    names, F = _read_poses(folder, convention, scale)
    profiles = tuple(_read_profile(folder / "profiles" / f"{n}.csv", scale) for n in names)
    return ImportedDataset(folder, convention, units, tuple(names), F, profiles)


# --------------------------------------------------------------------------------------------
# Calibration


@dataclass(frozen=True, eq=False)
class ImportResult:
    """What ``calibrate import`` found."""

    dataset: ImportedDataset
    solution: perpose.PerPoseResult
    jackknife: perpose.Jackknife | None
    ball_radius_m: float
    robot_sigma_m: float
    duration_s: float
    notes: tuple[str, ...] = ()

    @property
    def joint(self) -> perpose.HandEyeResult:
        return self.solution.joint


def calibrate_dataset(
    data: ImportedDataset,
    ball_radius_m: float,
    *,
    robot_sigma_m: float = DEFAULT_ROBOT_SIGMA_M,
    side: perpose.Side = "auto",
    with_jackknife: bool = True,
) -> ImportResult:
    """The per-pose calibration of ``data`` and its jackknife over poses. A problem of one pose's
    profile is a :class:`DatasetError` naming its file; a data set that does not determine the
    solution raises :class:`ImportFailed`."""
    t0 = time.monotonic()
    try:
        sol = perpose.calibrate_per_pose(
            data.flange2base,
            data.profiles,
            ball_radius_m,
            side=side,
            robot_sigma_m=robot_sigma_m,
        )
    except perpose.PerPoseDataError as exc:
        if exc.pose is not None:
            raise DatasetError(data.profile_path(exc.pose), str(exc)) from None
        raise ImportFailed(str(exc)) from None
    except PoorlyConstrained as exc:
        raise ImportFailed(str(exc)) from None
    jk = perpose.jackknife(sol, robot_sigma_m) if with_jackknife else None
    notes = [] if jk is None else _jackknife_notes(sol.joint, jk)
    if sol.joint.advice:
        notes.append(
            f"weakly constrained (condition {sol.joint.condition:.1f}): {sol.joint.advice}"
        )
    if sol.side == 0:
        notes.append(
            "the ball centre lies on different sides of the laser plane at different poses: "
            + " ".join(f"{n}:{int(s):+d}" for n, s in zip(data.names, sol.sides, strict=True))
        )
    return ImportResult(
        data, sol, jk, float(ball_radius_m), float(robot_sigma_m), time.monotonic() - t0,
        tuple(notes),
    )  # fmt: skip


JACKKNIFE_RATIO = 1.5
"""A jackknife sigma more than this many times the reported one is noted."""


def _jackknife_notes(j: perpose.HandEyeResult, jk: perpose.Jackknife) -> list[str]:
    """A note for each parameter whose jackknife sigma exceeds the reported one by more than
    :data:`JACKKNIFE_RATIO`: the robot's errors then are probably not independent per pose."""
    names = ("rotation about sensor X", "rotation about sensor Y", "rotation about sensor Z",
             "x", "y", "z")  # fmt: skip
    sig = np.sqrt(np.clip(np.diag(j.cov), 0.0, None))
    sjk = np.sqrt(np.clip(np.diag(jk.cov), 0.0, None))
    out = []
    for name, a, b in zip(names, sig, sjk, strict=True):
        if a > 0 and b > JACKKNIFE_RATIO * a:
            out.append(
                f"{name}: the jackknife over poses gives {b / a:.1f}x the reported 1 sigma; the "
                "robot's pose errors are probably systematic (trust the larger)"
            )
    return out


def calibration_of(
    result: ImportResult, robot: RobotIdentity, sensor: SensorIdentity
) -> Calibration:
    """The calibration file: the joint solution, its covariance (the order of ``calibrate
    sensor``'s file), the per-pose residuals and the figures as named parameters."""
    j = result.joint
    d = result.dataset
    start = result.solution.start
    params: dict[str, float] = {
        "n_poses": float(len(d.names)),
        "ball_side": float(result.solution.side),
        "robot_sigma_m": result.robot_sigma_m,
        "point_sigma_m": float(getattr(j, "point_sigma_m", math.nan)),
        "closed_form_translation_diff_m": float(
            np.linalg.norm(start.sensor2flange[:3, 3] - j.sensor2flange[:3, 3])
        ),
    }
    if result.jackknife is not None:
        for a, v in zip("xyz", result.jackknife.sigma_translation_m, strict=True):
            params[f"jackknife_sigma_{a}_m"] = float(v)
        for a, v in zip("xyz", result.jackknife.sigma_rotation_rad, strict=True):
            params[f"jackknife_sigma_rot_sensor_{a}_rad"] = float(v)
    notes = [f"imported from {d.folder} ({d.convention}, {d.units})", *result.notes]
    return joint_calibration(
        j,
        result.ball_radius_m,
        params,
        method=METHOD,
        notes="; ".join(notes),
        robot=robot,
        sensor=sensor,
    )


def run(
    folder: Path,
    convention: str,
    ball_radius_m: float,
    *,
    units: str = "mm",
    out: Path,
    report: Path | None = None,
    robot: RobotIdentity | None = None,
    sensor: SensorIdentity | None = None,
    robot_sigma_m: float = DEFAULT_ROBOT_SIGMA_M,
    side: perpose.Side = "auto",
) -> ImportResult:
    """Read the data set, calibrate, write the calibration file ``out`` (atomically) and the
    report. Raises :class:`DatasetError`, :class:`ImportFailed` or ``OSError``; nothing is
    written then."""
    from wristscan.daemon.calibrate.imported_report import build_report

    data = read_dataset(folder, convention, units)
    result = calibrate_dataset(data, ball_radius_m, robot_sigma_m=robot_sigma_m, side=side)
    calib = calibration_of(
        result, robot or RobotIdentity("unknown"), sensor or SensorIdentity("imported")
    )
    write_calibration(out, calib)
    if report is not None:
        build_report(result).write(report)
    return result
