"""Riftek RF627 UDP profile stream (the "old" RF627 protocol, v1.x): encoder and decoder.

Layout (little-endian, PROTOCOLS.md; checked against RIFTEK-LLC/RF627-Protocol
``rf627_protocol_old_unpack_header_msg_from_profile_packet``), 64-byte header:

======  ====  ===================  ==================================================
offset  type  field                notes
======  ====  ===================  ==================================================
0       u8    data_type            0x10 pixels, 0x11 profile, 0x12/0x13 interpolated
1       u8    flags                bit0: intensity array follows the points
2       u16   device_type          627
4       u32   serial
8       u64   system_time          device clock (unit: see ``time_unit_ns``)
16      u8    proto_version_major  1
17      u8    proto_version_minor  0
18      u8    hardware_params_off  48
19      u8    data_offset          64
20      u32   packet_count         packets sent
24      u32   measure_count        exposures taken (the frame counter)
28      u16   zmr                  Z measurement range, mm
30      u16   xemr                 X extent at the end of the range, mm
32      u16   discrete_value       raw units per (zmr or xemr)
34      10B   reserved
44      u32   license_hash
48      u32   exposure_time        (at hardware_params_off)
52      u32   laser_value
56      u32   step_count           encoder
60      u8    dir                  encoder direction
61      u16   payload_size         bytes of points (0: the model default, 648 or 1296)
63      u8    bytes_per_point      4
======  ====  ===================  ==================================================

Points at ``data_offset``: ``x int16, z uint16`` pairs; ``x = x_raw * xemr / discrete`` and
``z = z_raw * zmr / discrete`` in millimetres (cast to float first). ``z_raw == 0`` marks a point
without a measurement (the vendor SDK drops such points). The intensity array (u8 per point)
follows when flagged. There is no checksum: truncation and header damage are detected, damage in
the point data is not; losses show in the counters.

Two choices of this module, to be checked against a real device: ``system_time`` is converted
with ``time_unit_ns`` (default 1: nanoseconds, which the simulated RF627 writes), and ``z`` is
reported from the sensor-frame origin (a driver can add a configured offset).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from wristscan.drivers.records import Profile

__all__ = [
    "DATA_TYPE_PROFILE",
    "DATA_TYPE_PROFILE_INTERPOLATED",
    "HEADER",
    "HEADER_LEN",
    "FrameError",
    "RF627Encoder",
    "RF627Frame",
    "RF627Header",
    "decode",
    "parse_header",
]

HEADER = struct.Struct("<BBHIQBBBBIIHHH10xIIIIBHB")
HEADER_LEN = HEADER.size  # 64
HW_PARAMS_OFFSET = 48
DATA_TYPE_PIXELS = 0x10
DATA_TYPE_PROFILE = 0x11
DATA_TYPE_PIXELS_INTERPOLATED = 0x12
DATA_TYPE_PROFILE_INTERPOLATED = 0x13
DEVICE_TYPE = 627
DEFAULT_POINTS = {DATA_TYPE_PROFILE: 648, DATA_TYPE_PROFILE_INTERPOLATED: 1296}
_HW = struct.Struct("<IIIBHB")  # exposure, laser, step_count, dir, payload_size, bytes_per_point


class FrameError(ValueError):
    """A datagram that is not a well-formed RF627 profile packet."""


@dataclass(frozen=True, slots=True)
class RF627Header:
    data_type: int
    flags: int
    device_type: int
    serial: int
    system_time: int
    proto_major: int
    proto_minor: int
    hardware_params_offset: int
    data_offset: int
    packet_count: int
    measure_count: int
    zmr: int
    xemr: int
    discrete_value: int
    license_hash: int
    exposure_time: int
    laser_value: int
    step_count: int
    direction: int
    payload_size: int
    bytes_per_point: int


@dataclass(frozen=True, slots=True)
class RF627Frame:
    header: RF627Header
    profile: Profile


def parse_header(buf: bytes | bytearray | memoryview) -> RF627Header:
    data = memoryview(buf)
    if len(data) < HEADER_LEN:
        raise FrameError(f"RF627 packet of {len(data)} bytes is shorter than its header")
    f = list(HEADER.unpack_from(data))
    hw_off, data_off = f[7], f[8]
    if hw_off != HW_PARAMS_OFFSET:
        # Later firmware may move the hardware block: read it where the header says.
        if hw_off < 34 or hw_off + _HW.size > min(len(data), data_off):
            raise FrameError(f"RF627 hardware_params_offset {hw_off} out of range")
        f[15:21] = _HW.unpack_from(data, hw_off)
    h = RF627Header(*f)
    if h.proto_major != 1:
        raise FrameError(f"RF627 protocol {h.proto_major}.{h.proto_minor} not supported")
    if h.data_type not in (DATA_TYPE_PROFILE, DATA_TYPE_PROFILE_INTERPOLATED):
        kind = (
            "pixel"
            if h.data_type in (DATA_TYPE_PIXELS, DATA_TYPE_PIXELS_INTERPOLATED)
            else "unknown"
        )
        raise FrameError(f"RF627 data_type 0x{h.data_type:02x} ({kind}) is not a profile")
    if data_off < HEADER_LEN:
        raise FrameError(f"RF627 data_offset {data_off} inside the header")
    if h.bytes_per_point != 4:
        raise FrameError(f"RF627 bytes_per_point {h.bytes_per_point} (4 expected)")
    if h.payload_size % 4:
        raise FrameError(f"RF627 payload_size {h.payload_size} is not a whole number of points")
    if h.discrete_value == 0 or h.zmr == 0 or h.xemr == 0:
        raise FrameError("RF627 scaling fields are zero")
    return h


def decode(
    buf: bytes | bytearray | memoryview, host_time_ns: int = 0, time_unit_ns: int = 1
) -> RF627Frame:
    """Decode one profile datagram; coordinates in metres in the sensor frame."""
    h = parse_header(buf)
    n = h.payload_size // 4 if h.payload_size else DEFAULT_POINTS[h.data_type]
    expected = h.data_offset + 4 * n + (n if h.flags & 1 else 0)
    if len(buf) < expected:
        raise FrameError(f"RF627 packet has {len(buf)} of {expected} bytes")
    if len(buf) > expected:
        raise FrameError(f"RF627 packet has {len(buf) - expected} unexpected trailing bytes")
    pts = np.frombuffer(buf, np.dtype([("x", "<i2"), ("z", "<u2")]), n, h.data_offset)
    # Cast to float before scaling: int16 * int would wrap.
    k_x = h.xemr / h.discrete_value * 1e-3
    k_z = h.zmr / h.discrete_value * 1e-3
    x = pts["x"].astype(np.float64) * k_x
    z = pts["z"].astype(np.float64) * k_z
    valid = pts["z"] != 0
    z[~valid] = np.nan
    intensity = None
    if h.flags & 1:
        intensity = np.frombuffer(buf, np.uint8, n, h.data_offset + 4 * n).copy()
    prof = Profile(
        sensor_id=h.serial,
        frame_counter=h.measure_count,
        sensor_time_ns=h.system_time * time_unit_ns,
        host_time_ns=host_time_ns,
        y=x,
        z=z,
        valid=valid,
        intensity=intensity,
        encoder=h.step_count,
    )
    return RF627Frame(h, prof)


class RF627Encoder:
    """Builds profile datagrams for the simulated RF627, vectorised over a batch.

    Defaults cover +-25 mm lateral (3 µm steps) and 0-400 mm depth (6 µm steps).
    """

    def __init__(
        self,
        serial: int = 1,
        *,
        zmr_mm: int = 100,
        xemr_mm: int = 50,
        discrete_value: int = 16384,
        interpolated: bool = False,
        intensity: bool = False,
        exposure_time: int = 300,
        laser_value: int = 100,
    ) -> None:
        if not (0 < zmr_mm < 65536 and 0 < xemr_mm < 65536 and 0 < discrete_value < 65536):
            raise ValueError("RF627 scaling fields must be u16 and non-zero")
        self.serial = serial
        self.zmr, self.xemr, self.discrete = zmr_mm, xemr_mm, discrete_value
        self.data_type = DATA_TYPE_PROFILE_INTERPOLATED if interpolated else DATA_TYPE_PROFILE
        self.intensity = intensity
        self.exposure_time, self.laser_value = exposure_time, laser_value
        self.packet_count = 0

    def encode(
        self,
        measure_count: ArrayLike,
        system_time: ArrayLike,
        x: ArrayLike,
        z: ArrayLike,
        valid: ArrayLike,
        intensity: ArrayLike | None = None,
        step_count: ArrayLike | None = None,
        direction: int = 0,
    ) -> list[bytes]:
        """Datagrams for ``P`` profiles (``x``, ``z``, ``valid`` ``(P, N)`` metres; counters,
        device times in the stream's unit and encoder steps ``(P,)``)."""
        z2 = np.atleast_2d(np.asarray(z, dtype=np.float64))
        n_prof, n = z2.shape
        if 4 * n > 0xFFFF:
            raise ValueError("RF627 payload_size is u16: at most 16383 points")
        v2 = np.broadcast_to(np.asarray(valid, dtype=bool), z2.shape)
        xr = np.broadcast_to(np.asarray(x, dtype=np.float64), z2.shape) * (
            1e3 * self.discrete / self.xemr
        )
        zr = z2 * (1e3 * self.discrete / self.zmr)
        np.rint(xr, out=xr)
        np.rint(zr, out=zr)
        with np.errstate(invalid="ignore"):  # NaN (no measurement) compares False: invalid
            ok = v2 & (zr >= 1) & (zr <= 65535) & (xr >= -32768) & (xr <= 32767)
        xr[~ok] = 0
        zr[~ok] = 0
        pts = np.empty((n_prof, n, 2), dtype="<u2")
        pts[..., 0] = xr.astype("<i2").view("<u2")
        pts[..., 1] = zr.astype("<u2")
        body = pts.reshape(n_prof, 2 * n).view(np.uint8)
        flags = 0
        if self.intensity:
            if intensity is None:
                raise ValueError("this encoder sends intensity: pass intensity")
            inten = np.broadcast_to(np.asarray(intensity, dtype=np.uint8), z2.shape)
            body = np.concatenate([body, inten], axis=1)
            flags |= 1
        counts = np.broadcast_to(np.asarray(measure_count, dtype=np.int64), (n_prof,))
        times = np.broadcast_to(np.asarray(system_time, dtype=np.int64), (n_prof,))
        steps = np.broadcast_to(
            np.asarray(0 if step_count is None else step_count, dtype=np.int64), (n_prof,)
        )
        out = []
        for p in range(n_prof):
            head = HEADER.pack(
                self.data_type,
                flags,
                DEVICE_TYPE,
                self.serial,
                int(times[p]) & 0xFFFF_FFFF_FFFF_FFFF,
                1,
                0,
                HW_PARAMS_OFFSET,
                HEADER_LEN,
                self.packet_count & 0xFFFF_FFFF,
                int(counts[p]) & 0xFFFF_FFFF,
                self.zmr,
                self.xemr,
                self.discrete,
                0,
                self.exposure_time,
                self.laser_value,
                int(steps[p]) & 0xFFFF_FFFF,
                direction,
                4 * n,
                4,
            )
            self.packet_count += 1
            out.append(head + body[p].tobytes())
        return out
