"""E57 files for CloudCompare and inspection software: extra ``e57`` (pye57, libE57Format).

One E57 ``data3D`` scan per pass: its points in the scan's own coordinates (float32 metres), its
pose (rotation quaternion and translation, metres) that carries them into the file's frame,
intensity (the sensor's 0..255, limits 0 and 255) when present, and the acquisition start and
end when known (GPS seconds, as E57 counts time). ``wristscan record`` writes the whole
recording as one scan with the identity pose.

:class:`E57Writer` writes each scan as it is given (only that scan is in memory) into a
temporary file beside the target, and :meth:`E57Writer.close` copies it through
:func:`atomic_writer`: the file appears complete under its name or not at all.
:class:`SpooledScan` collects a long recording's batches on disk and hands them to the writer
as memory-mapped arrays.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from types import SimpleNamespace
from typing import IO, Any

import numpy as np
import pye57
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from wristscan.daemon.io.atomic import CloseOrAbort, atomic_writer

__all__ = ["GPS_UTC_OFFSET_S", "E57Writer", "SpooledScan", "utc_ns_to_gps_s"]

GPS_UTC_OFFSET_S = 315_964_800 - 18
"""GPS time = UTC (Unix) seconds - this: the GPS epoch 1980-01-06 and 18 leap seconds."""


def utc_ns_to_gps_s(t_ns: int) -> float:
    """E57's ``dateTimeValue`` (GPS seconds) of a UTC time in ns since the Unix epoch."""
    return t_ns * 1e-9 - GPS_UTC_OFFSET_S


class E57Writer(CloseOrAbort):
    """Write scans into an E57 file one at a time; see the module doc."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.n_scans = 0
        self.n_points = 0
        self._closed = False
        fd, tmp = tempfile.mkstemp(
            prefix=f".{self.path.name}.", suffix=".e57.tmp", dir=self.path.parent or Path(".")
        )
        os.close(fd)
        self._tmp = tmp
        try:
            self._e57: Any = pye57.E57(tmp, mode="w")
        except BaseException:
            self._discard()
            raise

    @property
    def closed(self) -> bool:
        return self._closed

    def add_scan(
        self,
        xyz: NDArray[np.floating],
        name: str,
        pose: NDArray[np.floating] | None = None,
        intensity: NDArray[np.integer] | NDArray[np.floating] | None = None,
        t_start_ns: int | None = None,
        t_end_ns: int | None = None,
    ) -> None:
        """One scan: ``xyz`` (N, 3) metres in the scan's coordinates, ``pose`` (4x4) from them
        to the file's frame (identity when None), ``intensity`` (N,) 0..255. An empty scan is
        not written (E57 has no bounds for it)."""
        if self._closed:
            raise ValueError(f"{self.path}: writer is closed")
        pts = np.asarray(xyz)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"xyz must be (N, 3), got {pts.shape}")
        n = pts.shape[0]
        if n == 0:
            return
        m = np.eye(4) if pose is None else np.asarray(pose, dtype=np.float64)
        if m.shape != (4, 4):
            raise ValueError(f"pose must be 4x4, got {m.shape}")
        data: dict[str, Any] = {
            "cartesianX": pts[:, 0],
            "cartesianY": pts[:, 1],
            "cartesianZ": pts[:, 2],
        }
        if intensity is not None:
            if np.shape(intensity) != (n,):
                raise ValueError(f"intensity must be ({n},), got {np.shape(intensity)}")
            data["intensity"] = intensity
        header = _scan_header(pts, m, name, intensity is not None, t_start_ns, t_end_ns)
        self._e57.write_scan_raw(
            data,
            name=name,
            rotation=header.rotation,
            translation=header.translation,
            scan_header=header,
        )
        self.n_scans += 1
        self.n_points += n

    def close(self) -> Path:
        """Finish the file and put it in place; returns its path. On failure nothing is left
        behind and the error propagates."""
        if self._closed:
            return self.path
        try:
            self._e57.close()
            with open(self._tmp, "rb") as src, atomic_writer(self.path) as out:
                shutil.copyfileobj(src, out, 1 << 22)
        except BaseException:
            self.abort()
            raise
        self._closed = True
        self._discard()
        return self.path

    def abort(self) -> None:
        """Drop everything written so far; nothing appears under ``path``."""
        if not self._closed:
            self._closed = True
            with contextlib.suppress(Exception):
                self._e57.close()
        self._discard()

    def _discard(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self._tmp)


def _scan_header(
    pts: NDArray[np.floating],
    pose: NDArray[np.float64],
    name: str,
    has_intensity: bool,
    t_start_ns: int | None,
    t_end_ns: int | None,
) -> SimpleNamespace:
    """What pye57 reads from a scan header when it writes a scan: name, pose, bounds in the
    file's frame, intensity limits, acquisition times."""
    qx, qy, qz, qw = Rotation.from_matrix(pose[:3, :3]).as_quat()
    lo = np.asarray(pts.min(axis=0), dtype=np.float64)
    hi = np.asarray(pts.max(axis=0), dtype=np.float64)
    corners = np.array(
        [[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])]
    )
    world = corners @ pose[:3, :3].T + pose[:3, 3]
    wlo, whi = world.min(axis=0), world.max(axis=0)
    head = SimpleNamespace(
        name=name,
        rotation=np.array([qw, qx, qy, qz]),
        translation=np.asarray(pose[:3, 3], dtype=np.float64),
        xMinimum=wlo[0],
        yMinimum=wlo[1],
        zMinimum=wlo[2],
        xMaximum=whi[0],
        yMaximum=whi[1],
        zMaximum=whi[2],
        acquisitionStart_dateTimeValue=0.0 if t_start_ns is None else utc_ns_to_gps_s(t_start_ns),
        acquisitionEnd_dateTimeValue=0.0 if t_end_ns is None else utc_ns_to_gps_s(t_end_ns),
    )
    if has_intensity:
        head.intensityMinimum = 0.0
        head.intensityMaximum = 255.0
    return head


class SpooledScan:
    """A scan collected batch by batch in temporary files beside ``path`` (float32 xyz and u8
    intensity), so that a long recording does not sit in memory; :meth:`write_into` hands it to
    an :class:`E57Writer` memory-mapped and removes the files."""

    def __init__(self, path: str | os.PathLike[str], has_intensity: bool) -> None:
        folder = Path(path).parent
        self.has_intensity = has_intensity
        self.n_points = 0
        self._files: list[tuple[str, IO[bytes]]] = []
        for what in ("xyz", "intensity")[: 1 + int(has_intensity)]:
            fd, name = tempfile.mkstemp(
                prefix=f".{Path(path).name}.", suffix=f".{what}.tmp", dir=folder
            )
            self._files.append((name, os.fdopen(fd, "w+b")))

    def add(self, xyz: NDArray[np.floating], intensity: NDArray[np.uint8] | None = None) -> None:
        self._files[0][1].write(np.ascontiguousarray(xyz, dtype="<f4").tobytes())
        if self.has_intensity:
            if intensity is None or intensity.shape != (len(xyz),):
                raise ValueError("this scan has intensity: give intensity (N,)")
            self._files[1][1].write(np.ascontiguousarray(intensity, dtype=np.uint8).tobytes())
        self.n_points += len(xyz)

    def write_into(
        self,
        writer: E57Writer,
        name: str,
        t_start_ns: int | None = None,
        t_end_ns: int | None = None,
    ) -> None:
        """Add the collected points to ``writer`` as one scan with the identity pose."""
        try:
            if self.n_points == 0:
                return
            for _, f in self._files:
                f.flush()
            xyz = np.memmap(self._files[0][0], dtype="<f4", mode="r", shape=(self.n_points, 3))
            inten = None
            if self.has_intensity:
                inten = np.memmap(
                    self._files[1][0], dtype=np.uint8, mode="r", shape=(self.n_points,)
                )
            writer.add_scan(xyz, name, intensity=inten, t_start_ns=t_start_ns, t_end_ns=t_end_ns)
            del xyz, inten
        finally:
            self.discard()

    def discard(self) -> None:
        """Remove the temporary files."""
        for name, f in self._files:
            with contextlib.suppress(OSError):
                f.close()
            with contextlib.suppress(FileNotFoundError):
                os.unlink(name)
        self._files = []
