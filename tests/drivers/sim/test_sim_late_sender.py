"""The simulated sensor as a sender that cannot keep its timing (``send_late_s``, issue 21):
profiles leave 5-50 ms late in bursts, in order, and the clock fit still locks on them."""

from __future__ import annotations

import time

import numpy as np
from support import udp_receiver

from wristscan.daemon.sync.clockmap import ClockMapper
from wristscan.drivers import lpf1, lpf1_reader
from wristscan.drivers.sim.sensors import SensorSimConfig, SimulatedSensor

MS = 1_000_000


def test_late_sender_sends_5_to_50_ms_late_in_bursts_and_the_clock_locks() -> None:
    rx = udp_receiver()
    cfg = SensorSimConfig(
        kind="lpf1-udp",
        rate_hz=1000,
        n_points=64,
        target=rx.getsockname(),
        send_late_s=(0.005, 0.05),
        send_late_spike_prob=0.02,
        clock_offset_ns=1000 * 10**9,
        clock_drift_ppm=30.0,
        heartbeat_s=0,
        seed=3,
    )
    stamps: dict[int, tuple[int, int]] = {}  # frame counter -> (device stamp, receipt)
    with rx, SimulatedSensor(cfg) as sim:
        sim.record_sends(True)
        reasm = lpf1_reader.Reassembler()
        deadline = time.monotonic() + 20.0
        while len(stamps) < 2500 and time.monotonic() < deadline:
            m = reasm.push(lpf1.parse_message(rx.recv(70000)))
            if m is not None and m.header.msg_type == lpf1.MsgType.PROFILE:
                p = lpf1.decode_profile(m, time.monotonic_ns())
                stamps[p.frame_counter] = (p.sensor_time_ns, p.host_time_ns)
        log = sim.sent_log()
        info = sim.info()
        stats = sim.stats()
    fc, exposure, sent = log["frame_counter"], log["exposure_ns"], log["sent_ns"]
    late = sent - exposure - info["latency_ns"]
    assert fc.size >= 2400 and np.all(np.diff(sent) >= 0)  # in order
    assert late.min() >= 5 * MS  # never on time
    assert np.percentile(late, 50) > 15 * MS and np.percentile(late, 80) < 60 * MS
    assert late.max() > 100 * MS  # spikes
    assert np.mean(np.diff(sent) < 100_000) > 0.5  # mostly in bursts
    assert stats["sent_late_5ms"] < 0.05 * fc.size  # the simulator itself kept up
    # The clock fit on what arrived: locked, no restart, every exposure mapped to within a
    # constant (the stamp delay and the smallest delay seen, ~5 ms) that stays put.
    got = [c for c in fc.tolist() if c in stamps]
    dev = np.array([stamps[c][0] for c in got], dtype=np.int64)
    host = np.array([stamps[c][1] for c in got], dtype=np.int64)
    truth = exposure[np.searchsorted(fc, got)]
    cm = ClockMapper()
    epochs = cm.feed_many(dev, host)
    assert cm.locked and cm.n_resets == 0 and np.all(epochs == 0)
    settled = host >= host[0] + 1_000 * MS
    err = cm.to_host(dev[settled]) - truth[settled]
    assert 5 * MS <= np.median(err) <= 10 * MS
    assert np.percentile(err, 99) - np.percentile(err, 1) < 1 * MS
