"""Wire codecs: LPF1, RF627 and SCIP 2.0 round trips, hand-built packets, and malformed input."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from wristscan.drivers import lpf1, lpf1_reader, rf627, scip
from wristscan.drivers.records import Profile

FAST = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _profile(n: int = 300, seed: int = 0, intensity: bool = False) -> Profile:
    rng = np.random.default_rng(seed)
    y = np.linspace(-0.025, 0.025, n)
    z = 0.1 + 0.02 * np.sin(y * 100) + rng.normal(0, 1e-5, n)
    valid = rng.random(n) > 0.1
    z[~valid] = np.nan
    inten = rng.integers(0, 256, n).astype(np.uint8) if intensity else None
    return Profile(7, 123456789, 10**15 + 17, 0, y, z, valid, inten, encoder=-42)


# ----------------------------------------------------------------------------------------------
# LPF1


def test_lpf1_header_is_72_bytes_little_endian() -> None:
    assert lpf1.HEADER_LEN == 72
    msg = lpf1.encode_profile(_profile(4), uniform_x=True)[0]
    assert msg[:4] == b"LPF1" and msg[4] == 1 and msg[5] == 72 and msg[6] == 1
    (payload_len,) = struct.unpack_from("<I", msg, 8)
    assert len(msg) == 72 + payload_len + 4
    (crc,) = struct.unpack_from("<I", msg, len(msg) - 4)
    assert crc == zlib.crc32(msg[:-4])
    (count,) = struct.unpack_from("<I", msg, 40)
    assert count == 4
    assert struct.unpack_from("<Q", msg, 16)[0] == 123456789  # frame counter
    assert struct.unpack_from("<q", msg, 32)[0] == -42  # encoder


@pytest.mark.parametrize("fmt", list(lpf1.PointFormat))
@pytest.mark.parametrize("uniform", [True, False])
def test_lpf1_round_trip(fmt: lpf1.PointFormat, uniform: bool) -> None:
    prof = _profile(500, intensity=True)
    msgs = lpf1.encode_profile(prof, fmt, uniform_x=uniform)
    assert len(msgs) == 1
    out = lpf1.decode_profile(msgs[0], host_time_ns=99)
    assert out.sensor_id == 7 and out.frame_counter == 123456789
    assert out.sensor_time_ns == 10**15 + 17 and out.host_time_ns == 99 and out.encoder == -42
    np.testing.assert_array_equal(out.valid, prof.valid)
    np.testing.assert_array_equal(out.intensity, prof.intensity)
    tol_z = 1.01e-6 if fmt != lpf1.PointFormat.F32 else 1e-8  # 2 µm steps: 1 µm at most
    assert np.max(np.abs(out.z[prof.valid] - prof.z[prof.valid])) <= tol_z
    assert np.all(np.isnan(out.z[~prof.valid]))
    tol_y = 0.6e-6 if uniform or fmt != lpf1.PointFormat.F32 else 1e-8
    assert np.max(np.abs(out.y - prof.y)) <= tol_y
    flags = out_flags(msgs[0])
    assert bool(flags & lpf1.Flags.EXPLICIT_X) == (not uniform)


def out_flags(msg: bytes) -> int:
    return msg[7]


def test_lpf1_out_of_range_points_become_invalid() -> None:
    prof = _profile(10)
    prof.z[:] = 0.1
    prof.valid[:] = True
    prof.z[3] = 0.5  # 400 mm from the 100 mm offset: beyond int16 * 2 µm
    out = lpf1.decode_profile(lpf1.encode_profile(prof)[0])
    assert not out.valid[3] and out.valid.sum() == 9


def test_lpf1_fragments_reassemble_in_any_order() -> None:
    prof = _profile(2048, intensity=True)
    msgs = lpf1.encode_profile(
        prof, lpf1.PointFormat.I32, uniform_x=False, z_scale_nm=10, max_message_bytes=1472
    )
    assert len(msgs) > 5 and all(len(m) <= 1472 for m in msgs)
    parsed = [lpf1.parse_message(m) for m in msgs]
    assert sum(bool(p.header.flags & lpf1.Flags.LAST_FRAGMENT) for p in parsed) == 1
    with pytest.raises(lpf1.FrameError):
        lpf1.decode_profile(parsed[0])  # a fragment alone is not a profile
    re = lpf1_reader.Reassembler()
    order = np.random.default_rng(1).permutation(len(parsed))
    results = [re.push(parsed[i]) for i in order]
    assert all(r is None for r in results[:-1]) and results[-1] is not None
    out = lpf1.decode_profile(results[-1])
    np.testing.assert_array_equal(out.valid, prof.valid)
    np.testing.assert_allclose(out.z[out.valid], prof.z[prof.valid], rtol=0, atol=5.01e-9)


def test_lpf1_reassembler_drops_incomplete_frames() -> None:
    re = lpf1_reader.Reassembler(max_pending=2)
    for counter in range(4):
        prof = _profile(2048)
        prof.frame_counter = counter
        first = lpf1.encode_profile(prof, max_message_bytes=1000)[0]
        assert re.push(lpf1.parse_message(first)) is None
    assert re.dropped_frames == 2


def test_lpf1_stream_decoder_resyncs_over_garbage_and_splits() -> None:
    msgs = []
    for k in range(5):
        prof = _profile(100, seed=k)
        prof.frame_counter = k
        msgs.append(lpf1.encode_profile(prof)[0])
    bad = bytearray(msgs[2])
    bad[100] ^= 0x10
    stream = b"junkLPF" + msgs[0] + msgs[1][:50] + msgs[1][50:] + bytes(bad) + b"LPF1\x01" + msgs[3]
    stream += msgs[4]
    dec = lpf1_reader.StreamDecoder()
    got = []
    for i in range(0, len(stream), 37):  # arbitrary chunking
        got += dec.feed(stream[i : i + 37])
    assert [m.header.frame_counter for m in got] == [0, 1, 3, 4]
    assert dec.bad_messages >= 1 and dec.skipped_bytes > 0


def test_lpf1_stream_decoder_does_not_wait_for_a_corrupted_length() -> None:
    msgs = []
    for k in range(4):
        prof = _profile(100, seed=k)
        prof.frame_counter = k
        msgs.append(lpf1.encode_profile(prof)[0])
    bad = bytearray(msgs[1])
    bad[10] = 0x10  # payload_len now claims ~1 MB
    dec = lpf1_reader.StreamDecoder()
    got = dec.feed(msgs[0] + bytes(bad) + msgs[2] + msgs[3])
    assert [m.header.frame_counter for m in got] == [0, 2, 3]


def test_lpf1_serial_cobs_framing() -> None:
    msgs = []
    for k in range(3):
        prof = _profile(64, seed=k)
        prof.frame_counter = k
        msgs.append(lpf1.cobs_frame(lpf1.encode_profile(prof)[0]))
    assert all(m.count(0) == 1 and m.endswith(b"\x00") for m in msgs)
    broken = bytearray(msgs[1])
    broken[20] = 0x55 if broken[20] != 0x55 else 0x56  # not a zero: the framing survives
    dec = lpf1_reader.SerialDecoder()
    # Line noise ended by a zero, frame 0 split across reads, a damaged frame, frame 2.
    got = dec.feed(b"\x13\x37\x00" + msgs[0][:10])
    got += dec.feed(msgs[0][10:] + bytes(broken) + msgs[2])
    assert [m.header.frame_counter for m in got] == [0, 2]
    assert dec.bad_messages == 2


def test_lpf1_control_messages() -> None:
    hello = lpf1.parse_message(lpf1.encode_control(lpf1.MsgType.HELLO, 3, 0, 5, {"model": "x"}))
    assert hello.header.msg_type == lpf1.MsgType.HELLO and hello.json() == {"model": "x"}
    hb = lpf1.parse_message(lpf1.encode_control(lpf1.MsgType.HEARTBEAT, 3, 9, 5))
    assert hb.payload == b"" and hb.header.frame_counter == 9
    with pytest.raises(lpf1.FrameError):
        lpf1.decode_profile(hb)


def test_lpf1_truncation_and_corruption_are_rejected() -> None:
    msg = lpf1.encode_profile(_profile(50))[0]
    for cut in (0, 10, 71, 72, len(msg) - 1):
        with pytest.raises(lpf1.TruncatedError):
            lpf1.parse_message(msg[:cut])
    with pytest.raises(lpf1.FrameError):
        lpf1.parse_message(msg + b"\x00")
    bad = bytearray(msg)
    bad[100] ^= 0xFF
    with pytest.raises(lpf1.ChecksumError):
        lpf1.parse_message(bytes(bad))


@FAST
@given(data=st.data())
def test_lpf1_any_mutation_is_rejected(data: st.DataObject) -> None:
    msg = lpf1.encode_profile(_profile(40, intensity=True), lpf1.PointFormat.I16)[0]
    n_changes = data.draw(st.integers(1, 4))
    buf = bytearray(msg)
    for _ in range(n_changes):
        i = data.draw(st.integers(0, len(buf) - 1))
        buf[i] ^= data.draw(st.integers(1, 255))
    cut = data.draw(st.integers(0, len(buf)))
    mutated = bytes(buf[:cut])
    if mutated == msg:
        return
    with pytest.raises(lpf1.FrameError):
        lpf1.decode_profile(mutated)


# ----------------------------------------------------------------------------------------------
# RF627


def _rf627_packet(points: list[tuple[int, int]], payload_size: int | None = None) -> bytes:
    """Built from the documented layout, independently of the encoder."""
    head = bytearray(64)
    struct.pack_into("<BBHIQ", head, 0, 0x11, 0, 627, 4242, 10**12)
    struct.pack_into("<BBBBII", head, 16, 1, 0, 48, 64, 5, 77)
    struct.pack_into("<HHH", head, 28, 100, 50, 16384)
    n = len(points)
    struct.pack_into(
        "<IIIBHB", head, 48, 300, 100, 9999, 1, 4 * n if payload_size is None else payload_size, 4
    )
    body = b"".join(struct.pack("<hH", x, z) for x, z in points)
    return bytes(head) + body


def test_rf627_decodes_a_hand_built_packet() -> None:
    pkt = _rf627_packet([(-32768, 16384), (32767, 65535), (0, 0), (100, 200)])
    frame = rf627.decode(pkt, host_time_ns=5)
    p = frame.profile
    # x = raw * xemr / discrete (mm): no int16 wrap-around
    np.testing.assert_allclose(p.y, np.array([-32768, 32767, 0, 100]) * 50 / 16384 * 1e-3)
    assert p.z[0] == pytest.approx(0.1) and p.z[1] == pytest.approx(65535 * 100 / 16384 * 1e-3)
    assert list(p.valid) == [True, True, False, True] and np.isnan(p.z[2])
    assert p.frame_counter == 77 and p.sensor_id == 4242 and p.encoder == 9999
    assert p.sensor_time_ns == 10**12 and frame.header.packet_count == 5
    assert frame.header.direction == 1


def test_rf627_default_point_count_when_payload_size_is_zero() -> None:
    pkt = _rf627_packet([(i, 1000 + i) for i in range(648)], payload_size=0)
    assert rf627.decode(pkt).profile.n_points == 648


def test_rf627_round_trip_and_counters() -> None:
    enc = rf627.RF627Encoder(serial=9, intensity=True)
    prof = _profile(648, intensity=True)
    grams = enc.encode([10, 11], [1000, 2000], prof.y, np.vstack([prof.z, prof.z]),
                       np.vstack([prof.valid, prof.valid]), intensity=prof.intensity,
                       step_count=[5, 6])  # fmt: skip
    assert len(grams) == 2 and len(grams[0]) == 64 + 648 * 5
    for k, g in enumerate(grams):
        f = rf627.decode(g)
        assert f.header.packet_count == k and f.profile.frame_counter == 10 + k
        assert f.profile.encoder == 5 + k
        np.testing.assert_array_equal(f.profile.valid, prof.valid)
        assert np.max(np.abs(f.profile.z[prof.valid] - prof.z[prof.valid])) <= 3.1e-6
        ok = prof.valid  # RF627 sends x = 0 for points without a measurement
        assert np.max(np.abs(f.profile.y[ok] - prof.y[ok])) <= 1.6e-6
        np.testing.assert_array_equal(f.profile.intensity, prof.intensity)


def test_rf627_rejects_truncated_and_bad_headers() -> None:
    good = rf627.RF627Encoder().encode(
        [1], [1], _profile(648).y, _profile(648).z, _profile(648).valid
    )[0]
    for cut in (0, 63, 64, len(good) - 1):
        with pytest.raises(rf627.FrameError):
            rf627.decode(good[:cut])
    with pytest.raises(rf627.FrameError):
        rf627.decode(good + b"\x00")
    for offset, value in ((0, 0x10), (0, 0x55), (16, 2), (32, 0), (33, 0), (63, 2), (19, 10)):
        bad = bytearray(good)
        bad[offset] = value
        if offset == 32:
            bad[33] = 0  # discrete_value == 0
        with pytest.raises(rf627.FrameError):
            rf627.decode(bytes(bad))


@FAST
@given(data=st.data())
def test_rf627_mutations_never_yield_a_malformed_profile(data: st.DataObject) -> None:
    good = rf627.RF627Encoder().encode(
        [1], [1], _profile(64).y, _profile(64).z, _profile(64).valid
    )[0]
    buf = bytearray(good)
    for _ in range(data.draw(st.integers(1, 3))):
        buf[data.draw(st.integers(0, len(buf) - 1))] = data.draw(st.integers(0, 255))
    buf = buf[: data.draw(st.integers(0, len(buf)))]
    try:
        frame = rf627.decode(bytes(buf))
    except rf627.FrameError:
        return
    # No checksum on RF627: damage in the points is undetectable, but the result is well formed.
    p, h = frame.profile, frame.header
    n = p.n_points
    assert p.y.shape == p.z.shape == p.valid.shape == (n,)
    assert len(buf) == h.data_offset + 4 * n + (n if h.flags & 1 else 0)
    assert np.all(np.isnan(p.z[~p.valid])) and np.all(p.z[p.valid] > 0)


# ----------------------------------------------------------------------------------------------
# SCIP 2.0


def test_scip_checksums_and_the_spec_example() -> None:
    assert scip.with_checksum(b"00") == b"00P"
    assert scip.with_checksum(b"99") == b"99b"
    assert scip.decode_values(b"1Dh", 3)[0] == 5432  # the SCIP 2.0 specification's example
    assert scip.encode_values([5432], 3) == b"1Dh"


@pytest.mark.parametrize("n_chars", [2, 3, 4])
def test_scip_value_encodings_round_trip(n_chars: int) -> None:
    top = (1 << (6 * n_chars)) - 1
    v = np.array([0, 1, 63, 64, top // 2, top])
    enc = scip.encode_values(v, n_chars)
    assert len(enc) == v.size * n_chars and min(enc) >= 0x30 and max(enc) <= 0x6F
    np.testing.assert_array_equal(scip.decode_values(enc, n_chars), v)


def test_scip_data_block_lines() -> None:
    chars = scip.encode_values(np.arange(100) * 37, 3)  # 300 characters
    block = scip.encode_data_block(chars)
    lines = block.split(b"\n")[:-1]
    assert [len(ln) for ln in lines] == [65, 65, 65, 65, 45]
    assert all(scip.checksum(ln[:-1]) == ln[-1] for ln in lines)


def test_scip_scan_reply_round_trip_and_rejection() -> None:
    ranges = (np.arange(1081) * 7) % 30000
    inten = np.arange(1081) % 5000
    reply_bytes = scip.scan_reply(b"ME0000108001001", b"99", 0x1234567, ranges, inten)
    [reply] = scip.ReplyDecoder().feed(reply_bytes)
    scan = scip.decode_scan(reply, with_intensity=True)
    assert scan.timestamp_ms == 0x1234567 % (1 << 24)
    np.testing.assert_array_equal(scan.ranges_mm, ranges)
    np.testing.assert_array_equal(scan.intensity, inten)
    assert scan.remaining == 1
    # One damaged data character is caught by the line checksum.
    text = bytearray(reply_bytes)
    i = reply_bytes.index(b"\n", 30) + 10  # inside the first data line
    text[i] = 0x30 + ((text[i] - 0x30 + 5) % 64)
    [bad] = scip.ReplyDecoder().feed(bytes(text))
    with pytest.raises(scip.FrameError):
        scip.decode_scan(bad, with_intensity=True)


@FAST
@given(data=st.data())
def test_scip_single_character_damage_in_scan_data_is_detected(data: st.DataObject) -> None:
    ranges = np.random.default_rng(3).integers(20, 30000, 200)
    msg = scip.scan_reply(b"GD0000019900", b"00", 1000, ranges)
    start = msg.index(b"\n", msg.index(b"\n") + 1) + 1  # from the timestamp line on
    i = data.draw(st.integers(start, len(msg) - 3))
    if msg[i] == 0x0A:
        return
    new = data.draw(st.integers(0x30, 0x6F).filter(lambda c: c != msg[i]))
    buf = bytearray(msg)
    buf[i] = new
    replies = scip.ReplyDecoder().feed(bytes(buf))
    assert len(replies) == 1
    with pytest.raises(scip.FrameError):
        scip.decode_scan(replies[0])


def test_scip_truncated_scan_is_rejected() -> None:
    msg = scip.scan_reply(b"GD0000019900", b"00", 1000, np.arange(200) + 20)
    # Cutting a reply and appending the end marker leaves a partial last line.
    for cut in (30, 80, 150, len(msg) - 5):
        blocks = scip.ReplyDecoder().feed(msg[:cut] + b"\n\n")
        for reply in blocks:
            with pytest.raises(scip.FrameError):
                scip.decode_scan(reply)


def test_scip_commands_and_info() -> None:
    cmd = scip.parse_command(b"MD0044072501000;tag")
    assert cmd.code == "MD" and cmd.string == "tag"
    assert cmd.scan_params() == (44, 725, 1, 0, 0)
    assert scip.parse_command(b"%ST").code == "%ST"
    assert scip.parse_command(b"GE0000108000").scan_params() == (0, 1080, 0, 0, 0)
    with pytest.raises(scip.FrameError):
        scip.parse_command(b"MD00x").scan_params()
    raw = scip.make_reply(b"PP", b"00", (scip.info_line("DMIN", 20), scip.info_line("MODL", "X")))
    assert raw.endswith(b"\n\n") and b"DMIN:20;" in raw
    [reply] = scip.ReplyDecoder().feed(raw)
    assert scip.decode_info(reply) == {"DMIN": "20", "MODL": "X"}
    broken = raw.replace(b"DMIN:20", b"DMIN:21")
    [reply] = scip.ReplyDecoder().feed(broken)
    with pytest.raises(scip.FrameError):
        scip.decode_info(reply)
    dec = scip.ReplyDecoder()
    assert dec.feed(b"PP\n00Q\n\n") == [] and dec.bad_replies == 1  # status checksum
