"""Triangle meshes in a simulated scene: the primitive, and the STL and PLY files it reads.

:class:`TriangleMesh` is a :class:`~.primitives.Primitive` (Möller-Trumbore against every
triangle, in chunks); :func:`read_mesh` reads binary or ASCII STL and ASCII or binary PLY
(triangles, or polygons split into fans), raising :class:`MeshFormatError` for anything else.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.drivers.sim.primitives import EPS_T, FloatArray, Mount, Primitive, Vec3, dot

__all__ = ["MeshFormatError", "TriangleMesh", "read_mesh"]


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
        b = dot(w, d2)
        near = b * b - (dot(w, w) - self._radius**2) >= 0
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
        det = dot(self._e1[None], pvec)
        ok = np.abs(det) > 1e-18
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tvec = o[:, None, :] - self._v0[None]
        u = dot(tvec, pvec) * inv
        qvec = np.cross(tvec, self._e1[None])
        v = dot(dd, qvec) * inv
        t = dot(self._e2[None], qvec) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > EPS_T)
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
