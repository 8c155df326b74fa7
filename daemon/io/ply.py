"""PLY point-cloud files: atomic whole-file writes, a streaming writer for long recordings, and a
reader for the files we write.

Layout (one ``vertex`` element, no faces)::

    ply
    format binary_little_endian 1.0
    comment <free text, one line each>
    element vertex <N>
    property float x
    property float y
    property float z
    property float nx        (optional normals)
    property float ny
    property float nz
    property uchar intensity (optional; or ``float`` in [0, 1], see below)
    property ushort scalar_pass   (optional scalar fields, see below)
    property double scalar_time
    end_header

Coordinates are float32 metres. Property names follow what viewers map without asking:
``x y z nx ny nz`` everywhere; ``intensity`` becomes a scalar field named "intensity" in
CloudCompare (any numeric type). MeshLab's importer (vcglib) only takes ``intensity`` when it is
a ``float`` (read as a grey shade in [0, 1]) and silently ignores a ``uchar`` one, so
``intensity_float=True`` writes ``u8 / 255`` as float32 for MeshLab users at 4 bytes a point;
the default keeps the exact 1-byte value.

Scalar fields: any other per-point value, named ``scalar_<what>`` so that CloudCompare shows it
as the scalar field ``<what>`` (it writes its own fields so). wristscan writes ``scalar_pass``
(``ushort``: the pass of a scan, from 1) and ``scalar_time`` (``double`` seconds since the time
a comment gives); another name is stored as ``float`` unless :data:`SCALAR_TYPES` says.

Every file appears under its final name complete or not at all: data goes to a temporary file
in the same folder, is flushed and fsynced, then ``os.replace``-d over the final name.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.daemon.io.atomic import CloseOrAbort, atomic_writer

__all__ = [
    "SCALAR_TYPES",
    "PlyElement",
    "PlyError",
    "PlyHeader",
    "PlyStreamWriter",
    "read_ply",
    "read_ply_header",
    "write_ply",
]

log = logging.getLogger(__name__)

# PLY type names (both spellings of the spec) -> little-endian numpy type.
_PLY_TYPES: dict[str, str] = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
_TYPE_NAMES = {"f4": "float", "f8": "double", "u1": "uchar", "u2": "ushort", "u4": "uint"}
SCALAR_TYPES: dict[str, str] = {"scalar_pass": "<u2", "scalar_time": "<f8"}
"""Types of the scalar fields wristscan writes; other scalar fields are float32."""
_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
_ASCII_CHUNK = 65536
"""Rows formatted per string operation in ASCII output (bounds the temporary Python objects)."""


class PlyError(ValueError):
    """A file that is not a PLY file this module can read."""


@dataclass(frozen=True)
class PlyElement:
    name: str
    count: int
    properties: tuple[tuple[str, str], ...]
    """(name, numpy type such as ``"f4"``) per scalar property, in file order."""
    has_list: bool = False


@dataclass(frozen=True)
class PlyHeader:
    format: str
    """``ascii``, ``binary_little_endian`` or ``binary_big_endian``."""
    elements: tuple[PlyElement, ...]
    comments: tuple[str, ...]
    size: int
    """Bytes up to and including the ``end_header`` line."""

    def element(self, name: str) -> PlyElement | None:
        return next((e for e in self.elements if e.name == name), None)


# ------------------------------------------------------------------------------------ writing


def _check_comment(text: str) -> str:
    if "\n" in text or "\r" in text:
        raise ValueError(f"PLY comment must be one line, got {text!r}")
    return text


def _vertex_dtype(
    has_normals: bool, has_intensity: bool, intensity_float: bool, scalars: Sequence[str] = ()
) -> np.dtype:
    fields: list[tuple[str, str]] = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if has_normals:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if has_intensity:
        fields.append(("intensity", "<f4" if intensity_float else "u1"))
    for name in scalars:
        if not name.isidentifier() or name in ("x", "y", "z", "nx", "ny", "nz", "intensity"):
            raise ValueError(f"bad scalar field name {name!r}")
        fields.append((name, SCALAR_TYPES.get(name, "<f4")))
    return np.dtype(fields)


def _header(n: int, dtype: np.dtype, ascii: bool, comments: Sequence[str]) -> bytes:
    lines = ["ply", f"format {'ascii' if ascii else 'binary_little_endian'} 1.0"]
    lines += [f"comment {_check_comment(c)}" for c in comments]
    lines.append(f"element vertex {n}")
    assert dtype.fields is not None
    for name, (ftype, *_) in dtype.fields.items():
        lines.append(f"property {_TYPE_NAMES[ftype.str[1:]]} {name}")
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def _records(
    xyz: ArrayLike,
    normals: ArrayLike | None,
    intensity: ArrayLike | None,
    dtype: np.dtype,
    scalars: Mapping[str, ArrayLike] | None = None,
) -> NDArray[Any]:
    pts = np.asarray(xyz)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"xyz must be (N, 3), got {pts.shape}")
    n = pts.shape[0]
    rec = np.empty(n, dtype=dtype)
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    assert dtype.names is not None
    if "nx" in dtype.names:
        if normals is None:
            raise ValueError("this file has normals: give normals (N, 3)")
        nrm = np.asarray(normals)
        if nrm.shape != (n, 3):
            raise ValueError(f"normals must be ({n}, 3), got {nrm.shape}")
        rec["nx"], rec["ny"], rec["nz"] = nrm[:, 0], nrm[:, 1], nrm[:, 2]
    elif normals is not None:
        raise ValueError("this file has no normals")
    if "intensity" in dtype.names:
        if intensity is None:
            raise ValueError("this file has intensity: give intensity (N,)")
        inten = np.asarray(intensity)
        if inten.shape != (n,):
            raise ValueError(f"intensity must be ({n},), got {inten.shape}")
        if inten.dtype != np.uint8:
            raise ValueError(f"intensity must be uint8, got {inten.dtype}")
        if dtype["intensity"].kind == "f":
            rec["intensity"] = inten.astype(np.float32) / np.float32(255.0)
        else:
            rec["intensity"] = inten
    elif intensity is not None:
        raise ValueError("this file has no intensity")
    _fill_scalars(rec, scalars or {})
    return rec


def _fill_scalars(rec: NDArray[Any], scalars: Mapping[str, ArrayLike]) -> None:
    assert rec.dtype.names is not None
    declared = rec.dtype.names[rec.dtype.names.index("z") + 1 :]
    declared = tuple(nm for nm in declared if nm not in ("nx", "ny", "nz", "intensity"))
    if set(scalars) != set(declared):
        raise ValueError(f"this file has the scalar fields {declared}, got {tuple(scalars)}")
    for name, values in scalars.items():
        v = np.broadcast_to(np.asarray(values), (rec.shape[0],))
        rec[name] = v


def _ascii_rows(rec: NDArray[Any]) -> Iterator[bytes]:
    """Text lines for ``rec`` in blocks: one %-format over a whole block, no per-point loop.
    ``%.9g`` round-trips float32 exactly."""
    assert rec.dtype.names is not None
    names = rec.dtype.names
    fmt = {"u": "%d", "f": "%.9g"}
    row = " ".join(
        "%.17g" if rec.dtype[nm].itemsize == 8 else fmt[rec.dtype[nm].kind] for nm in names
    )
    row += "\n"
    for start in range(0, rec.shape[0], _ASCII_CHUNK):
        block = rec[start : start + _ASCII_CHUNK]
        cols = np.empty((block.shape[0], len(names)), dtype=np.float64)
        for j, nm in enumerate(names):  # a handful of columns, not points
            cols[:, j] = block[nm]
        yield ((row * block.shape[0]) % tuple(cols.ravel().tolist())).encode("ascii")


def _write_records(f: IO[bytes], rec: NDArray[Any], ascii: bool) -> None:
    if ascii:
        for chunk in _ascii_rows(rec):
            f.write(chunk)
    elif rec.shape[0]:
        f.write(np.ascontiguousarray(rec).view(np.uint8).data)


def write_ply(
    path: str | os.PathLike[str],
    xyz: ArrayLike,
    normals: ArrayLike | None = None,
    intensity: ArrayLike | None = None,
    binary: bool = True,
    comments: Sequence[str] = (),
    intensity_float: bool = False,
    scalars: Mapping[str, ArrayLike] | None = None,
) -> None:
    """Write a point cloud atomically. ``xyz`` (N, 3) metres and ``normals`` (N, 3) are stored as
    float32; ``intensity`` (N,) uint8 as ``uchar intensity`` (or ``float`` in [0, 1] with
    ``intensity_float``); ``scalars`` maps scalar field names to (N,) values (or one value for
    every point). ``binary=False`` writes ASCII."""
    names = tuple(scalars or {})
    dtype = _vertex_dtype(normals is not None, intensity is not None, intensity_float, names)
    rec = _records(xyz, normals, intensity, dtype, scalars)
    header = _header(rec.shape[0], dtype, not binary, comments)
    with atomic_writer(path) as f:
        f.write(header)
        _write_records(f, rec, not binary)


class PlyStreamWriter(CloseOrAbort):
    """Write a PLY file chunk by chunk without holding the cloud in memory.

    Chunks go to a temporary body file beside ``path``; :meth:`close` writes the header with the
    final vertex count, appends the body and atomically renames the result to ``path``. Leaving
    a ``with`` block by an exception (or calling :meth:`abort`) removes the temporary files and
    creates nothing under ``path``. ``comments`` may be extended until :meth:`close`.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        has_intensity: bool = False,
        has_normals: bool = False,
        binary: bool = True,
        comments: Sequence[str] = (),
        intensity_float: bool = False,
        scalars: Sequence[str] = (),
    ) -> None:
        self.path = Path(path)
        self.binary = binary
        self.comments: list[str] = [_check_comment(c) for c in comments]
        self.dtype = _vertex_dtype(has_normals, has_intensity, intensity_float, scalars)
        self.n_points = 0
        self._closed = False
        fd, body = tempfile.mkstemp(
            prefix=f".{self.path.name}.", suffix=".body.tmp", dir=self.path.parent
        )
        self._body_path = body
        self._body: IO[bytes] = os.fdopen(fd, "w+b")

    @property
    def has_intensity(self) -> bool:
        return "intensity" in (self.dtype.names or ())

    @property
    def has_normals(self) -> bool:
        return "nx" in (self.dtype.names or ())

    @property
    def closed(self) -> bool:
        return self._closed

    def write(
        self,
        xyz: ArrayLike,
        intensity: ArrayLike | None = None,
        normals: ArrayLike | None = None,
        scalars: Mapping[str, ArrayLike] | None = None,
    ) -> None:
        """Append ``xyz`` (N, 3) metres with the optional per-point blocks this file declares
        (``scalars``: one (N,) array, or one value, per scalar field)."""
        if self._closed:
            raise ValueError(f"{self.path}: writer is closed")
        rec = _records(xyz, normals, intensity, self.dtype, scalars)
        _write_records(self._body, rec, not self.binary)
        self.n_points += rec.shape[0]

    def close(self) -> Path:
        """Finish the file: header + body into a temporary file, fsync, rename. Returns the path.
        On failure nothing is left behind and the error propagates."""
        if self._closed:
            return self.path
        try:
            self._body.flush()
            header = _header(self.n_points, self.dtype, not self.binary, self.comments)
            with atomic_writer(self.path) as out:
                out.write(header)
                self._body.seek(0)
                shutil.copyfileobj(self._body, out, 1 << 22)
        except BaseException:
            self.abort()
            raise
        self._closed = True
        self._discard_body()
        return self.path

    def abort(self) -> None:
        """Drop everything written so far; nothing appears under ``path``."""
        self._closed = True
        self._discard_body()

    def _discard_body(self) -> None:
        with contextlib.suppress(OSError):
            self._body.close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self._body_path)


# ------------------------------------------------------------------------------------ reading


def _parse_header(f: IO[bytes], source: str) -> PlyHeader:
    first = f.readline()
    if first.rstrip(b"\r\n") != b"ply":
        raise PlyError(f"{source}: not a PLY file (no 'ply' magic line)")
    size = len(first)
    fmt: str | None = None
    comments: list[str] = []
    elements: list[dict[str, Any]] = []
    while True:
        raw = f.readline()
        if not raw:
            raise PlyError(f"{source}: header ends before 'end_header'")
        size += len(raw)
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise PlyError(f"{source}: non-ASCII byte in the header") from None
        words = line.split()
        if not words:
            continue
        key = words[0]
        if key == "end_header":
            break
        if key in ("comment", "obj_info"):
            comments.append(line[len(key) :].strip())
        elif key == "format":
            if len(words) != 3 or words[1] not in _FORMATS:
                raise PlyError(f"{source}: unsupported format line {line!r}")
            fmt = words[1]
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise PlyError(f"{source}: bad element line {line!r}")
            elements.append({"name": words[1], "count": int(words[2]), "props": [], "list": False})
        elif key == "property":
            if not elements:
                raise PlyError(f"{source}: property before any element: {line!r}")
            if len(words) >= 2 and words[1] == "list":
                elements[-1]["list"] = True
                continue
            if len(words) != 3 or words[1] not in _PLY_TYPES:
                raise PlyError(f"{source}: bad property line {line!r}")
            elements[-1]["props"].append((words[2], _PLY_TYPES[words[1]]))
        else:
            raise PlyError(f"{source}: unknown header line {line!r}")
    if fmt is None:
        raise PlyError(f"{source}: no format line")
    return PlyHeader(
        fmt,
        tuple(PlyElement(e["name"], e["count"], tuple(e["props"]), e["list"]) for e in elements),
        tuple(comments),
        size,
    )


def read_ply_header(path: str | os.PathLike[str]) -> PlyHeader:
    """The parsed header of a PLY file."""
    with open(path, "rb") as f:
        return _parse_header(f, str(path))


def read_ply(path: str | os.PathLike[str]) -> dict[str, NDArray[Any]]:
    """Read the ``vertex`` element of a PLY file (ASCII or binary, either byte order).

    Returns ``xyz`` (N, 3) and, when present, ``normals`` (N, 3) and ``intensity`` (N,) in the
    file's types, plus every other vertex property under its own name. Elements before the
    vertex element must have no list properties; elements after it are ignored.
    """
    source = str(path)
    with open(path, "rb") as f:
        header = _parse_header(f, source)
        body = f.read()
    order = _FORMATS[header.format]
    offset = 0
    lines_before = 0
    vertex: PlyElement | None = None
    for el in header.elements:
        if el.name == "vertex":
            vertex = el
            break
        if el.has_list:
            raise PlyError(f"{source}: list properties before the vertex element")
        offset += el.count * np.dtype([(n, order + t) for n, t in el.properties]).itemsize
        lines_before += el.count
    if vertex is None:
        raise PlyError(f"{source}: no vertex element")
    if vertex.has_list:
        raise PlyError(f"{source}: list properties in the vertex element are not supported")
    n = vertex.count
    names = [p for p, _ in vertex.properties]
    if header.format == "ascii":
        lines = body.split(b"\n", lines_before + n)
        if len(lines) < lines_before + n:
            raise PlyError(f"{source}: {len(lines)} text lines, header promises {n} vertices")
        text = b" ".join(lines[lines_before : lines_before + n])
        k = len(names)
        try:
            flat = np.array(text.split(), dtype=np.float64)
        except ValueError:
            raise PlyError(f"{source}: non-numeric vertex data") from None
        if flat.size != n * k:
            raise PlyError(f"{source}: {flat.size} values for {n} vertices x {k} properties")
        table = flat.reshape(n, k)
        cols = {nm: table[:, j].astype(t) for j, (nm, t) in enumerate(vertex.properties)}
    else:
        dtype = np.dtype([(nm, order + t) for nm, t in vertex.properties])
        need = offset + n * dtype.itemsize
        if len(body) < need:
            raise PlyError(f"{source}: truncated ({len(body)} body bytes, header needs {need})")
        rec = np.frombuffer(body, dtype=dtype, count=n, offset=offset)
        cols = {nm: rec[nm].astype(dtype[nm].newbyteorder("=")) for nm in names}
    out: dict[str, NDArray[Any]] = {}
    for group, keys in (("xyz", ("x", "y", "z")), ("normals", ("nx", "ny", "nz"))):
        if all(k in cols for k in keys):
            out[group] = np.stack([cols.pop(k) for k in keys], axis=1)
    if "xyz" not in out:
        raise PlyError(f"{source}: vertex element lacks x, y, z")
    out.update(cols)
    return out
