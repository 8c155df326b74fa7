"""Edge models found in one laser profile, and 3D edge paths smoothed and resampled at a
resolution (Borangiu et al. 2009, section 5: "the user teaches the edge model into the vision
software ... the robot learns the trajectory with a resolution specified by the user").

Profiles are in the sensor frame: points ``(y, z)`` of the laser plane, ``+z`` away from the
sensor (DESIGN.md). Metres and radians throughout. Steps 1-2 below are
:mod:`wristscan.calib.edge_profile`; the paths (:func:`smooth_path`, :class:`EdgePath`,
importable from here) are :mod:`wristscan.calib.edge_path`.

Edge models (:class:`EdgeModel`)
--------------------------------
``step``
    A nearer ("upper") face, then a drop to a farther ("lower") face: through a gap or jump (the
    wall hidden from the laser), or down a visible wall. The lower face may also lie beyond the
    measuring range (``allow_open``). The edge point is the **upper corner** (where a deburring
    tool works); the normal is the upper face's.
``lap_joint``
    The same shape (the edge of an upper plate on a lower one), but the edge point is the
    **root** at the foot of the wall (where a fillet weld or a sealant bead goes): the wall line
    meets the lower face; with the wall hidden, the upper corner projected onto the lower face.
    The normal is the lower face's.
``v_groove``
    Two faces meeting in a concave corner (a valley seen from the sensor); the edge point is the
    intersection of the two face lines, the normal the bisector of the face normals.
``outer_corner``
    Two faces meeting in a convex corner (a ridge); same construction.

Detection (:func:`detect_edge`)
-------------------------------
1. Valid points in profile order; isolated spikes (off a 5-point running median by more than
   ``8 sigma``, sigma from the MAD of second differences) are dropped.
2. Douglas-Peucker splits the profile into straight pieces (tolerance from the noise); pieces of
   at least ``min_face_points`` points are faces, shorter ones (jumps, gaps, rounded corners)
   transitions; neighbouring faces that turn by less than ``merge_deg`` are merged (gently
   curved surfaces).
3. Every placement of the model on the faces is a candidate; each face gets a robust line fit
   (:func:`wristscan.calib.plane.fit_hyperplane`, Tukey) on its points within ``window_m`` of
   the corner, leaving out ``skip_m`` at the corner itself.
4. A candidate's score is a product of factors in [0, 1]: support (visible width of each face
   against ``min_face_m``), fit quality (face RMS against the noise), parameter match (angle or
   height inside the model's range; outside, a Gaussian fall-off), side (``side``). With a prior
   position (tracking), candidates are ranked after a Gaussian penalty on the distance to it.
   The **confidence** is the best score lowered by ambiguity: ``s1 (1 - r^2 / 2)`` with ``r``
   the ratio of the runner-up's ranked score to the best's.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib.edge_path import EdgePath, smooth_path
from wristscan.calib.edge_profile import (
    Face,
    Profile,
    angle_between_dirs,
    face_line,
    intersect,
    next_sensor_point_y,
    segment_profile,
    towards_sensor,
)
from wristscan.calib.plane import HyperplaneFit

__all__ = [
    "EDGE_KINDS",
    "EdgeDetection",
    "EdgeKind",
    "EdgeModel",
    "EdgePath",
    "detect_edge",
    "smooth_path",
]

FloatArray = NDArray[np.float64]
EdgeKind = Literal["step", "lap_joint", "v_groove", "outer_corner"]
EDGE_KINDS: tuple[str, ...] = ("step", "lap_joint", "v_groove", "outer_corner")
Side = Literal["left", "right", "any"]

_WALL_MIN_DEG = 40.0  # a face this steep against the upper face is a wall
_NOT_FOUND_REASON_NO_POINTS = "too few valid points in the profile"


# --------------------------------------------------------------------------------------------
# The model


def _pair(value: Any, name: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be two numbers [min, max]") from None
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo < 0 or hi <= lo:
        raise ValueError(f"{name} must be [min, max] with 0 <= min < max, got [{lo}, {hi}]")
    return lo, hi


@dataclass(frozen=True)
class EdgeModel:
    """What edge to look for in a profile, and how strictly (SI units; angles in degrees as the
    names say)."""

    kind: EdgeKind = "step"
    height_m: tuple[float, float] = (0.001, 0.1)
    """Step height range (``step``, ``lap_joint``): distance from the upper corner to the lower
    face."""
    angle_deg: tuple[float, float] = (30.0, 150.0)
    """Included angle between the two faces (``v_groove``, ``outer_corner``)."""
    face_angle_deg: float = 30.0
    """Largest angle between the upper and lower faces of a step or lap joint."""
    side: Side = "any"
    """Where the upper face (step, lap joint) lies along the laser line: ``left`` (-y),
    ``right`` (+y) or ``any``."""
    allow_open: bool = True
    """Step: accept a step whose lower face lies beyond the measuring range (height unknown)."""
    min_face_m: float = 0.002
    """Visible width each face needs for full support."""
    min_face_points: int = 6
    window_m: float = 0.005
    """Face lines are fitted on points within this distance of the corner."""
    skip_m: float = 0.0003
    """... leaving out this much right at the corner (rounding, blooming)."""
    merge_deg: float = 8.0
    """Neighbouring straight pieces turning by less than this are one (curved) face."""
    min_turn_deg: float = 15.0
    """Corner models: faces must turn by at least this much."""
    min_confidence: float = 0.5
    """Detections below this confidence count as not found."""
    prior_sigma_m: float = 0.005
    """Tracking: Gaussian width of the penalty on the distance to the prior position."""

    def __post_init__(self) -> None:
        if self.kind not in EDGE_KINDS:
            raise ValueError(f"edge kind must be one of {', '.join(EDGE_KINDS)}, got {self.kind!r}")
        if self.side not in ("left", "right", "any"):
            raise ValueError(f"side must be left, right or any, got {self.side!r}")
        object.__setattr__(self, "height_m", _pair(self.height_m, "height_m"))
        object.__setattr__(self, "angle_deg", _pair(self.angle_deg, "angle_deg"))
        if self.angle_deg[1] > 180:
            raise ValueError("angle_deg must lie within [0, 180]")
        for name in ("min_face_m", "window_m", "prior_sigma_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")
        if self.skip_m < 0 or self.skip_m >= self.window_m:
            raise ValueError("skip_m must be >= 0 and smaller than window_m")
        if self.min_face_points < 3:
            raise ValueError("min_face_points must be >= 3")
        if not 0 <= self.min_confidence < 1:
            raise ValueError("min_confidence must be in [0, 1)")
        if not 0 < self.face_angle_deg < 90:
            raise ValueError("face_angle_deg must be in (0, 90)")

    @classmethod
    def from_mapping(cls, doc: Mapping[str, Any]) -> EdgeModel:
        """From a parsed TOML/JSON table (keys as the field names); unknown keys are an error."""
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(doc) - known)
        if unknown:
            raise ValueError(f"unknown edge model key(s): {', '.join(unknown)}")
        kw = dict(doc)
        for k in ("height_m", "angle_deg"):
            if k in kw:
                kw[k] = _pair(kw[k], k)
        return cls(**kw)

    def to_dict(self) -> dict[str, Any]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


@dataclass(frozen=True, eq=False)
class EdgeDetection:
    """The edge found in one profile (sensor frame, laser plane coordinates ``(y, z)``)."""

    found: bool
    point: FloatArray
    """(2,) edge point ``(y, z)`` (m); NaN when not found."""
    normal: FloatArray
    """(2,) unit surface normal at the edge in the laser plane, pointing back towards the
    sensor (``z`` component <= 0)."""
    confidence: float
    kind: str
    angle_deg: float = math.nan
    """Included angle between the faces (corner models) or between the wall and the upper face
    (step, lap joint, when the wall is seen)."""
    height_m: float = math.nan
    """Step height (step, lap joint; NaN when the lower face is out of range)."""
    side: str = ""
    """Side of the upper face (step, lap joint): ``left`` or ``right``."""
    rms_m: float = math.nan
    """RMS of the face line fits."""
    noise_m: float = math.nan
    """Noise level estimated from the profile."""
    faces: tuple[tuple[FloatArray, FloatArray], ...] = ()
    """The fitted face lines as ``(point, unit normal)``."""
    reason: str = ""
    """Why nothing was found (empty when found)."""

    @staticmethod
    def none(kind: str, reason: str, noise_m: float = math.nan) -> EdgeDetection:
        nan2 = np.full(2, math.nan)
        return EdgeDetection(False, nan2, nan2.copy(), 0.0, kind, noise_m=noise_m, reason=reason)


def _unit(v: FloatArray) -> FloatArray:
    return np.asarray(v / np.linalg.norm(v))


# --------------------------------------------------------------------------------------------
# Face lines and candidates


def _face_line(
    prof: Profile, face: Face, corner_end: int, model: EdgeModel
) -> tuple[HyperplaneFit, float] | None:
    """The face's line near its ``corner_end`` with the model's window (see
    :func:`~wristscan.calib.edge_profile.face_line`)."""
    return face_line(prof, face, corner_end, model.window_m, model.skip_m)


def _range_factor(x: float, lo: float, hi: float, tol: float) -> float:
    """1 inside ``[lo, hi]``, a Gaussian fall-off of width ``tol`` outside (NaN: 1)."""
    if not math.isfinite(x):
        return 1.0
    if lo <= x <= hi:
        return 1.0
    d = lo - x if x < lo else x - hi
    return math.exp(-((d / tol) ** 2))


def _ratio_factor(x: float, lo: float, hi: float, rel: float = 0.25) -> float:
    """1 inside ``[lo, hi]``; outside, a fall-off in the ratio to the nearer bound (a 25 %
    excess or shortfall gives exp(-1)). For lengths; NaN: 1."""
    if not math.isfinite(x) or lo <= x <= hi:
        return 1.0
    r = lo / max(x, 1e-12) if x < lo else x / hi
    return math.exp(-(((r - 1.0) / rel) ** 2))


@dataclass
class _Candidate:
    score: float
    point: FloatArray
    normal: FloatArray
    angle_deg: float
    height_m: float
    side: str
    rms: float
    faces: tuple[tuple[FloatArray, FloatArray], ...]


def _support(width: float, model: EdgeModel) -> float:
    return min(1.0, width / model.min_face_m)


def _fit_factor(rms: float, sigma: float) -> float:
    ref = 3.0 * sigma + 5e-6
    return math.exp(-0.5 * (rms / ref) ** 2)


def _corner_candidates(prof: Profile, model: EdgeModel) -> list[_Candidate]:
    out: list[_Candidate] = []
    faces = prof.faces
    gap_m = 0.001
    for fa, fb in itertools.pairwise(faces):
        if int(prof.orig[fb.a]) - int(prof.orig[fa.b]) > 8:
            continue  # more than a rounded corner between them
        if fb.a != fa.b:
            between = prof.pts(fa.b, fb.a)
            if float(np.hypot(*np.ptp(between, axis=0))) > gap_m:
                continue
        la = _face_line(prof, fa, fa.b, model)
        lb = _face_line(prof, fb, fb.a, model)
        if la is None or lb is None:
            continue
        (ga, wa), (gb, wb) = la, lb
        v = intersect(ga, gb)
        if v is None:
            continue
        junction = 0.5 * (prof.point(fa.b) + prof.point(fb.a))
        if float(np.hypot(*(v - junction))) > 0.5 * model.window_m:
            continue
        da = np.array([ga.normal[1], -ga.normal[0]])
        if float(da @ fa.direction) < 0:
            da = -da
        db = np.array([gb.normal[1], -gb.normal[0]])
        if float(db @ fb.direction) < 0:
            db = -db
        turn = math.atan2(float(da[0] * db[1] - da[1] * db[0]), float(da @ db))
        if abs(math.degrees(turn)) < model.min_turn_deg:
            continue
        # Profile order runs along +y-ish; z grows away from the sensor. Turning towards +z
        # (positive cross in the (y, z) plane) makes a ridge seen from the sensor.
        concave = turn < 0
        if (model.kind == "v_groove") != concave:
            continue
        included = 180.0 - abs(math.degrees(turn))
        na = towards_sensor(np.asarray(ga.normal), v)
        nb = towards_sensor(np.asarray(gb.normal), v)
        bis = _unit(na + nb)
        lo, hi = model.angle_deg
        score = (
            _support(wa, model)
            * _support(wb, model)
            * _fit_factor(math.hypot(ga.rms, gb.rms) / math.sqrt(2), prof.sigma)
            * _range_factor(included, lo, hi, max(0.1 * (hi - lo), 2.0))
        )
        out.append(
            _Candidate(
                score,
                v,
                bis,
                included,
                math.nan,
                "",
                math.hypot(ga.rms, gb.rms) / math.sqrt(2),
                ((np.asarray(ga.point), na), (np.asarray(gb.point), nb)),
            )
        )
    return out


def _step_candidates(prof: Profile, model: EdgeModel) -> list[_Candidate]:
    out: list[_Candidate] = []
    for iu in range(len(prof.faces)):
        for step in (1, -1):
            cand = _step_candidate(prof, model, iu, step)
            if cand is not None:
                out.append(cand)
    return out


def _step_candidate(prof: Profile, model: EdgeModel, iu: int, step: int) -> _Candidate | None:
    """The step (or lap joint) whose upper face is face ``iu``, dropping in direction ``step``
    (+1: towards the later points), or None where that placement does not fit."""
    up = prof.faces[iu]
    end = up.b if step > 0 else up.a
    lu = _face_line(prof, up, end, model)
    if lu is None:
        return None
    gu, wu = lu
    nu = towards_sensor(np.asarray(gu.normal), prof.point(end))
    # The candidate continues with a wall and/or a lower face, or nothing.
    below = _faces_below(prof, iu, step, gu, nu)
    if below is None:
        return None
    wall, lower = below
    top = _upper_corner(prof, model, gu, wall, end, step)
    if top is None:
        return None
    corner, wall_line, wall_angle = top
    low = _lower_face(prof, model, gu, lower, wall, end, step, corner)
    if low is None:
        return None
    gl, height, face_ang, lower_factor = low
    if model.kind == "lap_joint":
        assert gl is not None
        if wall_line is not None:
            root = intersect(wall_line, gl)
            if root is None:
                return None
            point = root
        else:
            point = np.asarray(gl.project(corner))
        normal = towards_sensor(np.asarray(gl.normal), point)
    else:
        point = corner
        normal = nu
    lo, hi = model.height_m
    side = "left" if step > 0 else "right"
    side_ok = model.side in ("any", side)
    rmss = [gu.rms] + ([gl.rms] if gl is not None else [])
    rms = float(np.sqrt(np.mean(np.square(rmss))))
    score = (
        _support(wu, model)
        * lower_factor
        * _fit_factor(rms, prof.sigma)
        * _ratio_factor(height, lo, hi)
        * _range_factor(face_ang, 0.0, model.face_angle_deg, 10.0)
        * (1.0 if side_ok else 0.0)
    )
    faces_out: list[tuple[FloatArray, FloatArray]] = [(np.asarray(gu.point), nu)]
    if gl is not None:
        faces_out.append((np.asarray(gl.point), towards_sensor(np.asarray(gl.normal), point)))
    return _Candidate(
        score,
        np.asarray(point, dtype=np.float64),
        normal,
        wall_angle,
        height,
        side,
        rms,
        tuple(faces_out),
    )


def _faces_below(
    prof: Profile, iu: int, step: int, gu: HyperplaneFit, nu: FloatArray
) -> tuple[Face | None, Face | None] | None:
    """The wall and the lower face that follow the upper face ``iu`` in direction ``step``
    (either may be missing); None when the next face rises (not the top of a step)."""
    faces = prof.faces
    n_faces = len(faces)
    up = faces[iu]
    j = iu + step
    wall: Face | None = None
    lower: Face | None = None
    if 0 <= j < n_faces:
        f = faces[j]
        ang = math.degrees(angle_between_dirs(f.direction, up.direction))
        far_end = f.b if step > 0 else f.a
        deeper = float(gu.distance(prof.point(far_end))) * float(np.sign(-nu @ gu.normal))
        if deeper <= 0:
            return None  # the next face rises: not the top of a step
        if ang >= _WALL_MIN_DEG:
            wall = f
            k = j + step
            if 0 <= k < n_faces:
                lower = faces[k]
        else:
            lower = f
    return wall, lower


def _upper_corner(
    prof: Profile, model: EdgeModel, gu: HyperplaneFit, wall: Face | None, end: int, step: int
) -> tuple[FloatArray, HyperplaneFit | None, float] | None:
    """The upper corner of a step: on the wall's line when the wall is seen (with the angle
    between wall and upper face), else on the upper line halfway to the next sensor point.
    Returns (corner, wall line or None, wall angle in degrees or NaN), None if there is none."""
    wall_line = None
    if wall is not None:
        lw = _face_line(prof, wall, wall.a if step > 0 else wall.b, model)
        if lw is None:
            return None
        wall_line = lw[0]
    if wall_line is not None:
        corner = intersect(gu, wall_line)
        if corner is None:
            return None
        wall_angle = 180.0 - math.degrees(
            angle_between_dirs(
                np.array([gu.normal[1], -gu.normal[0]]),
                np.array([wall_line.normal[1], -wall_line.normal[0]]),
            )
        )
        return corner, wall_line, wall_angle
    ym = next_sensor_point_y(prof, end, step)
    # Upper line at the ray halfway to the next point (parallel rays along +z).
    n = gu.normal
    if abs(float(n[1])) < 1e-6:
        return None
    return np.array([ym, (gu.offset - n[0] * ym) / n[1]]), None, math.nan


def _lower_face(
    prof: Profile,
    model: EdgeModel,
    gu: HyperplaneFit,
    lower: Face | None,
    wall: Face | None,
    end: int,
    step: int,
    corner: FloatArray,
) -> tuple[HyperplaneFit | None, float, float, float] | None:
    """The lower face's line below ``corner`` (None for an open step: nothing valid beyond the
    upper face or its wall for a while), the step height (NaN when open), the angle between
    the faces (degrees) and the lower face's support factor; None where that does not fit."""
    if lower is not None:
        ll = _face_line(prof, lower, lower.a if step > 0 else lower.b, model)
        if ll is None:
            return None
        gl, wl = ll
        nl = towards_sensor(np.asarray(gl.normal), corner)
        height = abs(float(gl.distance(corner)))
        if float(gl.distance(corner)) * float(np.sign(nl @ gl.normal)) <= 0:
            return None  # the "lower" face is nearer: not a step down
        face_ang = math.degrees(angle_between_dirs(gu.normal, gl.normal))
        return gl, height, face_ang, _support(wl, model)
    if not (model.kind == "step" and model.allow_open):
        return None
    # Open step: nothing valid beyond the upper face (or its wall) for a while.
    last = (wall.b if step > 0 else wall.a) if wall is not None else end
    o = int(prof.orig[last])
    beyond = prof.n_all - 1 - o if step > 0 else o
    n_valid_beyond = prof.Y.shape[0] - 1 - last if step > 0 else last  # cleaned points past it
    if beyond < 2 * model.min_face_points or n_valid_beyond > model.min_face_points:
        return None
    return None, math.nan, 0.0, 1.0


def detect_edge(
    y: ArrayLike,
    z: ArrayLike,
    valid: ArrayLike | None,
    model: EdgeModel,
    *,
    prior_y: float | None = None,
) -> EdgeDetection:
    """Find ``model``'s edge in one profile (see the module doc).

    ``y``, ``z`` ``(N,)`` sensor-frame coordinates (m) in the sensor's point order (NaN or
    ``valid`` False where nothing was measured); ``prior_y`` the lateral position where the edge
    is expected (tracking). Always returns an :class:`EdgeDetection`; ``found`` is False (with a
    ``reason``) when no candidate reaches ``model.min_confidence``.
    """
    ya = np.asarray(y, dtype=np.float64).reshape(-1)
    za = np.asarray(z, dtype=np.float64).reshape(-1)
    if ya.shape != za.shape:
        raise ValueError("y and z must have the same length")
    va = np.ones(ya.shape, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    if va.shape != ya.shape:
        raise ValueError("valid must have the length of y")
    prof = segment_profile(ya, za, va, model.min_face_points, model.merge_deg)
    if prof is None:
        return EdgeDetection.none(model.kind, _NOT_FOUND_REASON_NO_POINTS)
    if model.kind in ("v_groove", "outer_corner"):
        cands = _corner_candidates(prof, model)
    else:
        cands = _step_candidates(prof, model)
    cands = [c for c in cands if c.score > 0]
    if not cands:
        return EdgeDetection.none(
            model.kind, f"no {model.kind} in the profile's {len(prof.faces)} faces", prof.sigma
        )
    if prior_y is not None:
        ranked = [
            c.score * math.exp(-0.5 * ((float(c.point[0]) - prior_y) / model.prior_sigma_m) ** 2)
            for c in cands
        ]
    else:
        ranked = [c.score for c in cands]
    order = np.argsort(ranked)[::-1]
    best = cands[int(order[0])]
    r1 = ranked[int(order[0])]
    ratio = 0.0
    if len(order) > 1 and r1 > 0:
        second = cands[int(order[1])]
        # Two placements of the same edge (a face split in two) are not an ambiguity.
        if float(np.hypot(*(second.point - best.point))) > 0.5e-3:
            ratio = ranked[int(order[1])] / r1
    confidence = float(best.score * (1.0 - 0.5 * ratio * ratio))
    found = confidence >= model.min_confidence
    return EdgeDetection(
        found=found,
        point=best.point,
        normal=best.normal,
        confidence=confidence,
        kind=model.kind,
        angle_deg=best.angle_deg,
        height_m=best.height_m,
        side=best.side,
        rms_m=best.rms,
        noise_m=prof.sigma,
        faces=best.faces,
        reason="" if found else f"confidence {confidence:.2f} below {model.min_confidence:.2f}",
    )
