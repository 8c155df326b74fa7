"""A scene of geometric primitives that the simulated laser is ray-cast against.

Frames
------
* Every primitive has a ``pose`` (``prim2mount``, 4x4) and a ``mount``: ``"base"`` (fixed in the
  robot base frame) or ``"table"`` (carried by the rotary table).
* The rotary table frame at angle ``theta`` is ``table2base(theta) = table_zero2base @ Rz(theta)``:
  its origin lies on the rotation axis and its Z axis is the axis. ``table_zero2base`` is the
  ground truth of the table-axis calibration.
* Primitives are defined in a local frame of their own (see each class) and the rays are moved
  into it, so each intersection routine only handles the canonical shape.

Ray casting returns the distance ``t`` (metres, along unit directions) to the nearest surface with
``t > 0``: every primitive occludes every other one (a union of solids). Surfaces are two-sided.

Speed: the intersection routines are vectorised over rays and broadcast over a leading batch
(profiles x points); :meth:`Scene.raycast_bundles` skips, per profile, the primitives whose
bounding sphere the ray bundle cannot reach, which keeps a tooling-ball scene cheap.

The primitives' common base is in :mod:`.primitives`, triangle meshes (and the STL and PLY files
they come from) in :mod:`.mesh`; here the analytic shapes, the scene and the demo cell.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from wristscan.calib import se3
from wristscan.drivers.sim.mesh import TriangleMesh
from wristscan.drivers.sim.primitives import (
    EPS_T,
    BoolArray,
    FloatArray,
    Mount,
    Primitive,
    Vec3,
    dot3,
    nearest_positive,
)

__all__ = [
    "Box",
    "Cylinder",
    "Plane",
    "Scene",
    "Sphere",
    "demo_scene",
    "sensor_looking_down",
]

log = logging.getLogger(__name__)


class Sphere(Primitive):
    """A sphere of ``radius`` (m) centred on the local origin (``centre`` sets a translation)."""

    def __init__(
        self,
        radius: float,
        centre: ArrayLike | None = None,
        *,
        pose: ArrayLike | None = None,
        mount: Mount = "base",
        name: str = "",
    ) -> None:
        if radius <= 0:
            raise ValueError("sphere radius must be positive")
        if centre is not None:
            if pose is not None:
                raise ValueError("give either centre or pose, not both")
            pose = se3.make(t=np.asarray(centre, dtype=np.float64))
        super().__init__(pose, mount, name)
        self.radius = float(radius)

    @property
    def centre(self) -> FloatArray:
        """Centre in the mount frame (m)."""
        return self.pose[:3, 3].copy()

    def intersect_local(self, o: Vec3, d: Vec3) -> FloatArray:
        b = dot3(o, d)
        c = dot3(o, o) - self.radius * self.radius
        with np.errstate(invalid="ignore"):
            s = np.sqrt(b * b - c)  # NaN on a miss
        return nearest_positive(-b - s, s - b)

    def local_bounds(self) -> tuple[FloatArray, float]:
        return np.zeros(3), self.radius


class Plane(Primitive):
    """The local plane ``z = 0`` (normal +Z); infinite, or the rectangle ``|x| <= sx/2,
    |y| <= sy/2`` when ``size = (sx, sy)`` is given."""

    def __init__(
        self,
        pose: ArrayLike | None = None,
        size: tuple[float, float] | None = None,
        *,
        mount: Mount = "base",
        name: str = "",
    ) -> None:
        super().__init__(pose, mount, name)
        if size is not None and (size[0] <= 0 or size[1] <= 0):
            raise ValueError("plane size must be positive")
        self.size = None if size is None else (float(size[0]), float(size[1]))

    def intersect_local(self, o: Vec3, d: Vec3) -> FloatArray:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -o[2] / d[2]
        if self.size is not None:
            x = o[0] + t * d[0]
            y = o[1] + t * d[1]
            inside = (np.abs(x) <= 0.5 * self.size[0]) & (np.abs(y) <= 0.5 * self.size[1])
            t = np.where(inside, t, np.inf)
        return nearest_positive(t)

    def local_bounds(self) -> tuple[FloatArray, float]:
        if self.size is None:
            return np.zeros(3), np.inf
        return np.zeros(3), 0.5 * float(np.hypot(*self.size))

    def may_hit(self, centres_local: FloatArray, radius: float) -> BoolArray:
        near = np.abs(centres_local[:, 2]) <= radius
        if self.size is None:
            return np.asarray(near)
        return np.asarray(near & super().may_hit(centres_local, radius))


class Box(Primitive):
    """An axis-aligned box of ``size = (sx, sy, sz)`` centred on the local origin."""

    def __init__(
        self,
        size: ArrayLike,
        pose: ArrayLike | None = None,
        *,
        mount: Mount = "base",
        name: str = "",
    ) -> None:
        super().__init__(pose, mount, name)
        s = np.asarray(size, dtype=np.float64)
        if s.shape != (3,) or np.any(s <= 0):
            raise ValueError("box size must be three positive lengths")
        self.half = 0.5 * s

    def intersect_local(self, o: Vec3, d: Vec3) -> FloatArray:
        # Slab method. A zero direction component becomes a tiny one of the same sign, which
        # keeps the arithmetic finite and gives the right inside/outside answer.
        t_near: FloatArray | None = None
        t_far: FloatArray | None = None
        for k in range(3):
            inv = 1.0 / np.where(d[k] == 0.0, 1e-300, d[k])
            t1 = (-self.half[k] - o[k]) * inv
            t2 = (self.half[k] - o[k]) * inv
            lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
            t_near = lo if t_near is None else np.maximum(t_near, lo)
            t_far = hi if t_far is None else np.minimum(t_far, hi)
        assert t_near is not None and t_far is not None
        hit = t_far >= np.maximum(t_near, EPS_T)
        t = np.where(t_near > EPS_T, t_near, t_far)  # from inside: the exit point
        return np.where(hit, t, np.inf)

    def local_bounds(self) -> tuple[FloatArray, float]:
        return np.zeros(3), float(np.linalg.norm(self.half))


class Cylinder(Primitive):
    """A cylinder of ``radius`` along local +Z from ``z = 0`` to ``z = height``; ``capped``
    closes both ends with discs (a solid), otherwise it is an open tube."""

    def __init__(
        self,
        radius: float,
        height: float,
        pose: ArrayLike | None = None,
        *,
        capped: bool = True,
        mount: Mount = "base",
        name: str = "",
    ) -> None:
        super().__init__(pose, mount, name)
        if radius <= 0 or height <= 0:
            raise ValueError("cylinder radius and height must be positive")
        self.radius = float(radius)
        self.height = float(height)
        self.capped = capped

    def intersect_local(self, o: Vec3, d: Vec3) -> FloatArray:
        r2 = self.radius * self.radius
        a = d[0] * d[0] + d[1] * d[1]
        b = o[0] * d[0] + o[1] * d[1]
        c = o[0] * o[0] + o[1] * o[1] - r2
        cands = []
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.sqrt(b * b - a * c)  # NaN on a miss
            for t in ((-b - s) / a, (s - b) / a):
                z = o[2] + t * d[2]
                cands.append(np.where((z >= 0) & (z <= self.height), t, np.inf))
            if self.capped:
                for zc in (0.0, self.height):
                    t = (zc - o[2]) / d[2]
                    x = o[0] + t * d[0]
                    y = o[1] + t * d[1]
                    cands.append(np.where(x * x + y * y <= r2, t, np.inf))
        return nearest_positive(*cands)

    def local_bounds(self) -> tuple[FloatArray, float]:
        return np.array([0.0, 0.0, 0.5 * self.height]), float(
            np.hypot(self.radius, 0.5 * self.height)
        )


# ----------------------------------------------------------------------------------------------
# Scene


class Scene:
    """Primitives in the base frame or on the rotary table, ray-cast together."""

    def __init__(
        self,
        primitives: Sequence[Primitive] = (),
        table_zero2base: ArrayLike | None = None,
    ) -> None:
        self.primitives: list[Primitive] = list(primitives)
        self.table_zero2base: FloatArray = (
            se3.identity()
            if table_zero2base is None
            else se3.check_transform(table_zero2base, "table_zero2base")
        )

    def add(self, primitive: Primitive) -> Primitive:
        self.primitives.append(primitive)
        return primitive

    def find(self, name: str) -> Primitive:
        for p in self.primitives:
            if p.name == name:
                return p
        raise KeyError(name)

    def table2base(self, angle_rad: ArrayLike) -> FloatArray:
        """Pose of the table frame at ``angle_rad`` ``(...)`` in the base frame ``(..., 4, 4)``."""
        return np.asarray(self.table_zero2base @ se3.make(se3.rot_z(angle_rad)))

    def prim2base(self, primitive: Primitive, table_angle_rad: float = 0.0) -> FloatArray:
        """Pose of ``primitive``'s local frame in the base frame (ground truth for tests)."""
        if primitive.mount == "table":
            return np.asarray(self.table2base(table_angle_rad) @ primitive.pose)
        return primitive.pose.copy()

    def raycast(
        self,
        origins: ArrayLike,
        dirs: ArrayLike,
        table_angle_rad: ArrayLike = 0.0,
    ) -> tuple[FloatArray, BoolArray]:
        """Nearest hit of rays given in the base frame.

        ``origins (R, 3)``, ``dirs (R, 3)`` (normalised here), ``table_angle_rad`` a scalar or
        ``(R,)``. Returns ``t (R,)`` (metres along the ray, ``inf`` on a miss) and ``hit (R,)``.
        """
        o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        best = np.full(o.shape[0], np.inf)
        ang = np.asarray(table_angle_rad, dtype=np.float64)
        if any(p.mount == "table" for p in self.primitives):
            base2table = se3.invert(self.table2base(ang))  # (4,4) or (R,4,4)
            if base2table.ndim == 2:
                o_t = o @ base2table[:3, :3].T + base2table[:3, 3]
                d_t = d @ base2table[:3, :3].T
            else:
                o_t = np.einsum("rij,rj->ri", base2table[:, :3, :3], o) + base2table[:, :3, 3]
                d_t = np.einsum("rij,rj->ri", base2table[:, :3, :3], d)
        for p in self.primitives:
            if p.mount == "table":
                t = p.intersect(o_t, d_t)
            else:
                t = p.intersect(o, d)
            best = np.minimum(best, t)
        return best, np.isfinite(best)

    def raycast_bundles(
        self,
        sensor2base: ArrayLike,
        origins_s: ArrayLike,
        dirs_s: ArrayLike,
        table_angle_rad: ArrayLike = 0.0,
        reach_m: float = np.inf,
    ) -> tuple[FloatArray, BoolArray]:
        """Cast the same ray bundle from ``P`` sensor poses at once.

        ``sensor2base (P, 4, 4)``; rays in the sensor frame ``origins_s (N, 3)``, unit
        ``dirs_s (N, 3)``; ``table_angle_rad`` scalar or ``(P,)``. ``reach_m`` bounds the useful
        length of the rays (hits beyond it may be reported as misses): it lets whole primitives
        be skipped per profile. Returns ``t (P, N)`` and ``hit (P, N)``.
        """
        s2b = np.asarray(sensor2base, dtype=np.float64).reshape(-1, 4, 4)
        n_prof = s2b.shape[0]
        o_s = np.asarray(origins_s, dtype=np.float64).reshape(-1, 3)
        d_s = np.asarray(dirs_s, dtype=np.float64).reshape(-1, 3)
        n_rays = o_s.shape[0]
        parallel = bool(np.all(d_s == d_s[0]))
        best = np.full((n_prof, n_rays), np.inf)
        if n_prof == 0 or not self.primitives:
            return best, np.zeros_like(best, dtype=bool)
        # Bounding sphere of the bundle's useful segments, in the sensor frame.
        if np.isfinite(reach_m):
            ends = np.vstack([o_s, o_s + reach_m * d_s])
            c_s = 0.5 * (ends.min(axis=0) + ends.max(axis=0))
            r_s = float(np.linalg.norm(ends - c_s, axis=1).max())
        else:
            c_s, r_s = np.zeros(3), np.inf
        angles = np.broadcast_to(np.asarray(table_angle_rad, dtype=np.float64), (n_prof,))
        o_cols = [j for j in range(3) if np.any(o_s[:, j] != 0)]
        d_cols = [j for j in range(3) if np.any(d_s[:, j] != 0)]
        s2table: FloatArray | None = None
        for prim in self.primitives:
            if prim.mount == "table":
                if s2table is None:
                    s2table = se3.invert(self.table2base(angles)) @ s2b
                s2local = prim.mount2local @ s2table
            else:
                s2local = prim.mount2local @ s2b
            if np.isfinite(r_s):
                keep = prim.may_hit(s2local[:, :3, :3] @ c_s + s2local[:, :3, 3], r_s)
                rows = np.flatnonzero(keep)
                if rows.size == 0:
                    continue
                if rows.size < n_prof:
                    s2local = s2local[rows]
            else:
                rows = np.arange(n_prof)
            R = s2local[:, :3, :3]
            o_l = _rotate_bundle(R, o_s, o_cols, s2local[:, :3, 3])
            if parallel:
                d0 = R @ d_s[0]
                d_l: Vec3 = (d0[:, 0, None], d0[:, 1, None], d0[:, 2, None])
            else:
                d_l = _rotate_bundle(R, d_s, d_cols, None)
            t = prim.intersect_local(o_l, d_l)
            if rows.size == n_prof:
                np.minimum(best, t, out=best)
            else:
                best[rows] = np.minimum(best[rows], t)
        return best, np.isfinite(best)


def _rotate_bundle(
    R: FloatArray, v: FloatArray, cols: list[int], offset: FloatArray | None
) -> Vec3:
    """``R (P, 3, 3) @ v (N, 3) (+ offset (P, 3))`` as three ``(P, N)`` component arrays.

    Sums of broadcast products over the non-zero columns of ``v`` only (a laser line has one),
    several times faster than einsum or a batched matmul with a 3-wide inner dimension.
    """
    comps = []
    for k in range(3):
        acc = np.zeros((R.shape[0], v.shape[0])) if offset is None else None
        for j in cols:
            term = R[:, k, j, None] * v[None, :, j]
            acc = term if acc is None else acc + term
        if offset is not None:
            acc = (
                np.broadcast_to(offset[:, k, None], (R.shape[0], v.shape[0]))
                if acc is None
                else acc + offset[:, k, None]
            )
        assert acc is not None
        comps.append(np.asarray(acc))
    return comps[0], comps[1], comps[2]


# ----------------------------------------------------------------------------------------------
# Demo scene


def sensor_looking_down(target: ArrayLike, standoff_m: float, yaw_rad: float = 0.0) -> FloatArray:
    """A ``sensor2base`` whose +Z points straight down (base -Z) at ``target`` from
    ``standoff_m`` above it; ``yaw_rad`` turns the laser line about the vertical."""
    R = se3.rot_z(yaw_rad) @ se3.rot_x(np.pi)
    p = np.asarray(target, dtype=np.float64) + np.array([0.0, 0.0, standoff_m])
    return se3.make(R, p)


def demo_scene(
    *,
    ball_radius_m: float = 0.0127,
    ball_centre: ArrayLike = (0.45, -0.20, 0.16),
    table_zero2base: ArrayLike | None = None,
    with_part: bool = True,
) -> Scene:
    """The default cell: a table top, a tooling ball on a post, a rotary table carrying a part.

    All within reach of a UR5e standing on the table top (base frame: Z up, table top ``z = 0``)
    with the sensor looking down from 0.1-0.2 m above. Names: ``"table_top"``, ``"ball"``,
    ``"post"``, ``"platter"``, ``"part"``, ``"boss"``, ``"ramp"``.
    """
    c = np.asarray(ball_centre, dtype=np.float64)
    prims: list[Primitive] = [
        Plane(name="table_top"),
        Sphere(ball_radius_m, c, name="ball"),
    ]
    post_top = c[2] - 0.8 * ball_radius_m  # the ball sits on its stem below the equator
    prims.append(Cylinder(0.004, post_top, se3.make(t=(c[0], c[1], 0.0)), name="post"))
    if table_zero2base is None:
        # A rotary table at (0.45, 0.25) whose axis leans 0.2 degrees: a known, non-trivial truth.
        table_zero2base = se3.make(se3.rot_x(np.radians(0.2)), (0.45, 0.25, 0.0))
    if with_part:
        platter_h = 0.03
        prims.append(Cylinder(0.15, platter_h, mount="table", name="platter"))
        top = platter_h
        prims.append(
            Box(
                (0.08, 0.06, 0.04), se3.make(t=(0.02, 0.01, top + 0.02)), mount="table", name="part"
            )
        )
        prims.append(
            Cylinder(0.012, 0.02, se3.make(t=(0.04, 0.01, top + 0.04)), mount="table", name="boss")
        )
        # A 30-degree ramp (a bevel) against the -X face of the box.
        ramp = [(0.0, 0.0), (0.0, 0.04), (-0.04 / np.tan(np.radians(30.0)), 0.0)]
        prims.append(
            TriangleMesh.prism(
                ramp, 0.06, se3.make(t=(-0.02, 0.01, top)), mount="table", name="ramp"
            )
        )
    return Scene(prims, table_zero2base)
