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
"""

from __future__ import annotations

import logging
import re
import struct
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import se3

__all__ = [
    "Box",
    "Cylinder",
    "MeshFormatError",
    "Plane",
    "Primitive",
    "Scene",
    "Sphere",
    "TriangleMesh",
    "demo_scene",
    "read_mesh",
    "sensor_looking_down",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
Mount = Literal["base", "table"]

_EPS_T = 1e-9
"""Hits closer than this (metres) are ignored, so a ray leaving a surface does not hit it."""


Vec3 = tuple[FloatArray, FloatArray, FloatArray]
"""A batch of 3-vectors as three component arrays (contiguous arrays make numpy fast)."""


def _dot(a: FloatArray, b: FloatArray) -> FloatArray:
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _dot3(a: Vec3, b: Vec3) -> FloatArray:
    return np.asarray(a[0] * b[0] + a[1] * b[1] + a[2] * b[2])


def _nearest_positive(*candidates: FloatArray) -> FloatArray:
    """Element-wise smallest candidate above ``_EPS_T`` (inf where none); NaN counts as a miss."""
    best: FloatArray | None = None
    for c in candidates:
        c = np.where(c > _EPS_T, c, np.inf)  # NaN > eps is False: NaN becomes a miss
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
        b = _dot3(o, d)
        c = _dot3(o, o) - self.radius * self.radius
        with np.errstate(invalid="ignore"):
            s = np.sqrt(b * b - c)  # NaN on a miss
        return _nearest_positive(-b - s, s - b)

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
        return _nearest_positive(t)

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
        hit = t_far >= np.maximum(t_near, _EPS_T)
        t = np.where(t_near > _EPS_T, t_near, t_far)  # from inside: the exit point
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
        return _nearest_positive(*cands)

    def local_bounds(self) -> tuple[FloatArray, float]:
        return np.array([0.0, 0.0, 0.5 * self.height]), float(
            np.hypot(self.radius, 0.5 * self.height)
        )


class TriangleMesh(Primitive):
    """Triangles ``faces (F, 3)`` (vertex indices) over ``vertices (V, 3)`` (m, local frame).

    Intersection is Möller-Trumbore over rays x triangles, in chunks that bound the memory used.
    """

    chunk_elements = 262_144
    """Rays x triangles evaluated per numpy step."""

    def __init__(
        self,
        vertices: ArrayLike,
        faces: ArrayLike,
        pose: ArrayLike | None = None,
        *,
        mount: Mount = "base",
        name: str = "",
    ) -> None:
        super().__init__(pose, mount, name)
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
            raise ValueError("mesh needs vertices (V, 3) and at least one face (F, 3)")
        if f.min() < 0 or f.max() >= v.shape[0]:
            raise ValueError("mesh face index out of range")
        self.vertices = v
        self.faces = f
        tri = v[f]
        self._v0 = tri[:, 0]
        self._e1 = tri[:, 1] - tri[:, 0]
        self._e2 = tri[:, 2] - tri[:, 0]
        lo, hi = v.min(axis=0), v.max(axis=0)
        self._centre = 0.5 * (lo + hi)
        self._radius = float(np.linalg.norm(v - self._centre, axis=1).max())

    @classmethod
    def from_file(
        cls,
        path: str | Path,
        *,
        scale: float = 1.0,
        pose: ArrayLike | None = None,
        mount: Mount = "base",
        name: str = "",
    ) -> TriangleMesh:
        """Read an STL (binary or ASCII) or PLY (ASCII or binary) file; ``scale`` converts its
        units to metres (``1e-3`` for millimetres)."""
        vertices, faces = read_mesh(path)
        return cls(vertices * scale, faces, pose, mount=mount, name=name or Path(path).stem)

    @classmethod
    def prism(
        cls,
        profile_xz: ArrayLike,
        width_y: float,
        pose: ArrayLike | None = None,
        *,
        mount: Mount = "base",
        name: str = "prism",
    ) -> TriangleMesh:
        """A closed prism: the convex polygon ``profile_xz (K, 2)`` extruded along local Y over
        ``[-width_y/2, width_y/2]`` (for ramps and chamfers)."""
        p = np.asarray(profile_xz, dtype=np.float64)
        k = p.shape[0]
        if p.ndim != 2 or p.shape[1] != 2 or k < 3:
            raise ValueError("prism profile must be (K >= 3, 2)")
        h = 0.5 * width_y
        front = np.column_stack([p[:, 0], np.full(k, -h), p[:, 1]])
        back = np.column_stack([p[:, 0], np.full(k, h), p[:, 1]])
        verts = np.vstack([front, back])
        faces = []
        for i in range(1, k - 1):  # caps as triangle fans (k is a handful of corners)
            faces.append((0, i, i + 1))
            faces.append((k, k + i + 1, k + i))
        for i in range(k):
            j = (i + 1) % k
            faces.append((i, j, k + j))
            faces.append((i, k + j, k + i))
        return cls(verts, np.asarray(faces), pose, mount=mount, name=name)

    def intersect_local(self, o: Vec3, d: Vec3) -> FloatArray:
        shape = np.broadcast_shapes(*(np.shape(c) for c in (*o, *d)))
        o2 = np.stack([np.broadcast_to(c, shape) for c in o], axis=-1).reshape(-1, 3)
        d2 = np.stack([np.broadcast_to(c, shape) for c in d], axis=-1).reshape(-1, 3)
        out = np.full(o2.shape[0], np.inf)
        # Rays that miss the bounding sphere cannot hit a triangle.
        w = o2 - self._centre
        b = _dot(w, d2)
        near = b * b - (_dot(w, w) - self._radius**2) >= 0
        idx = np.flatnonzero(near)
        if idx.size == 0:
            return out.reshape(shape)
        n_faces = self._v0.shape[0]
        step = max(1, self.chunk_elements // n_faces)
        for start in range(0, idx.size, step):
            sel = idx[start : start + step]
            out[sel] = self._moller_trumbore(o2[sel], d2[sel])
        return out.reshape(shape)

    def _moller_trumbore(self, o: FloatArray, d: FloatArray) -> FloatArray:
        """Nearest hit of rays ``(R, 3)`` against all triangles; ``(R,)``."""
        dd = d[:, None, :]
        pvec = np.cross(dd, self._e2[None])  # (R, F, 3)
        det = _dot(self._e1[None], pvec)
        ok = np.abs(det) > 1e-18
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tvec = o[:, None, :] - self._v0[None]
        u = _dot(tvec, pvec) * inv
        qvec = np.cross(tvec, self._e1[None])
        v = _dot(dd, qvec) * inv
        t = _dot(self._e2[None], qvec) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > _EPS_T)
        return np.asarray(np.where(hit, t, np.inf).min(axis=1))

    def local_bounds(self) -> tuple[FloatArray, float]:
        return self._centre.copy(), self._radius


# ----------------------------------------------------------------------------------------------
# Mesh files


class MeshFormatError(ValueError):
    """A mesh file that cannot be read (unknown format, truncated, unsupported layout)."""


def read_mesh(path: str | Path) -> tuple[FloatArray, NDArray[np.int64]]:
    """Vertices ``(V, 3)`` (file units) and triangles ``(F, 3)`` from an STL or PLY file."""
    data = Path(path).read_bytes()
    if data[:3] == b"ply":
        return _read_ply(data)
    if len(data) >= 84:
        (n,) = struct.unpack_from("<I", data, 80)
        if len(data) == 84 + 50 * n:
            return _read_stl_binary(data, n)
    if data.lstrip()[:5].lower() == b"solid":
        return _read_stl_ascii(data)
    raise MeshFormatError(f"{path}: neither PLY nor a well-formed STL")


def _read_stl_binary(data: bytes, n: int) -> tuple[FloatArray, NDArray[np.int64]]:
    rec = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    tris = np.frombuffer(data, dtype=rec, count=n, offset=84)["v"].astype(np.float64)
    if n == 0:
        raise MeshFormatError("STL holds no triangles")
    return tris.reshape(-1, 3), np.arange(3 * n, dtype=np.int64).reshape(n, 3)


def _read_stl_ascii(data: bytes) -> tuple[FloatArray, NDArray[np.int64]]:
    tokens = np.array(data.split())
    idx = np.flatnonzero(np.char.lower(tokens) == b"vertex")
    if idx.size == 0 or idx.size % 3 or idx[-1] + 3 >= tokens.size:
        raise MeshFormatError("ASCII STL: vertex count is not a multiple of 3")
    try:
        xyz = tokens[idx[:, None] + np.arange(1, 4)].astype(np.float64)
    except ValueError as exc:
        raise MeshFormatError(f"ASCII STL: bad number ({exc})") from exc
    n = idx.size // 3
    return xyz, np.arange(3 * n, dtype=np.int64).reshape(n, 3)


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


@dataclass
class _PlyElement:
    name: str
    count: int
    props: list[tuple[str, str, str | None]] = field(default_factory=list)
    """(name, value type, list count type or None)."""


def _read_ply(data: bytes) -> tuple[FloatArray, NDArray[np.int64]]:
    end = re.search(rb"end_header\r?\n", data)
    if end is None:
        raise MeshFormatError("PLY: no end_header")
    header = data[: end.start()].decode("ascii", "replace").splitlines()
    body = data[end.end() :]
    fmt = ""
    elements: list[_PlyElement] = []
    for line in header[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append(_PlyElement(words[1], int(words[2])))
        elif words[0] == "property" and elements:
            if words[1] == "list":
                elements[-1].props.append((words[4], _ply_type(words[3]), _ply_type(words[2])))
            else:
                elements[-1].props.append((words[2], _ply_type(words[1]), None))
    names = [e.name for e in elements]
    if "vertex" not in names or "face" not in names:
        raise MeshFormatError("PLY: needs vertex and face elements")
    if fmt == "ascii":
        verts, faces = _ply_ascii(body, elements)
    elif fmt in ("binary_little_endian", "binary_big_endian"):
        verts, faces = _ply_binary(body, elements, "<" if fmt.endswith("little_endian") else ">")
    else:
        raise MeshFormatError(f"PLY: unknown format {fmt!r}")
    if faces.size == 0:
        raise MeshFormatError("PLY holds no faces")
    if faces.min() < 0 or faces.max() >= verts.shape[0]:
        raise MeshFormatError("PLY: face index out of range")
    return verts, faces


def _ply_type(name: str) -> str:
    try:
        return _PLY_TYPES[name]
    except KeyError:
        raise MeshFormatError(f"PLY: unknown type {name!r}") from None


def _xyz_columns(el: _PlyElement) -> list[int]:
    names = [p[0] for p in el.props]
    try:
        return [names.index(c) for c in ("x", "y", "z")]
    except ValueError:
        raise MeshFormatError("PLY: vertex element lacks x, y or z") from None


def _fan(polys: Sequence[Sequence[int]]) -> NDArray[np.int64]:
    """Triangulate polygons as fans (quads and n-gons from some exporters)."""
    tris = [(p[0], p[i], p[i + 1]) for p in polys for i in range(1, len(p) - 1)]
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def _ply_ascii(body: bytes, elements: list[_PlyElement]) -> tuple[FloatArray, NDArray[np.int64]]:
    lines = body.decode("ascii", "replace").splitlines()
    pos = 0
    verts: FloatArray | None = None
    faces: NDArray[np.int64] | None = None
    for el in elements:
        chunk = lines[pos : pos + el.count]
        if len(chunk) < el.count:
            raise MeshFormatError(f"PLY: truncated {el.name} element")
        pos += el.count
        if el.name == "vertex":
            cols = _xyz_columns(el)
            try:
                table = np.array([ln.split()[: len(el.props)] for ln in chunk], dtype=np.float64)
            except ValueError as exc:
                raise MeshFormatError(f"PLY: bad vertex line ({exc})") from exc
            verts = table[:, cols]
        elif el.name == "face":
            rows = [ln.split() for ln in chunk]
            try:
                if all(len(r) >= 4 and r[0] == "3" for r in rows):
                    faces = np.array([r[1:4] for r in rows], dtype=np.int64)
                else:
                    faces = _fan([[int(v) for v in r[1 : 1 + int(r[0])]] for r in rows])
            except ValueError as exc:
                raise MeshFormatError(f"PLY: bad face line ({exc})") from exc
    assert verts is not None and faces is not None
    return verts, faces


def _ply_binary(
    body: bytes, elements: list[_PlyElement], endian: str
) -> tuple[FloatArray, NDArray[np.int64]]:
    offset = 0
    verts: FloatArray | None = None
    faces: NDArray[np.int64] | None = None
    for el in elements:
        if all(p[2] is None for p in el.props):
            dt = np.dtype([(p[0], endian + p[1]) for p in el.props])
            if offset + dt.itemsize * el.count > len(body):
                raise MeshFormatError(f"PLY: truncated {el.name} element")
            rec = np.frombuffer(body, dtype=dt, count=el.count, offset=offset)
            offset += dt.itemsize * el.count
            if el.name == "vertex":
                verts = np.column_stack([rec[c].astype(np.float64) for c in ("x", "y", "z")])
            continue
        if el.name != "face":
            raise MeshFormatError(f"PLY: list properties in element {el.name!r} not supported")
        faces, offset = _ply_binary_faces(body, offset, el, endian)
    assert verts is not None and faces is not None
    return verts, faces


def _ply_binary_faces(
    body: bytes, offset: int, el: _PlyElement, endian: str
) -> tuple[NDArray[np.int64], int]:
    # Fast path: every face is a triangle, so each record has a fixed size.
    fields: list[tuple[str, str] | tuple[str, str, int]] = []
    list_name = ""
    for name, vtype, ctype in el.props:
        if ctype is None:
            fields.append((name, endian + vtype))
        else:
            list_name = name
            fields.append(("_n", endian + ctype))
            fields.append((name, endian + vtype, 3))
    dt = np.dtype(fields)
    if offset + dt.itemsize * el.count <= len(body):
        rec = np.frombuffer(body, dtype=dt, count=el.count, offset=offset)
        if np.all(rec["_n"] == 3):
            return rec[list_name].astype(np.int64), offset + dt.itemsize * el.count
    # General polygons: walk the records (rare; exporters of scanned parts use triangles).
    polys: list[list[int]] = []
    for _ in range(el.count):
        poly: list[int] = []
        for _name, vtype, ctype in el.props:
            if ctype is None:
                offset += np.dtype(vtype).itemsize
                continue
            if offset + np.dtype(ctype).itemsize > len(body):
                raise MeshFormatError("PLY: truncated face element")
            n = int(np.frombuffer(body, endian + ctype, 1, offset)[0])
            offset += np.dtype(ctype).itemsize
            size = np.dtype(vtype).itemsize * n
            if offset + size > len(body):
                raise MeshFormatError("PLY: truncated face element")
            poly = np.frombuffer(body, endian + vtype, n, offset).astype(int).tolist()
            offset += size
        polys.append(poly)
    return _fan(polys), offset


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
