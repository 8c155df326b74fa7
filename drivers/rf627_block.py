"""RF627 datagrams decoded many at once (the sensor's UDP profile stream, :mod:`.rf627`).

The 64-byte headers of a receive pass are read through one numpy structured dtype;
:func:`matching` says which datagrams are well-formed profile packets that agree with the
stream's locked header fields, and :func:`decode_rows` turns consecutive ones into one
:class:`~wristscan.drivers.records.ProfileBlock` with the values
:func:`wristscan.drivers.rf627.decode` gives, bit for bit (the same float64 operations, element
by element). The driver's counter/clock checks stay in :mod:`.sensor_rf627`.
"""

from __future__ import annotations

from functools import lru_cache
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from wristscan.drivers.records import ProfileBlock
from wristscan.drivers.rf627 import (
    DATA_TYPE_PROFILE,
    DATA_TYPE_PROFILE_INTERPOLATED,
    HEADER_LEN,
    HW_PARAMS_OFFSET,
)

if TYPE_CHECKING:
    from wristscan.drivers._udp import Datagrams

__all__ = ["HEADER_DTYPE", "SIGNATURE", "decode_rows", "matching", "read_headers"]

HEADER_DTYPE = np.dtype(
    {
        "names": [
            "data_type", "flags", "device_type", "serial", "system_time", "proto_major",
            "proto_minor", "hardware_params_offset", "data_offset", "packet_count",
            "measure_count", "zmr", "xemr", "discrete_value", "license_hash", "exposure_time",
            "laser_value", "step_count", "direction", "payload_size", "bytes_per_point",
        ],
        "formats": [
            "u1", "u1", "<u2", "<u4", "<u8", "u1", "u1", "u1", "u1", "<u4", "<u4", "<u2",
            "<u2", "<u2", "<u4", "<u4", "<u4", "<u4", "u1", "<u2", "u1",
        ],
        "offsets": [0, 1, 2, 4, 8, 16, 17, 18, 19, 20, 24, 28, 30, 32, 44, 48, 52, 56, 60, 61,
                    63],
        "itemsize": HEADER_LEN,
    }
)  # fmt: skip
"""``rf627.HEADER`` as a numpy record (hardware block at its usual offset, 48)."""

SIGNATURE = (
    "data_type", "flags", "device_type", "serial", "proto_major", "proto_minor",
    "hardware_params_offset", "data_offset", "zmr", "xemr", "discrete_value", "payload_size",
    "bytes_per_point",
)  # fmt: skip
"""The fields the driver locks on (``Rf627Sensor._sig``), in its order."""


def read_headers(grams: Datagrams) -> NDArray[Any]:
    """Every datagram's first 64 bytes as a :data:`HEADER_DTYPE` record."""
    rows = (len(grams.buf) - HEADER_LEN) // grams.stride + 1
    table = np.ndarray((rows,), HEADER_DTYPE, grams.buf, 0, (grams.stride,))
    return table[grams.rows]


@lru_cache(maxsize=8)
def _signature_words(signature: tuple[int, ...]) -> tuple[NDArray[np.uint64], NDArray[np.uint64]]:
    """The header's eight 64-bit words as a packet of ``signature`` has them, and the mask of
    the signature's bits (the fields that vary from packet to packet are masked out)."""
    values = dict.fromkeys(HEADER_DTYPE.names or (), 0)
    values.update(zip(SIGNATURE, signature, strict=True))
    head = np.zeros(1, HEADER_DTYPE)
    mask = np.zeros(1, HEADER_DTYPE)
    for name in SIGNATURE:
        head[name] = values[name]
        mask[name] = np.iinfo(HEADER_DTYPE[name]).max
    return head.view(np.uint64)[0:8].copy(), mask.view(np.uint64)[0:8].copy()


def matching(
    grams: Datagrams, h: NDArray[Any], signature: tuple[int, ...], sensor_id: int | None
) -> NDArray[np.bool_]:
    """Datagrams that ``rf627.decode`` accepts, whose locked fields equal ``signature`` (so
    with its scaling and size), of ``sensor_id`` when given, with the hardware block at 48."""
    sig = dict(zip(SIGNATURE, signature, strict=True))
    data_off, flags, size = sig["data_offset"], sig["flags"], sig["payload_size"]
    if (
        sig["proto_major"] != 1
        or sig["data_type"] not in (DATA_TYPE_PROFILE, DATA_TYPE_PROFILE_INTERPOLATED)
        or data_off < HEADER_LEN
        or sig["hardware_params_offset"] != HW_PARAMS_OFFSET
        or sig["bytes_per_point"] != 4
        or size == 0
        or size % 4
        or 0 in (sig["discrete_value"], sig["zmr"], sig["xemr"])
        or (sensor_id is not None and sig["serial"] != sensor_id)
    ):
        return np.zeros(len(grams), dtype=bool)
    head, mask = _signature_words(signature)
    words = h.view(np.uint64).reshape(len(grams), HEADER_LEN // 8)
    ok: NDArray[np.bool_] = ((words & mask) == head).all(axis=1)
    n = size // 4
    ok &= grams.lengths == data_off + 4 * n + (n if flags & 1 else 0)
    return ok


def decode_rows(
    grams: Datagrams, h: NDArray[Any], a: int, b: int, time_unit_ns: int
) -> ProfileBlock:
    """The block of datagrams ``a .. b - 1`` (all :func:`matching`)."""
    h0 = h[a]
    n = int(h0["payload_size"]) // 4
    off = int(h0["data_offset"])
    rows = grams.rows[a:b]
    p, first, stride = b - a, int(rows[0]), grams.stride

    def field(offset: int, dtype: str, step: int) -> Any:
        dt = np.dtype(dtype)
        if int(rows[-1]) - first == p - 1:
            return np.ndarray((p, n), dt, grams.buf, first * stride + offset, (stride, step))
        table = np.ndarray((int(rows[-1]) + 1, n), dt, grams.buf, offset, (stride, step))
        return table[rows]

    discrete = int(h0["discrete_value"])
    k_x = int(h0["xemr"]) / discrete * 1e-3
    k_z = int(h0["zmr"]) / discrete * 1e-3
    z_raw = field(off + 2, "<u2", 4)
    x = field(off, "<i2", 4).astype(np.float64)
    x *= k_x
    z = z_raw.astype(np.float64)
    z *= k_z
    valid = z_raw != 0
    bad = np.flatnonzero(~valid)
    if bad.size:
        z.reshape(-1)[bad] = np.nan
    intensity = None
    if int(h0["flags"]) & 1:
        intensity = np.array(field(off + 4 * n, "u1", 1))
    hh = h[a:b]
    return ProfileBlock(
        sensor_id=hh["serial"].astype(np.int64),
        frame_counter=hh["measure_count"].astype(np.int64),
        sensor_time_ns=hh["system_time"].astype(np.int64) * time_unit_ns,
        host_time_ns=grams.stamps[a:b].copy(),
        y=x,
        z=z,
        valid=valid,
        intensity=intensity,
        encoder=hh["step_count"].astype(np.int64),
        encoder_valid=np.ones(p, dtype=bool),
    )
