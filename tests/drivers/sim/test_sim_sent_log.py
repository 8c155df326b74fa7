"""The simulated sensor's log of true exposure instants (ground truth for latency benchmarks)."""

from __future__ import annotations

import time

import numpy as np
from support import udp_receiver

from wristscan.drivers import lpf1, lpf1_reader
from wristscan.drivers.sim.sensors import SensorSimConfig, SimulatedSensor


def test_sent_log_gives_the_true_exposure_of_every_profile_sent() -> None:
    rx = udp_receiver()
    cfg = SensorSimConfig(
        kind="lpf1-udp",
        rate_hz=500,
        n_points=256,
        target=rx.getsockname(),
        latency_s=0.004,
        stamp_delay_s=0.001,
        clock_drift_ppm=50.0,
    )
    with rx, SimulatedSensor(cfg) as sim:
        assert sim.sent_log()["exposure_ns"].size == 0  # off by default
        sim.record_sends(True)
        reasm = lpf1_reader.Reassembler()
        received: dict[int, int] = {}  # frame counter -> receipt (host ns)
        deadline = time.monotonic() + 20.0
        while len(received) < 40 and time.monotonic() < deadline:
            m = reasm.push(lpf1.parse_message(rx.recv(70000)))
            if m is not None and m.header.msg_type == lpf1.MsgType.PROFILE:
                p = lpf1.decode_profile(m, time.monotonic_ns())
                received[p.frame_counter] = p.host_time_ns
        log = sim.sent_log()
        again = sim.sent_log()  # cleared by the read, still recording
        sim.record_sends(False)
        info = sim.info()
        off = sim.sent_log()
    assert len(received) == 40
    fc, exposure, sent = log["frame_counter"], log["exposure_ns"], log["sent_ns"]
    assert fc.size >= 30 and np.all(np.diff(fc) == 1)
    # The simulator's timing model: exposure k at t0 + k * period (host clock, no drift there).
    k = fc + info["counter_base"]
    expected = info["t0_ns"] + (k * info["period_ns"]).astype(np.int64)
    np.testing.assert_array_equal(exposure, expected)
    np.testing.assert_allclose(np.diff(exposure), 1e9 / 500 / (1 + 50e-6), atol=1)
    assert np.all(sent >= exposure + info["latency_ns"])
    # Every profile received after the log began is in it, and arrived after it was sent.
    logged = dict(zip(fc.tolist(), sent.tolist(), strict=True))
    late = [c for c in received if c > fc[0]]
    assert len(late) >= 29
    assert all(c in logged and received[c] >= logged[c] for c in late)
    assert again["exposure_ns"].size == 0 or again["frame_counter"][0] > fc[-1]
    assert off["exposure_ns"].size == 0
