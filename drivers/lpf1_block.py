"""LPF1 datagrams decoded many at once: the headers of a receive pass read through one numpy
structured dtype, and the complete single-fragment PROFILE messages of one shape decoded
together into a :class:`~wristscan.drivers.records.ProfileBlock` (``docs/lpf1.md``).

:func:`plan` splits a pass (:class:`wristscan.drivers._udp.Datagrams`) into runs in arrival
order: a run of datagrams that are complete, CRC-checked PROFILE messages of one shape
(``point_count``, ``point_format``, the x/intensity flags, scales and offsets) of the expected
sensor becomes one block; every other datagram (fragments, HELLO/STATUS/HEARTBEAT, damaged or
malformed ones, foreign sensor ids, a header longer than version 1's) is left to the
per-datagram path, which parses and rejects or handles it exactly as before. The values are
those :func:`wristscan.drivers.lpf1.decode_profile` gives, bit for bit: the same float64
operations, element by element, on (profiles x points) arrays.

Per datagram the only Python work is its CRC-32 (:data:`wristscan.drivers._crc.crc32`, in C);
nothing per point.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import jit
from wristscan.drivers._crc import crc32
from wristscan.drivers.lpf1 import _FORMAT, CRC_LEN, HEADER_LEN, MAGIC, VERSION, MsgType, _x_grid
from wristscan.drivers.records import PointCodes, ProfileBlock, codes_to_metres

if TYPE_CHECKING:
    from wristscan.drivers._udp import Datagrams

__all__ = ["HEADER_DTYPE", "Run", "decode_run", "decode_uniform", "plan", "read_headers"]

HEADER_DTYPE = np.dtype(
    [
        ("magic", "S4"),
        ("version", "u1"),
        ("header_len", "u1"),
        ("msg_type", "u1"),
        ("flags", "u1"),
        ("payload_len", "<u4"),
        ("sensor_id", "<u4"),
        ("frame_counter", "<u8"),
        ("timestamp_ns", "<u8"),
        ("encoder", "<i8"),
        ("point_count", "<u4"),
        ("point_format", "u1"),
        ("reserved", "V3"),
        ("x_scale_nm", "<u4"),
        ("z_scale_nm", "<u4"),
        ("x_offset_um", "<i4"),
        ("z_offset_um", "<i4"),
        ("frag_index", "<u2"),
        ("frag_count", "<u2"),
        ("frag_offset", "<u4"),
    ]
)
"""The 72-byte version-1 header (``lpf1.HEADER``) as a numpy record."""
assert HEADER_DTYPE.itemsize == HEADER_LEN

_MASK_ANY_ID = np.array(
    [(1 << 56) - 1 | 0x03 << 56, (1 << 32) - 1, 0, 0, 0, (1 << 40) - 1, ~0, ~0, ~0], np.int64
).view(np.uint64)
"""The bits of the header's nine 64-bit words that a block's datagrams share: magic, version,
header_len, msg_type and the INTENSITY and EXPLICIT_X flags; payload_len; point_count and
point_format; the scales; the offsets; the fragment fields (``frame_counter``,
``timestamp_ns``, ``encoder``, ENCODER_VALID and LAST_FRAGMENT vary)."""
_MASK_ONE_ID = _MASK_ANY_ID.copy()
_MASK_ONE_ID[1] = np.uint64(2**64 - 1)
"""... and the sensor id, when one is expected."""
_MAX_SHAPES = 4
"""Shapes looked for per pass; datagrams of further shapes take the per-datagram path."""
_COUNTER_LIMIT = np.uint64(1 << 63)
"""Frame counters from here on do not fit a block's int64 (the per-datagram path takes them)."""
_ITEMSIZE = {0: 2, 1: 4, 2: 4}
_PROFILE = int(MsgType.PROFILE)


@dataclass(frozen=True, slots=True)
class Run:
    """Datagrams ``start .. stop - 1`` of a pass: one block (``fast``) or the per-datagram path."""

    start: int
    stop: int
    fast: bool


def plan(grams: Datagrams, headers: NDArray[Any], sensor_id: int | None) -> list[Run]:
    """The runs of a pass in arrival order (``headers``: :func:`read_headers`).

    A datagram is decodable in a block when its header is a valid single-fragment PROFILE
    header (checked once per shape, on the first datagram of the shape), its shared words
    equal that first datagram's, its length is the same and its CRC-32 matches: exactly what
    ``parse_message`` and ``decode_profile`` accept, restricted to one shape."""
    k = len(grams)
    words = _header_words(grams, headers)
    key = words & (_MASK_ANY_ID if sensor_id is None else _MASK_ONE_ID)
    if _uniform(grams, headers, words, key, sensor_id):
        crc_ok = _crc_ok(grams, None)
        if crc_ok.all():  # the usual pass: one shape, every datagram whole
            return [Run(0, k, True)]
    shape = np.full(k, -1, np.int64)  # index of the shape's first datagram; -1: per datagram
    i, found, whole = 0, 0, False
    while True:
        if _profile_header(grams, headers, i, sensor_id):
            same = (key == key[i]).all(axis=1)
            same &= grams.lengths == grams.lengths[i]
            same &= words[:, 2] < _COUNTER_LIMIT
            if found:
                same &= shape < 0
            shape[same] = i
            found += 1
            whole = found == 1 and bool(same.all())  # the usual pass: one shape
        rest = np.flatnonzero(shape[i + 1 :] < 0)
        if whole or found == _MAX_SHAPES or rest.size == 0:
            break
        i += 1 + int(rest[0])
    fast = np.arange(k) if whole else np.flatnonzero(shape >= 0)
    if fast.size:
        crc_ok = _crc_ok(grams, fast)
        if whole and crc_ok.all():
            return [Run(0, k, True)]
        shape[fast[~crc_ok]] = -1
    edges = np.flatnonzero(shape[1:] != shape[:-1]) + 1
    bounds = [0, *edges.tolist(), k]
    return [Run(a, b, bool(shape[a] >= 0)) for a, b in itertools.pairwise(bounds)]


def _uniform(
    grams: Datagrams, headers: NDArray[Any], words: NDArray[np.uint64], key: Any, sid: int | None
) -> bool:
    """Every datagram of the pass has the first one's shape and length and is a whole PROFILE
    message as ``decode_profile`` takes it (CRCs aside): :func:`plan`'s usual case, told in a
    few whole-array steps."""
    return bool(
        (key == key[0]).all()
        and (grams.lengths == grams.lengths[0]).all()
        and (words[:, 2] < _COUNTER_LIMIT).all()
        and _profile_header(grams, headers, 0, sid)
    )


def read_headers(grams: Datagrams) -> NDArray[Any]:
    """Every datagram's first 72 bytes as a :data:`HEADER_DTYPE` record (whatever they hold:
    :func:`plan` checks them): a view of the buffer when the datagrams lie in consecutive rows
    (the usual pass), else a copy."""
    rows = (len(grams.buf) - HEADER_LEN) // grams.stride + 1
    table = np.ndarray((rows,), HEADER_DTYPE, grams.buf, 0, (grams.stride,))
    first, k = int(grams.rows[0]), len(grams)
    if int(grams.rows[-1]) - first == k - 1:
        return table[first : first + k]
    return table[grams.rows]


def _header_words(grams: Datagrams, headers: NDArray[Any]) -> NDArray[np.uint64]:
    """The nine 64-bit words of each header, (k, 9): a view of ``headers``."""
    k = headers.shape[0]
    if headers.flags.c_contiguous:
        return headers.view(np.uint64).reshape(k, HEADER_LEN // 8)
    # A view of the buffer's rows (read_headers' consecutive case).
    at = int(grams.rows[0]) * grams.stride
    return np.ndarray((k, HEADER_LEN // 8), np.uint64, grams.buf, at, (grams.stride, 8))


def _profile_header(grams: Datagrams, headers: NDArray[Any], i: int, sensor_id: int | None) -> bool:
    """Datagram ``i`` is a whole version-1 PROFILE message as ``decode_profile`` takes it
    (its CRC aside), of ``sensor_id`` when given."""
    length = int(grams.lengths[i])
    if length < HEADER_LEN + CRC_LEN:
        return False
    (magic, version, header_len, msg_type, flags, payload_len, sid, counter, _t, _e, n, fmt,
     _r, _xs, _zs, _xo, _zo, frag_index, frag_count, _fo) = headers[i].item()  # fmt: skip
    if fmt not in _ITEMSIZE or n == 0:
        return False
    payload = n * _ITEMSIZE[fmt] * (2 if flags & 0x02 else 1) + (n if flags & 0x01 else 0)
    return bool(
        magic == MAGIC
        and version == VERSION
        and header_len == HEADER_LEN
        and msg_type == _PROFILE
        and frag_index == 0
        and frag_count == 1
        and payload_len == payload
        and length == HEADER_LEN + payload + CRC_LEN
        and counter < 1 << 63
        and (sensor_id is None or sid == sensor_id)
    )


_CRC_RESIDUE = 0x2144DF1C
"""CRC-32 of a message followed by its own CRC (little-endian): the same for every message,
and only when the CRC matches (the last four bytes map one to one onto the result)."""


def _crc_ok(grams: Datagrams, idx: NDArray[np.intp] | None) -> NDArray[np.bool_]:
    """The CRC-32 of datagrams ``idx`` (None: all) checked (one CRC-32 call each, over the
    whole datagram: :data:`_CRC_RESIDUE`)."""
    view, stride = grams.view, grams.stride
    if idx is None:
        rows, lengths = grams.rows.tolist(), grams.lengths.tolist()
    else:
        rows, lengths = grams.rows[idx].tolist(), grams.lengths[idx].tolist()
    got = [crc32(view[r * stride : r * stride + n]) for r, n in zip(rows, lengths, strict=True)]
    return np.array(got, np.int64) == _CRC_RESIDUE


def _rows_of(grams: Datagrams, run: Run, offset: int, dtype: np.dtype[Any], n: int) -> Any:
    """(P, n) ``dtype`` values at ``offset`` of each datagram of ``run``: a strided view of the
    buffer when the datagrams lie in consecutive rows, else a copy."""
    rows = grams.rows[run.start : run.stop]
    p = run.stop - run.start
    first = int(rows[0])
    if int(rows[-1]) - first == p - 1:
        return np.ndarray((p, n), dtype, grams.buf, first * grams.stride + offset,
                          (grams.stride, dtype.itemsize))  # fmt: skip
    last = int(rows[-1])
    table = np.ndarray((last + 1, n), dtype, grams.buf, offset, (grams.stride, dtype.itemsize))
    return table[rows]


def decode_run(grams: Datagrams, headers: NDArray[Any], run: Run) -> ProfileBlock:
    """The block of a fast run (every datagram checked by :func:`plan`)."""
    a, b = run.start, run.stop
    h0 = headers[a].item()  # one tuple, in HEADER_DTYPE's order
    flags, n, fmt = h0[4], h0[10], h0[11]
    xs, zs, xo, zo = h0[13:17]
    dt, sentinel = _FORMAT[fmt]
    pos = HEADER_LEN
    x_raw = None
    if flags & 0x02:
        x_raw = _rows_of(grams, run, pos, dt, n)
        pos += n * dt.itemsize
    z, valid, invalid = _decode_z(grams, run, pos, dt, n, zs, zo, sentinel)
    pos += n * dt.itemsize
    intensity = None
    if flags & 0x01:
        intensity = np.array(_rows_of(grams, run, pos, np.dtype(np.uint8), n))
    if x_raw is None:
        x = _x_grid(n, xs, xo)
    elif sentinel is None:
        x = x_raw.astype(np.float64)
        x_bad = ~np.isfinite(x)
    else:
        x_bad = x_raw == sentinel
        x = x_raw.astype(np.float64) * (xs * 1e-9) + xo * 1e-6
        np.copyto(x, np.nan, where=x_bad)
    if invalid is None:  # compiled: z and valid done but for explicit x's invalid points
        assert valid is not None
        if x_raw is not None:
            valid &= ~x_bad
            np.copyto(z, np.nan, where=x_bad)
    else:
        if x_raw is not None:
            invalid |= x_bad
        # Invalid points are few: their indices, then NaN there (a masked copy of every point
        # costs twice as much).
        bad = np.flatnonzero(invalid)
        if bad.size:
            z.reshape(-1)[bad] = np.nan
        valid = ~invalid
    # The per-profile fields from the headers' first five 64-bit words, one copy for all.
    w = np.array(_header_words(grams, headers)[a:b, :_FIELD_WORDS].T, order="C")
    return _block(grams, w, a, b, x, z, valid, intensity)


_FIELD_WORDS = 5
"""The header words with per-profile fields: magic .. flags (ENCODER_VALID), payload_len and
sensor_id, frame_counter, timestamp_ns, encoder."""


def _block(
    grams: Datagrams,
    w: NDArray[np.uint64],
    a: int,
    b: int,
    x: NDArray[np.float64],
    z: NDArray[np.float64] | None,
    valid: NDArray[np.bool_],
    intensity: NDArray[np.uint8] | None,
    codes: PointCodes | None = None,
) -> ProfileBlock:
    """The block of datagrams ``a .. b - 1`` (``w``: their :data:`_FIELD_WORDS` header words,
    (5, P))."""
    ev = (w[0] & _ENCODER_VALID_BIT) != 0
    encoder = None
    if ev.all():
        encoder = w[4].view(np.int64)
    elif ev.any():
        encoder = np.where(ev, w[4].view(np.int64), 0)
    return ProfileBlock(
        sensor_id=(w[1] >> np.uint64(32)).view(np.int64),
        frame_counter=w[2].view(np.int64),
        sensor_time_ns=w[3].view(np.int64),
        host_time_ns=grams.stamps[a:b].copy(),
        y=x,
        z=z,
        valid=valid,
        intensity=intensity,
        encoder=encoder,
        encoder_valid=None if encoder is None else ev,
        codes=codes,
    )


def decode_uniform(
    grams: Datagrams, headers: NDArray[Any], sensor_id: int | None
) -> ProfileBlock | None:
    """The usual pass in two compiled calls (:mod:`wristscan.calib.jit`): every datagram a
    whole PROFILE message of the first one's shape with integer points on a uniform grid, all
    CRCs right. None otherwise, or without the compiled kernels: then :func:`plan` and
    :func:`decode_run`, which give the same block (tests/drivers/test_sensor_blocks.py)."""
    same, take_codes = jit.kernel("same_headers"), jit.kernel("take_codes")
    if same is None or take_codes is None or not _profile_header(grams, headers, 0, sensor_id):
        return None
    h0 = headers[0].item()
    flags, n, fmt = h0[4], h0[10], h0[11]
    xs, zs, xo, zo = h0[13:17]
    dt, sentinel = _FORMAT[fmt]
    if sentinel is None or flags & 0x02:  # float points or explicit x: numpy's path
        return None
    k = len(grams)
    w = np.empty((_FIELD_WORDS, k), np.uint64)
    words = np.frombuffer(grams.buf, np.uint64, len(grams.buf) // 8)
    mask = _MASK_ANY_ID if sensor_id is None else _MASK_ONE_ID
    if not same(words, grams.rows, grams.stride // 8, mask, grams.lengths, _COUNTER_LIMIT, w):
        return None
    if not _crc_ok(grams, None).all():
        return None
    # The points kept as their codes (a copy: the buffer is reused), z decoded only if asked
    # for: the alignment reads the codes, a quarter of the bytes of float64 z.
    codes = np.empty((k, n), dt)
    valid = np.empty((k, n), np.bool_)
    buf = np.frombuffer(grams.buf, dt, len(grams.buf) // dt.itemsize)
    size = dt.itemsize
    take_codes(buf, grams.rows, grams.stride // size, HEADER_LEN // size, sentinel, codes, valid)
    intensity = None
    if flags & 0x01:
        at = HEADER_LEN + n * size
        intensity = np.array(_rows_of(grams, Run(0, k, True), at, np.dtype(np.uint8), n))
    coded = PointCodes(codes, zs * 1e-9, zo * 1e-6, sentinel)
    return _block(grams, w, 0, k, _x_grid(n, xs, xo), None, valid, intensity, coded)


_ENCODER_VALID_BIT = np.uint64(0x04 << 56)
"""ENCODER_VALID in the first header word (``flags`` is its top byte)."""


def _decode_z(
    grams: Datagrams,
    run: Run,
    at: int,
    dt: np.dtype[Any],
    n: int,
    zs: int,
    zo: int,
    sentinel: int | None,
) -> tuple[NDArray[np.float64], NDArray[np.bool_] | None, NDArray[np.bool_] | None]:
    """The run's z (P, n) in metres as ``decode_profile`` gives them, and either ``valid``
    (compiled) or ``invalid`` (numpy; z not yet NaN there)."""
    a, b = run.start, run.stop
    scale_codes = jit.kernel("scale_codes") if sentinel is not None else None
    if scale_codes is not None:
        # Compiled: one call where numpy takes five passes (cast, scale, offset, compare,
        # negate), read straight from the receive buffer.
        z = np.empty((b - a, n))
        valid = np.empty((b - a, n), np.bool_)
        codes = np.frombuffer(grams.buf, dt, len(grams.buf) // dt.itemsize)
        size = dt.itemsize
        rows = grams.rows[a:b]
        scale_codes(codes, rows, grams.stride // size, at // size, zs * 1e-9, zo * 1e-6,
                    sentinel, z, valid)  # fmt: skip
        return z, valid, None
    z_raw = _rows_of(grams, run, at, dt, n)
    if sentinel is None:
        z = z_raw.astype(np.float64)
        return z, None, ~np.isfinite(z)
    z, invalid = codes_to_metres(z_raw, zs * 1e-9, zo * 1e-6, sentinel)
    return z, None, invalid
