"""LMI Gocator Protocol: control commands and replies, data and health messages (GDP).

The reference is the "Gocator Protocol" chapter of LMI's Gocator user manual; ``docs/gocator.md``
maps each layout here to its section. In short (little-endian throughout):

* **Control channel** (TCP 3190): a command is ``length u32, id u16`` and its parameters; the
  reply is ``length u32, id u16, status i32`` and its fields (status 1 = OK). ``length`` counts
  the whole message including itself.
* **Data channel** (TCP 3196) and **health channel** (TCP 3194) carry GDP messages: ``size u32,
  control u16`` (bit 15: last message of a group, bits 0-14: type), then the message. A frame's
  results come as one group: a Stamp (type 1: frame index, timestamp in µs, encoder, status,
  serial number), then the profile (type 5 profile point cloud: ``x, z`` int16 pairs; type 6
  uniform profile: int16 ranges on the grid ``x_i = xOffset + i * xScale``), then optionally the
  profile intensity (type 7). Profile messages carry ``attributeSize``: the points start at
  ``8 + attributeSize`` whatever the firmware's attribute list. Coordinates are
  ``offset (µm) + raw * scale (nm)``; the int16 null ``-32768`` marks a point without data.

:class:`~wristscan.drivers.gocator_reader.GdpReader` splits a byte stream into message groups
and resynchronises after damage (a TCP stream carries no checksum: the structure of each
message is checked here, :func:`check_message`). Decoders never return a
partial profile: malformed input raises :class:`FrameError`. :class:`GocatorEncoder` builds
the groups the simulated sensor sends, vectorised over a batch.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "CONTROL_PORT",
    "DATA_PORT",
    "HEALTH_PORT",
    "Cmd",
    "FrameError",
    "GocatorEncoder",
    "Msg",
    "ProfileData",
    "SensorInfo",
    "Stamp",
    "Status",
    "decode_health",
    "decode_intensity",
    "decode_profile",
    "decode_stamp",
    "encode_command",
    "encode_health",
    "encode_reply",
    "encode_system_info",
    "parse_reply",
    "parse_system_info",
]

CONTROL_PORT = 3190
HEALTH_PORT = 3194
DATA_PORT = 3196
NULL16 = -32768
"""The int16 null value: a point without data."""
LAST = 0x8000
"""Control bit 15: the last message of a group."""
MAX_MESSAGE = 1 << 24
"""Larger sizes are damage (a 16-bit profile of 2^22 points is far beyond any sensor)."""


class Cmd:
    """Control command identifiers used here ("Control Commands" in the manual)."""

    STOP = 0x1001
    GET_TIMESTAMP = 0x100A
    START = 0x100D
    GET_SYSTEM_INFO = 0x4002
    PROTOCOL_VERSION = 0x4511


class Status:
    """Reply status codes ("Commands", Status Codes)."""

    OK = 1
    FAILED = 0
    INVALID_STATE = -1000
    ITEM_NOT_FOUND = -999
    INVALID_COMMAND = -998
    INVALID_PARAMETER = -997
    NOT_SUPPORTED = -996


class Msg:
    """GDP message types ("Data Results", "Health Results")."""

    HEALTH = 0
    STAMP = 1
    PROFILE_POINT_CLOUD = 5
    UNIFORM_PROFILE = 6
    PROFILE_INTENSITY = 7


class FrameError(ValueError):
    """Malformed Gocator input: a message whose structure does not hold together."""


# ----------------------------------------------------------------------------------------------
# Control channel

CMD_HEADER = struct.Struct("<IH")  # length, id
REPLY_HEADER = struct.Struct("<IHi")  # length, id, status
SENSOR_INFO = struct.Struct("<I4s32s4siii")  # deviceId, address, modelName, firmware, state...
MAX_COMMAND = 1 << 16


def encode_command(cmd_id: int, payload: bytes = b"") -> bytes:
    return CMD_HEADER.pack(CMD_HEADER.size + len(payload), cmd_id) + payload


def encode_reply(cmd_id: int, status: int, payload: bytes = b"") -> bytes:
    return REPLY_HEADER.pack(REPLY_HEADER.size + len(payload), cmd_id, status) + payload


def parse_reply(msg: bytes | bytearray | memoryview) -> tuple[int, int, bytes]:
    """``(id, status, fields)`` of one complete reply."""
    if len(msg) < REPLY_HEADER.size:
        raise FrameError(f"Gocator reply of {len(msg)} bytes is shorter than its header")
    length, cmd_id, status = REPLY_HEADER.unpack_from(msg)
    if length != len(msg):
        raise FrameError(f"Gocator reply length {length} but {len(msg)} bytes")
    return cmd_id, status, bytes(msg[REPLY_HEADER.size :])


@dataclass(frozen=True, slots=True)
class SensorInfo:
    """The ``localInfo`` of the Get System Info reply."""

    device_id: int
    """Serial number."""
    address: str
    model: str
    firmware: tuple[int, int, int, int]
    state: int
    """-1 conflict, 0 ready, 1 running."""
    role: int
    buddy_id: int


def encode_system_info(info: SensorInfo) -> bytes:
    """Reply fields of Get System Info (no remote sensors)."""
    return SENSOR_INFO.pack(
        info.device_id,
        bytes(int(p) for p in info.address.split(".")),
        info.model.encode("ascii")[:31],
        bytes(info.firmware),
        info.state,
        info.role,
        info.buddy_id,
    ) + struct.pack("<I", 0)


def parse_system_info(fields: bytes) -> SensorInfo:
    if len(fields) < SENSOR_INFO.size:
        raise FrameError(f"Get System Info reply of {len(fields)} bytes lacks the sensor info")
    dev, addr, model, fw, state, role, buddy = SENSOR_INFO.unpack_from(fields)
    return SensorInfo(
        dev,
        ".".join(str(b) for b in addr),
        model.split(b"\0", 1)[0].decode("ascii", "replace"),
        (fw[0], fw[1], fw[2], fw[3]),
        state,
        role,
        buddy,
    )


# ----------------------------------------------------------------------------------------------
# GDP messages: layouts

GDP_HEADER = struct.Struct("<IH")  # size, control
STAMP_HEADER = struct.Struct("<IHIHBB")  # size, control, count, stampSize, source, reserved
STAMP = struct.Struct("<QQqqQI")  # frameIndex, timestamp, encoder, encoderAtZ, status, serial
STAMP_SIZE = 56
"""What the simulated sensor writes (the manual's current stamp size); readers use the field."""
PROFILE_HEADER = struct.Struct("<IHHIIIIii")  # ... attributeSize, count, width, scales, offsets
PROFILE_ATTRS_MIN = 24  # count .. zOffset: what decoding needs (the manual's minimum is 32)
INTENSITY_HEADER = struct.Struct("<IHHIIIi")  # ..., count, width, xScale, xOffset
INTENSITY_ATTRS_MIN = 16
HEALTH_HEADER = struct.Struct("<IHIB3x")  # size, control, count, source
INDICATOR = np.dtype([("id", "<u4"), ("instance", "<u4"), ("value", "<i8")])


def _stamp_dtype() -> np.dtype:
    return np.dtype(
        [("size", "<u4"), ("control", "<u2"), ("count", "<u4"), ("stamp_size", "<u2"),
         ("source", "u1"), ("reserved", "u1"), ("frame_index", "<u8"), ("timestamp", "<u8"),
         ("encoder", "<i8"), ("encoder_at_z", "<i8"), ("status", "<u8"), ("serial", "<u4"),
         ("reserved2", "V12")]
    )  # fmt: skip


def _profile_dtype(width: int, uniform: bool) -> np.dtype:
    points = ("ranges", "<i2", (width,)) if uniform else ("points", "<i2", (width, 2))
    return np.dtype(
        [("size", "<u4"), ("control", "<u2"), ("attr_size", "<u2"), ("count", "<u4"),
         ("width", "<u4"), ("x_scale", "<u4"), ("z_scale", "<u4"), ("x_offset", "<i4"),
         ("z_offset", "<i4"), ("source", "u1"), ("exposure", "<u4"), ("camera", "u1"),
         ("reserved", "V2"), ("stream_step", "<i4"), ("stream_step_id", "<i4"), points]
    )  # fmt: skip


def _intensity_dtype(width: int) -> np.dtype:
    return np.dtype(
        [("size", "<u4"), ("control", "<u2"), ("attr_size", "<u2"), ("count", "<u4"),
         ("width", "<u4"), ("x_scale", "<u4"), ("x_offset", "<i4"), ("source", "u1"),
         ("exposure", "<u4"), ("camera", "u1"), ("reserved", "V2"), ("points", "u1", (width,))]
    )  # fmt: skip


def check_message(buf: bytes | bytearray | memoryview, pos: int = 0) -> tuple[int, int, bool]:
    """``(size, type, last)`` of the message at ``pos`` of ``buf`` (complete or not): the size
    field must be plausible and, for the types decoded here, agree with the counts inside.
    Raises :class:`FrameError`; :class:`IndexError`-free on a short buffer (checks what is
    there: the caller waits for more bytes when ``size`` exceeds what it holds)."""
    have = len(buf) - pos
    size, control = GDP_HEADER.unpack_from(buf, pos)
    kind, last = control & 0x7FFF, bool(control & LAST)
    if not GDP_HEADER.size <= size <= MAX_MESSAGE:
        raise FrameError(f"Gocator message size {size} out of range")
    if kind == Msg.STAMP:
        if have >= STAMP_HEADER.size:
            _, _, count, stamp_size, _, _ = STAMP_HEADER.unpack_from(buf, pos)
            if stamp_size < STAMP.size or count < 1 or size != 14 + count * stamp_size:
                raise FrameError(f"Gocator stamp message of {size} bytes: {count} x {stamp_size}")
    elif kind in (Msg.UNIFORM_PROFILE, Msg.PROFILE_POINT_CLOUD, Msg.PROFILE_INTENSITY):
        if have >= 16:
            attr, count, width = struct.unpack_from("<HII", buf, pos + 6)
            point = 1 if kind == Msg.PROFILE_INTENSITY else 2 if kind == Msg.UNIFORM_PROFILE else 4
            least = INTENSITY_ATTRS_MIN if kind == Msg.PROFILE_INTENSITY else PROFILE_ATTRS_MIN
            if attr < least or size != 8 + attr + count * width * point:
                raise FrameError(
                    f"Gocator type {kind} message of {size} bytes: attributes {attr}, "
                    f"{count} x {width} points"
                )
    elif kind == Msg.HEALTH and have >= HEALTH_HEADER.size:
        count = struct.unpack_from("<I", buf, pos + 6)[0]
        if size != HEALTH_HEADER.size + INDICATOR.itemsize * count:
            raise FrameError(f"Gocator health message of {size} bytes: {count} indicators")
    return size, kind, last


# ----------------------------------------------------------------------------------------------
# GDP messages: decoding


@dataclass(frozen=True, slots=True)
class Stamp:
    frame_index: int
    timestamp_us: int
    encoder: int
    encoder_at_z: int
    status: int
    serial: int
    stamp_size: int


@dataclass(frozen=True, slots=True)
class ProfileData:
    """One decoded profile message: coordinates in metres (NaN ``z`` where invalid)."""

    kind: int
    x: NDArray[np.float64]
    """Read-only and shared between profiles for a uniform profile: copy before editing."""
    z: NDArray[np.float64]
    valid: NDArray[np.bool_]
    signature: tuple[int, ...]
    """The fields that stay constant in a stream (type, attributes size, width, scaling)."""


def decode_stamp(msg: bytes | bytearray | memoryview) -> Stamp:
    """The first stamp of a complete Stamp message."""
    size, kind, _ = check_message(msg)
    if kind != Msg.STAMP or size != len(msg):
        raise FrameError("not a complete Gocator stamp message")
    stamp_size = STAMP_HEADER.unpack_from(msg)[3]
    frame, time_us, encoder, at_z, status, serial = STAMP.unpack_from(msg, STAMP_HEADER.size)
    return Stamp(frame, time_us, encoder, at_z, status, serial, stamp_size)


@lru_cache(maxsize=16)
def _uniform_x(width: int, x_scale_nm: int, x_offset_um: int) -> NDArray[np.float64]:
    x = np.arange(width, dtype=np.float64) * (x_scale_nm * 1e-9) + x_offset_um * 1e-6
    x.flags.writeable = False
    return x


def decode_profile(msg: bytes | bytearray | memoryview) -> ProfileData:
    """A complete uniform profile (type 6) or profile point cloud (type 5) message holding one
    profile array; the ``x`` of a uniform profile is the grid ``xOffset + i * xScale``."""
    size, kind, _ = check_message(msg)
    if kind not in (Msg.UNIFORM_PROFILE, Msg.PROFILE_POINT_CLOUD) or size != len(msg):
        raise FrameError("not a complete Gocator profile message")
    _, _, attr, count, width, xs, zs, xo, zo = PROFILE_HEADER.unpack_from(msg)
    if count != 1:
        raise FrameError(f"Gocator profile message with {count} arrays (1 expected)")
    if xs == 0 or zs == 0:
        raise FrameError("Gocator profile scale is zero")
    start = 8 + attr
    if kind == Msg.UNIFORM_PROFILE:
        raw = np.frombuffer(msg, "<i2", width, start)
        valid = raw != NULL16
        x = _uniform_x(width, xs, xo)
    else:
        pts = np.frombuffer(msg, "<i2", 2 * width, start).reshape(width, 2)
        raw = pts[:, 1]
        valid = (raw != NULL16) & (pts[:, 0] != NULL16)
        x = pts[:, 0] * (xs * 1e-9) + xo * 1e-6
    z = raw * (zs * 1e-9) + zo * 1e-6
    z[~valid] = np.nan
    return ProfileData(kind, x, z, valid, (kind, attr, width, xs, zs, xo, zo))


def decode_intensity(msg: bytes | bytearray | memoryview) -> NDArray[np.uint8]:
    """The 8-bit intensities of a complete profile intensity message holding one array."""
    size, kind, _ = check_message(msg)
    if kind != Msg.PROFILE_INTENSITY or size != len(msg):
        raise FrameError("not a complete Gocator profile intensity message")
    _, _, attr, count, width, _, _ = INTENSITY_HEADER.unpack_from(msg)
    if count != 1:
        raise FrameError(f"Gocator intensity message with {count} arrays (1 expected)")
    return np.frombuffer(msg, np.uint8, width, 8 + attr).copy()


def decode_health(msg: bytes | bytearray | memoryview) -> dict[tuple[int, int], int]:
    """``{(indicator id, instance): value}`` of a complete health message."""
    size, kind, _ = check_message(msg)
    if kind != Msg.HEALTH or size != len(msg):
        raise FrameError("not a complete Gocator health message")
    count = struct.unpack_from("<I", msg, 6)[0]
    rows = np.frombuffer(msg, INDICATOR, count, HEALTH_HEADER.size)
    return {(int(r["id"]), int(r["instance"])): int(r["value"]) for r in rows}


# ----------------------------------------------------------------------------------------------
# Encoding (the simulated sensor)


def encode_health(indicators: dict[tuple[int, int], int], source: int = 0) -> bytes:
    rows = np.zeros(len(indicators), INDICATOR)
    for i, ((ident, inst), value) in enumerate(indicators.items()):
        rows[i] = (ident, inst, value)
    size = HEALTH_HEADER.size + rows.nbytes
    return HEALTH_HEADER.pack(size, Msg.HEALTH | LAST, len(rows), source) + rows.tobytes()


class GocatorEncoder:
    """Builds the message groups of a Gocator streaming profiles: Stamp, then a uniform profile
    (``uniform``) or a profile point cloud, then the profile intensity (``intensity``).

    Scaling: ``z`` spans ``z_range_m`` with 16-bit steps (``z_scale_nm``, ``z_offset_um``);
    a uniform profile's grid is ``x_offset_um + i * x_scale_nm`` (set by :meth:`set_grid`).
    """

    def __init__(
        self,
        serial: int,
        width: int,
        *,
        uniform: bool = True,
        intensity: bool = False,
        z_range_m: tuple[float, float] = (0.05, 0.15),
        x_half_width_m: float = 0.025,
        exposure_ns: int = 100_000,
    ) -> None:
        if width < 1:
            raise ValueError("a Gocator profile needs at least one point")
        self.serial, self.width = int(serial), int(width)
        self.uniform, self.intensity = uniform, intensity
        lo, hi = z_range_m
        self.z_offset_um = round((lo + hi) / 2 * 1e6)
        self.z_scale_nm = max(1, int(np.ceil((hi - lo) * 1e9 / 65000)))
        self.x_scale_nm = max(1, int(np.ceil(2 * x_half_width_m * 1e9 / 65000)))
        self.x_offset_um = 0
        self.exposure_ns = exposure_ns
        if uniform:
            self.set_grid(np.linspace(-x_half_width_m, x_half_width_m, width))
        parts = [("stamp", _stamp_dtype()), ("profile", _profile_dtype(width, uniform))]
        if intensity:
            parts.append(("intensity", _intensity_dtype(width)))
        self.dtype = np.dtype(parts)

    def set_grid(self, x: ArrayLike) -> None:
        """The uniform grid nearest to the lateral positions ``x`` (m): ``xScale`` their mean
        step, ``xOffset`` centring the rounding error."""
        xs = np.asarray(x, dtype=np.float64)
        step = (xs[-1] - xs[0]) / max(1, xs.size - 1)
        self.x_scale_nm = max(1, round(step * 1e9))
        i = np.arange(xs.size)
        self.x_offset_um = round(float(np.mean(xs - i * self.x_scale_nm * 1e-9)) * 1e6)

    def _fill_header(self, rec: np.ndarray, n_prof: int) -> None:
        w, dt = self.width, self.dtype
        st = rec["stamp"]
        st["size"] = dt["stamp"].itemsize
        st["control"] = Msg.STAMP
        st["count"] = 1
        st["stamp_size"] = STAMP_SIZE
        st["serial"] = self.serial
        pr = rec["profile"]
        pr["size"] = dt["profile"].itemsize
        pr["control"] = (Msg.UNIFORM_PROFILE if self.uniform else Msg.PROFILE_POINT_CLOUD) | (
            0 if self.intensity else LAST
        )
        pr["attr_size"] = 40
        pr["count"], pr["width"] = 1, w
        pr["x_scale"], pr["z_scale"] = self.x_scale_nm, self.z_scale_nm
        pr["x_offset"], pr["z_offset"] = self.x_offset_um, self.z_offset_um
        pr["exposure"], pr["stream_step"] = self.exposure_ns, 2
        if self.intensity:
            it = rec["intensity"]
            it["size"] = dt["intensity"].itemsize
            it["control"] = Msg.PROFILE_INTENSITY | LAST
            it["attr_size"] = 24
            it["count"], it["width"] = 1, w
            it["x_scale"], it["x_offset"] = self.x_scale_nm, self.x_offset_um
            it["exposure"] = self.exposure_ns

    def encode(
        self,
        frame_index: ArrayLike,
        timestamp_us: ArrayLike,
        x: ArrayLike,
        z: ArrayLike,
        valid: ArrayLike,
        intensity: ArrayLike | None = None,
        encoder: ArrayLike | None = None,
    ) -> list[bytes]:
        """One group (bytes) per profile; ``x``, ``z``, ``valid`` ``(P, W)`` in metres (``x``
        is ignored for a uniform profile: its grid is fixed), counters and times ``(P,)``."""
        z2 = np.atleast_2d(np.asarray(z, dtype=np.float64))
        n_prof = z2.shape[0]
        if z2.shape[1] != self.width:
            raise ValueError(f"profiles of {z2.shape[1]} points, the encoder has {self.width}")
        v2 = np.broadcast_to(np.asarray(valid, dtype=bool), z2.shape)
        rec = np.zeros(n_prof, self.dtype)
        self._fill_header(rec, n_prof)
        st = rec["stamp"]
        st["frame_index"] = np.asarray(frame_index, dtype=np.int64).astype(np.uint64)
        st["timestamp"] = np.maximum(np.asarray(timestamp_us, dtype=np.int64), 0)
        if encoder is not None:
            st["encoder"] = np.asarray(encoder, dtype=np.int64)
        zr = np.rint((z2 - self.z_offset_um * 1e-6) / (self.z_scale_nm * 1e-9))
        with np.errstate(invalid="ignore"):
            ok = v2 & (zr > NULL16) & (zr <= 32767)
        if self.uniform:
            rec["profile"]["ranges"] = np.where(ok, zr, NULL16).astype("<i2")
        else:
            x2 = np.broadcast_to(np.asarray(x, dtype=np.float64), z2.shape)
            xr = np.rint((x2 - self.x_offset_um * 1e-6) / (self.x_scale_nm * 1e-9))
            with np.errstate(invalid="ignore"):
                ok &= (xr > NULL16) & (xr <= 32767)
            pts = rec["profile"]["points"]
            pts[..., 0] = np.where(ok, xr, NULL16)
            pts[..., 1] = np.where(ok, zr, NULL16)
        if self.intensity:
            if intensity is None:
                raise ValueError("this encoder sends intensity: pass intensity")
            rec["intensity"]["points"] = np.where(ok, np.asarray(intensity, dtype=np.uint8), 0)
        blob = rec.tobytes()
        size = self.dtype.itemsize
        return [blob[i * size : (i + 1) * size] for i in range(n_prof)]
