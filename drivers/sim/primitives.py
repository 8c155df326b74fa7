"""What every primitive of a simulated scene shares: its pose, mount and ray interface.

A primitive is defined in a local frame of its own; :meth:`Primitive.intersect` moves rays
given in its mount frame (``"base"`` or ``"table"``) into it, so each intersection routine only
handles the canonical shape (:mod:`.scene` for the analytic shapes, :mod:`.mesh` for triangle
meshes). Rays come as component triples (:data:`Vec3`), and :func:`nearest_positive` picks the
hit in front of the ray. The scene that ray-casts them together is :class:`~.scene.Scene`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import se3

__all__ = [
    "EPS_T",
    "BoolArray",
    "FloatArray",
    "Mount",
    "Primitive",
    "Vec3",
    "dot",
    "dot3",
    "nearest_positive",
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
Mount = Literal["base", "table"]

EPS_T = 1e-9
"""Hits closer than this (metres) are ignored, so a ray leaving a surface does not hit it."""


Vec3 = tuple[FloatArray, FloatArray, FloatArray]
"""A batch of 3-vectors as three component arrays (contiguous arrays make numpy fast)."""


def dot(a: FloatArray, b: FloatArray) -> FloatArray:
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def dot3(a: Vec3, b: Vec3) -> FloatArray:
    return np.asarray(a[0] * b[0] + a[1] * b[1] + a[2] * b[2])


def nearest_positive(*candidates: FloatArray) -> FloatArray:
    """Element-wise smallest candidate above ``EPS_T`` (inf where none); NaN counts as a miss."""
    best: FloatArray | None = None
    for c in candidates:
        c = np.where(c > EPS_T, c, np.inf)  # NaN > eps is False: NaN becomes a miss
        best = c if best is None else np.minimum(best, c)
    assert best is not None
    return best


class Primitive(ABC):
    """A solid or surface with a pose in its mount frame."""

    def __init__(
        self, pose: ArrayLike | None = None, mount: Mount = "base", name: str = ""
    ) -> None:
        if mount not in ("base", "table"):
            raise ValueError(f"mount must be 'base' or 'table', got {mount!r}")
        self.pose: FloatArray = (
            se3.identity() if pose is None else se3.check_transform(pose, "primitive pose")
        )
        self.mount: Mount = mount
        self.name = name or type(self).__name__.lower()
        self.mount2local: FloatArray = se3.invert(self.pose)

    @abstractmethod
    def intersect_local(self, o: Vec3, d: Vec3) -> FloatArray:
        """Distance to the nearest hit for rays ``o + t d`` in the local frame.

        ``o`` and ``d`` are component triples ``(x, y, z)`` of arrays that all broadcast together
        (for example ``(P, N)`` origins and ``(P, 1)`` directions); ``d`` is unit length. Returns
        ``t`` with the broadcast shape, ``inf`` where the ray misses.
        """

    @abstractmethod
    def local_bounds(self) -> tuple[FloatArray, float]:
        """Bounding sphere in the local frame: ``(centre (3,), radius)``; radius may be inf."""

    def may_hit(self, centres_local: FloatArray, radius: float) -> BoolArray:
        """Whether a ball ``(centre, radius)`` (local frame, centres ``(P, 3)``) can touch us."""
        c, r = self.local_bounds()
        if not np.isfinite(r):
            return np.ones(centres_local.shape[0], dtype=bool)
        gap = np.linalg.norm(centres_local - c, axis=-1)
        return np.asarray(gap <= r + radius)

    def intersect(self, origins: ArrayLike, dirs: ArrayLike) -> FloatArray:
        """Distance to the nearest hit for rays ``(R, 3)`` given in the mount frame (unit
        ``dirs``); ``(R,)``, ``inf`` on a miss."""
        o = np.asarray(origins, dtype=np.float64) @ self.mount2local[:3, :3].T
        o += self.mount2local[:3, 3]
        d = np.asarray(dirs, dtype=np.float64) @ self.mount2local[:3, :3].T
        return self.intersect_local(_split(o), _split(d))


def _split(v: FloatArray) -> Vec3:
    return (
        np.ascontiguousarray(v[..., 0]),
        np.ascontiguousarray(v[..., 1]),
        np.ascontiguousarray(v[..., 2]),
    )
