"""Property tests of the frame parsers: damaged frames are rejected with the codec's FrameError or
decode to exactly what the intact frame decodes to (benchmarks/fuzz_parsers.py runs the same at
scale)."""

from __future__ import annotations

from typing import Any

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from support import same_profile

from wristscan.drivers import gocator, lpf1, lpf1_reader, rf627, scip
from wristscan.drivers.records import Profile
from wristscan.drivers.sensor_gocator import GocatorSensor

SETTINGS = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
_rng = np.random.default_rng(7)


@st.composite
def damage(draw: st.DrawFn, frame: bytes) -> bytes:
    """``frame`` with substitutions, a truncation, an insertion or a deletion (never intact)."""
    b = bytearray(frame)
    how = draw(st.sampled_from(["substitute", "truncate", "insert", "delete"]))
    if how == "substitute":
        for _ in range(draw(st.integers(1, 4))):
            pos = draw(st.integers(0, len(b) - 1))
            b[pos] = (b[pos] + draw(st.integers(1, 255))) & 0xFF
    elif how == "truncate":
        del b[draw(st.integers(0, len(b) - 1)) :]
    elif how == "insert":
        pos = draw(st.integers(0, len(b)))
        b[pos:pos] = draw(st.binary(min_size=1, max_size=8))
    else:
        pos = draw(st.integers(0, len(b) - 1))
        del b[pos : pos + draw(st.integers(1, 8))]
    if bytes(b) == frame:
        b.append(0)
    return bytes(b)


# ----------------------------------------------------------------------------------------------
# LPF1: the CRC-32 lets nothing through


def _lpf1_frames() -> list[bytes]:
    z = _rng.uniform(0.06, 0.14, (2, 64))
    out = []
    for fmt, explicit in ((lpf1.PointFormat.I16, False), (lpf1.PointFormat.F32, True)):
        enc = lpf1.ProfileEncoder(2, fmt, x_uniform=None if explicit else (-0.01, 3e-4),
                                  intensity=explicit, max_message_bytes=None)  # fmt: skip
        msgs = enc.encode([5, 6], [10, 20], z, z > 0.07, x=np.linspace(-0.01, 0.01, 64),
                          intensity=np.full((2, 64), 9), encoder=[1, 2])  # fmt: skip
        out += [m[0] for m in msgs]
    out.append(lpf1.encode_control(lpf1.MsgType.HELLO, 2, 6, 30, {"model": "t"}))
    return out


LPF1_FRAMES = _lpf1_frames()


def _lpf1_decode(data: bytes) -> Any:
    msg = lpf1.parse_message(data)
    return lpf1.decode_profile(msg) if msg.header.msg_type == lpf1.MsgType.PROFILE else msg


@SETTINGS
@given(st.sampled_from(LPF1_FRAMES).flatmap(lambda f: st.tuples(st.just(f), damage(f))))
def test_lpf1_datagram_damage_is_always_rejected(case: tuple[bytes, bytes]) -> None:
    frame, bad = case
    try:
        got = _lpf1_decode(bad)
    except lpf1.FrameError:
        return
    expect = _lpf1_decode(frame)
    assert same_profile(got, expect) if isinstance(got, Profile) else got == expect


@SETTINGS
@given(
    st.integers(0, len(LPF1_FRAMES) - 3).flatmap(
        lambda i: st.tuples(st.just(i), damage(LPF1_FRAMES[i + 1]), st.integers(0, 10_000))
    ),
    st.booleans(),
)
def test_lpf1_stream_decoders_resynchronise_and_pass_only_intact_messages(
    case: tuple[int, bytes, int], serial: bool
) -> None:
    i, bad, cut = case
    frames = LPF1_FRAMES[i : i + 3]
    originals = [lpf1.parse_message(f) for f in frames]
    wire = [lpf1.cobs_frame(f) for f in frames] if serial else list(frames)
    bad_wire = lpf1.cobs_frame(bad) if serial else bad
    stream = wire[0] + bad_wire + wire[2]
    cut = min(cut, len(stream))
    dec: lpf1_reader.StreamDecoder | lpf1_reader.SerialDecoder = (
        lpf1_reader.SerialDecoder() if serial else lpf1_reader.StreamDecoder()
    )
    got = dec.feed(stream[:cut]) + dec.feed(stream[cut:])
    assert all(m in originals for m in got)
    # The message after the damage always survives (resynchronisation).
    assert got and got[-1] == originals[2]


# ----------------------------------------------------------------------------------------------
# RF627: no checksum; framing damage is caught, an accepted packet is always well-formed


def _rf627_frames() -> list[bytes]:
    enc = rf627.RF627Encoder(serial=9, intensity=True)
    x = np.linspace(-0.02, 0.02, 100)
    z = _rng.uniform(0.02, 0.09, (2, 100))
    return enc.encode([1, 2], [0, 10], x, z, z > 0.03, intensity=np.full((2, 100), 7))


RF627_FRAMES = _rf627_frames()


@SETTINGS
@given(st.sampled_from(RF627_FRAMES).flatmap(lambda f: st.tuples(st.just(f), damage(f))))
def test_rf627_damage_is_rejected_or_gives_a_well_formed_profile(case: tuple[bytes, bytes]) -> None:
    frame, bad = case
    try:
        p = rf627.decode(bad).profile
    except rf627.FrameError:
        return
    assert len(bad) == len(frame)  # length damage never passes
    n = p.n_points
    assert p.z.shape == p.valid.shape == (n,)
    assert p.intensity is None or p.intensity.shape == (n,)
    assert np.all(np.isfinite(p.y)) and np.all(np.isfinite(p.z[p.valid]))
    assert np.all(np.isnan(p.z[~p.valid]))


# ----------------------------------------------------------------------------------------------
# SCIP: line checksums plus the character range


def _scip_frames() -> list[bytes]:
    ranges = _rng.integers(0, 30000, 100)
    return [
        scip.scan_reply(b"MD000009901000", b"99", 1234, ranges),
        scip.scan_reply(b"ME000009901000", b"99", 1259, ranges, _rng.integers(0, 9000, 100)),
    ]


SCIP_FRAMES = _scip_frames()


def _scip_decode(data: bytes) -> scip.Scan | None:
    replies = scip.ReplyDecoder().feed(data)
    if len(replies) != 1:
        return None
    scan = scip.decode_scan(replies[0], 3, replies[0].echo.startswith(b"ME"))
    return scan if scan.ranges_mm.size == 100 else None  # the driver checks the count


@SETTINGS
@given(st.sampled_from(SCIP_FRAMES).flatmap(lambda f: st.tuples(st.just(f), damage(f))))
def test_scip_scan_damage_is_rejected(case: tuple[bytes, bytes]) -> None:
    frame, bad = case
    try:
        got = _scip_decode(bad)
    except scip.FrameError:
        return
    if got is None:
        return
    expect = _scip_decode(frame)
    assert expect is not None
    # Several changed characters can keep a 6-bit checksum; one never does.
    single = len(bad) == len(frame) and sum(a != b for a, b in zip(bad, frame, strict=True)) == 1
    if single or len(bad) < len(frame):
        assert got.timestamp_ms == expect.timestamp_ms
        assert np.array_equal(got.ranges_mm, expect.ranges_mm)


# ----------------------------------------------------------------------------------------------
# Gocator: no checksum on a TCP stream; framing damage is caught by the stream reader and the
# lookahead, header damage by the driver's stream lock and frame index/timestamp agreement


def _gocator_groups() -> list[bytes]:
    enc = gocator.GocatorEncoder(4, 80, intensity=True)
    z = _rng.uniform(0.06, 0.14, (8, 80))
    frames = np.arange(100, 108)
    return enc.encode(frames, frames * 1000, 0, z, z > 0.07, np.full((8, 80), 9), frames)


GOCATOR_GROUPS = _gocator_groups()


def _gocator_profiles(groups: list[bytes]) -> list[Profile]:
    drv = GocatorSensor("127.0.0.1")
    drv._consume(b"".join(groups), 0)
    return list(drv._ready)


GOCATOR_INTACT = {p.frame_counter: p for p in _gocator_profiles(GOCATOR_GROUPS)}


@SETTINGS
@given(st.integers(4, 6).flatmap(lambda i: st.tuples(st.just(i), damage(GOCATOR_GROUPS[i]))))
def test_gocator_damage_is_caught_or_undetectable_point_damage(case: tuple[int, bytes]) -> None:
    i, bad = case
    got = _gocator_profiles([*GOCATOR_GROUPS[:i], bad, *GOCATOR_GROUPS[i + 1 :]])
    counters = [p.frame_counter for p in got]
    assert np.all(np.diff(counters) >= 1)
    # The intact frames before it (the one just before may go: what follows it is damaged).
    assert set(counters) >= set(range(100, 99 + i))
    for p in got:
        intact = GOCATOR_INTACT[p.frame_counter]
        if same_profile(p, intact):
            continue  # e.g. bytes inserted before a group: skipped as garbage
        assert p.frame_counter == 100 + i
        # The damaged group itself: only damage among the points, in the encoder or in the
        # timestamp by less than half a frame period can pass.
        assert len(bad) == len(GOCATOR_GROUPS[i])  # framing damage never passes
        assert abs(p.sensor_time_ns - intact.sensor_time_ns) <= 500_000
        assert np.array_equal(p.y, intact.y) and p.sensor_id == intact.sensor_id
        assert p.z.shape == p.valid.shape == (80,)
        assert np.all(np.isnan(p.z[~p.valid])) and np.all(np.isfinite(p.z[p.valid]))
