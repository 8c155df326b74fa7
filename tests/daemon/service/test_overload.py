"""Admission under overload (daemon/service/overload.py): a worker simulated tick by tick with
known costs, so the capacity is known exactly and what the shedder admits can be checked; the
steering of a real UDP driver's socket filter (shedding before reading); then the real pipeline
(the LPF1-over-UDP driver on loopback, the pairer, a controller stand-in sending states every
2 ms) with a publish call made slow enough that twice its capacity fits in a test."""

from __future__ import annotations

import math
import multiprocessing
import socket
import time
from typing import Any

import numpy as np
import pytest
from support import StandInRobot

from wristscan.daemon.cloud import wsc1
from wristscan.daemon.service.overload import KernelAdmission, Shedder, spread_rows, take_rows
from wristscan.daemon.service.pipeline import AlignmentSetup, Pipeline
from wristscan.daemon.sync.pairing import Pairer, PairerConfig
from wristscan.drivers import lpf1
from wristscan.drivers.records import ProfileBlock, RobotState
from wristscan.drivers.sensor_lpf1 import Lpf1TcpSensor, Lpf1UdpSensor

C_READ_NS = 3_000
C_KEEP_NS = 20_000
TICK_NS = 10_000_000


class _Clock:
    now = 0
    """The simulated worker's time (ns), carried from one run to the next."""


def _run(shedder: Shedder, rates: list[tuple[float, float]]) -> list[tuple[float, int, int, float]]:
    """Simulate ticks: (rate Hz, seconds) phases; a worker that reads everything and processes
    what is admitted, at the costs above; what arrives while a tick runs waits for the next.
    Returns (phase rate, arrived, admitted, largest lag s) per phase."""
    now = _Clock.now
    out = []
    carry = 0.0
    step = TICK_NS
    for rate, seconds in rates:
        arrived = admitted = 0
        lag = 0.0
        end = now + int(seconds * 1e9)
        while now < end:
            carry += rate * step * 1e-9  # what arrived while the last tick ran
            n = int(carry)
            carry -= n
            k = shedder.admit(n, now, now - step)  # the oldest came right after the last tick
            lag = max(lag, shedder.lag_s)
            step = max(TICK_NS, n * C_READ_NS + k * C_KEEP_NS)  # an overrun delays the next
            now += step
            arrived += n
            admitted += k
        out.append((rate, arrived, admitted, lag))
    _Clock.now = now
    return out


def test_below_capacity_nothing_is_shed() -> None:
    s = Shedder()
    ((_, arrived, admitted, lag),) = _run(s, [(20_000.0, 2.0)])  # 46 % of the worker
    assert admitted == arrived and lag <= 0.011
    assert s.shed == 0 and not s.shedding


def test_overload_publishes_near_capacity_with_a_bounded_lag_and_recovers() -> None:
    s = Shedder()
    capacity = 1e9 / (C_READ_NS + C_KEEP_NS)  # 43 478 profiles/s when everything is kept
    # The overload's first second finds the rate; the next two count.
    phases = _run(s, [(5_000.0, 1.0), (2 * capacity, 1.0), (2 * capacity, 2.0), (5_000.0, 1.0)])
    (_, a0, k0, _), (_, a_on, k_on, _), (rate, a1, k1, lag1), (_, a2, k2, _) = phases
    assert k0 == a0
    # At twice the capacity the worker still reads everything (3 us each), so it can keep at
    # most (1 - rate * 3 us) / 20 us per second: what it admits must come close to that.
    keepable = (1.0 - rate * C_READ_NS * 1e-9) / (C_KEEP_NS * 1e-9)
    kept_rate = k1 / 2.0
    assert 0.85 * keepable <= kept_rate <= 1.06 * keepable, (kept_rate, keepable)  # backlog
    assert lag1 <= 0.3, lag1  # behind by a bounded amount, not without bound
    assert s.shed - (a2 - k2) - (a_on - k_on) == a1 - k1 > 0
    # The rate drops: nothing is shed any more from the first tick on.
    assert k2 == a2, (a2, k2)


def test_without_shedding_the_lag_grows_without_bound() -> None:
    """The reference the shedder is judged against: a worker that admits everything."""
    s = Shedder(max_lag_s=1e9)
    capacity = 1e9 / (C_READ_NS + C_KEEP_NS)
    ((_, _, _, lag),) = _run(s, [(2 * capacity, 2.0)])
    assert lag > 0.5


def test_a_pause_backlog_goes_through_whole() -> None:
    s = Shedder()
    _run(s, [(5_000.0, 1.0)])
    # 1 s of a 5 kHz stream at once (the worker was paused): one late tick is no overload.
    t = _Clock.now + 100 * TICK_NS
    assert s.admit(5000, t, t - 100 * TICK_NS) == 5000
    assert s.admit(5, t + TICK_NS, t) == 5


def test_spread_rows_keeps_ends_and_order() -> None:
    r = spread_rows(100, 10)
    assert r[0] == 0 and r[-1] == 99 and np.all(np.diff(r) > 0) and r.shape == (10,)
    assert spread_rows(5, 9).tolist() == [0, 1, 2, 3, 4]
    assert spread_rows(5, 0).shape == (0,)


def _block(first: int, p: int, n: int = 4) -> ProfileBlock:
    i = np.arange(first, first + p, dtype=np.int64)
    z = np.repeat(i[:, None].astype(np.float64), n, axis=1)
    return ProfileBlock(i * 0, i, i * 10, i * 20, np.arange(n, dtype=np.float64), z,
                        np.ones(z.shape, bool))  # fmt: skip


def test_take_rows_selects_across_blocks() -> None:
    blocks = [_block(0, 3), _block(3, 4), _block(7, 2)]
    got = take_rows(blocks, np.array([0, 2, 3, 8]))
    assert [b.frame_counter.tolist() for b in got] == [[0, 2], [3], [8]]
    assert got[0].z[:, 0].tolist() == [0.0, 2.0]
    whole = take_rows(blocks, np.arange(9))
    assert [b is o for b, o in zip(whole, blocks, strict=True)] == [True, True, True]


def test_bad_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="headroom"):
        Shedder(headroom=1.5)


def test_kernel_admission_follows_the_shedder_and_a_reopened_socket() -> None:
    """``KernelAdmission``: the fraction from the shedder's state, none once it stops; a driver
    without a filter is not asked again."""
    shedder = Shedder()
    shedder.limit, shedder.rate_in, shedder.admitted = 2000.0, 5000.0, 0.3
    with Lpf1UdpSensor(sensor_id=7, bind_host="127.0.0.1", port=0) as drv:
        k = KernelAdmission(drv, enabled=True)
        k.steer(shedder)  # 1.1 x max(0.3, 0.5 x 2000 / 5000)
        assert k.fraction == pytest.approx(0.33) and drv.admission == k.fraction
        shedder.admitted = 0.05  # next to nothing admitted: held at half the rate in force
        k.steer(shedder)
        assert k.fraction == pytest.approx(0.22)
        drv.close()
        drv.open()
        assert drv.admission is None and drv.health().detail["admission"] is None
        k.steer(shedder)  # set again on the new socket
        assert drv.admission == pytest.approx(0.22)
        shedder.limit = math.inf
        k.steer(shedder)
        assert drv.admission is None and k.enabled
    tcp = Lpf1TcpSensor("127.0.0.1", 9)  # a stream: no filter (never opened)
    k = KernelAdmission(tcp, enabled=True)
    shedder.limit = 2000.0
    k.steer(shedder)
    assert not k.enabled and k.fraction is None


# --- the real pipeline under overload ---------------------------------------------------------

PUBLISH_COST_S = 500e-6
"""Wall time the publish call takes per profile: the worker's capacity is at most 2 kHz."""


class _StateRobot(StandInRobot):
    """A controller sending a state every 2 ms on the host's clock (its own clock = the host's
    monotonic, in s), the arm still."""

    def _open(self) -> None:
        self._next = time.monotonic()

    def _read_internal(self, timeout: float | None) -> RobotState | None:
        self._next += 0.002
        time.sleep(max(0.0, self._next - time.monotonic()))
        now = time.monotonic_ns()
        return RobotState(
            now * 1e-9, now, np.array([0.0, -1.2, 1.5, -1.9, -1.57, 0.0]), np.zeros(6)
        )


def _send(addr: tuple[str, int], phases: list[tuple[float, float]]) -> None:
    """LPF1 profiles of 256 points stamped with the host clock (their exposure), at each
    phase's rate for its duration, in 1 ms bursts."""
    n_points = 256
    enc = lpf1.ProfileEncoder(1, lpf1.PointFormat.I16, x_uniform=(-0.025, 0.05 / (n_points - 1)))
    z = np.full((1, n_points), 0.1)
    ok = np.ones(z.shape, bool)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    k = 0
    try:
        for rate, seconds in phases:
            t0 = time.monotonic()
            sent = 0
            while (now := time.monotonic()) < t0 + seconds:
                while sent < rate * (now - t0):  # the rate kept however long a sleep lasts
                    msg = enc.encode(np.array([k]), np.array([time.monotonic_ns()]), z, ok)
                    tx.sendto(msg[0][0], addr)
                    k += 1
                    sent += 1
                time.sleep(0.001)
    finally:
        tx.close()


def _run_pipeline(publish: Any, phases: list[tuple[float, float]]) -> tuple[dict[str, Any], float]:
    """The pipeline on a real LPF1-over-UDP driver fed ``phases`` (rate Hz, s) by a sender
    process of its own (it takes no time from the worker's GIL); its stats once the stream has
    ended, and when it started (monotonic s)."""
    sensor = Lpf1UdpSensor(bind_host="127.0.0.1", port=0)
    robot = _StateRobot()
    sensor.open()
    robot.open()
    pipeline = Pipeline(sensor, robot, Pairer(PairerConfig()), AlignmentSetup(np.eye(4)), publish)
    assert sensor.local_address is not None
    sender = multiprocessing.get_context("fork").Process(
        target=_send, args=(sensor.local_address, phases)
    )
    try:
        pipeline.start()
        t_start = time.monotonic()
        sender.start()
        sender.join(30.0)
        time.sleep(0.3)
        return pipeline.stats(), t_start
    finally:
        if sender.is_alive():
            sender.kill()
            sender.join()
        pipeline.stop()
        sensor.close()
        robot.close()


def test_the_pipeline_sheds_under_overload_and_recovers() -> None:
    published: list[tuple[float, int]] = []

    def publish(cloud: Any, t0: int, t1: int, n_profiles: int, *_: Any) -> int:
        time.sleep(n_profiles * PUBLISH_COST_S)  # a worker that can do 2 kHz at most
        published.append((time.monotonic(), n_profiles))
        return len(published) - 1

    # 0.8 s to lock the clocks at 500 Hz, 2.2 s at 4 kHz (twice the capacity), 1.4 s at 500 Hz.
    st, t_start = _run_pipeline(publish, [(500.0, 0.8), (4000.0, 2.2), (500.0, 1.4)])
    times = np.array([t for t, _ in published]) - t_start
    counts = np.array([n for _, n in published])
    # In the second half of the overload the worker keeps publishing: at most its 2 kHz, and
    # at least half of it (0.95 of the throughput it showed is aimed at; reading what is shed
    # takes its share, more on a loaded machine). The benchmark measures the ratio against a
    # capacity measured apart (benchmarks/overload.py).
    window = (times > 2.0) & (times <= 3.0)
    rate = counts[window].sum() / 1.0
    # (A batch counts whole when its put returns: up to ~0.2 s of profiles across an edge.)
    assert 0.5 * 2000 <= rate <= 1.2 * 2000, rate
    assert st["dropped"].get("overload", 0) > 1000, st["dropped"]
    # Part of it shed before reading, by the UDP socket's filter (counted from the gaps: how
    # much depends on how long the publisher's backlog lasts), counted as overload; the filter
    # removed once the rate dropped.
    kernel = st["sensor"]["shed"]
    assert 0 < kernel <= st["dropped"]["overload"], (st["sensor"], st["dropped"])
    assert st["overload"]["kernel_fraction"] is None, st["overload"]
    # Counters add up; the clock never restarted, and it is locked at the end.
    assert st["received"] == st["published"] + sum(st["dropped"].values()) + st["pending"]
    clocks = st["pairing"]["sensor_clocks"]
    assert all(c["locked"] and c["epoch"] == 0 for c in clocks.values()), clocks
    # The rate dropped at 3 s: from 3.6 s on every profile is published again (what arrives
    # after that is all published: 500 Hz, none shed).
    late = times > 3.6
    assert counts[late].sum() >= 0.9 * 500 * (times[late].max() - 3.6), counts[late].sum()
    assert st["overload"]["shedding"] is False


def test_a_payload_kept_by_the_publisher_is_never_written_over() -> None:
    """The worker writes each batch into the last payload again when nobody holds it (zenoh
    copies what it is given); one the publisher kept must stay as it was."""
    kept: list[bytearray] = []

    def publish(cloud: Any, t0: int, t1: int, n_profiles: int, frame_id: str, *_: Any) -> int:
        if len(kept) % 2:  # every other payload kept, the others dropped (free for reuse)
            kept.append(cloud.finish(seq=len(kept), t_first_ns=t0, t_last_ns=t1,
                                     n_profiles=n_profiles, frame_id=frame_id))  # fmt: skip
        else:
            kept.append(bytearray(bytes(cloud.finish(seq=len(kept), t_first_ns=t0, t_last_ns=t1,
                                                     n_profiles=n_profiles))))  # fmt: skip
        return len(kept) - 1

    _run_pipeline(publish, [(1000.0, 1.0)])
    assert len(kept) > 20
    clouds = [wsc1.decode(b) for b in kept]
    assert [c.seq for c in clouds] == list(range(len(kept)))
    assert all(c.n_points == 256 * c.n_profiles for c in clouds)
