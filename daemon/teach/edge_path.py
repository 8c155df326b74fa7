"""The learned edge path on disk: what :func:`~.edge.learn_edge` returns (:class:`EdgeResult`),
its JSON file (:func:`write_edge_path`: the resampled points, tangents and normals in the base
frame, the arc length, the raw points, the edge model and the statistics) and reading one back
(:func:`read_edge_path`, :class:`LearnedPath`) for the replay (:mod:`.replay`).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib.edge import EdgeModel, EdgePath
from wristscan.daemon.config import Config
from wristscan.daemon.io.atomic import write_atomic

__all__ = [
    "PATH_FORMAT",
    "PATH_VERSION",
    "EdgeResult",
    "LearnedPath",
    "PathFileError",
    "read_edge_path",
    "write_edge_path",
]

FloatArray = NDArray[np.float64]

PATH_FORMAT = "wristscan-edge-path"
PATH_VERSION = 1


class PathFileError(ValueError):
    """A path file that cannot be read."""


@dataclass(frozen=True)
class EdgeResult:
    path: EdgePath
    model: EdgeModel
    raw_points: FloatArray
    raw_normals: FloatArray
    """Normals measured in the laser plane (base frame)."""
    raw_view_x: FloatArray
    """The sensor's X axis at each raw point (base frame)."""
    raw_confidence: FloatArray
    steps: int
    lost_steps: int
    end_reason: str
    closed: bool
    standoff_m: float
    duration_s: float
    sensor_calibration: str = ""

    def summary_lines(self) -> list[str]:
        p = self.path
        return [
            f"edge path     {p.points.shape[0]} points every {p.resolution_m * 1e3:g} mm over "
            f"{p.length_m * 1e3:.1f} mm ({self.model.kind}; {self.end_reason})",
            f"  raw         {self.raw_points.shape[0]} edge points from {self.steps} steps "
            f"({self.lost_steps} without the edge), mean confidence "
            f"{float(np.mean(self.raw_confidence)):.2f}",
            f"  smoothing   raw points within {p.residual_rms_m * 1e6:.1f} um RMS of the path; "
            f"largest gap between them {p.max_gap_m * 1e3:.2f} mm",
            "  ends        "
            + " ".join(f"{v * 1e3:.3f}" for v in p.points[0])
            + " -> "
            + " ".join(f"{v * 1e3:.3f}" for v in p.points[-1])
            + " mm (base)",
            f"  guidance    standoff {self.standoff_m * 1e3:.1f} mm, {self.duration_s:.1f} s",
        ]

    def to_dict(self, cfg: Config | None = None) -> dict[str, Any]:
        p = self.path
        return {
            "format": PATH_FORMAT,
            "version": PATH_VERSION,
            "frame": "base",
            "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "robot": None if cfg is None else cfg.robot.model,
            "sensor_calibration": self.sensor_calibration,
            "edge_model": self.model.to_dict(),
            "resolution_m": p.resolution_m,
            "length_m": p.length_m,
            "closed": self.closed,
            "end_reason": self.end_reason,
            "points_m": p.points.tolist(),
            "tangents": p.tangents.tolist(),
            "normals": p.normals.tolist(),
            "s_m": p.s.tolist(),
            "stats": {
                "residual_rms_m": p.residual_rms_m,
                "max_gap_m": p.max_gap_m,
                "raw_points": int(self.raw_points.shape[0]),
                "mean_confidence": float(np.mean(self.raw_confidence)),
                "steps": self.steps,
                "lost_steps": self.lost_steps,
                "standoff_m": self.standoff_m,
                "duration_s": self.duration_s,
            },
            "raw_points_m": self.raw_points.tolist(),
            "raw_normals": self.raw_normals.tolist(),
            "raw_view_x": self.raw_view_x.tolist(),
            "raw_confidence": self.raw_confidence.tolist(),
        }


def write_edge_path(path: str | Path, result: EdgeResult, cfg: Config | None = None) -> Path:
    """Write the learned path (JSON, atomically)."""
    return write_atomic(path, json.dumps(result.to_dict(cfg)) + "\n")


@dataclass(frozen=True)
class LearnedPath:
    """A learned edge path read back (base frame, metres)."""

    points: FloatArray
    tangents: FloatArray
    normals: FloatArray
    resolution_m: float
    closed: bool = False
    source: str = ""
    robot: str | None = None
    """The robot model the path was learned with (for reachability checks)."""


def read_edge_path(path: str | Path) -> LearnedPath:
    """Read a path file of :func:`write_edge_path`; :class:`PathFileError` when it is not
    one."""
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise PathFileError(f"not JSON: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != PATH_FORMAT:
        raise PathFileError("not a wristscan edge path file")
    if doc.get("version") != PATH_VERSION:
        raise PathFileError(f"unsupported version {doc.get('version')!r}")
    try:
        pts = np.asarray(doc["points_m"], dtype=np.float64)
        tan = np.asarray(doc["tangents"], dtype=np.float64)
        nrm = np.asarray(doc["normals"], dtype=np.float64)
        res = float(doc["resolution_m"])
    except (KeyError, TypeError, ValueError) as exc:
        raise PathFileError(f"missing or bad field: {exc}") from None
    n = pts.shape[0]
    if (
        pts.ndim != 2
        or pts.shape[1] != 3
        or n < 2
        or tan.shape != pts.shape
        or nrm.shape != pts.shape
    ):
        raise PathFileError("points_m, tangents and normals must be (N >= 2, 3) arrays")
    if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(tan)) and np.all(np.isfinite(nrm))):
        raise PathFileError("the path holds non-finite values")
    if np.any(np.abs(np.linalg.norm(nrm, axis=1) - 1) > 1e-6):
        raise PathFileError("the normals must be unit vectors")
    robot = doc.get("robot")
    return LearnedPath(
        pts,
        tan,
        nrm,
        res,
        bool(doc.get("closed", False)),
        str(path),
        robot if isinstance(robot, str) else None,
    )
