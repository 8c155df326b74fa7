"""One laser profile cut into faces, for the edge models (:mod:`wristscan.calib.edge`).

Profiles are in the sensor frame: points ``(y, z)`` of the laser plane, ``+z`` away from the
sensor. Valid points in profile order; isolated spikes (off a 5-point running median by more
than ``8 sigma``, sigma from the MAD of second differences) are dropped. Douglas-Peucker splits
the profile into straight pieces (tolerance from the noise); pieces of at least
``min_face_points`` points are faces, shorter ones (jumps, gaps, rounded corners) transitions;
neighbouring faces that turn by less than ``merge_deg`` are merged (gently curved surfaces),
and the ends of the faces are adjusted to the points that lie on their lines.

Face lines are robust line fits (:func:`wristscan.calib.plane.fit_hyperplane`, Tukey) on a
face's points near a corner, with the geometry of lines in the laser plane that the edge models
build on (intersections, normals turned towards the sensor).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import median_filter, uniform_filter1d

from wristscan.calib.plane import HyperplaneFit, fit_hyperplane

__all__ = [
    "Face",
    "Profile",
    "angle_between_dirs",
    "face_line",
    "intersect",
    "next_sensor_point_y",
    "segment_profile",
    "towards_sensor",
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

_MAD_TO_SIGMA = 1.482602218505602
_SPIKE_SIGMAS = 8.0
_DP_SIGMAS = 5.0
_DP_MIN_TOL_M = 50e-6
_MAX_PIECES = 64
_LOCAL = 15  # points of the local line at a face's end


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
class Face:
    """A straight (or gently curved) run of the cleaned profile's points."""

    a: int
    """First point (index into the cleaned profile)."""
    b: int
    """Last point (inclusive)."""
    direction: FloatArray
    """Unit principal direction of its points, along the profile order."""


@dataclass
class Profile:
    """A cleaned profile, its noise level and its faces; face lines are cached per profile."""

    Y: FloatArray
    Z: FloatArray
    orig: NDArray[np.int64]
    """Index of each cleaned point in the sensor's point array."""
    y_all: FloatArray
    n_all: int
    sigma: float
    faces: list[Face] = field(default_factory=list)
    lines: dict[tuple[int, int, int], tuple[HyperplaneFit, float] | None] = field(
        default_factory=dict
    )

    def pts(self, a: int, b: int) -> FloatArray:
        return np.column_stack([self.Y[a : b + 1], self.Z[a : b + 1]])

    def point(self, i: int) -> FloatArray:
        return np.array([self.Y[i], self.Z[i]])


def angle_between_dirs(u: FloatArray, v: FloatArray) -> float:
    """Angle (rad, 0..pi/2) between two undirected directions."""
    c = abs(float(u @ v))
    return math.acos(min(1.0, c))


def _principal(Q: FloatArray) -> FloatArray:
    """Unit direction of the points' principal axis, oriented along the profile order."""
    _, _, vt = np.linalg.svd(Q - Q.mean(axis=0), full_matrices=False)
    d = vt[0]
    return np.asarray(d if float(d @ (Q[-1] - Q[0])) >= 0 else -d)


def _grow(
    P: FloatArray, faces: list[Face], breaks: NDArray[np.int64], tol: float, min_points: int
) -> list[Face]:
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

    out = [Face(f.a, f.b, f.direction) for f in faces]
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


def segment_profile(
    y: FloatArray, z: FloatArray, valid: BoolArray, min_face_points: int, merge_deg: float
) -> Profile | None:
    """The profile ``(y, z)`` (sensor order, ``valid`` where measured) cleaned and cut into
    faces of at least ``min_face_points`` points (see the module doc); None with too few valid
    points."""
    idx = np.flatnonzero(valid & np.isfinite(y) & np.isfinite(z))
    if idx.size < 2 * min_face_points:
        return None
    Y, Z = y[idx], z[idx]
    sigma = _noise_sigma(Z)
    med = median_filter(Z, size=5, mode="nearest")
    keep = np.abs(Z - med) <= max(_SPIKE_SIGMAS * sigma, 30e-6)
    idx, Y, Z = idx[keep], Y[keep], Z[keep]
    if idx.size < 2 * min_face_points:
        return None
    prof = Profile(Y, Z, idx, y, int(y.shape[0]), max(sigma, 1e-7))
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
    faces: list[Face] = []
    for a, b in pieces:
        n_pts = b - a + 1
        if n_pts < min_face_points:
            continue
        d = _principal(P[a : b + 1])
        if (
            faces
            and faces[-1].b == a
            and math.degrees(angle_between_dirs(faces[-1].direction, d)) < merge_deg
        ):
            prev = faces[-1]
            faces[-1] = Face(prev.a, b, _principal(P[prev.a : b + 1]))
        else:
            faces.append(Face(a, b, d))
    prof.faces = _grow(P, faces, breaks, tol, min_face_points)
    return prof


# --------------------------------------------------------------------------------------------
# Face lines


def face_line(
    prof: Profile, face: Face, corner_end: int, window_m: float, skip_m: float
) -> tuple[HyperplaneFit, float] | None:
    """Robust line on the face's points near its ``corner_end`` (face.a or face.b): within
    ``window_m`` of it, leaving out ``skip_m`` at the corner; returns the fit and the width of
    the points used (cached per profile)."""
    key = (face.a, face.b, corner_end)
    if key not in prof.lines:
        prof.lines[key] = _fit_face_line(prof, face, corner_end, window_m, skip_m)
    return prof.lines[key]


def _fit_face_line(
    prof: Profile, face: Face, corner_end: int, window_m: float, skip_m: float
) -> tuple[HyperplaneFit, float] | None:
    P = prof.pts(face.a, face.b)
    c = prof.point(corner_end)
    dist = np.hypot(P[:, 0] - c[0], P[:, 1] - c[1])
    sel = (dist <= window_m) & (dist >= skip_m)
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


def towards_sensor(n: FloatArray, at: FloatArray) -> FloatArray:
    """Orient a 2D normal back towards the sensor (negative z; the sensor origin side)."""
    s = float(n[1]) if abs(float(n[1])) > 1e-12 else -float(n @ at)
    return np.asarray(-n if s > 0 else n)


def intersect(f1: HyperplaneFit, f2: HyperplaneFit) -> FloatArray | None:
    A = np.vstack([f1.normal, f2.normal])
    if abs(float(np.linalg.det(A))) < 1e-6:
        return None
    return np.asarray(np.linalg.solve(A, np.array([f1.offset, f2.offset])))


def next_sensor_point_y(prof: Profile, i: int, step: int) -> float:
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
