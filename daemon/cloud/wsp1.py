"""The ``WSP1`` robot-pose payload published on ``<prefix>/pose`` beside each WSC1 batch.

One message per published cloud batch, with the pose of every profile in it, so a subscriber
can draw the flange's trail, place the sensor in the world or write a ``PoseStamped`` per batch
without knowing the calibration or the kinematics.

Little-endian; a 48-byte header, then three arrays of ``n_poses`` rows:

| offset | type | field |
|---|---|---|
| 0 | 4 bytes | magic ``WSP1`` |
| 4 | u16 | version (1) |
| 6 | u16 | flags (0; reserved) |
| 8 | u64 | ``seq``: the sequence number of the WSC1 batch these profiles make |
| 16 | u32 | ``n_poses`` (the batch's profiles, in exposure order) |
| 20 | u32 | reserved (0) |
| 24 | 16 bytes | ``frame_id`` of ``sensor2frame``: ``base``, ``table``, ``part``; NUL padded |
| 40 | 8 bytes | reserved (0) |
| 48 | i64 ``[n]`` | ``t_ns``: each profile's exposure, UTC ns |
| | f64 ``[n][3][4]`` | ``flange2base``: the flange in the robot base frame, rows of [R t], metres |
| | f64 ``[n][3][4]`` | ``sensor2frame``: the sensor in ``frame_id`` (what its points used) |
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["ENCODING", "HEADER", "PoseBatch", "Wsp1Error", "decode", "encode"]

MAGIC = b"WSP1"
VERSION = 1
HEADER = struct.Struct("<4sHHQII16s8s")
assert HEADER.size == 48
ENCODING = "application/octet-stream;wsp1"
_ROW = 8 + 2 * 12 * 8
"""Bytes per pose: the time and two 3x4 float64 matrices."""


class Wsp1Error(ValueError):
    """A payload that is not a valid WSP1 version 1 message."""


@dataclass(frozen=True)
class PoseBatch:
    """The poses of one batch's profiles. Arrays are read-only views into the payload."""

    seq: int
    frame_id: str
    t_ns: NDArray[np.int64]
    """(P,) exposure, UTC ns."""
    flange2base: NDArray[np.float64]
    """(P, 4, 4) the flange in the base frame, metres."""
    sensor2frame: NDArray[np.float64]
    """(P, 4, 4) the sensor in ``frame_id``, metres."""

    @property
    def n_poses(self) -> int:
        return int(self.t_ns.shape[0])


def _rows(m: NDArray[np.floating], name: str, n: int) -> NDArray[np.float64]:
    a = np.asarray(m, dtype=np.float64)
    if a.shape != (n, 4, 4):
        raise ValueError(f"{name} must be ({n}, 4, 4), got {a.shape}")
    return np.ascontiguousarray(a[:, :3, :], dtype="<f8")


def encode(
    seq: int,
    frame_id: str,
    t_ns: NDArray[np.integer],
    flange2base: NDArray[np.floating],
    sensor2frame: NDArray[np.floating],
) -> bytes:
    """One WSP1 message; ``t_ns`` (P,), the transforms (P, 4, 4) in metres."""
    t = np.ascontiguousarray(t_ns, dtype="<i8")
    if t.ndim != 1:
        raise ValueError(f"t_ns must be 1-D, got shape {t.shape}")
    n = int(t.shape[0])
    frame = frame_id.encode()
    if len(frame) > 16:
        raise ValueError(f"frame_id longer than 16 bytes: {frame_id!r}")
    head = HEADER.pack(MAGIC, VERSION, 0, seq, n, 0, frame, b"")
    f2b = _rows(flange2base, "flange2base", n)
    s2f = _rows(sensor2frame, "sensor2frame", n)
    return b"".join((head, t.tobytes(), f2b.tobytes(), s2f.tobytes()))


def _square(rows: NDArray[np.float64]) -> NDArray[np.float64]:
    n = rows.shape[0]
    out = np.zeros((n, 4, 4))
    out[:, :3, :] = rows
    out[:, 3, 3] = 1.0
    out.flags.writeable = False
    return out


def decode(payload: bytes | bytearray | memoryview) -> PoseBatch:
    """Parse a WSP1 message; raises :class:`Wsp1Error` on anything malformed."""
    buf = memoryview(payload).cast("B")
    if buf.nbytes < HEADER.size:
        raise Wsp1Error(f"{buf.nbytes} bytes is shorter than the {HEADER.size}-byte header")
    magic, version, flags, seq, n, _r, frame, _r2 = HEADER.unpack_from(buf)
    if magic != MAGIC:
        raise Wsp1Error(f"bad magic {bytes(magic)!r}")
    if version != VERSION or flags != 0:
        raise Wsp1Error(f"unsupported version {version} / flags {flags:#x}")
    if buf.nbytes != HEADER.size + n * _ROW:
        raise Wsp1Error(f"{buf.nbytes} bytes where {n} poses need {HEADER.size + n * _ROW}")
    try:
        frame_id = bytes(frame).rstrip(b"\0").decode()
    except UnicodeDecodeError as exc:
        raise Wsp1Error(f"frame_id is not UTF-8: {exc}") from exc
    t = np.frombuffer(buf, "<i8", n, HEADER.size)
    mats = np.frombuffer(buf, "<f8", 24 * n, HEADER.size + 8 * n).reshape(2, n, 3, 4)
    if not np.all(np.isfinite(mats)):
        raise Wsp1Error("a transform holds a non-finite number")
    return PoseBatch(int(seq), frame_id, t, _square(mats[0]), _square(mats[1]))
