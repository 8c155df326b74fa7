"""The ``WSC1`` point-cloud payload published on ``<prefix>/cloud`` (DESIGN.md, zenoh contract).

Little-endian; a 64-byte header, then ``xyz`` as float32 ``[n_points][3]`` metres, then the
optional blocks in flag-bit order: intensity (u8 per point, bit 0) and profile index (u32 per
point, bit 1). The header layout never changes within version 1.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "ENCODING",
    "FLAG_INTENSITY",
    "FLAG_PROFILE_INDEX",
    "HEADER",
    "Cloud",
    "Wsc1Error",
    "decode",
    "encode",
]

MAGIC = b"WSC1"
VERSION = 1
HEADER = struct.Struct("<4sHHQqqII16s8s")
assert HEADER.size == 64
ENCODING = "application/octet-stream;wsc1"
FLAG_INTENSITY = 1 << 0
FLAG_PROFILE_INDEX = 1 << 1
_KNOWN_FLAGS = FLAG_INTENSITY | FLAG_PROFILE_INDEX
FRAMES = ("base", "table", "part")


class Wsc1Error(ValueError):
    """A payload that is not a valid WSC1 version 1 message."""


@dataclass(frozen=True)
class Cloud:
    """One decoded WSC1 batch. Arrays are read-only views into the payload where possible."""

    seq: int
    t_first_ns: int
    """UTC ns of the first profile in the batch."""
    t_last_ns: int
    n_profiles: int
    frame_id: str
    xyz: NDArray[np.float32]
    """(N, 3) metres."""
    intensity: NDArray[np.uint8] | None = None
    profile_index: NDArray[np.uint32] | None = None

    @property
    def n_points(self) -> int:
        return int(self.xyz.shape[0])


def encode(
    xyz: NDArray[np.floating],
    *,
    seq: int,
    t_first_ns: int,
    t_last_ns: int,
    n_profiles: int,
    frame_id: str = "base",
    intensity: NDArray[np.uint8] | None = None,
    profile_index: NDArray[np.integer] | None = None,
) -> bytes:
    """Serialise one batch. ``xyz`` (N, 3) metres; optional per-point blocks of length N."""
    xyz_a = np.asarray(xyz)
    if xyz_a.ndim != 2 or xyz_a.shape[1] != 3:
        raise ValueError(f"xyz must be (N, 3), got {xyz_a.shape}")
    n = xyz_a.shape[0]
    frame = frame_id.encode("ascii")
    if len(frame) > 16:
        raise ValueError(f"frame_id {frame_id!r} longer than 16 bytes")
    flags = 0
    if intensity is not None:
        if intensity.shape != (n,):
            raise ValueError(f"intensity must be ({n},), got {intensity.shape}")
        flags |= FLAG_INTENSITY
    if profile_index is not None:
        if profile_index.shape != (n,):
            raise ValueError(f"profile_index must be ({n},), got {profile_index.shape}")
        flags |= FLAG_PROFILE_INDEX
    size = HEADER.size + 12 * n
    size += n if intensity is not None else 0
    size += 4 * n if profile_index is not None else 0
    # One buffer, each block converted straight into its place, then one copy into the bytes
    # object: a batch is megabytes at 5 kHz, and every extra pass over it costs.
    buf = np.empty(size, dtype=np.uint8)
    head = HEADER.pack(
        MAGIC, VERSION, flags, seq, t_first_ns, t_last_ns, n, n_profiles, frame, bytes(8)
    )
    off = HEADER.size
    buf[:off] = np.frombuffer(head, dtype=np.uint8)
    buf[off : off + 12 * n].view("<f4").reshape(n, 3)[...] = xyz_a
    off += 12 * n
    if intensity is not None:
        buf[off : off + n] = intensity
        off += n
    if profile_index is not None:
        buf[off : off + 4 * n].view("<u4")[...] = profile_index
    return buf.tobytes()


def decode(payload: bytes | bytearray | memoryview) -> Cloud:
    """Parse one WSC1 payload; raises :class:`Wsc1Error` on anything malformed."""
    buf = memoryview(payload).cast("B")
    if len(buf) < HEADER.size:
        raise Wsc1Error(f"payload of {len(buf)} bytes is shorter than the 64-byte header")
    magic, version, flags, seq, t0, t1, n, n_prof, frame, _ = HEADER.unpack_from(buf)
    if magic != MAGIC:
        raise Wsc1Error(f"bad magic {magic!r}")
    if version != VERSION:
        raise Wsc1Error(f"unsupported WSC1 version {version}")
    if flags & ~_KNOWN_FLAGS:
        # Unknown blocks would sit after the known ones; we cannot size them, so refuse.
        raise Wsc1Error(f"unknown flag bits 0x{flags & ~_KNOWN_FLAGS:04x}")
    expected = HEADER.size + 12 * n
    expected += n if flags & FLAG_INTENSITY else 0
    expected += 4 * n if flags & FLAG_PROFILE_INDEX else 0
    if len(buf) != expected:
        raise Wsc1Error(f"payload has {len(buf)} bytes, header implies {expected}")
    off = HEADER.size
    xyz = np.frombuffer(buf, dtype="<f4", count=3 * n, offset=off).reshape(n, 3)
    off += 12 * n
    intensity = None
    if flags & FLAG_INTENSITY:
        intensity = np.frombuffer(buf, dtype=np.uint8, count=n, offset=off)
        off += n
    pidx = None
    if flags & FLAG_PROFILE_INDEX:
        pidx = np.frombuffer(buf, dtype="<u4", count=n, offset=off)
        if n and int(pidx.max()) >= n_prof:
            raise Wsc1Error("profile index beyond n_profiles")
    frame_id = frame.rstrip(b"\0").decode("ascii", errors="replace")
    return Cloud(seq, t0, t1, n_prof, frame_id, xyz, intensity, pidx)
