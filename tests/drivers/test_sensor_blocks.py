"""``read_blocks`` (one receive pass, one vectorised decode per run of datagrams) against
``read`` (one datagram, one profile at a time): the same datagram stream, sent over real loopback
UDP sockets to two drivers, must give the same profiles bit for bit, the same counters and the
same health detail, whatever the stream holds: fragments, control messages, damaged and foreign
datagrams, duplicated, reordered and lost frames, device restarts, every point format, explicit
x, intensity and encoder counts. The stream comes from the real encoders
(:class:`~wristscan.drivers.lpf1.ProfileEncoder`, :class:`~wristscan.drivers.rf627.RF627Encoder`)
and from the simulated LPF1-UDP sensor with its fault injection.

Only the receipt stamps differ between two sockets: they are checked against the send and read
times instead (kernel stamps of the arrival, not of the late reader).
"""

from __future__ import annotations

import contextlib
import socket
import time
import zlib
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from wristscan.calib import jit
from wristscan.drivers import _mmsg, lpf1, lpf1_block, rf627, rf627_block
from wristscan.drivers._sensor import SensorCore
from wristscan.drivers._udp import SO_TIMESTAMPNS, UdpProfileSensor, kernel_stamp
from wristscan.drivers.records import Profile, ProfileBlock
from wristscan.drivers.sensor_lpf1 import Lpf1UdpSensor
from wristscan.drivers.sensor_rf627 import Rf627Sensor
from wristscan.drivers.sim.sensors import FaultConfig, SensorSimConfig, SimulatedSensor

VOLATILE = {"local_address", "last_rx_age_s", "stale", "rcvbuf_bytes"}
"""Health detail that differs between two sockets (or two instants)."""


def _profiles(blocks: list[ProfileBlock]) -> list[Profile]:
    return [b.profile(k) for b in blocks for k in range(b.n_profiles)]


def _same(a: Profile, b: Profile) -> bool:
    """Bitwise equal, receipt stamps aside."""

    def eq(u: Any, v: Any) -> bool:
        if u is None or v is None:
            return u is None and v is None
        u, v = np.asarray(u), np.asarray(v)
        return u.dtype == v.dtype and u.shape == v.shape and u.tobytes() == v.tobytes()

    u64 = 1 << 64  # values of 2**63 and more are negative in a block's int64 arrays
    return (
        (a.sensor_id, a.frame_counter % u64, a.sensor_time_ns % u64, a.encoder)
        == (b.sensor_id, b.frame_counter % u64, b.sensor_time_ns % u64, b.encoder)
        and eq(a.y, b.y)
        and eq(a.z, b.z)
        and eq(a.valid, b.valid)
        and eq(a.intensity, b.intensity)
    )


def _read_all(drv: UdpProfileSensor) -> list[Profile]:
    out = []
    while (p := drv.read(timeout=0.2)) is not None:
        out.append(p)
    return out


def _read_all_blocks(drv: UdpProfileSensor, max_profiles: int) -> list[ProfileBlock]:
    """Blocks until the socket stays empty for 0.2 s (several passes: ``max_profiles``)."""
    out: list[ProfileBlock] = []
    quiet_until = time.monotonic() + 0.2
    while time.monotonic() < quiet_until:
        got = drv.read_blocks(max_profiles)
        assert sum(b.n_profiles for b in got) <= max_profiles
        if got:
            out += got
            quiet_until = time.monotonic() + 0.2
        else:
            time.sleep(0.005)
    return out


def _compare(a: UdpProfileSensor, b: UdpProfileSensor, ref: list[Profile],
             blocks: list[ProfileBlock]) -> list[Profile]:  # fmt: skip
    got = _profiles(blocks)
    assert [p.frame_counter % (1 << 64) for p in got] == [p.frame_counter for p in ref]
    bad = [k for k, (p, q) in enumerate(zip(ref, got, strict=True)) if not _same(p, q)]
    assert not bad, f"profiles {bad[:5]} differ"
    ha, hb = a.health(), b.health()
    assert ha.counters == hb.counters
    da = {k: v for k, v in ha.detail.items() if k not in VOLATILE}
    db = {k: v for k, v in hb.detail.items() if k not in VOLATILE}
    assert da == db
    return got


def _twin_send(drivers: tuple[UdpProfileSensor, UdpProfileSensor], grams: list[bytes]) -> None:
    """Every datagram to both drivers, paced so that no socket buffer overflows."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        for k, g in enumerate(grams):
            for d in drivers:
                assert d.local_address is not None
                tx.sendto(g, d.local_address)
            if k % 64 == 63:
                time.sleep(0.002)


@contextlib.contextmanager
def _kernel_stamping() -> Iterator[None]:
    """Linux stamps arriving datagrams only while some socket asks for stamps, and turns that
    on a little after the first one asks (deferred work): until then a datagram is stamped
    when it is read. This socket asks first and holds it on until the stamps come early."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        probe.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        deadline = time.monotonic() + 10.0
        while True:
            probe.sendto(b"probe", probe.getsockname())
            time.sleep(0.02)
            _, anc, _, _ = probe.recvmsg(16, socket.CMSG_SPACE(16))
            read_ns = time.monotonic_ns()
            if kernel_stamp(anc, read_ns) < read_ns - 10_000_000:
                break
            assert time.monotonic() < deadline, "the kernel does not stamp on arrival"
        yield


def _lpf1_stream() -> list[bytes]:
    """Profiles of every format and option, with the faults a link and a sender make."""
    rng = np.random.default_rng(5)
    n = 300
    out: list[bytes] = []

    def profiles(enc: lpf1.ProfileEncoder, start: int, count: int, n: int = n,
                 **kw: Any) -> list[list[bytes]]:  # fmt: skip
        z = rng.uniform(0.06, 0.14, (count, n))
        valid = rng.random(z.shape) > 0.1
        x = np.linspace(-0.02, 0.02, n) + rng.normal(0, 1e-6, (count, n))
        x[rng.random(x.shape) < 0.02] = np.nan  # explicit x without a value: invalid point
        inten = rng.integers(0, 256, z.shape)
        counters = np.arange(start, start + count)
        return enc.encode(counters, counters * 100_000 + 7, z, valid,
                          x=None if not enc.explicit_x else x,
                          intensity=inten if enc.intensity else None, **kw)  # fmt: skip

    grid = (-0.02, 0.04 / (n - 1))
    i16 = lpf1.ProfileEncoder(7, lpf1.PointFormat.I16, x_uniform=grid, intensity=True)
    i32 = lpf1.ProfileEncoder(7, lpf1.PointFormat.I32, x_scale_nm=500, x_offset_um=-30)
    f32 = lpf1.ProfileEncoder(7, lpf1.PointFormat.F32, intensity=True)
    f32u = lpf1.ProfileEncoder(7, lpf1.PointFormat.F32, x_uniform=grid)
    frag = lpf1.ProfileEncoder(7, lpf1.PointFormat.I16, x_uniform=grid, max_message_bytes=400)
    other = lpf1.ProfileEncoder(8, lpf1.PointFormat.I16, x_uniform=grid)
    hello = lpf1.encode_control(lpf1.MsgType.HELLO, 7, 0, 0, {"model": "sim"})
    out.append(hello)
    a = [m[0] for m in profiles(i16, 0, 40, encoder=np.arange(40) * 3)]
    a[5], a[6] = a[6], a[5]  # reordered
    a.insert(12, a[11])  # duplicated
    del a[20]  # lost
    damaged = bytearray(a[25])
    damaged[500] ^= 0x10  # a bit flip among the points: CRC mismatch
    a[25] = bytes(damaged)
    a.insert(30, a[29][:-3])  # truncated
    a.insert(31, b"LPF1 garbage")
    a.insert(33, lpf1.encode_control(lpf1.MsgType.HEARTBEAT, 7, 31, 10))
    out += a
    out += [m[0] for m in profiles(other, 0, 5)]  # another sensor on the same port
    out += [m[0] for m in profiles(i32, 40, 30)]
    fr = [m for frags in profiles(frag, 70, 6) for m in frags]
    fr[0], fr[1] = fr[1], fr[0]  # fragments out of order
    out += fr
    out += [m[0] for m in profiles(f32, 76, 30, encoder=np.arange(30))]
    out.append(lpf1.encode_control(lpf1.MsgType.STATUS, 7, 105, 0, {"state": "warm"}))
    out += [m[0] for m in profiles(f32u, 106, 30)]
    # Datagrams of 18 kB, longer than a receive row at first (one per call: the row grows).
    out += [m[0] for m in profiles(f32, 136, 12, n=2048, encoder=np.arange(12))]
    # A device reboot announced by HELLO, then counting from 0 again; later a silent restart.
    out.append(lpf1.encode_control(lpf1.MsgType.HELLO, 7, 0, 0, {"model": "sim", "boot": 2}))
    out += [m[0] for m in profiles(i16, 0, 40)]
    out += [m[0] for m in profiles(i16, 5000, 20)]  # jumps ahead (a gap) ...
    out += [m[0] for m in profiles(i16, 2000, 20)]  # ... far back: a restart
    return out


RECEIVE = ["recvmmsg", "recvmsg"]
"""Both ways ``read_blocks`` receives (many datagrams per system call, or one)."""


@pytest.mark.parametrize(
    ("receive", "decode"),
    [("recvmmsg", "compiled"), ("recvmmsg", "numpy"), ("recvmsg", "compiled")],
)
def test_lpf1_blocks_equal_the_profile_by_profile_path(
    receive: str, decode: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The pass read back and its integer points scaled by the compiled kernels (numba, in the
    # test install) or by numpy: both the per-datagram parser's values, bit for bit.
    monkeypatch.setattr(jit, "enabled", decode == "compiled")
    assert jit.available() == (decode == "compiled")
    grams = _lpf1_stream()
    fast = _spy(monkeypatch, lpf1_block, "decode_run")
    usual = _spy(monkeypatch, lpf1_block, "decode_uniform")
    a = Lpf1UdpSensor(sensor_id=7, bind_host="127.0.0.1", port=0)
    b = Lpf1UdpSensor(sensor_id=7, bind_host="127.0.0.1", port=0)
    b.batch_receive = receive
    with _kernel_stamping(), a, b:
        sent0 = time.monotonic_ns()
        _twin_send((a, b), grams)
        time.sleep(0.08)
        read_ns = time.monotonic_ns()
        ref = _read_all(a)
        # Small passes: runs cut at pass boundaries, the stride grows after the fragments.
        blocks = _read_all_blocks(b, 23)
        got = _compare(a, b, ref, blocks)
    h = b.health()
    assert len(ref) > 200 and h.counters.lost > 0 and h.counters.malformed >= 3
    assert h.counters.duplicates + h.counters.reordered >= 2
    assert h.detail["foreign"] == 5 and h.detail["restarts"] == 2
    assert h.detail["hellos"] == 2 and h.detail["statuses"] == 1 and h.detail["heartbeats"] == 1
    # Most profiles came through the vectorised decoder, in blocks of many.
    assert sum(fast + usual) >= 0.8 * len(ref) and max(fast + usual) >= 20
    # The usual passes in two compiled calls when compiled, never without.
    assert (sum(usual) >= 20) == (decode == "compiled")
    assert any(bl.y.ndim == 2 for bl in blocks) and any(bl.intensity is not None for bl in blocks)
    # Receipt stamps are the kernel's: on arrival, not when the late reader came.
    stamps = np.array([p.host_time_ns for p in got])
    assert np.all(stamps >= sent0) and np.all(stamps < read_ns - 60_000_000)
    assert np.all(np.diff(stamps) >= 0)


def test_lpf1_blocks_from_the_simulated_sensor_with_faults() -> None:
    """The simulated sensor's own stream (2048 points, intensity, encoder, faults injected),
    relayed datagram by datagram to both drivers."""
    a = Lpf1UdpSensor(bind_host="127.0.0.1", port=0)
    b = Lpf1UdpSensor(bind_host="127.0.0.1", port=0)
    with a, b, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as relay:
        relay.bind(("127.0.0.1", 0))
        relay.settimeout(0.5)
        faults = FaultConfig(drop=0.02, duplicate=0.02, reorder=0.02, truncate=0.01,
                             corrupt=0.02)  # fmt: skip
        cfg = SensorSimConfig(kind="lpf1-udp", rate_hz=2000.0, n_points=2048, intensity=True,
                              encoder="time", target=relay.getsockname(), heartbeat_s=0.1,
                              faults=faults, seed=4)  # fmt: skip
        grams: list[bytes] = []
        with SimulatedSensor(cfg) as sim:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
                end = time.monotonic() + 30.0
                while len(grams) < 600 and time.monotonic() < end:
                    try:
                        g = relay.recv(1 << 16)
                    except TimeoutError:
                        continue
                    grams.append(g)
                    for d in (a, b):
                        assert d.local_address is not None
                        tx.sendto(g, d.local_address)
            stats = sim.stats()
        ref = _read_all(a)
        blocks = _read_all_blocks(b, 4096)
        _compare(a, b, ref, blocks)
    h = b.health()
    assert len(grams) == 600 and len(ref) > 500
    assert stats["corrupted"] > 0 and h.counters.malformed > 0 and h.counters.lost > 0
    assert h.detail["hellos"] == 1 and h.detail["heartbeats"] >= 1
    assert all(p.encoder is not None and p.intensity is not None for p in ref)


@pytest.mark.parametrize("receive", RECEIVE)
def test_rf627_blocks_equal_the_datagram_by_datagram_path(
    receive: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    enc = rf627.RF627Encoder(serial=42, intensity=True)
    n = 200
    rng = np.random.default_rng(9)
    # Counters wrap at 2**32, the device clock jitters (1 %), then the device reboots.
    counts = np.r_[np.arange((1 << 32) - 30, 1 << 32), np.arange(0, 60), np.arange(0, 30)]
    steps = 1_000_000 + rng.integers(-10_000, 10_000, counts.size)
    times = 5_000_000_000 + np.cumsum(steps)
    times[75:] += 700_000  # a clock step (0.7 periods) with the counter going on
    times[90:] -= times[90] - 1_000_000  # the reboot restarts the clock too
    z = rng.uniform(0.02, 0.09, (counts.size, n))
    grams = enc.encode(counts, times, np.linspace(-0.02, 0.02, n), z, rng.random(z.shape) > 0.1,
                       intensity=rng.integers(0, 256, z.shape), step_count=counts)  # fmt: skip
    damaged = bytearray(grams[60])
    damaged[28] ^= 0x04  # zmr: header damage
    grams[60] = bytes(damaged)
    wild = bytearray(grams[70])
    wild[24:28] = (7777).to_bytes(4, "little")  # a wild counter
    grams[70] = bytes(wild)
    grams.insert(10, grams[9])  # duplicated
    del grams[40]  # lost
    grams.insert(50, grams[49][:-10])  # truncated
    fast = _spy(monkeypatch, rf627_block, "decode_rows")
    a = Rf627Sensor(sensor_id=42, bind_host="127.0.0.1", port=0)
    b = Rf627Sensor(sensor_id=42, bind_host="127.0.0.1", port=0)
    b.batch_receive = receive
    with a, b:
        _twin_send((a, b), grams)
        ref = _read_all(a)
        blocks = _read_all_blocks(b, 16)
        _compare(a, b, ref, blocks)
    h = b.health()
    assert len(ref) > 100 and h.counters.lost >= 1 and h.counters.duplicates == 1
    assert h.counters.malformed >= 4 and h.detail["restarts"] == 2
    assert sum(fast) >= 0.9 * len(ref)  # most in blocks


def _spy(monkeypatch: pytest.MonkeyPatch, module: Any, name: str) -> list[int]:
    """Profiles decoded by ``module.name`` (a block decoder), call by call."""
    real = getattr(module, name)
    sizes: list[int] = []

    def spy(*args: Any, **kw: Any) -> ProfileBlock | None:
        block: ProfileBlock | None = real(*args, **kw)
        if block is not None:  # decode_uniform: None when the pass is not the usual one
            sizes.append(block.n_profiles)
        return block

    monkeypatch.setattr(module, name, spy)
    return sizes


def _with_fields(msg: bytes, **values: int) -> bytes:
    """``msg`` with header fields set and a CRC that matches again."""
    b = bytearray(msg[:-4])
    for field, value in values.items():
        offset = lpf1_block.HEADER_DTYPE.fields[field][1]  # type: ignore[index]
        size = lpf1_block.HEADER_DTYPE[field].itemsize
        b[offset : offset + size] = (value % (1 << (8 * size))).to_bytes(size, "little")
    return bytes(b) + zlib.crc32(b).to_bytes(4, "little")


def _rewritten(msg: bytes, rng: np.random.Generator) -> bytes:
    """``msg`` with one header field set to an odd value and a CRC that matches again (a
    sender's bug, not line damage): what the per-datagram parser rejects or accepts, the block
    path must too."""
    field = rng.choice(["version", "header_len", "msg_type", "flags", "payload_len", "point_count",
                        "point_format", "frag_index", "frag_count", "frag_offset", "reserved",
                        "x_scale_nm", "sensor_id", "frame_counter"])  # fmt: skip
    value = int(rng.choice([0, 1, 2, 3, 4, 7, 8, 0x80, 0xFF, 73, 300, 600]))
    return _with_fields(msg, **{str(field): value})


@pytest.mark.parametrize("receive", RECEIVE)
def test_lpf1_blocks_accept_and_reject_what_the_parser_does(receive: str) -> None:
    rng = np.random.default_rng(11)
    n = 300
    enc = lpf1.ProfileEncoder(7, lpf1.PointFormat.I16, x_uniform=(-0.02, 0.04 / (n - 1)))
    z = rng.uniform(0.06, 0.14, (400, n))
    msgs = [m[0] for m in enc.encode(np.arange(400), np.arange(400), z, z > 0.07)]
    grams = [_rewritten(m, rng) if rng.random() < 0.3 else m for m in msgs]
    # A counter and a device time past 2**63 (a faulty sender: the CRC is right).
    grams.append(_with_fields(msgs[-1], frame_counter=1 << 63, timestamp_ns=(1 << 64) - 5))
    a = Lpf1UdpSensor(bind_host="127.0.0.1", port=0)
    b = Lpf1UdpSensor(bind_host="127.0.0.1", port=0)
    b.batch_receive = receive
    with a, b:
        _twin_send((a, b), grams)
        ref = _read_all(a)
        got = _compare(a, b, ref, _read_all_blocks(b, 64))
    assert 200 < len(ref) < 400 and a.health().counters.malformed > 20
    assert ref[-1].frame_counter == 1 << 63 and got[-1].frame_counter == -(1 << 63)


def _random_counters(rng: np.random.Generator, modulo: int) -> Iterator[int]:
    c = int(rng.integers(0, min(modulo, 1 << 62)))
    for _ in range(400):
        r = rng.random()
        if r < 0.6:
            c += 1
        elif r < 0.7:
            c += int(rng.integers(2, 40))  # lost frames
        elif r < 0.78:
            c -= int(rng.integers(0, 5))  # duplicate or late
        elif r < 0.8:
            c -= int(rng.integers(2000, 10**6))  # restart
        elif r < 0.82:
            c += modulo // 2  # exactly half-way: behind or ahead is a matter of definition
        else:
            c += 1
        yield c % modulo


class _Book(SensorCore):
    """The shared bookkeeping alone (no transport)."""

    kind = "book"

    def _open(self) -> None: ...

    def _close(self) -> None: ...

    def _read_internal(self, timeout: float | None) -> Profile | None:
        return self._pop()


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("expected", [7, None])
@pytest.mark.parametrize("modulo", [1 << 32, 1 << 64])
def test_block_bookkeeping_counts_as_profile_by_profile(
    modulo: int, expected: int | None, compiled: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(jit, "enabled", compiled)  # the counters' steps: one kernel, or numpy
    rng = np.random.default_rng(modulo % 97)
    seq = list(_random_counters(rng, modulo))
    seq = [c for c in seq if c < 1 << 63]
    ids = [7 if rng.random() > 0.05 else 8 for _ in seq]
    times = np.cumsum(rng.choice([100_000, 600_000_000], len(seq), p=[0.97, 0.03]))
    y = np.zeros(2)
    recs = [Profile(i, c, 0, int(t), y, np.zeros(2), np.ones(2, bool))
            for i, c, t in zip(ids, seq, times.tolist(), strict=True)]  # fmt: skip
    one, many = _Book(expected), _Book(expected)
    kept_one = [r.frame_counter for r in recs if one._deliver(r, modulo)]
    kept_many: list[int] = []
    a = 0
    while a < len(recs):
        b = a + int(rng.integers(1, 30))
        (block,) = ProfileBlock.from_profiles(recs[a:b])
        out = many._deliver_block(block, modulo)
        kept_many += [] if out is None else out.frame_counter.tolist()
        a = b
    assert kept_many == kept_one
    assert one.counters == many.counters and one.stats == many.stats
    assert one._last_counter == many._last_counter and one.sensor_id == many.sensor_id
    assert one.counters.lost > 0 and one.stats["restarts"] > 0
    assert one.stats["foreign"] > 0 or expected is None


@pytest.mark.parametrize("receive", RECEIVE)
def test_read_blocks_takes_what_read_left_keeps_the_budget_and_filters_sources(
    receive: str,
) -> None:
    grams = [m[0] for m in lpf1.ProfileEncoder(7, x_uniform=(0.0, 1e-4)).encode(
        np.arange(50), np.arange(50), np.full((50, 64), 0.1), np.ones((50, 64), bool))]  # fmt: skip
    drv = Lpf1UdpSensor(bind_host="127.0.0.1", port=0)
    drv.batch_receive = receive
    with drv, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        assert drv.local_address is not None
        for g in grams:
            tx.sendto(g, drv.local_address)
        first = drv.read(timeout=1.0)
        assert first is not None and first.frame_counter == 0
        counters: list[int] = []
        while len(counters) < 49:
            blocks = drv.read_blocks(10)
            assert sum(b.n_profiles for b in blocks) <= 10
            counters += [c for b in blocks for c in b.frame_counter.tolist()]
        assert counters == list(range(1, 50))
        assert drv.health().counters.received == 50
        assert (drv._mmsg is not None) == (receive == "recvmmsg")
        assert _mmsg.available()  # Linux: "auto" receives with recvmmsg (checked at first use)
    with pytest.raises(Exception, match="closed"):
        drv.read_blocks()

    drv = Lpf1UdpSensor(bind_host="127.0.0.1", port=0, source_host="127.0.0.2")
    drv.batch_receive = receive
    with drv, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as own:  # fmt: skip
        own.bind(("127.0.0.2", 0))
        assert drv.local_address is not None
        for k, g in enumerate(grams[:10]):
            (own if k % 2 else other).sendto(g, drv.local_address)
        time.sleep(0.05)
        got = _profiles(_read_all_blocks(drv, 4096))
        h = drv.health()
    assert [p.frame_counter for p in got] == [1, 3, 5, 7, 9]
    assert h.detail["foreign_source"] == 5 and h.counters.received == 5
