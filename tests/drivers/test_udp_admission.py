"""Kernel-side admission (``set_admission``): a socket filter the kernel runs before queueing
(the daemon's steering of it: tests/daemon/service/test_overload.py).

Real loopback UDP, frames from the real LPF1 encoder: with a fraction set, exactly the frames the
filter's rule keeps reach the driver (fragments of a frame share its fate, control messages
always pass), the missing ones are counted as ``shed``, not ``lost``; once removed, everything
arrives again and gaps are losses again.
"""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from wristscan.drivers import _bpf, lpf1, rf627
from wristscan.drivers.records import ProfileBlock
from wristscan.drivers.sensor_lpf1 import Lpf1UdpSensor
from wristscan.drivers.sensor_rf627 import Rf627Sensor

pytestmark = pytest.mark.skipif(not _bpf.available(), reason="socket filters are Linux's")


def test_the_rule_keeps_the_fraction_evenly_spread() -> None:
    for f in (0.1, 0.3, 0.5, 0.77):
        keep = np.array(_bpf.kept(list(range(1_000, 11_000)), f))
        assert abs(keep.sum() - f * 10_000) <= 1
        runs = np.diff(np.flatnonzero(keep))  # steps between kept frames: 1/f, never more
        assert runs.max() <= int(np.ceil(1 / f)) and runs.min() >= int(np.floor(1 / f))
    with pytest.raises(ValueError, match="outside"):
        _bpf.kept([1], 1.0)


def _frames(enc: lpf1.ProfileEncoder, counters: np.ndarray, n: int = 64) -> list[list[bytes]]:
    z = np.full((counters.shape[0], n), 0.1)
    return enc.encode(counters, counters * 1000, z, np.ones(z.shape, bool))


def _send_read(drv: Lpf1UdpSensor | Rf627Sensor, grams: list[bytes]) -> list[int]:
    assert drv.local_address is not None
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        for g in grams:
            tx.sendto(g, drv.local_address)
    got: list[ProfileBlock] = []
    quiet = time.monotonic() + 0.2
    while time.monotonic() < quiet:
        b = drv.read_blocks(4096)
        if b:
            got += b
            quiet = time.monotonic() + 0.2
        time.sleep(0.002)
    return [int(c) for b in got for c in b.frame_counter]


def test_lpf1_frames_shed_in_the_kernel_and_counted() -> None:
    whole = lpf1.ProfileEncoder(7, lpf1.PointFormat.I16, x_uniform=(-0.02, 1e-4))
    frag = lpf1.ProfileEncoder(7, lpf1.PointFormat.I16, x_uniform=(-0.02, 1e-4),
                               max_message_bytes=200)  # fmt: skip
    a, b = np.arange(0, 300), np.arange(300, 360)  # b: three fragments a frame
    hello = lpf1.encode_control(lpf1.MsgType.HELLO, 7, 0, 0, {"model": "sim"})
    beat = lpf1.encode_control(lpf1.MsgType.HEARTBEAT, 7, 299, 0)
    with Lpf1UdpSensor(sensor_id=7, bind_host="127.0.0.1", port=0) as drv:
        assert drv.set_admission(0.3) and drv.health().detail["admission"] == 0.3
        grams = [hello] + [m for ms in _frames(whole, a) for m in ms] + [beat]
        grams += [m for ms in _frames(frag, b) for m in ms]
        got = _send_read(drv, grams)
        sent = [int(c) for c in np.r_[a, b]]
        want = [c for c, k in zip(sent, _bpf.kept(sent, 0.3), strict=True) if k]
        assert got == want and len(want) == 108
        c = drv.health().counters
        # Gaps between delivered frames (frame 0 is kept; the tail waits for the next frame).
        assert (c.shed, c.lost, c.malformed) == (want[-1] + 1 - 108, 0, 0)
        assert drv.stats["hellos"] == 1 and drv.stats["heartbeats"] == 1
        # Removed: every frame again; a gap is a loss again once the queue was drained.
        assert drv.set_admission(None) and drv.admission is None
        assert _send_read(drv, [m for ms in _frames(whole, np.arange(360, 400)) for m in ms])
        got = _send_read(drv, [m for ms in _frames(whole, np.r_[400:420, 425:430]) for m in ms])
        assert got == list(range(400, 420)) + list(range(425, 430))
        c = drv.health().counters
        assert (c.shed, c.lost) == (360 - 108, 5)  # the tail shed, 420-424 lost


def test_rf627_frames_shed_in_the_kernel_by_measure_count() -> None:
    """RF627: every datagram is a profile; its ``measure_count`` decides (wrapping at 2**32)."""
    enc = rf627.RF627Encoder(serial=42)
    counts = np.arange((1 << 32) - 100, (1 << 32) + 200) % (1 << 32)
    times = 5_000_000_000 + np.arange(counts.size) * 1_000_000
    z = np.full((counts.size, 40), 0.05)
    grams = enc.encode(counts, times, np.linspace(-0.02, 0.02, 40), z, np.ones(z.shape, bool))
    with Rf627Sensor(sensor_id=42, bind_host="127.0.0.1", port=0) as drv:
        assert drv.set_admission(0.4)
        got = _send_read(drv, grams)
        sent = [int(c) for c in counts]
        want = [c for c, k in zip(sent, _bpf.kept(sent, 0.4), strict=True) if k]
        assert got == want and len(want) == 120
        c = drv.health().counters
        assert (c.lost, c.malformed) == (0, 0) and c.shed == sent.index(want[-1]) + 1 - 120
