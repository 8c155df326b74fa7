"""Edge models found in one laser profile, and 3D edge paths smoothed and resampled at a
resolution (Borangiu et al. 2009, section 5: "the user teaches the edge model into the vision
software ... the robot learns the trajectory with a resolution specified by the user").

Profiles are in the sensor frame: points ``(y, z)`` of the laser plane, ``+z`` away from the
sensor (DESIGN.md). Metres and radians throughout.

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

Paths (:func:`smooth_path`)
---------------------------
Raw edge points (one per profile, in acquisition order) are parametrised by arc length,
smoothed by local quadratic regression (Gaussian kernel of ``bandwidth_m``), re-parametrised on
the smoothed curve and resampled at exactly ``resolution_m``. The local quadratic follows
curvature without the shrinkage of a moving average. Normals measured in the laser plane miss
their component along the sensor's X axis; given that axis per point, they are completed with
the condition that the surface normal is perpendicular to the edge tangent.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import median_filter, uniform_filter1d
from scipy.spatial import cKDTree

from wristscan.calib.plane import HyperplaneFit, fit_hyperplane

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
BoolArray = NDArray[np.bool_]
EdgeKind = Literal["step", "lap_joint", "v_groove", "outer_corner"]
EDGE_KINDS: tuple[str, ...] = ("step", "lap_joint", "v_groove", "outer_corner")
Side = Literal["left", "right", "any"]

_MAD_TO_SIGMA = 1.482602218505602
_SPIKE_SIGMAS = 8.0
_DP_SIGMAS = 5.0
_DP_MIN_TOL_M = 50e-6
_MAX_PIECES = 64
_LOCAL = 15  # points of the local line at a face's end
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


# --------------------------------------------------------------------------------------------
# Profile segmentation


def _noise_sigma(z: FloatArray) -> float:
    if z.size < 5:
        return 0.0
    d2 = z[2:] - 2 * z[1:-1] + z[:-2]
    return float(_MAD_TO_SIGMA * np.median(np.abs(d2)) / math.sqrt(6.0))


def _douglas_peucker(P: FloatArray, tol: float) -> list[int]:
    """Vertex indices (first and last included) of the Douglas-Peucker simplification."""
    n = P.shape[0]
    keep = np.zeros(n, dtype=bool)
    keep[0] = keep[-1] = True
    stack = [(0, n - 1)]
    pieces = 1
    while stack and pieces < _MAX_PIECES:
        a, b = stack.pop()
        if b - a < 2:
            continue
        seg = P[b] - P[a]
        L = float(np.hypot(seg[0], seg[1]))
        rel = P[a + 1 : b] - P[a]
        if L > 0:
            dist = np.abs(rel[:, 0] * seg[1] - rel[:, 1] * seg[0]) / L
        else:
            dist = np.hypot(rel[:, 0], rel[:, 1])
        k = int(np.argmax(dist))
        if float(dist[k]) > tol:
            m = a + 1 + k
            keep[m] = True
            pieces += 1
            stack.append((a, m))
            stack.append((m, b))
    return [int(i) for i in np.flatnonzero(keep)]


@dataclass
class _Face:
    a: int
    """First point (index into the cleaned profile)."""
    b: int
    """Last point (inclusive)."""
    direction: FloatArray
    """Unit principal direction of its points, along the profile order."""


@dataclass
class _Profile:
    Y: FloatArray
    Z: FloatArray
    orig: NDArray[np.int64]
    """Index of each cleaned point in the sensor's point array."""
    y_all: FloatArray
    n_all: int
    sigma: float
    faces: list[_Face] = field(default_factory=list)
    lines: dict[tuple[int, int, int], tuple[HyperplaneFit, float] | None] = field(
        default_factory=dict
    )

    def pts(self, a: int, b: int) -> FloatArray:
        return np.column_stack([self.Y[a : b + 1], self.Z[a : b + 1]])

    def point(self, i: int) -> FloatArray:
        return np.array([self.Y[i], self.Z[i]])


def _unit(v: FloatArray) -> FloatArray:
    return np.asarray(v / np.linalg.norm(v))


def _angle_between_dirs(u: FloatArray, v: FloatArray) -> float:
    """Angle (rad, 0..pi/2) between two undirected directions."""
    c = abs(float(u @ v))
    return math.acos(min(1.0, c))


def _principal(Q: FloatArray) -> FloatArray:
    """Unit direction of the points' principal axis, oriented along the profile order."""
    _, _, vt = np.linalg.svd(Q - Q.mean(axis=0), full_matrices=False)
    d = vt[0]
    return np.asarray(d if float(d @ (Q[-1] - Q[0])) >= 0 else -d)


def _grow(
    P: FloatArray, faces: list[_Face], breaks: NDArray[np.int64], tol: float, min_points: int
) -> list[_Face]:
    """Adjust the ends of the faces: trim end points off the line of the points next to them
    (the Douglas-Peucker vertex shared with the neighbouring face may lie on that face, across
    a jump), drop what is left too short (a jump, not a face), then extend each face over the
    neighbouring points within ``tol`` of the line of its end (short pieces left at corners,
    holes of the spike filter at sharp vertices). Lines are local (``_LOCAL`` points), so
    gently curved faces keep their ends."""
    if not faces:
        return faces
    n = P.shape[0]
    cuts = np.concatenate([[0], breaks, [n]])

    def line(a: int, b: int) -> tuple[FloatArray, FloatArray]:
        Q = P[a : b + 1]
        c = Q.mean(axis=0)
        _, _, vt = np.linalg.svd(Q - c, full_matrices=False)
        return c, vt[1]

    def off(i: int, ln: tuple[FloatArray, FloatArray]) -> float:
        return abs(float((P[i] - ln[0]) @ ln[1]))

    out = [_Face(f.a, f.b, f.direction) for f in faces]
    for f in out:
        while f.b - f.a > 3 and off(f.b, line(max(f.a, f.b - _LOCAL), f.b - 1)) > tol:
            f.b -= 1
        while f.b - f.a > 3 and off(f.a, line(f.a + 1, min(f.b, f.a + _LOCAL))) > tol:
            f.a += 1
    out = [f for f in out if f.b - f.a + 1 >= min_points]
    for i, f in enumerate(out):
        run = int(np.searchsorted(cuts, f.a, side="right")) - 1
        lo_run, hi_run = int(cuts[run]), int(cuts[run + 1]) - 1
        hi = min(hi_run, out[i + 1].a - 1 if i + 1 < len(out) else n - 1)
        lo = max(lo_run, out[i - 1].b + 1 if i > 0 else 0)
        if hi > f.b:
            c, normal = line(max(f.a, f.b - _LOCAL + 1), f.b)
            d = np.abs((P[f.b + 1 : hi + 1] - c) @ normal)
            bad = np.flatnonzero(d > tol)
            f.b = f.b + (int(bad[0]) if bad.size else hi - f.b)
        if lo < f.a:
            c, normal = line(f.a, min(f.b, f.a + _LOCAL - 1))
            d = np.abs((P[lo : f.a][::-1] - c) @ normal)
            bad = np.flatnonzero(d > tol)
            f.a = f.a - (int(bad[0]) if bad.size else f.a - lo)
        f.direction = _principal(P[f.a : f.b + 1])
    return out


def _segment(y: FloatArray, z: FloatArray, valid: BoolArray, model: EdgeModel) -> _Profile | None:
    idx = np.flatnonzero(valid & np.isfinite(y) & np.isfinite(z))
    if idx.size < 2 * model.min_face_points:
        return None
    Y, Z = y[idx], z[idx]
    sigma = _noise_sigma(Z)
    med = median_filter(Z, size=5, mode="nearest")
    keep = np.abs(Z - med) <= max(_SPIKE_SIGMAS * sigma, 30e-6)
    idx, Y, Z = idx[keep], Y[keep], Z[keep]
    if idx.size < 2 * model.min_face_points:
        return None
    prof = _Profile(Y, Z, idx, y, int(y.shape[0]), max(sigma, 1e-7))
    P = np.column_stack([Y, Z])
    tol = max(_DP_SIGMAS * sigma, _DP_MIN_TOL_M)
    # A run of invalid points (shadow, out of range) always separates pieces. Douglas-Peucker
    # runs on a lightly smoothed copy so that noise alone never splits a face.
    breaks = np.flatnonzero(np.diff(idx) > 2) + 1
    pieces: list[tuple[int, int]] = []
    for r0, r1 in itertools.pairwise([0, *breaks.tolist(), idx.size]):
        if r1 - r0 < 2:
            continue
        Ps = np.column_stack([Y[r0:r1], uniform_filter1d(Z[r0:r1], 5, mode="nearest")])
        verts = _douglas_peucker(Ps, tol)
        pieces.extend((r0 + a, r0 + b) for a, b in itertools.pairwise(verts))
    faces: list[_Face] = []
    for a, b in pieces:
        n_pts = b - a + 1
        if n_pts < model.min_face_points:
            continue
        d = _principal(P[a : b + 1])
        if (
            faces
            and faces[-1].b == a
            and math.degrees(_angle_between_dirs(faces[-1].direction, d)) < model.merge_deg
        ):
            prev = faces[-1]
            faces[-1] = _Face(prev.a, b, _principal(P[prev.a : b + 1]))
        else:
            faces.append(_Face(a, b, d))
    prof.faces = _grow(P, faces, breaks, tol, model.min_face_points)
    return prof


# --------------------------------------------------------------------------------------------
# Face lines and candidates


def _face_line(
    prof: _Profile, face: _Face, corner_end: int, model: EdgeModel
) -> tuple[HyperplaneFit, float] | None:
    """Robust line on the face's points near its ``corner_end`` (face.a or face.b); returns the
    fit and the width of the points used (cached per profile)."""
    key = (face.a, face.b, corner_end)
    if key not in prof.lines:
        prof.lines[key] = _fit_face_line(prof, face, corner_end, model)
    return prof.lines[key]


def _fit_face_line(
    prof: _Profile, face: _Face, corner_end: int, model: EdgeModel
) -> tuple[HyperplaneFit, float] | None:
    P = prof.pts(face.a, face.b)
    c = prof.point(corner_end)
    dist = np.hypot(P[:, 0] - c[0], P[:, 1] - c[1])
    sel = (dist <= model.window_m) & (dist >= model.skip_m)
    if np.count_nonzero(sel) < 4:
        sel = dist > 0
        if np.count_nonzero(sel) < 3:
            return None
    Q = P[sel]
    normal0 = np.array([-face.direction[1], face.direction[0]])
    try:
        fit = fit_hyperplane(
            Q,
            "tukey",
            init=(normal0, Q.mean(axis=0)),
            max_iter=12,
            tol=1e-7,
            min_scale=0.25 * prof.sigma,
        )
    except ValueError:
        return None
    along = Q @ np.array([fit.normal[1], -fit.normal[0]])
    return fit, float(np.ptp(along))


def _towards_sensor(n: FloatArray, at: FloatArray) -> FloatArray:
    """Orient a 2D normal back towards the sensor (negative z; the sensor origin side)."""
    s = float(n[1]) if abs(float(n[1])) > 1e-12 else -float(n @ at)
    return np.asarray(-n if s > 0 else n)


def _intersect(f1: HyperplaneFit, f2: HyperplaneFit) -> FloatArray | None:
    A = np.vstack([f1.normal, f2.normal])
    if abs(float(np.linalg.det(A))) < 1e-6:
        return None
    return np.asarray(np.linalg.solve(A, np.array([f1.offset, f2.offset])))


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


def _corner_candidates(prof: _Profile, model: EdgeModel) -> list[_Candidate]:
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
        v = _intersect(ga, gb)
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
        na = _towards_sensor(np.asarray(ga.normal), v)
        nb = _towards_sensor(np.asarray(gb.normal), v)
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


def _next_sensor_point_y(prof: _Profile, i: int, step: int) -> float:
    """Lateral position halfway between cleaned point ``i`` and the next sensor point (valid or
    not) in direction ``step``; the next valid point when invalid points carry no ``y``."""
    j = int(prof.orig[i]) + step
    yi = float(prof.Y[i])
    if 0 <= j < prof.n_all and math.isfinite(float(prof.y_all[j])):
        return 0.5 * (yi + float(prof.y_all[j]))
    k = i + step
    if 0 <= k < prof.Y.shape[0]:
        return 0.5 * (yi + float(prof.Y[k]))
    return yi


def _step_candidates(prof: _Profile, model: EdgeModel) -> list[_Candidate]:
    out: list[_Candidate] = []
    faces = prof.faces
    n_faces = len(faces)
    lo, hi = model.height_m
    for iu in range(n_faces):
        for step in (1, -1):
            up = faces[iu]
            end = up.b if step > 0 else up.a
            lu = _face_line(prof, up, end, model)
            if lu is None:
                continue
            gu, wu = lu
            nu = _towards_sensor(np.asarray(gu.normal), prof.point(end))
            # The candidate continues with a wall and/or a lower face, or nothing.
            j = iu + step
            wall: _Face | None = None
            lower: _Face | None = None
            if 0 <= j < n_faces:
                f = faces[j]
                ang = math.degrees(_angle_between_dirs(f.direction, up.direction))
                far_end = f.b if step > 0 else f.a
                deeper = float(gu.distance(prof.point(far_end))) * float(np.sign(-nu @ gu.normal))
                if deeper <= 0:
                    continue  # the next face rises: not the top of a step
                if ang >= _WALL_MIN_DEG:
                    wall = f
                    k = j + step
                    if 0 <= k < n_faces:
                        lower = faces[k]
                else:
                    lower = f
            wall_line = None
            if wall is not None:
                lw = _face_line(prof, wall, wall.a if step > 0 else wall.b, model)
                if lw is None:
                    continue
                wall_line = lw[0]
            if wall_line is not None:
                corner = _intersect(gu, wall_line)
                if corner is None:
                    continue
                wall_angle = 180.0 - math.degrees(
                    _angle_between_dirs(
                        np.array([gu.normal[1], -gu.normal[0]]),
                        np.array([wall_line.normal[1], -wall_line.normal[0]]),
                    )
                )
            else:
                ym = _next_sensor_point_y(prof, end, step)
                # Upper line at the ray halfway to the next point (parallel rays along +z).
                n = gu.normal
                if abs(float(n[1])) < 1e-6:
                    continue
                corner = np.array([ym, (gu.offset - n[0] * ym) / n[1]])
                wall_angle = math.nan
            gl = None
            wl = 0.0
            if lower is not None:
                ll = _face_line(prof, lower, lower.a if step > 0 else lower.b, model)
                if ll is None:
                    continue
                gl, wl = ll
            if gl is None:
                if not (model.kind == "step" and model.allow_open):
                    continue
                # Open step: nothing valid beyond the upper face (or its wall) for a while.
                last = (wall.b if step > 0 else wall.a) if wall is not None else end
                o = int(prof.orig[last])
                beyond = prof.n_all - 1 - o if step > 0 else o
                n_valid_beyond = (
                    prof.Y.shape[0] - 1 - last if step > 0 else last
                )  # cleaned points past it
                if beyond < 2 * model.min_face_points or n_valid_beyond > model.min_face_points:
                    continue
                height = math.nan
                face_ang = 0.0
                lower_factor = 1.0
            else:
                nl = _towards_sensor(np.asarray(gl.normal), corner)
                height = abs(float(gl.distance(corner)))
                if float(gl.distance(corner)) * float(np.sign(nl @ gl.normal)) <= 0:
                    continue  # the "lower" face is nearer: not a step down
                face_ang = math.degrees(_angle_between_dirs(gu.normal, gl.normal))
                lower_factor = _support(wl, model)
            if model.kind == "lap_joint":
                assert gl is not None
                if wall_line is not None:
                    root = _intersect(wall_line, gl)
                    if root is None:
                        continue
                    point = root
                else:
                    point = np.asarray(gl.project(corner))
                normal = _towards_sensor(np.asarray(gl.normal), point)
            else:
                point = corner
                normal = nu
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
                faces_out.append(
                    (np.asarray(gl.point), _towards_sensor(np.asarray(gl.normal), point))
                )
            out.append(
                _Candidate(
                    score,
                    np.asarray(point, dtype=np.float64),
                    normal,
                    wall_angle,
                    height,
                    side,
                    rms,
                    tuple(faces_out),
                )
            )
    return out


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
    prof = _segment(ya, za, va, model)
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


# --------------------------------------------------------------------------------------------
# Paths


@dataclass(frozen=True, eq=False)
class EdgePath:
    """An edge path resampled at a constant spacing (base frame, metres)."""

    points: FloatArray
    """(K, 3) points spaced ``resolution_m`` along the smoothed curve."""
    tangents: FloatArray
    """(K, 3) unit tangents in the direction of travel."""
    normals: FloatArray
    """(K, 3) unit surface normals, perpendicular to the tangents (zeros when not given)."""
    s: FloatArray
    """(K,) arc length from the first point (m)."""
    resolution_m: float
    support: FloatArray
    """(K,) raw points within half a spacing of each station."""
    residual_rms_m: float
    """RMS distance of the raw points to the smoothed curve."""
    max_gap_m: float
    """Largest arc-length gap between consecutive raw points (m): the path has no hole wider."""

    @property
    def length_m(self) -> float:
        return float(self.s[-1]) if self.s.size else 0.0


def _loess(
    s: FloatArray,
    values: FloatArray,
    stations: FloatArray,
    h: float,
    weights: FloatArray,
    degree: int = 2,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Local polynomial regression of ``values (N, m)`` over sorted ``s`` at ``stations``:
    returns values, first derivatives (K, m) and the kernel weight sums (K,)."""
    lo = np.searchsorted(s, stations - 3 * h, side="left")
    hi = np.searchsorted(s, stations + 3 * h, side="right")
    width = int(max(1, (hi - lo).max()))
    K = stations.shape[0]
    m = values.shape[1]
    out = np.full((K, m), np.nan)
    der = np.full((K, m), np.nan)
    wsum = np.zeros(K)
    chunk = max(1, 2_000_000 // width)
    for c0 in range(0, K, chunk):
        c1 = min(K, c0 + chunk)
        idx = lo[c0:c1, None] + np.arange(width)[None, :]
        inside = idx < hi[c0:c1, None]
        idx = np.minimum(idx, s.shape[0] - 1)
        d = (s[idx] - stations[c0:c1, None]) / h
        w = np.where(inside, np.exp(-0.5 * d * d), 0.0) * weights[idx]
        cols = [np.ones_like(d), d, d * d][: degree + 1]
        X = np.stack(cols, axis=-1)  # (k, W, p)
        XtW = X * w[..., None]
        A = np.einsum("kwp,kwq->kpq", XtW, X)
        B = np.einsum("kwp,kwm->kpm", XtW, values[idx])
        p = degree + 1
        ridge = 1e-9 * np.maximum(np.trace(A, axis1=1, axis2=2), 1e-300)
        A = A + ridge[:, None, None] * np.eye(p)
        coef = np.linalg.solve(A, B)  # (k, p, m)
        out[c0:c1] = coef[:, 0, :]
        der[c0:c1] = coef[:, 1, :] / h
        wsum[c0:c1] = w.sum(axis=1)
    return out, der, wsum


def _arc(points: FloatArray) -> FloatArray:
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)])


def _project_on_polyline(poly: FloatArray, s_poly: FloatArray, P: FloatArray) -> FloatArray:
    """Arc-length parameter of the nearest point of ``poly`` to each of ``P``."""
    tree = cKDTree(poly)
    _, j = tree.query(P)
    j = np.asarray(j, dtype=np.int64)
    # Refine on the two neighbouring segments.
    best_s = s_poly[j].astype(np.float64)
    best_d = np.linalg.norm(P - poly[j], axis=1)
    for k0 in (j - 1, j):
        k0 = np.clip(k0, 0, poly.shape[0] - 2)
        a, b = poly[k0], poly[k0 + 1]
        ab = b - a
        L2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
        t = np.clip(np.einsum("ij,ij->i", P - a, ab) / L2, 0.0, 1.0)
        q = a + t[:, None] * ab
        dist = np.linalg.norm(P - q, axis=1)
        better = dist < best_d
        best_d = np.where(better, dist, best_d)
        best_s = np.where(better, s_poly[k0] + t * np.sqrt(L2), best_s)
    return np.asarray(best_s)


def smooth_path(
    points: ArrayLike,
    resolution_m: float = 0.001,
    *,
    bandwidth_m: float | None = None,
    normals: ArrayLike | None = None,
    view_x: ArrayLike | None = None,
    weights: ArrayLike | None = None,
) -> EdgePath:
    """Smooth raw edge points ``(N, 3)`` given in acquisition order and resample them every
    ``resolution_m`` along the curve (see the module doc).

    ``bandwidth_m``: kernel width (default: the resolution, at least 0.5 mm). ``normals
    (N, 3)``: measured surface normals (laser-plane projections when ``view_x (N, 3)``, the
    sensor X axis per point, is given: they are completed to be perpendicular to the edge).
    ``weights (N,)``: confidence per point. Raises ValueError with fewer than 5 points or a path
    shorter than one resolution step.
    """
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {P.shape}")
    if P.shape[0] < 5:
        raise ValueError("a path needs at least 5 points")
    if not resolution_m > 0:
        raise ValueError("resolution_m must be positive")
    n = P.shape[0]
    W = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64).reshape(n)
    h = float(bandwidth_m) if bandwidth_m is not None else max(float(resolution_m), 0.0005)
    # 1. A first parameter: arc length of a running mean in acquisition order.
    k = int(min(15, max(1, n // 5)))
    kernel = np.ones(k) / k
    pad = np.pad(P, ((k // 2, k - 1 - k // 2), (0, 0)), mode="edge")
    Q = np.column_stack([np.convolve(pad[:, i], kernel, mode="valid") for i in range(3)])
    s0 = _arc(Q)
    if s0[-1] < resolution_m:
        raise ValueError(f"the path is only {s0[-1] * 1e3:.2f} mm long")
    order = np.argsort(s0, kind="stable")
    s0, P0, W0 = s0[order], P[order], W[order]
    # 2. A first smooth curve, densely sampled.
    dense_step = min(h, float(resolution_m)) / 4
    st0 = np.arange(s0[0], s0[-1] + 1e-12, dense_step)
    C1, _, _ = _loess(s0, P0, st0, h, W0)
    ok = np.all(np.isfinite(C1), axis=1)
    C1 = C1[ok]
    s_c1 = _arc(C1)
    # 3. Parameter = arc length of the nearest point on it; resample at the resolution.
    s1 = _project_on_polyline(C1, s_c1, P)
    order = np.argsort(s1, kind="stable")
    s1s = s1[order]
    Ps, Ws = P[order], W[order]
    # Exact spacing on the final curve: re-sample it by its own arc length.
    dense = np.arange(s1s[0], s1s[-1] + 1e-12, dense_step)
    Cd, _, _ = _loess(s1s, Ps, dense, h, Ws)
    s_cd = _arc(Cd)
    targets = np.arange(0.0, s_cd[-1] + 1e-12, float(resolution_m))
    u = np.interp(targets, s_cd, dense)
    pts, der, _ = _loess(s1s, Ps, u, h, Ws)
    tang = der / np.maximum(np.linalg.norm(der, axis=1, keepdims=True), 1e-300)
    nrm = np.zeros_like(pts)
    if normals is not None:
        N = np.asarray(normals, dtype=np.float64).reshape(n, 3)
        if view_x is not None:
            X = np.asarray(view_x, dtype=np.float64).reshape(n, 3)
            # Tangent at each raw point from the curve, then n = n_m + lam X with n . t = 0.
            t_raw = np.column_stack([np.interp(s1, u, tang[:, i]) for i in range(3)])
            xt = np.einsum("ij,ij->i", X, t_raw)
            nt = np.einsum("ij,ij->i", N, t_raw)
            lam = np.where(np.abs(xt) > 0.2, -nt / np.where(np.abs(xt) > 0.2, xt, 1.0), 0.0)
            N = N + lam[:, None] * X
        N = N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-300)
        Ns = N[order]
        nv, _, _ = _loess(s1s, Ns, u, h, Ws, degree=1)
        nv = nv - np.einsum("ij,ij->i", nv, tang)[:, None] * tang
        nrm = nv / np.maximum(np.linalg.norm(nv, axis=1, keepdims=True), 1e-300)
    # Statistics.
    s_final = _arc(pts)
    s_fp = _project_on_polyline(pts, s_final, P) if pts.shape[0] >= 2 else np.zeros(n)
    near = np.column_stack([np.interp(s_fp, s_final, pts[:, i]) for i in range(3)])
    # Points past the last station (less than a spacing) project onto the end: not residuals.
    inside = s_fp < s_final[-1] - 1e-9
    resid = np.linalg.norm(P - near, axis=1)[inside]
    gaps = np.diff(np.sort(s_fp))
    support = np.histogram(
        s_fp, bins=np.concatenate([s_final - resolution_m / 2, [s_final[-1] + resolution_m / 2]])
    )[0].astype(np.float64)
    return EdgePath(
        points=pts,
        tangents=tang,
        normals=nrm,
        s=s_final,
        resolution_m=float(resolution_m),
        support=support,
        residual_rms_m=float(np.sqrt(np.mean(resid**2))) if resid.size else 0.0,
        max_gap_m=float(gaps.max()) if gaps.size else 0.0,
    )
