"""Edge path learning (``wristscan teach edge``; Borangiu et al. 2009, section 5: "the robot uses
the laser sensor in order to automatically identify the 3D path, adjusting its position and
orientation, and learning the trajectory with a resolution specified by the user").

The operator places the sensor above the edge with the laser line across it. The robot then
follows the edge under closed-loop guidance, **stop and go**:

1. Standing still, the edge model (:class:`wristscan.calib.edge.EdgeModel`) is found in the
   latest profiles: the edge point and the surface normal in the laser plane, put into the base
   frame with ``flange2base @ sensor2flange`` (the calibration in force).
2. The edge's course ahead is predicted from the path learned so far: a quadratic through the
   last ``fit_m`` of edge points gives the tangent and the curvature at the end; the next edge
   point lies ``step_m`` further on that curve (at the start, before there is any course, along
   the sensor's X axis as the operator placed it).
3. The sensor moves (one ``move_l``) to the pose that centres that point in the laser line at
   the standoff, looking along the surface normal (sensor Z = -normal) with its X axis along the
   edge (the laser line across it). The turn per step is limited (``max_turn_deg``).
4. Every profile exposed during the move and the stop is paired with the robot pose by the
   synchroniser; the edge is detected in profiles spaced at least ``resolution_m / 4`` apart
   (and the last ones, still) and kept with its confidence. These are the raw path points, so
   the path has no gap: everything the laser crossed between two stops is measured.

It stops after ``length_m`` of edge, when the edge is lost for more than ``max_lost_m`` (an end
of the edge), or back at the start point (a closed contour). The raw points are then smoothed
and resampled at ``resolution_m`` (:func:`wristscan.calib.edge.smooth_path`); the normals
measured in the laser plane are completed with the condition that the surface normal is
perpendicular to the edge.

The stop-and-go loop keeps the guidance simple and its timing irrelevant: the accuracy of the
path comes from the pairing of every profile with the robot pose, not from the controller. At the
default 2 mm step, 20 mm/s and 30 ms of stillness it learns some 3-6 mm of edge per second.

Output (:func:`write_edge_path`): JSON with the resampled points, tangents and normals in the base
frame, the arc length, the raw points, the edge model and the statistics.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import se3
from wristscan.calib.edge import EdgeDetection, EdgeModel, EdgePath, detect_edge, smooth_path
from wristscan.daemon.calibrate.table import Progress, no_progress
from wristscan.daemon.config import Config
from wristscan.daemon.io.atomic import write_atomic
from wristscan.daemon.procedure.in_force import load_sensor_calibration
from wristscan.daemon.procedure.motion import require_motion
from wristscan.daemon.teach.plane import Mover, TeachError, guarded, record_still, teach_acquisition

if TYPE_CHECKING:
    from wristscan.daemon.procedure.acquisition import Acquisition, Sweep
__all__ = [
    "EdgeOptions",
    "EdgeResult",
    "LearnedPath",
    "PathFileError",
    "RawEdge",
    "detections_from_sweep",
    "learn_edge",
    "model_from_sweep",
    "model_toml",
    "read_edge_path",
    "teach_edge_model",
    "write_edge_path",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

PATH_FORMAT = "wristscan-edge-path"
PATH_VERSION = 1
_STEP_TRIES = 3


class PathFileError(ValueError):
    """A path file that cannot be read."""


@dataclass(frozen=True)
class EdgeOptions:
    """Settings of edge learning (SI units)."""

    resolution_m: float = 0.001
    """Spacing of the learned path."""
    length_m: float = 0.2
    """Stop after this much edge."""
    step_m: float = 0.002
    """Guidance step along the edge."""
    standoff_m: float | None = None
    """Distance from the sensor to the edge along the sensor's Z axis (None: as at the start)."""
    direction: int = 1
    """+1: along the sensor's +X axis at the start, -1: along -X."""
    speed_m_s: float = 0.02
    settle_s: float = 0.03
    """Still time recorded after each step."""
    fit_m: float = 0.008
    """Edge length the course ahead is predicted from."""
    max_turn_deg: float = 12.0
    """Largest change of direction (of the tangent and of the normal) per step."""
    max_lost_m: float = 0.004
    """Stop when the edge was not seen for this long (dead reckoning meanwhile)."""
    bandwidth_m: float | None = None
    """Smoothing kernel width (default: the resolution, at least 0.5 mm)."""
    start_dwell_s: float = 0.1

    def __post_init__(self) -> None:
        for name in ("resolution_m", "length_m", "step_m", "speed_m_s", "fit_m", "max_lost_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")
        if self.direction not in (1, -1):
            raise ValueError("direction must be 1 or -1")
        if self.standoff_m is not None and not self.standoff_m > 0:
            raise ValueError("standoff_m must be positive")
        if not 0 < self.max_turn_deg <= 45:
            raise ValueError("max_turn_deg must be in (0, 45]")
        if self.step_m > 0.02:
            raise ValueError("step_m must be at most 20 mm (the edge could leave the view)")


@dataclass
class RawEdge:
    """Edge points found in single profiles (base frame), in acquisition order."""

    points: list[FloatArray] = field(default_factory=list)
    normals: list[FloatArray] = field(default_factory=list)
    """Surface normals measured in the laser plane (towards the sensor)."""
    view_x: list[FloatArray] = field(default_factory=list)
    """The sensor's X axis (normal to the laser plane) for each point."""
    confidence: list[float] = field(default_factory=list)
    t_ns: list[int] = field(default_factory=list)

    def truncate(self, n: int) -> None:
        """Keep the first ``n`` points."""
        for lst in (self.points, self.normals, self.view_x, self.confidence, self.t_ns):
            del lst[n:]

    def extend(self, other: RawEdge) -> None:
        self.points += other.points
        self.normals += other.normals
        self.view_x += other.view_x
        self.confidence += other.confidence
        self.t_ns += other.t_ns

    def __len__(self) -> int:
        return len(self.points)

    def arrays(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        return (
            np.asarray(self.points, dtype=np.float64).reshape(-1, 3),
            np.asarray(self.normals, dtype=np.float64).reshape(-1, 3),
            np.asarray(self.view_x, dtype=np.float64).reshape(-1, 3),
            np.asarray(self.confidence, dtype=np.float64),
        )


def detections_from_sweep(
    sweep: Sweep,
    sensor2flange: ArrayLike,
    model: EdgeModel,
    *,
    min_spacing_m: float = 0.0,
    last: int = 3,
    prior_y: float | None = 0.0,
) -> tuple[RawEdge, list[EdgeDetection]]:
    """Detect the edge in the profiles of ``sweep``: those whose sensor origin moved at least
    ``min_spacing_m`` since the previous one used, plus the ``last`` ones. Returns the found
    points in the base frame and the detections of the ``last`` profiles (found or not)."""
    s2f = np.asarray(sensor2flange, dtype=np.float64)
    raw = RawEdge()
    n = sweep.n_profiles
    if n == 0:
        return raw, []
    s2b = sweep.flange2base @ s2f
    order = np.argsort(sweep.profile_index, kind="stable")
    pidx = sweep.profile_index[order]
    starts = np.searchsorted(pidx, np.arange(n + 1))
    chosen: list[int] = []
    last_pos: FloatArray | None = None
    for i in range(n):
        pos = s2b[i, :3, 3]
        if last_pos is None or float(np.linalg.norm(pos - last_pos)) >= min_spacing_m:
            chosen.append(i)
            last_pos = pos
    tail = list(range(max(0, n - last), n))
    chosen = sorted(set(chosen) | set(tail))
    tail_dets: list[EdgeDetection] = []
    prior = prior_y
    for i in chosen:
        sel = order[starts[i] : starts[i + 1]]
        det = detect_edge(sweep.y[sel], sweep.z[sel], sweep.valid[sel], model, prior_y=prior)
        if i in tail:
            tail_dets.append(det)
        if not det.found:
            continue
        prior = float(det.point[0])
        T = s2b[i]
        R = T[:3, :3]
        raw.points.append(np.asarray(T[:3, 3] + R[:, 1] * det.point[0] + R[:, 2] * det.point[1]))
        raw.normals.append(np.asarray(R[:, 1] * det.normal[0] + R[:, 2] * det.normal[1]))
        raw.view_x.append(np.asarray(R[:, 0]).copy())
        raw.confidence.append(det.confidence)
        raw.t_ns.append(int(sweep.exposure_ns[i]))
    return raw, tail_dets


def model_from_sweep(
    sweep: Sweep,
    kind: str,
    *,
    height_tolerance: float = 0.3,
    angle_tolerance_deg: float = 15.0,
    min_confidence: float = 0.6,
) -> EdgeModel:
    """Teach an edge model from still profiles of an example edge: the edge of ``kind`` is
    looked for with wide ranges, and the model keeps what was seen - the step height within
    ``+-height_tolerance`` (relative), the included angle within ``+-angle_tolerance_deg``, the
    side of the upper face. Raises :class:`~.teach_plane.TeachError` when no such edge is seen
    in most profiles."""
    loose = EdgeModel(
        kind,  # type: ignore[arg-type]
        height_m=(0.0003, 0.3),
        angle_deg=(5.0, 175.0),
        face_angle_deg=60.0,
        min_confidence=0.3,
    )
    order = np.argsort(sweep.profile_index, kind="stable")
    pidx = sweep.profile_index[order]
    starts = np.searchsorted(pidx, np.arange(sweep.n_profiles + 1))
    dets = []
    for i in range(sweep.n_profiles):
        sel = order[starts[i] : starts[i + 1]]
        dets.append(detect_edge(sweep.y[sel], sweep.z[sel], sweep.valid[sel], loose))
    found = [d for d in dets if d.found]
    if len(found) < max(3, len(dets) // 2):
        why = next((d.reason for d in dets if not d.found and d.reason), "")
        raise TeachError(
            f"no clear {kind} edge in view ({len(found)} of {len(dets)} profiles; {why}): place "
            "the laser line across the example edge"
        )
    kw: dict[str, Any] = {"kind": kind, "min_confidence": min_confidence}
    heights = np.array([d.height_m for d in found])
    if np.isfinite(heights).sum() >= len(found) // 2 + 1:
        h = float(np.nanmedian(heights))
        kw["height_m"] = (h * (1 - height_tolerance), h * (1 + height_tolerance))
    elif kind == "step":
        kw["height_m"] = (0.001, 0.3)  # the lower face out of range: any height
    if kind in ("v_groove", "outer_corner"):
        a = float(np.median([d.angle_deg for d in found]))
        kw["angle_deg"] = (max(0.0, a - angle_tolerance_deg), min(180.0, a + angle_tolerance_deg))
    sides = [d.side for d in found if d.side]
    if sides:
        kw["side"] = max(set(sides), key=sides.count)
    return EdgeModel(**kw)


def model_toml(model: EdgeModel) -> str:
    """The model as an ``[edge]`` TOML table (the file ``teach edge`` reads)."""
    lines = ["[edge]"]
    for k, v in model.to_dict().items():
        if isinstance(v, str):
            lines.append(f'{k} = "{v}"')
        elif isinstance(v, bool):
            lines.append(f"{k} = {'true' if v else 'false'}")
        elif isinstance(v, list):
            lines.append(f"{k} = [{', '.join(repr(float(x)) for x in v)}]")
        else:
            lines.append(f"{k} = {v!r}")
    return "\n".join(lines) + "\n"


def teach_edge_model(cfg: Config, kind: str, dwell_s: float = 0.2) -> EdgeModel:
    """Teach the edge model from the example edge under the sensor (nothing moves; the model
    lives in the laser plane, so no calibration is needed)."""
    with teach_acquisition(cfg) as acq:
        sweep = record_still(acq, dwell_s, 0.0)
    return model_from_sweep(sweep, kind)


def _rotate_towards(a: FloatArray, b: FloatArray, max_rad: float) -> FloatArray:
    """Unit ``a`` turned towards unit ``b`` by at most ``max_rad``."""
    c = float(np.clip(a @ b, -1.0, 1.0))
    ang = math.acos(c)
    if ang <= max_rad:
        return b
    axis = np.cross(a, b)
    na = float(np.linalg.norm(axis))
    if na < 1e-12:
        return a
    R = se3.rotvec_to_matrix(axis / na * max_rad)
    return np.asarray(R @ a)


def complete_normal(n_meas: FloatArray, view_x: FloatArray, tangent: FloatArray) -> FloatArray:
    """The surface normal from its laser-plane projection ``n_meas``: ``n_meas + lam view_x``
    perpendicular to the edge ``tangent`` (unit)."""
    xt = float(view_x @ tangent)
    n = n_meas if abs(xt) < 0.2 else n_meas - float(n_meas @ tangent) / xt * view_x
    return np.asarray(n / np.linalg.norm(n))


@dataclass(frozen=True)
class _Course:
    point: FloatArray
    tangent: FloatArray
    normal: FloatArray
    curvature: FloatArray
    """d2p/ds2 at the end (1/m, a vector normal to the tangent)."""


def _course(
    pts: FloatArray, normals: FloatArray, view_x: FloatArray, fit_m: float, t_prev: FloatArray
) -> _Course | None:
    """Edge course at the end of the raw points: a quadratic in arc length over ``fit_m``."""
    if pts.shape[0] < 4:
        return None
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    s = s - s[-1]  # 0 at the end
    sel = s >= -fit_m
    if np.count_nonzero(sel) < 4:
        sel[-4:] = True
    P, S = pts[sel], s[sel]
    span = float(S.max() - S.min())
    if span < 0.25 * fit_m:
        return None
    # Chord-length parameters are inflated by noise; a line fit first gives a cleaner one.
    c = P.mean(axis=0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)
    d = vt[0] if float(vt[0] @ t_prev) >= 0 else -vt[0]
    u = (P - c) @ d
    u = u - u.max()
    deg = 2 if span > 0.5 * fit_m else 1
    A = np.vander(u, deg + 1, increasing=True)
    coef, *_ = np.linalg.lstsq(A, P, rcond=None)
    end = coef[0]
    t = coef[1]
    t = t / np.linalg.norm(t)
    k = 2 * coef[2] if deg == 2 else np.zeros(3)
    k = k - (k @ t) * t
    nrm = np.array(
        [complete_normal(n, x, t) for n, x in zip(normals[sel][-5:], view_x[sel][-5:], strict=True)]
    ).mean(axis=0)
    nrm = nrm - (nrm @ t) * t
    nrm /= np.linalg.norm(nrm)
    return _Course(np.asarray(end), np.asarray(t), np.asarray(nrm), np.asarray(k))


def _sensor_pose(
    point: FloatArray, normal: FloatArray, tangent: FloatArray, standoff: float
) -> FloatArray:
    z = -normal / np.linalg.norm(normal)
    x = tangent - (tangent @ z) * z
    x = x / np.linalg.norm(x)
    return np.asarray(se3.make(np.column_stack([x, np.cross(z, x), z]), point - standoff * z))


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


def learn_edge(
    cfg: Config,
    model: EdgeModel,
    options: EdgeOptions | None = None,
    *,
    confirmed: bool = False,
    progress: Progress | None = None,
) -> EdgeResult:
    """Follow and learn the edge on the devices of ``cfg`` (see the module doc).

    Raises :class:`~.calib_table.MotionNotConfirmed` before anything moves,
    :class:`~.teach_plane.TeachError` when the edge is not in view at the start or too little
    of it was learned, :class:`~.teach_plane.TeachAborted` when the run stopped part way.
    """
    opts = options or EdgeOptions()
    require_motion(cfg, confirmed)
    calib = load_sensor_calibration(cfg)
    s2f = np.asarray(calib.transform, dtype=np.float64)
    report = progress or no_progress
    total = max(1, math.ceil(opts.length_m / opts.step_m))
    t0 = time.monotonic()
    report(0, total, "connecting, waiting for paired profiles")
    with teach_acquisition(cfg) as acq:
        with guarded(acq, "edge learning"):
            follower = _Follower(acq, s2f, model, opts)
            follower.start()
            while follower.reason is None:
                follower.step()
                report(
                    min(follower.steps, total),
                    total,
                    f"{follower.travelled * 1e3:.1f} mm of edge",
                )
    raw = follower.raw
    pts, nrm, vx, conf = raw.arrays()
    if pts.shape[0] < 5:
        raise TeachError(f"too little edge learned ({pts.shape[0]} points): {follower.reason}")
    try:
        path = smooth_path(
            pts,
            opts.resolution_m,
            bandwidth_m=opts.bandwidth_m,
            normals=nrm,
            view_x=vx,
            weights=conf,
        )
    except ValueError as exc:
        raise TeachError(f"cannot make a path of the edge points: {exc}") from None
    return EdgeResult(
        path=path,
        model=follower.model,
        raw_points=pts,
        raw_normals=nrm,
        raw_view_x=vx,
        raw_confidence=conf,
        steps=follower.steps,
        lost_steps=follower.lost_steps,
        end_reason=follower.reason or "",
        closed=follower.closed,
        standoff_m=follower.standoff,
        duration_s=time.monotonic() - t0,
        sensor_calibration=str(cfg.calibration.file),
    )


class _Follower:
    """The stop-and-go guidance loop (module doc)."""

    def __init__(
        self, acq: Acquisition, s2f: FloatArray, model: EdgeModel, opts: EdgeOptions
    ) -> None:
        self.acq = acq
        self.s2f = s2f
        self.model = model
        self.opts = opts
        self.mover = Mover(acq, s2f, opts.speed_m_s)
        self.raw = RawEdge()
        self.steps = 0
        self.lost_steps = 0
        self.lost_m = 0.0
        self.travelled = 0.0
        self.reason: str | None = None
        self.closed = False
        self.standoff = 0.0
        self.tangent = np.zeros(3)
        self.normal = np.zeros(3)
        self.point = np.zeros(3)
        self.first = np.zeros(3)
        self.curvature = np.zeros(3)
        self.pose = np.eye(4)
        """Sensor pose at the last stop."""

    def _detect(self, sweep: Sweep, still: bool) -> list[EdgeDetection]:
        raw, tail = detections_from_sweep(
            sweep,
            self.s2f,
            self.model,
            min_spacing_m=0.0 if still else self.opts.resolution_m / 4,
            last=3,
        )
        self.raw.extend(raw)
        return tail

    def start(self) -> None:
        sweep = record_still(self.acq, self.opts.start_dwell_s, 0.0)
        tail = self._detect(sweep, still=True)
        if len(self.raw) == 0:
            why = next((d.reason for d in reversed(tail) if d.reason), "nothing found")
            raise TeachError(
                f"no {self.model.kind} edge in view at the start ({why}): place the sensor over "
                "the edge with the laser line across it"
            )
        found = [d for d in tail if d.found]
        if self.model.side == "any" and found and found[-1].side:
            # Keep the side seen at the start: the same edge stays on the same side.
            self.model = replace(self.model, side=found[-1].side)  # type: ignore[arg-type]
        pts, nrm, _, _ = self.raw.arrays()
        S = sweep.flange2base[-1] @ self.s2f
        self.point = np.median(pts, axis=0)
        x = self.opts.direction * S[:3, 0]
        n = nrm.mean(axis=0)
        n /= np.linalg.norm(n)
        self.tangent = x - (x @ n) * n
        self.tangent /= np.linalg.norm(self.tangent)
        self.normal = complete_normal(n, S[:3, 0], self.tangent)
        self.first = self.point.copy()
        self.standoff = (
            self.opts.standoff_m
            if self.opts.standoff_m is not None
            else float((self.point - S[:3, 3]) @ S[:3, 2])
        )
        log.info(
            "edge found at %s mm (standoff %.1f mm, side %s)",
            np.round(self.point * 1e3, 3).tolist(),
            self.standoff * 1e3,
            self.model.side,
        )
        # Centre the edge in view, normal to the surface, before moving along.
        self.pose = _sensor_pose(self.point, self.normal, self.tangent, self.standoff)
        self.mover.move_sensor(self.pose)

    def _gap(self, before: int) -> float:
        """Largest distance between consecutive edge points from the last one before the
        step on (infinite without new points)."""
        if len(self.raw) <= before:
            return math.inf
        pts = np.asarray(self.raw.points[max(0, before - 1) :])
        return float(np.linalg.norm(np.diff(pts, axis=0), axis=1).max()) if len(pts) > 1 else 0.0

    def step(self) -> None:
        o = self.opts
        pts, nrm, vx, _ = self.raw.arrays()
        course = _course(pts, nrm, vx, o.fit_m, self.tangent)
        max_turn = math.radians(o.max_turn_deg)
        if course is not None and self.lost_m == 0.0:
            self.tangent = _rotate_towards(self.tangent, course.tangent, max_turn)
            self.normal = _rotate_towards(self.normal, course.normal, max_turn)
            self.point = course.point
            self.curvature = course.curvature
        elif self.lost_m == 0.0 and len(self.raw):
            self.point = pts[-1]
        # The next edge point on the predicted curve; the normal kept perpendicular to it.
        h = o.step_m
        target = self.point + h * self.tangent + 0.5 * h * h * self.curvature
        t_next = self.tangent + h * self.curvature
        t_next /= np.linalg.norm(t_next)
        n_next = self.normal - (self.normal @ t_next) * t_next
        n_next /= np.linalg.norm(n_next)
        pose = _sensor_pose(target, n_next, t_next, self.standoff)
        before = len(self.raw)
        for attempt in range(_STEP_TRIES):
            with self.acq.record(settle_timeout_s=5.0) as rec:
                self.mover.move_sensor(pose)
                time.sleep(o.settle_s)
            sweep = rec.result()
            tail = self._detect(sweep, still=False)
            seen = any(d.found for d in tail)
            gap = self._gap(before)
            log.debug(
                "step %d: %d profiles, %d edge points (largest gap %.2f mm), edge %s in the "
                "last profiles",
                self.steps + 1,
                sweep.n_profiles,
                len(self.raw) - before,
                gap * 1e3,
                "seen" if seen else "not seen",
            )
            if gap <= 0.5 * o.resolution_m or attempt + 1 == _STEP_TRIES:
                break
            # Profiles went missing during the move (not paired, or the edge not found in
            # them): go back and cover the stretch again, so that the path has no hole. (At
            # the real end of an edge this costs two extra moves per step.)
            log.info("a %.2f mm gap in the edge points: repeating the step", gap * 1e3)
            self.raw.truncate(before)
            self.mover.move_sensor(self.pose)
        self.steps += 1
        self.pose = pose
        if seen:
            self.lost_m = 0.0
        else:
            self.lost_steps += 1
            self.lost_m += h
            # Dead reckoning along the prediction until the edge comes back or is given up.
            self.point, self.tangent = target, t_next
            if self.lost_m > o.max_lost_m:
                self.reason = f"edge lost after {self.travelled * 1e3:.1f} mm"
                return
        if len(self.raw) > before:
            new = np.asarray(self.raw.points[before:])
            ref = pts[-1] if pts.shape[0] else self.first
            self.travelled += float(np.linalg.norm(new[-1] - ref))
        if self.travelled >= o.length_m:
            self.reason = f"{o.length_m * 1e3:.0f} mm learned"
        elif (
            self.travelled > 10 * o.step_m
            and float(np.linalg.norm(self.raw.points[-1] - self.first)) < 0.75 * o.step_m
        ):
            self.closed = True
            self.reason = "closed contour: back at the start"


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
