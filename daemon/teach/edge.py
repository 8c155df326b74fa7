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

Output (:func:`~.edge_path.write_edge_path`, in :mod:`.edge_path` with the result and the
reading back): JSON with the resampled points, tangents and normals in the base frame, the arc
length, the raw points, the edge model and the statistics. The edge model and its detection in
the profiles are in :mod:`.edge_model`.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import se3
from wristscan.calib.edge import EdgeDetection, EdgeModel, smooth_path
from wristscan.daemon.config import Config
from wristscan.daemon.procedure.in_force import load_sensor_calibration
from wristscan.daemon.procedure.motion import require_motion
from wristscan.daemon.procedure.progress import Progress, stage_reporter
from wristscan.daemon.teach.edge_model import (
    RawEdge,
    detections_from_sweep,
)
from wristscan.daemon.teach.edge_path import (
    EdgeResult,
)
from wristscan.daemon.teach.kit import Mover, TeachError, guarded, record_still, teach_acquisition

if TYPE_CHECKING:
    from wristscan.daemon.procedure.acquisition import Acquisition, Sweep

__all__ = ["EdgeOptions", "learn_edge"]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

_STEP_TRIES = 3


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


def learn_edge(
    cfg: Config,
    model: EdgeModel,
    options: EdgeOptions | None = None,
    *,
    confirmed: bool = False,
    progress: Progress | None = None,
) -> EdgeResult:
    """Follow and learn the edge on the devices of ``cfg`` (see the module doc).

    Raises :class:`~wristscan.daemon.procedure.errors.MotionNotConfirmed` before anything
    moves, :class:`~.kit.TeachError` when the edge is not in view at the start or too little
    of it was learned, :class:`~.kit.TeachAborted` when the run stopped part way.
    """
    opts = options or EdgeOptions()
    require_motion(cfg, confirmed)
    calib = load_sensor_calibration(cfg)
    s2f = np.asarray(calib.transform, dtype=np.float64)
    report = stage_reporter(progress, "edge")
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
