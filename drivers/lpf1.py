"""LPF1: wristscan's own framed profile protocol (one message: its format, parser and encoder).

The normative specification is ``docs/lpf1.md``; this module follows it. In short: a 72-byte
little-endian header, the payload (``x[N]`` unless uniform, ``z[N]``, ``intensity[N]`` if flagged)
and a CRC-32 (``zlib.crc32``) of header + payload. One message per UDP datagram, split into
fragments when larger than the datagram limit; on byte streams (TCP) a reader resynchronises on
the magic and the length; on serial links every message is COBS-encoded and ends with a zero byte.

Points are profile coordinates ``x`` (lateral, along the laser line) and ``z`` (depth), which are
the sensor frame's Y and Z (DESIGN.md): a :class:`~wristscan.drivers.records.Profile` gets
``y = x``. Decoders never return a partial or guessed profile: malformed input raises
:class:`FrameError` (or a subclass).

Reading a link (fragment reassembly, stream resynchronisation, serial frames) keeps state from
one read to the next; it lives in :mod:`wristscan.drivers.lpf1_reader`.
"""

from __future__ import annotations

import json
import logging
import struct
from dataclasses import dataclass
from enum import IntEnum, IntFlag
from functools import lru_cache
from typing import Any

import numpy as np
from cobs import cobs
from numpy.typing import ArrayLike, NDArray

from wristscan.drivers._crc import crc32
from wristscan.drivers.records import Profile

__all__ = [
    "CRC_LEN",
    "HEADER",
    "HEADER_LEN",
    "MAGIC",
    "MAX_PAYLOAD",
    "VERSION",
    "ChecksumError",
    "Flags",
    "FrameError",
    "Header",
    "Message",
    "MsgType",
    "PointFormat",
    "ProfileEncoder",
    "TruncatedError",
    "cobs_frame",
    "decode_profile",
    "encode_control",
    "encode_profile",
    "parse_message",
]

log = logging.getLogger(__name__)

MAGIC = b"LPF1"
VERSION = 1
HEADER = struct.Struct("<4sBBBBIIQQqIB3xIIiiHHI")
HEADER_LEN = HEADER.size  # 72
CRC_LEN = 4
MAX_PAYLOAD = 16 * 1024 * 1024
"""Largest payload a reader accepts (bytes); bigger lengths are treated as corruption."""
DEFAULT_MAX_MESSAGE = 65000
"""Default UDP datagram limit (bytes): above it a frame is split into fragments."""


class FrameError(ValueError):
    """Input that is not a well-formed LPF1 message (or not a consistent frame)."""


class TruncatedError(FrameError):
    """Fewer bytes than the header announces."""


class ChecksumError(FrameError):
    """CRC-32 mismatch: the message was corrupted."""


class MsgType(IntEnum):
    PROFILE = 1
    HEARTBEAT = 2
    STATUS = 3
    HELLO = 4


class Flags(IntFlag):
    INTENSITY = 0x01
    EXPLICIT_X = 0x02
    ENCODER_VALID = 0x04
    LAST_FRAGMENT = 0x08


class PointFormat(IntEnum):
    I16 = 0
    I32 = 1
    F32 = 2


_DTYPES: dict[PointFormat, np.dtype[Any]] = {
    PointFormat.I16: np.dtype("<i2"),
    PointFormat.I32: np.dtype("<i4"),
    PointFormat.F32: np.dtype("<f4"),
}
_SENTINEL = {PointFormat.I16: -32768, PointFormat.I32: -(2**31)}
"""Invalid-point marker in ``z`` for integer formats (f32 uses NaN)."""

# Plain ints for the per-frame path: an IntFlag ``&`` or an enum lookup costs about a
# microsecond each, which was most of a 2048-point profile's decoding time.
_F_INTENSITY = int(Flags.INTENSITY)
_F_EXPLICIT_X = int(Flags.EXPLICIT_X)
_F_ENCODER_VALID = int(Flags.ENCODER_VALID)
_F_LAST_FRAGMENT = int(Flags.LAST_FRAGMENT)
_PROFILE = int(MsgType.PROFILE)
_MSG_TYPES = frozenset(int(t) for t in MsgType)
_FORMAT = {int(f): (_DTYPES[f], _SENTINEL.get(f)) for f in PointFormat}
"""point_format -> (dtype, invalid marker or None for f32)."""


@lru_cache(maxsize=16)
def _x_grid(n: int, x_scale_nm: int, x_offset_um: int) -> NDArray[np.float64]:
    """The uniform x coordinates (m) of a profile without explicit x (read-only, shared)."""
    x = np.arange(n, dtype=np.float64) * (x_scale_nm * 1e-9) + x_offset_um * 1e-6
    x.flags.writeable = False
    return x


@dataclass(slots=True)
class Header:
    """Decoded header fields (units: ns, nm, µm as in the names); treat as read-only (not
    frozen: a frozen dataclass costs 2 µs more to build, once per datagram)."""

    version: int
    header_len: int
    msg_type: int
    flags: int
    payload_len: int
    sensor_id: int
    frame_counter: int
    timestamp_ns: int
    encoder: int
    point_count: int
    point_format: int
    x_scale_nm: int
    z_scale_nm: int
    x_offset_um: int
    z_offset_um: int
    frag_index: int
    frag_count: int
    frag_offset: int

    def frame_payload_len(self) -> int:
        """Bytes of the whole frame's payload (all fragments) implied by the point fields."""
        if self.msg_type != _PROFILE:
            return self.payload_len
        size = _FORMAT[self.point_format][0].itemsize
        n = self.point_count
        total = n * size
        if self.flags & _F_EXPLICIT_X:
            total += n * size
        if self.flags & _F_INTENSITY:
            total += n
        return total


@dataclass(frozen=True, slots=True)
class Message:
    header: Header
    payload: bytes

    @property
    def is_fragment(self) -> bool:
        return self.header.frag_count > 1

    def json(self) -> dict[str, Any]:
        """Payload of a HELLO or STATUS message (UTF-8 JSON object)."""
        try:
            value = json.loads(self.payload.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise FrameError(
                f"LPF1 {MsgType(self.header.msg_type).name} payload is not JSON"
            ) from exc
        if not isinstance(value, dict):
            raise FrameError("LPF1 control payload must be a JSON object")
        return value


# ----------------------------------------------------------------------------------------------
# Parsing


def parse_message(buf: bytes | bytearray | memoryview) -> Message:
    """Validate one complete message (exactly ``header_len + payload_len + 4`` bytes)."""
    data = bytes(buf)
    if len(data) < HEADER_LEN + CRC_LEN:
        raise TruncatedError(f"LPF1 message of {len(data)} bytes is shorter than a header")
    f = HEADER.unpack_from(data)
    if f[0] != MAGIC:
        raise FrameError(f"bad LPF1 magic {f[0]!r}")
    version, header_len, payload_len = f[1], f[2], f[5]
    if version != VERSION:
        raise FrameError(f"unsupported LPF1 version {version}")
    if header_len < HEADER_LEN:
        raise FrameError(f"LPF1 header_len {header_len} < {HEADER_LEN}")
    if payload_len > MAX_PAYLOAD:
        raise FrameError(f"LPF1 payload_len {payload_len} exceeds {MAX_PAYLOAD}")
    total = header_len + payload_len + CRC_LEN
    if len(data) < total:
        raise TruncatedError(f"LPF1 message has {len(data)} of {total} bytes")
    if len(data) > total:
        raise FrameError(f"LPF1 message has {len(data) - total} trailing bytes")
    (crc,) = struct.unpack_from("<I", data, total - CRC_LEN)
    if crc32(memoryview(data)[: total - CRC_LEN]) != crc:
        raise ChecksumError("LPF1 CRC-32 mismatch")
    h = Header(version, *f[2:])
    if h.msg_type not in _MSG_TYPES:
        raise FrameError(f"LPF1: {h.msg_type} is not a valid MsgType")
    if h.point_format not in _FORMAT:
        raise FrameError(f"LPF1: {h.point_format} is not a valid PointFormat")
    if h.frag_count < 1 or h.frag_index >= h.frag_count:
        raise FrameError(f"LPF1 fragment {h.frag_index} of {h.frag_count}")
    return Message(h, data[header_len : header_len + payload_len])


def decode_profile(message: Message | bytes, host_time_ns: int = 0) -> Profile:
    """A :class:`Profile` from one complete (unfragmented or reassembled) PROFILE message."""
    msg = message if isinstance(message, Message) else parse_message(message)
    h = msg.header
    if h.msg_type != _PROFILE:
        raise FrameError(f"LPF1 message type {MsgType(h.msg_type).name} carries no profile")
    if h.frag_count != 1:
        raise FrameError("LPF1 fragment: reassemble before decoding")
    n = h.point_count
    if n == 0:
        raise FrameError("LPF1 profile without points")
    if len(msg.payload) != h.frame_payload_len():
        raise FrameError(
            f"LPF1 payload of {len(msg.payload)} bytes, {h.frame_payload_len()} expected"
        )
    dt, sentinel = _FORMAT[h.point_format]
    flags = h.flags
    pos = 0
    x_raw = None
    if flags & _F_EXPLICIT_X:
        x_raw = np.frombuffer(msg.payload, dt, n, pos)
        pos += n * dt.itemsize
    z_raw = np.frombuffer(msg.payload, dt, n, pos)
    pos += n * dt.itemsize
    intensity = None
    if flags & _F_INTENSITY:
        intensity = np.frombuffer(msg.payload, np.uint8, n, pos).copy()
    if sentinel is None:
        z = z_raw.astype(np.float64)
        valid = np.isfinite(z)
    else:
        valid = z_raw != sentinel
        # Scaled in float64 (the ufunc casts first): integer products would wrap.
        z = np.multiply(z_raw, h.z_scale_nm * 1e-9, dtype=np.float64)
        z += h.z_offset_um * 1e-6
    if x_raw is None:
        x = _x_grid(n, h.x_scale_nm, h.x_offset_um)  # read-only, shared by such profiles
    elif sentinel is None:
        x = x_raw.astype(np.float64)
        valid &= np.isfinite(x)
    else:
        x_ok = x_raw != sentinel
        x = x_raw.astype(np.float64) * (h.x_scale_nm * 1e-9) + h.x_offset_um * 1e-6
        x[~x_ok] = np.nan
        valid &= x_ok
    if not valid.all():
        z[~valid] = np.nan
    return Profile(
        sensor_id=h.sensor_id,
        frame_counter=h.frame_counter,
        sensor_time_ns=h.timestamp_ns,
        host_time_ns=host_time_ns,
        y=x,
        z=z,
        valid=valid,
        intensity=intensity,
        encoder=h.encoder if flags & _F_ENCODER_VALID else None,
    )


def cobs_frame(message: bytes) -> bytes:
    """One message framed for a serial link: COBS-encoded, then a zero delimiter."""
    return bytes(cobs.encode(message)) + b"\x00"


# ----------------------------------------------------------------------------------------------
# Encoding


def _pack(
    msg_type: int,
    flags: int,
    payload: bytes | memoryview,
    sensor_id: int,
    frame_counter: int,
    timestamp_ns: int,
    encoder: int = 0,
    point_count: int = 0,
    point_format: int = 0,
    scales: tuple[int, int, int, int] = (0, 0, 0, 0),
    frag: tuple[int, int, int] = (0, 1, 0),
) -> bytes:
    """One message: header, payload, CRC-32 (the one place that lays a message out)."""
    head = HEADER.pack(
        MAGIC,
        VERSION,
        HEADER_LEN,
        msg_type,
        flags,
        len(payload),
        sensor_id,
        frame_counter,
        timestamp_ns,
        encoder,
        point_count,
        point_format,
        *scales,
        *frag,
    )
    crc = crc32(payload, crc32(head))
    return b"".join((head, payload, crc.to_bytes(4, "little")))


def encode_control(
    msg_type: MsgType,
    sensor_id: int,
    frame_counter: int,
    timestamp_ns: int,
    info: dict[str, Any] | None = None,
) -> bytes:
    """A HEARTBEAT (empty payload), HELLO or STATUS (JSON object payload) message."""
    if msg_type == MsgType.PROFILE:
        raise ValueError("use ProfileEncoder for profiles")
    payload = b"" if info is None else json.dumps(info, separators=(",", ":")).encode()
    return _pack(
        int(msg_type), Flags.LAST_FRAGMENT, payload, sensor_id, frame_counter, timestamp_ns
    )


class ProfileEncoder:
    """Encodes batches of profiles with one vectorised quantisation step.

    ``x_uniform=(x0_m, step_m)`` declares the lateral grid ``x_i = x0 + i * step`` (it is written
    as ``x_offset_um``/``x_scale_nm`` and the x array is omitted); otherwise x is sent explicitly
    with ``x_scale_nm``/``x_offset_um``. ``z_scale_nm``/``z_offset_um`` quantise z for the integer
    formats (F32 sends metres). Points outside the representable range become invalid.
    ``max_message_bytes`` splits frames into fragments (UDP).
    """

    def __init__(
        self,
        sensor_id: int,
        point_format: PointFormat = PointFormat.I16,
        *,
        z_scale_nm: int = 2000,
        z_offset_um: int = 100_000,
        x_scale_nm: int = 1000,
        x_offset_um: int = 0,
        x_uniform: tuple[float, float] | None = None,
        intensity: bool = False,
        max_message_bytes: int | None = DEFAULT_MAX_MESSAGE,
    ) -> None:
        self.sensor_id = int(sensor_id)
        self.point_format = PointFormat(point_format)
        self.intensity = intensity
        if self.point_format != PointFormat.F32 and (z_scale_nm <= 0 or x_scale_nm <= 0):
            raise ValueError("scales must be positive")
        self.z_scale_nm, self.z_offset_um = int(z_scale_nm), int(z_offset_um)
        self.x_scale_nm, self.x_offset_um = int(x_scale_nm), int(x_offset_um)
        self.explicit_x = x_uniform is None
        if x_uniform is not None:
            self.x_offset_um = round(x_uniform[0] * 1e6)
            self.x_scale_nm = round(x_uniform[1] * 1e9)
            if self.x_scale_nm <= 0:
                raise ValueError("uniform x step must be at least 1 nm")
        if max_message_bytes is not None and max_message_bytes < HEADER_LEN + CRC_LEN + 16:
            raise ValueError("max_message_bytes too small")
        self.max_message_bytes = max_message_bytes

    def _quantise(self, v: NDArray[np.float64], valid: NDArray[np.bool_], scale_nm: int,
                  offset_um: int) -> tuple[NDArray[Any], NDArray[np.bool_]]:  # fmt: skip
        fmt = self.point_format
        if fmt == PointFormat.F32:
            out32 = np.where(valid, v, np.nan).astype("<f4")
            return out32, valid & np.isfinite(out32)
        info = np.iinfo(_DTYPES[fmt])
        k = 1.0 / (scale_nm * 1e-9)
        q = v * k
        q -= offset_um * 1e-6 * k
        np.rint(q, out=q)
        with np.errstate(invalid="ignore"):  # NaN (no measurement) compares False: invalid
            ok = valid & (q > info.min) & (q <= info.max)  # info.min is the sentinel
        q[~ok] = info.min
        return q.astype(_DTYPES[fmt]), ok

    def encode(
        self,
        frame_counter: ArrayLike,
        timestamp_ns: ArrayLike,
        z: ArrayLike,
        valid: ArrayLike,
        x: ArrayLike | None = None,
        intensity: ArrayLike | None = None,
        encoder: ArrayLike | None = None,
    ) -> list[list[bytes]]:
        """Messages for ``P`` profiles: ``z``, ``valid`` (and explicit ``x``, ``intensity``)
        ``(P, N)`` in metres; counters, timestamps (device ns) and encoder counts ``(P,)``.
        Returns one list of messages (fragments) per profile."""
        z2 = np.atleast_2d(np.asarray(z, dtype=np.float64))
        v2 = np.atleast_2d(np.asarray(valid, dtype=bool))
        n_prof, n = z2.shape
        counters = np.broadcast_to(np.asarray(frame_counter, dtype=np.int64), (n_prof,))
        stamps = np.broadcast_to(np.asarray(timestamp_ns, dtype=np.int64), (n_prof,))
        payloads, flags = self._payloads(z2, v2, x, intensity)
        enc_list = [0] * n_prof
        if encoder is not None:
            enc_list = np.broadcast_to(np.asarray(encoder, dtype=np.int64), (n_prof,)).tolist()
            flags |= Flags.ENCODER_VALID
        scales = self._scales()
        total = payloads.shape[1]
        chunk = (
            total
            if self.max_message_bytes is None
            else self.max_message_bytes - HEADER_LEN - CRC_LEN
        )
        # Per-profile work is plain ints and bytes: this loop runs up to 10 000 times a second.
        count = max(1, -(-total // chunk))
        frame_flags = [int(flags)] * (count - 1) + [int(flags | Flags.LAST_FRAGMENT)]
        fmt = int(self.point_format)
        counter_list, stamp_list = counters.tolist(), stamps.tolist()
        out: list[list[bytes]] = []
        for p in range(n_prof):
            row = payloads[p].tobytes()
            out.append(
                [
                    _pack(
                        _PROFILE,
                        frame_flags[i],
                        row[i * chunk : (i + 1) * chunk] if count > 1 else row,
                        self.sensor_id,
                        counter_list[p],
                        stamp_list[p],
                        enc_list[p],
                        n,
                        fmt,
                        scales,
                        (i, count, i * chunk),
                    )
                    for i in range(count)
                ]
            )
        return out

    def _payloads(
        self,
        z2: NDArray[np.float64],
        v2: NDArray[np.bool_],
        x: ArrayLike | None,
        intensity: ArrayLike | None,
    ) -> tuple[NDArray[np.uint8], int]:
        """Each profile's payload bytes (one row per profile: x when explicit, z, intensity
        when sent), and the flags they imply."""
        n_prof = z2.shape[0]
        zq, ok = self._quantise(z2, v2, self.z_scale_nm, self.z_offset_um)
        flags = 0
        blocks: list[NDArray[Any]] = []
        if self.explicit_x:
            if x is None:
                raise ValueError("this encoder sends explicit x: pass x")
            x2 = np.broadcast_to(np.asarray(x, dtype=np.float64), z2.shape)
            # x is sent for invalid points too (their lateral position stays known).
            xq, xok = self._quantise(x2, np.isfinite(x2), self.x_scale_nm, self.x_offset_um)
            # A point whose x is unrepresentable is invalid as a whole.
            zq = np.where(xok | ~ok, zq, _SENTINEL.get(self.point_format, np.nan)).astype(zq.dtype)
            blocks.append(xq)
            flags |= Flags.EXPLICIT_X
        blocks.append(zq)
        if self.intensity:
            if intensity is None:
                raise ValueError("this encoder sends intensity: pass intensity")
            blocks.append(np.broadcast_to(np.asarray(intensity, dtype=np.uint8), z2.shape))
            flags |= Flags.INTENSITY
        payloads = np.concatenate([b.view(np.uint8).reshape(n_prof, -1) for b in blocks], axis=1)
        return payloads, int(flags)

    def _scales(self) -> tuple[int, int, int, int]:
        """The header's ``x_scale_nm, z_scale_nm, x_offset_um, z_offset_um`` (F32 sends
        metres: only a uniform x grid keeps its scale)."""
        if self.point_format == PointFormat.F32 and not self.explicit_x:
            return (self.x_scale_nm, 0, self.x_offset_um, 0)
        if self.point_format == PointFormat.F32:
            return (0, 0, 0, 0)
        return (self.x_scale_nm, self.z_scale_nm, self.x_offset_um, self.z_offset_um)


def encode_profile(
    profile: Profile,
    point_format: PointFormat = PointFormat.I16,
    *,
    uniform_x: bool | None = None,
    z_scale_nm: int = 2000,
    z_offset_um: int = 100_000,
    x_scale_nm: int = 1000,
    x_offset_um: int = 0,
    max_message_bytes: int | None = DEFAULT_MAX_MESSAGE,
) -> list[bytes]:
    """Messages (one, or several fragments) for one :class:`Profile`.

    ``uniform_x=None`` sends x as a uniform grid when ``profile.y`` is one (to within half a nm
    per point), explicitly otherwise.
    """
    y = np.asarray(profile.y, dtype=np.float64)
    n = y.shape[0]
    grid: tuple[float, float] | None = None
    if uniform_x is not False and n >= 2 and np.all(np.isfinite(y)):
        x0_um = round(y[0] * 1e6)
        step_nm = round((y[-1] - y[0]) / (n - 1) * 1e9)
        expect = x0_um * 1e-6 + np.arange(n) * step_nm * 1e-9
        if step_nm > 0 and np.max(np.abs(expect - y)) <= 0.5e-9 * n + 0.5e-6:
            grid = (x0_um * 1e-6, step_nm * 1e-9)
    if uniform_x and grid is None:
        raise ValueError("profile.y is not a uniform grid")
    enc = ProfileEncoder(
        profile.sensor_id,
        point_format,
        z_scale_nm=z_scale_nm,
        z_offset_um=z_offset_um,
        x_scale_nm=x_scale_nm,
        x_offset_um=x_offset_um,
        x_uniform=grid,
        intensity=profile.intensity is not None,
        max_message_bytes=max_message_bytes,
    )
    return enc.encode(
        profile.frame_counter,
        profile.sensor_time_ns,
        profile.z[None],
        profile.valid[None],
        x=None if grid is not None else y[None],
        intensity=None if profile.intensity is None else profile.intensity[None],
        encoder=profile.encoder,
    )[0]
