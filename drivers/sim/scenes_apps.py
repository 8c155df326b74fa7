"""Scenes for the applications of the calibrated sensor (Borangiu et al. 2009, section 5): a
tilted plate to teach a plane frame on, and a part with a curved 3D edge to learn a path along.

Both come with their exact ground truth (the plate's top plane; the edge as an analytic curve
with its surface normal), so that benchmarks and tests can score what the procedures find.

:class:`DomeBoss` is a solid of its own with an exact ray intersection, so the simulated sensor
stays as fast as with the basic primitives: a vertical cylinder (radius ``Rc``, from ``z = 0``
up to ``height``) intersected with a ball (centre ``c``, radius ``Rs``) whose cap forms the top.
With the ball's centre off the cylinder's axis the rim (top face meets side wall) is a closed
3D curve whose height and direction vary all the way round, and the top's normal turns along
it: a "curved 3D edge" for path learning. In the cylinder's local frame the rim at azimuth
``phi`` is ``(Rc cos phi, Rc sin phi, cz + sqrt(Rs^2 - (Rc cos phi - cx)^2 - (Rc sin phi -
cy)^2))``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import kinematics, se3
from wristscan.drivers.sim.primitives import Mount, Primitive, Vec3, nearest_positive
from wristscan.drivers.sim.scene import Box, Plane, Scene

__all__ = [
    "DomeBoss",
    "EdgeTruth",
    "PlateTruth",
    "dome_scene",
    "sensor_pose_at_edge",
    "start_q_for_sensor",
    "tilted_plate_scene",
]

FloatArray = NDArray[np.float64]


class DomeBoss(Primitive):
    """Vertical cylinder ``x^2 + y^2 <= radius^2``, ``0 <= z <= height`` (local frame),
    intersected with the ball ``|p - dome_centre| <= dome_radius``: a boss with a domed top."""

    def __init__(
        self,
        radius: float,
        height: float,
        dome_centre: ArrayLike,
        dome_radius: float,
        pose: ArrayLike | None = None,
        *,
        mount: Mount = "base",
        name: str = "dome_boss",
    ) -> None:
        super().__init__(pose, mount, name)
        if radius <= 0 or height <= 0 or dome_radius <= 0:
            raise ValueError("radius, height and dome_radius must be positive")
        self.radius = float(radius)
        self.height = float(height)
        self.dome_centre = np.asarray(dome_centre, dtype=np.float64).reshape(3)
        self.dome_radius = float(dome_radius)
        z = self.rim_local(np.linspace(0, 2 * np.pi, 721))[:, 2]
        if np.any(~np.isfinite(z)) or z.min() <= 0 or z.max() >= self.height:
            raise ValueError("the dome must cut the side wall all round between 0 and height")

    # --- geometry of the rim (local frame) ----------------------------------------------
    def rim_local(self, phi: ArrayLike) -> FloatArray:
        """Rim points ``(..., 3)`` at azimuths ``phi`` (rad)."""
        p = np.asarray(phi, dtype=np.float64)
        x, y = self.radius * np.cos(p), self.radius * np.sin(p)
        c = self.dome_centre
        with np.errstate(invalid="ignore"):
            z = c[2] + np.sqrt(self.dome_radius**2 - (x - c[0]) ** 2 - (y - c[1]) ** 2)
        return np.stack([x, y, z], axis=-1)

    def top_normal_local(self, points: ArrayLike) -> FloatArray:
        """Outward unit normal of the domed top at ``points (..., 3)``."""
        d = np.asarray(points, dtype=np.float64) - self.dome_centre
        return np.asarray(d / np.linalg.norm(d, axis=-1, keepdims=True))

    # --- ray casting --------------------------------------------------------------------
    def intersect_local(self, o: Vec3, d: Vec3) -> FloatArray:
        # Each convex part gives an interval of t; the solid is where all three overlap.
        inf = np.inf
        with np.errstate(divide="ignore", invalid="ignore"):
            # Cylinder (infinite in z).
            a = d[0] * d[0] + d[1] * d[1]
            b = o[0] * d[0] + o[1] * d[1]
            c = o[0] * o[0] + o[1] * o[1] - self.radius**2
            disc = b * b - a * c
            sq = np.sqrt(disc)
            vertical = a < 1e-18
            t0c = np.where(vertical, np.where(c <= 0, -inf, inf), (-b - sq) / a)
            t1c = np.where(vertical, np.where(c <= 0, inf, -inf), (-b + sq) / a)
            miss = ~vertical & ~(disc >= 0)
            t0c = np.where(miss, inf, t0c)
            t1c = np.where(miss, -inf, t1c)
            # Slab 0 <= z <= height.
            flat = np.abs(d[2]) < 1e-18
            inside_z = (o[2] >= 0) & (o[2] <= self.height)
            za = (0.0 - o[2]) / d[2]
            zb = (self.height - o[2]) / d[2]
            t0z = np.where(flat, np.where(inside_z, -inf, inf), np.minimum(za, zb))
            t1z = np.where(flat, np.where(inside_z, inf, -inf), np.maximum(za, zb))
            # Ball.
            q = (o[0] - self.dome_centre[0], o[1] - self.dome_centre[1], o[2] - self.dome_centre[2])
            bb = q[0] * d[0] + q[1] * d[1] + q[2] * d[2]
            cc = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] - self.dome_radius**2
            db = bb * bb - cc
            sb = np.sqrt(db)
            ok_b = db >= 0
            t0b = np.where(ok_b, -bb - sb, inf)
            t1b = np.where(ok_b, -bb + sb, -inf)
        t_in = np.maximum(np.maximum(t0c, t0z), t0b)
        t_out = np.minimum(np.minimum(t1c, t1z), t1b)
        hit = t_in <= t_out
        # Entering: the entry point; from inside: the exit point (two-sided surfaces).
        return nearest_positive(np.where(hit, t_in, inf), np.where(hit, t_out, inf))

    def local_bounds(self) -> tuple[FloatArray, float]:
        return np.array([0.0, 0.0, 0.5 * self.height]), float(
            math.hypot(self.radius, 0.5 * self.height)
        )


@dataclass(frozen=True)
class PlateTruth:
    """The top face of the tilted plate (base frame)."""

    normal: FloatArray
    """Unit normal pointing up, away from the plate."""
    point: FloatArray
    """Centre of the top face (m)."""
    size: tuple[float, float]

    def intersect_line(self, origin: ArrayLike, direction: ArrayLike) -> FloatArray:
        o = np.asarray(origin, dtype=np.float64)
        d = np.asarray(direction, dtype=np.float64)
        t = float((self.point - o) @ self.normal) / float(d @ self.normal)
        return np.asarray(o + t * d)


@dataclass(frozen=True)
class EdgeTruth:
    """The rim of a :class:`DomeBoss` in the base frame."""

    boss: DomeBoss
    boss2base: FloatArray

    def points(self, phi: ArrayLike) -> FloatArray:
        """Rim points (base, m) at azimuths ``phi`` (rad, about the boss axis)."""
        return np.asarray(se3.apply(self.boss2base, self.boss.rim_local(phi)))

    def normals(self, phi: ArrayLike) -> FloatArray:
        """Unit outward normals of the top at the rim (base)."""
        n = self.boss.top_normal_local(self.boss.rim_local(phi))
        return np.asarray(n @ self.boss2base[:3, :3].T)

    def tangents(self, phi: ArrayLike, eps: float = 1e-6) -> FloatArray:
        """Unit tangents in the direction of growing ``phi``."""
        p = np.asarray(phi, dtype=np.float64)
        t = self.points(p + eps) - self.points(p - eps)
        return np.asarray(t / np.linalg.norm(t, axis=-1, keepdims=True))

    def dense(self, phi0: float, phi1: float, step_m: float = 1e-5) -> FloatArray:
        """The rim between two azimuths as a dense polyline (for distances)."""
        n = max(2, math.ceil(abs(phi1 - phi0) * self.boss.radius / step_m) + 1)
        return self.points(np.linspace(phi0, phi1, n))

    def azimuth_of(self, points: ArrayLike) -> FloatArray:
        """Azimuth (rad) of points about the boss axis."""
        loc = se3.apply(se3.invert(self.boss2base), np.asarray(points, dtype=np.float64))
        return np.asarray(np.arctan2(loc[..., 1], loc[..., 0]))


def tilted_plate_scene(
    centre: ArrayLike = (0.45, 0.05, 0.08),
    tilt_deg: float = 12.0,
    tilt_axis_deg: float = 30.0,
    size: tuple[float, float, float] = (0.20, 0.15, 0.02),
) -> tuple[Scene, PlateTruth]:
    """The table top and a plate whose top face is tilted by ``tilt_deg`` about a horizontal
    axis at ``tilt_axis_deg`` from base X, its top face centred on ``centre`` (base, m)."""
    ax = math.radians(tilt_axis_deg)
    axis = np.array([math.cos(ax), math.sin(ax), 0.0])
    R = se3.rotvec_to_matrix(axis * math.radians(tilt_deg))
    n = R[:, 2]
    c = np.asarray(centre, dtype=np.float64)
    box_centre = c - 0.5 * size[2] * n
    plate = Box(size, se3.make(R, box_centre), name="plate")
    scene = Scene([Plane(name="table_top"), plate])
    return scene, PlateTruth(normal=n.copy(), point=c.copy(), size=(size[0], size[1]))


def dome_scene(
    centre_xy: ArrayLike = (0.42, -0.05),
    radius: float = 0.06,
    dome_offset: ArrayLike = (0.03, 0.0),
    dome_radius: float = 0.25,
    rim_top_m: float = 0.04,
) -> tuple[Scene, EdgeTruth]:
    """The table top and a :class:`DomeBoss` standing on it at ``centre_xy`` (base, m): radius
    ``radius``, the dome's centre ``dome_offset`` off the axis, the rim's highest point at
    ``rim_top_m`` above the table. Defaults: the rim climbs from 25 mm to 40 mm, the top tilts by
    7 to 21 degrees at the rim."""
    off = np.asarray(dome_offset, dtype=np.float64).reshape(2)
    d_min = abs(radius - float(np.linalg.norm(off)))
    cz = rim_top_m - math.sqrt(dome_radius**2 - d_min**2)
    boss = DomeBoss(
        radius,
        rim_top_m + 0.05,
        (off[0], off[1], cz),
        dome_radius,
        se3.make(t=(float(np.asarray(centre_xy)[0]), float(np.asarray(centre_xy)[1]), 0.0)),
    )
    scene = Scene([Plane(name="table_top"), boss])
    return scene, EdgeTruth(boss, boss.pose.copy())


def sensor_pose_at_edge(
    truth: EdgeTruth, phi: float, standoff_m: float, sign: int = 1
) -> FloatArray:
    """A ``sensor2base`` looking along the top's inward normal at the rim point of azimuth
    ``phi`` from ``standoff_m``, its X axis along the rim (``sign`` +1: growing ``phi``), so
    that the laser line crosses the edge at the middle of its range."""
    p = truth.points(phi)
    n = truth.normals(phi)
    t = sign * truth.tangents(phi)
    z = -n
    x = t - (t @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2] = x, y, z
    T[:3, 3] = p - standoff_m * z
    return T


def start_q_for_sensor(
    model: str | kinematics.DHParams,
    sensor2base: ArrayLike,
    sensor2flange: ArrayLike,
    seed_q: ArrayLike,
) -> FloatArray:
    """Joint positions (rad) that put the sensor at ``sensor2base``, nearest to ``seed_q``."""
    f2b = np.asarray(sensor2base, dtype=np.float64) @ se3.invert(np.asarray(sensor2flange))
    return np.asarray(kinematics.inverse_nearest(model, f2b, np.asarray(seed_q, dtype=np.float64)))
