"""The worker's schedule: reading ahead between ticks, and the slow-tick counters.

A real LPF1-over-UDP driver on loopback (kernel receipt stamps) receives datagrams from a plain
UDP socket; the robot is a silent stand-in device (no states: the profiles stay pending, which
is all the schedule needs).

The first tick is put a minute away, so that "before the first tick" holds however slowly a
loaded machine runs the test: waits are for the counters, not for a fixed time."""

from __future__ import annotations

import socket
import time
from typing import Any

import numpy as np
from support import StandInRobot

from wristscan.daemon.service.pipeline import AlignmentSetup, Pipeline, PipelineSettings
from wristscan.daemon.sync.pairing import Pairer, PairerConfig
from wristscan.drivers import lpf1
from wristscan.drivers.sensor_lpf1 import Lpf1UdpSensor


def _datagrams(n: int, n_points: int = 256) -> list[bytes]:
    enc = lpf1.ProfileEncoder(1, lpf1.PointFormat.I16, x_uniform=(-0.025, 0.05 / (n_points - 1)))
    z = np.full((n, n_points), 0.1)
    t = (np.arange(n) * 1_000_000).astype(np.int64)
    return [m[0] for m in enc.encode(np.arange(n), t, z, np.ones(z.shape, bool))]


def _received_before_first_tick(read_ahead_s: float, expect: int) -> tuple[int, dict[str, Any]]:
    """Send 20 profiles, then wait until ``expect`` are received (up to 30 s) or, with
    ``expect`` 0, for the time read-ahead takes to read them (0.5 s, many of its 0.02 s
    steps); returns what was received, all well before the first tick (60 s)."""
    sensor = Lpf1UdpSensor(bind_host="127.0.0.1", port=0)
    robot = StandInRobot()
    sensor.open()
    robot.open()
    assert sensor.stamped_on_receipt, "Linux stamps UDP receipt in the kernel"
    pipeline = Pipeline(
        sensor,
        robot,
        Pairer(PairerConfig()),
        AlignmentSetup(np.eye(4)),
        None,
        settings=PipelineSettings(batch_s=60.0, read_ahead_s=read_ahead_s),
    )
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        assert pipeline.inline_sensor
        pipeline.start()
        for g in _datagrams(20):
            tx.sendto(g, sensor.local_address)
        deadline = time.monotonic() + (30.0 if expect else 0.5)
        while pipeline.stats()["received"] < max(expect, 1) and time.monotonic() < deadline:
            time.sleep(0.01)
        early = pipeline.stats()
    finally:
        pipeline.stop(drain=False)
        tx.close()
        sensor.close()
        robot.close()
    return int(early["received"]), early


def test_the_worker_reads_ahead_between_ticks() -> None:
    received, stats = _received_before_first_tick(read_ahead_s=0.02, expect=20)
    assert received == 20
    # Read and queued for pairing: pending (no robot state), none lost, counters add up.
    assert stats["pending"] == 20 and stats["published"] == 0 and not stats["dropped"]
    assert stats["slow_ticks"] == 0 and stats["read_errors"] == {}


def test_without_read_ahead_the_socket_is_read_at_ticks_only() -> None:
    received, _ = _received_before_first_tick(read_ahead_s=0.0, expect=0)
    assert received == 0


class _CountingSensor(Lpf1UdpSensor):
    """The real driver, counting the worker's read passes that found profiles."""

    passes = 0

    def read_blocks(self, max_profiles: int = 4096) -> list[Any]:
        out = super().read_blocks(max_profiles)
        if out:
            self.passes += 1
        return out


def _passes_per_tick(read_ahead_profiles: int) -> float:
    """A 1 kHz stream for 0.6 s into a worker ticking every 20 ms and reading ahead every
    2 ms at most: read passes that found profiles, per tick."""
    sensor = _CountingSensor(bind_host="127.0.0.1", port=0)
    sensor.open()
    settings = PipelineSettings(
        batch_s=0.02, read_ahead_s=0.002, read_ahead_profiles=read_ahead_profiles
    )
    pipeline = Pipeline(
        sensor, StandInRobot(), Pairer(PairerConfig()), AlignmentSetup(np.eye(4)), None,
        settings=settings,
    )  # fmt: skip
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    grams = _datagrams(600, n_points=64)
    try:
        pipeline.start()
        t0 = time.monotonic()
        for k, g in enumerate(grams):
            time.sleep(max(0.0, t0 + k * 0.001 - time.monotonic()))
            tx.sendto(g, sensor.local_address)
        ticks = (time.monotonic() - t0) / settings.batch_s
    finally:
        pipeline.stop(drain=False)
        tx.close()
        sensor.close()
    return sensor.passes / ticks


def test_read_ahead_waits_for_enough_profiles() -> None:
    # A pass costs ~0.1 ms however few profiles it decodes: at 1 kHz, 32 profiles come every
    # 32 ms, so the worker reads at its ticks only; asked for one, it reads every 2-3 ms.
    sparse, eager = _passes_per_tick(32), _passes_per_tick(1)
    assert sparse <= 1.5, sparse
    assert eager >= 3.0, eager
