"""The Gocator Protocol codec: messages built by hand from the manual's layouts, round trips of
the simulator's encoder, the stream reader's resynchronisation, control replies, health."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from wristscan.drivers import gocator
from wristscan.drivers.gocator import Msg
from wristscan.drivers.gocator_reader import GdpReader


def _stamp_msg(frame: int, time_us: int, encoder: int, serial: int, last: bool = False) -> bytes:
    """A Stamp message from the manual's table ("Stamp": 14-byte header, 56-byte stamps)."""
    stamp = struct.pack("<QQqqQI", frame, time_us, encoder, -5, 0, serial) + bytes(12)
    return struct.pack("<IHIHBB", 14 + 56, 1 | (0x8000 if last else 0), 1, 56, 0, 0) + stamp


def _uniform_msg(ranges: list[int], attr_size: int = 32, last: bool = True) -> bytes:
    """A Uniform Profile (type 6): xScale 10 µm, zScale 2 µm, xOffset -1 mm, zOffset 100 mm."""
    attrs = struct.pack("<IIIIii", 1, len(ranges), 10_000, 2_000, -1_000, 100_000)
    attrs += bytes(attr_size - len(attrs))  # source, exposure, camera index ... (not decoded)
    body = struct.pack(f"<{len(ranges)}h", *ranges)
    size = 8 + attr_size + len(body)
    return struct.pack("<IHH", size, 6 | (0x8000 if last else 0), attr_size) + attrs + body


def test_hand_built_uniform_profile_and_stamp_decode_to_metres() -> None:
    for attr_size in (32, 40, 64):  # read attributeSize, never assume where the points start
        msg = _uniform_msg([0, 500, -32768, 32767], attr_size)
        p = gocator.decode_profile(msg)
        np.testing.assert_allclose(p.x, [-1e-3, -0.99e-3, -0.98e-3, -0.97e-3], atol=1e-12)
        np.testing.assert_allclose(p.z[[0, 1, 3]], [0.1, 0.101, 0.1 + 32767 * 2e-6], atol=1e-12)
        assert list(p.valid) == [True, True, False, True] and np.isnan(p.z[2])
        assert not p.x.flags.writeable  # the grid is shared between profiles
    s = gocator.decode_stamp(_stamp_msg(7, 123_456, -9, 4242))
    assert (s.frame_index, s.timestamp_us, s.encoder, s.encoder_at_z, s.serial) == (
        7, 123_456, -9, -5, 4242)  # fmt: skip


def test_hand_built_point_cloud_and_intensity() -> None:
    pts = [(100, 200), (-32768, -32768), (-50, 0)]
    attrs = struct.pack("<IIIIii", 1, 3, 5_000, 1_000, 0, 50_000) + bytes(16)
    body = b"".join(struct.pack("<hh", x, z) for x, z in pts)
    msg = struct.pack("<IHH", 8 + 40 + len(body), 5, 40) + attrs + body
    p = gocator.decode_profile(msg)
    np.testing.assert_allclose(p.x[[0, 2]], [0.5e-3, -0.25e-3])
    np.testing.assert_allclose(p.z[[0, 2]], [0.0502, 0.05])
    assert list(p.valid) == [True, False, True]
    inten_attrs = struct.pack("<IIIi", 1, 3, 5_000, 0) + bytes(8)
    imsg = struct.pack("<IHH", 8 + 24 + 3, 7 | 0x8000, 24) + inten_attrs + bytes([9, 0, 255])
    assert list(gocator.decode_intensity(imsg)) == [9, 0, 255]


def test_inconsistent_messages_are_rejected() -> None:
    good = _uniform_msg([1, 2, 3])
    for bad in (
        good[:-1],  # truncated
        good + b"\x00",  # trailing byte
        good[:6] + struct.pack("<H", 8) + good[8:],  # attributeSize below the minimum
        good[:8] + struct.pack("<I", 2) + good[12:],  # two arrays claimed, one present
        good[:16] + struct.pack("<I", 0) + good[20:],  # xScale zero
    ):
        with pytest.raises(gocator.FrameError):
            gocator.decode_profile(bad)
    stamp = _stamp_msg(1, 2, 3, 4)
    with pytest.raises(gocator.FrameError):
        gocator.decode_stamp(stamp[:10] + struct.pack("<H", 20) + stamp[12:])  # stamp too small
    with pytest.raises(gocator.FrameError):
        gocator.decode_profile(stamp)


def test_encoder_round_trip_uniform_and_point_cloud() -> None:
    rng = np.random.default_rng(4)
    n = 512
    x = np.linspace(-0.025, 0.025, n)
    z = rng.uniform(0.06, 0.14, (3, n))
    valid = rng.random((3, n)) > 0.1
    inten = rng.integers(1, 256, (3, n)).astype(np.uint8)
    for uniform in (True, False):
        enc = gocator.GocatorEncoder(9, n, uniform=uniform, intensity=True)
        groups = enc.encode([10, 11, 12], [100, 200, 300], x, z, valid, inten, encoder=[1, 2, 3])
        reader = GdpReader()
        msgs = reader.feed(b"".join(groups) + groups[0][:16])  # the next header releases
        assert [(k, last) for k, last, _, _ in msgs[:3]] == [
            (Msg.STAMP, False),
            (Msg.UNIFORM_PROFILE if uniform else Msg.PROFILE_POINT_CLOUD, False),
            (Msg.PROFILE_INTENSITY, True),
        ]
        assert len(msgs) == 9 and reader.bad == 0
        for k in range(3):
            s = gocator.decode_stamp(msgs[3 * k][2])
            assert (s.frame_index, s.timestamp_us, s.encoder, s.serial) == (10 + k, 100 * (k + 1),
                                                                           1 + k, 9)  # fmt: skip
            p = gocator.decode_profile(msgs[3 * k + 1][2])
            np.testing.assert_array_equal(p.valid, valid[k])
            assert np.max(np.abs(p.z[valid[k]] - z[k][valid[k]])) <= 0.8e-6
            assert np.max(np.abs(p.x[valid[k]] - x[valid[k]])) <= 1e-6
            got_i = gocator.decode_intensity(msgs[3 * k + 2][2])
            np.testing.assert_array_equal(got_i[valid[k]], inten[k][valid[k]])


def test_reader_splits_anywhere_skips_unknown_types_and_resynchronises() -> None:
    enc = gocator.GocatorEncoder(1, 64)
    z = np.full((4, 64), 0.1)
    groups = enc.encode(np.arange(4), np.arange(4) * 1000, 0, z, np.ones((4, 64), bool))
    unknown = struct.pack("<IH", 10, 99 | 0x8000) + b"abcd"  # inside a group: skipped by size
    g0 = groups[0][:70] + groups[0][70:].replace(
        struct.pack("<H", 6 | 0x8000), struct.pack("<H", 6), 1
    )  # the profile is no longer last: the unknown message ends the group
    garbage = b"\xff" * 37
    stream = (g0 + unknown + groups[1] + garbage + groups[2] + groups[3][:100] + groups[0]
              + groups[1][:16])  # fmt: skip
    reader = GdpReader()
    got = []
    for i in range(0, len(stream), 7):  # split at every 7 bytes
        got += reader.feed(stream[i : i + 7], host_ns=i)
    kinds = [k for k, *_ in got]
    # Group 1 is followed by garbage and group 3 is cut short: neither can be trusted.
    assert kinds == [Msg.STAMP, Msg.UNIFORM_PROFILE, 99, Msg.STAMP, Msg.UNIFORM_PROFILE,
                     Msg.STAMP, Msg.UNIFORM_PROFILE]  # fmt: skip
    assert reader.bad == 2  # two damaged spots, once each
    frames = [gocator.decode_stamp(m).frame_index for k, _, m, _ in got if k == Msg.STAMP]
    assert frames == [0, 2, 0]
    # Each message carries the receipt time of the chunk that completed it.
    ends = np.cumsum([len(m) for _, _, m, _ in got[:3]])
    assert [t for *_, t in got[:3]] == [(e - 1) // 7 * 7 for e in ends]


def test_reader_does_not_wait_for_a_group_that_starts_wrong() -> None:
    """After damage, a message that is not a Stamp cannot start a group (a bogus size would
    otherwise make the reader wait for megabytes)."""
    enc = gocator.GocatorEncoder(1, 64)
    good = enc.encode([5], [1], 0, np.full((1, 64), 0.1), np.ones((1, 64), bool))[0]
    bogus = struct.pack("<IH", 900_000, 123) + bytes(20)
    reader = GdpReader()
    assert reader.feed(bogus + good) == [] and reader.bad == 1  # the group waits for the next
    got = reader.feed(good[:16])
    assert [k for k, *_ in got] == [Msg.STAMP, Msg.UNIFORM_PROFILE]


def test_control_replies_and_system_info() -> None:
    assert gocator.encode_command(gocator.Cmd.START) == struct.pack("<IH", 6, 0x100D)
    info = gocator.SensorInfo(4242, "127.0.0.9", "G2342", (6, 1, 0, 7), 1, 0, 0)
    reply = gocator.encode_reply(gocator.Cmd.GET_SYSTEM_INFO, 1, gocator.encode_system_info(info))
    assert struct.unpack_from("<IHi", reply) == (len(reply), 0x4002, 1)
    assert len(reply) == 70  # localInfo at 10 (56 bytes), remoteCount at 66
    cmd_id, status, fields = gocator.parse_reply(reply)
    assert (cmd_id, status) == (0x4002, 1) and gocator.parse_system_info(fields) == info
    with pytest.raises(gocator.FrameError):
        gocator.parse_reply(reply[:-1])


def test_health_message_round_trip() -> None:
    msg = gocator.encode_health({(21000, 0): 3, (2002, 0): 4150, (2501, 2): -1})
    assert struct.unpack_from("<IHI", msg) == (14 + 3 * 16, 0x8000, 3)
    assert gocator.decode_health(msg) == {(21000, 0): 3, (2002, 0): 4150, (2501, 2): -1}
    with pytest.raises(gocator.FrameError):
        gocator.decode_health(msg[:-16])


def test_a_group_is_released_when_the_stream_goes_quiet_after_it() -> None:
    enc = gocator.GocatorEncoder(1, 64)
    g = enc.encode([1, 2], [0, 1000], 0, np.full((2, 64), 0.1), True)
    reader = GdpReader()
    assert reader.feed(g[0], host_ns=7) == [] and reader.holding
    assert [(k, t) for k, _, _, t in reader.release()] == [(Msg.STAMP, 7), (Msg.UNIFORM_PROFILE, 7)]
    assert not reader.holding and reader.release() == []
    # Bytes after the group: it may be a message cut short and completed by them; not released.
    assert reader.feed(g[1] + g[0][:10]) == [] and reader.release() == []
