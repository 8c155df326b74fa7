"""The cloud file format, chosen by the file's extension everywhere a cloud is written.

| extension | format | extra to install |
|---|---|---|
| ``.ply`` | PLY (:mod:`~wristscan.daemon.io.ply`) | none |
| ``.npz`` | NumPy archive | none |
| ``.mcap`` | MCAP, ROS 2 messages (:mod:`~wristscan.daemon.io.mcap_out`) | ``mcap`` |
| ``.e57`` | E57 (:mod:`~wristscan.daemon.io.e57_out`) | ``e57`` |

:func:`cloud_format` names the format of a path or raises :class:`CloudFormatError` with a
message a user can act on (the extensions there are, or the ``pip install`` line of the missing
extra). :func:`open_batch_sink` opens the MCAP or E57 sink ``wristscan record`` streams its
batches into.
"""

from __future__ import annotations

import importlib.util
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "FORMATS",
    "Batch",
    "BatchSink",
    "CloudFormatError",
    "cloud_format",
    "open_batch_sink",
]


@dataclass(frozen=True)
class _Format:
    name: str
    extra: str | None
    modules: tuple[str, ...]
    """Top-level modules the format needs (the extra's packages)."""


FORMATS: dict[str, _Format] = {
    ".ply": _Format("ply", None, ()),
    ".npz": _Format("npz", None, ()),
    ".mcap": _Format("mcap", "mcap", ("mcap", "mcap_ros2", "rosbags")),
    ".e57": _Format("e57", "e57", ("pye57",)),
}


class CloudFormatError(ValueError):
    """An extension wristscan cannot write, or a format whose extra is not installed."""


def cloud_format(path: str | os.PathLike[str], allowed: tuple[str, ...] | None = None) -> str:
    """The format (``ply``, ``npz``, ``mcap``, ``e57``) of ``path`` by its extension, checked
    against ``allowed`` (format names; all when None) and the installed extras."""
    suffix = Path(path).suffix.lower()
    fmt = FORMATS.get(suffix)
    ok = [s for s, f in FORMATS.items() if allowed is None or f.name in allowed]
    if fmt is None or fmt.name not in [FORMATS[s].name for s in ok]:
        raise CloudFormatError(
            f"{str(path)!r}: unknown cloud file extension {suffix or '(none)'!r}; "
            f"use one of {', '.join(ok)}"
        )
    missing = [m for m in fmt.modules if importlib.util.find_spec(m) is None]
    if missing:
        raise CloudFormatError(
            f"writing {suffix} files needs the optional dependencies of the {fmt.extra!r} extra "
            f"(missing: {', '.join(missing)}): pip install 'wristscan[{fmt.extra}]'"
        )
    return fmt.name


@dataclass(frozen=True)
class Batch:
    """One batch of points as a sink takes it (what WSC1 carries)."""

    xyz: NDArray[np.float32]
    t_first_ns: int
    t_last_ns: int
    frame_id: str
    intensity: NDArray[np.uint8] | None = None
    flange2base: NDArray[np.float64] | None = None
    """The robot's flange in the base frame at the batch's exposure, when known."""


class BatchSink(Protocol):
    intensity_mismatch: int
    takes_poses: bool
    """Whether the format records robot poses (``add_pose``)."""

    def add_batch(self, batch: Batch) -> None: ...

    def add_pose(
        self,
        stamp_ns: int,
        flange2base: NDArray[np.float64],
        sensor2frame: NDArray[np.float64],
        frame_id: str,
    ) -> None: ...

    def finish(self) -> Path: ...

    def abort(self) -> None: ...


class _McapSink:
    def __init__(self, path: Path, metadata: dict[str, str]) -> None:
        from wristscan.daemon.io.mcap_out import McapCloudWriter

        self.writer = McapCloudWriter(path, metadata=metadata)
        self.intensity_mismatch = 0
        self.takes_poses = True

    def add_batch(self, batch: Batch) -> None:
        self.writer.write_cloud(batch.xyz, batch.t_first_ns, batch.frame_id, batch.intensity)
        if batch.flange2base is not None:
            self.writer.write_pose(batch.flange2base, batch.t_first_ns)

    def add_pose(
        self,
        stamp_ns: int,
        flange2base: NDArray[np.float64],
        sensor2frame: NDArray[np.float64],
        frame_id: str,
    ) -> None:
        """The flange in the base frame and the sensor in ``frame_id`` at ``stamp_ns``."""
        from wristscan.daemon.io.mcap_out import SENSOR_POSE_TOPIC

        self.writer.write_pose(flange2base, stamp_ns)
        self.writer.write_pose(sensor2frame, stamp_ns, frame_id, SENSOR_POSE_TOPIC)

    def finish(self) -> Path:
        return self.writer.close()

    def abort(self) -> None:
        self.writer.abort()


class _E57Sink:
    """One scan for the whole recording, spooled on disk; opened at the first batch (which
    decides whether the scan carries intensity)."""

    def __init__(self, path: Path, name: str) -> None:
        from wristscan.daemon.io.e57_out import E57Writer, SpooledScan

        self.path = path
        self.name = name
        self.writer = E57Writer(path)
        self.spool: SpooledScan | None = None
        self._spool_t = SpooledScan
        self.intensity_mismatch = 0
        self.takes_poses = False
        self.t_first_ns: int | None = None
        self.t_last_ns: int | None = None

    def add_batch(self, batch: Batch) -> None:
        if self.spool is None:
            self.spool = self._spool_t(self.path, batch.intensity is not None)
        intensity = batch.intensity
        if self.spool.has_intensity != (intensity is not None):
            self.intensity_mismatch += 1
            if self.spool.has_intensity:
                intensity = np.zeros(len(batch.xyz), np.uint8)
        self.spool.add(batch.xyz, intensity if self.spool.has_intensity else None)
        if self.t_first_ns is None:
            self.t_first_ns = batch.t_first_ns
        self.t_last_ns = batch.t_last_ns

    def add_pose(
        self,
        stamp_ns: int,
        flange2base: NDArray[np.float64],
        sensor2frame: NDArray[np.float64],
        frame_id: str,
    ) -> None:
        """Not recorded: the recording is one scan in the frame of its points."""

    def finish(self) -> Path:
        try:
            if self.spool is not None:
                self.spool.write_into(self.writer, self.name, self.t_first_ns, self.t_last_ns)
        except BaseException:
            self.abort()
            raise
        return self.writer.close()

    def abort(self) -> None:
        if self.spool is not None:
            self.spool.discard()
        self.writer.abort()


def open_batch_sink(path: Path, fmt: str, source: str) -> BatchSink:
    """The sink ``wristscan record`` streams into for ``fmt`` ``mcap`` or ``e57``."""
    if fmt == "mcap":
        return _McapSink(path, {"source": source, "units": "metres"})
    if fmt == "e57":
        return _E57Sink(path, f"wristscan record {source}")
    raise CloudFormatError(f"no batch sink for format {fmt!r}")
