"""Pairer against a synthetic cell with known truth: clocks with drift, offset, jitter, latency."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pytest

from wristscan.calib import kinematics
from wristscan.daemon.sync.batch import PairedBatch
from wristscan.daemon.sync.clockconfig import ClockConfig
from wristscan.daemon.sync.pairing import DROP_REASONS, Pairer, PairerConfig
from wristscan.drivers.records import Profile, RobotState, TableState

MS = 1_000_000
S = 1_000_000_000
T0 = 50 * S  # host time at which everything starts
C0 = 3600 * S  # controller clock at T0 (controller booted an hour earlier)
Q0 = np.array([0.3, -1.2, 1.4, -1.8, -1.57, 0.2])
W = np.array([0.2, -0.1, 0.15, 0.3, -0.25, 0.5])  # rad/s
LATENCY = 1_500_000
TABLE_RATE = 0.7  # rad/s


def q_at(t_host: np.ndarray) -> np.ndarray:
    return Q0 + (np.asarray(t_host, dtype=np.float64) - T0)[..., None] * 1e-9 * W


@dataclass
class Cell:
    """Records in arrival order and the true exposure instant of each frame."""

    events: list[tuple[int, object]] = field(default_factory=list)
    exposure: dict[int, int] = field(default_factory=dict)

    def sorted(self) -> list[object]:
        self.events.sort(key=lambda e: e[0])
        return [r for _, r in self.events]


def make_cell(
    seconds: float = 3.0,
    seed: int = 0,
    profile_hz: float = 1000.0,
    jitter_ns: float = 300_000.0,
    robot_gap: tuple[float, float] | None = None,
    robot_stop: float | None = None,
    table: bool = False,
    encoder: bool = False,
    n_points: int = 8,
    sensor_clock=None,
) -> Cell:
    rng = np.random.default_rng(seed)
    cell = Cell()
    # Robot: controller ticks every 2 ms on its own clock (-30 ppm against the host).
    n_r = int(seconds * 500)
    c = C0 + np.arange(n_r) * 2 * MS
    h = T0 + np.rint((c - C0) * (1 - 30e-6)).astype(np.int64)
    arrive = h + np.rint(rng.exponential(jitter_ns, n_r)).astype(np.int64)
    q = q_at(h)
    keep = np.ones(n_r, dtype=bool)
    if robot_gap is not None:
        keep &= ~((h >= T0 + robot_gap[0] * S) & (h < T0 + robot_gap[1] * S))
    if robot_stop is not None:
        keep &= h < T0 + robot_stop * S
    enc_per_s = 20_000.0  # encoder counts per second of controller time
    for k in np.flatnonzero(keep):
        state = RobotState(
            controller_time_s=float(c[k]) / 1e9,
            host_time_ns=int(arrive[k]),
            q=q[k],
            tcp_pose=np.zeros(6),
        )
        cell.events.append((int(arrive[k]), state))
        if encoder:
            count = int((c[k] - C0) * 1e-9 * enc_per_s + 65_000) % 65_536  # 16-bit, wraps
            cell.events.append((int(arrive[k]), ("enc", count, float(c[k]) / 1e9, int(arrive[k]))))
    # Sensor: exposure, stamped LATENCY later on a clock with 50 ppm drift and 20 ms offset.
    n_p = int(seconds * profile_hz)
    if encoder:
        # Triggered every 10 counts: exposure when the robot's count reaches the value.
        counts = 65_000 + 10 * np.arange(1, n_p)
        c_exp = C0 + (counts - 65_000) / enc_per_s * 1e9
        e = T0 + np.rint((c_exp - C0) * (1 - 30e-6)).astype(np.int64)
        enc = counts % 65_536
        e, enc = e[e < T0 + seconds * S], enc[e < T0 + seconds * S]
    else:
        e = T0 + 300_000 + np.rint(np.arange(n_p) * (S / profile_hz)).astype(np.int64)
        enc = None
    stamp = e + LATENCY
    dev = (
        np.rint((stamp - 20e6) / (1 + 50e-6)).astype(np.int64)
        if sensor_clock is None
        else (sensor_clock(stamp))
    )
    arrive_p = stamp + np.rint(rng.exponential(jitter_ns, e.shape[0])).astype(np.int64)
    for j in range(e.shape[0]):
        y = np.linspace(-0.02, 0.02, n_points)
        prof = Profile(
            sensor_id=1,
            frame_counter=j,
            sensor_time_ns=int(dev[j]),
            host_time_ns=int(arrive_p[j]),
            y=y,
            z=np.full(n_points, 0.1 + j * 1e-6),
            valid=np.ones(n_points, dtype=bool),
            intensity=np.full(n_points, j % 256, dtype=np.uint8),
            encoder=None if enc is None else int(enc[j]),
        )
        cell.events.append((int(arrive_p[j]), prof))
        cell.exposure[j] = int(e[j])
    if table:
        n_t = int(seconds * 100)
        ht = T0 + np.arange(n_t) * 10 * MS
        for k in range(n_t):
            angle = (TABLE_RATE * (ht[k] - T0) * 1e-9) % (2 * math.pi)
            arrival = int(ht[k] + 2 * MS)  # polled: no device time, 2 ms to read
            cell.events.append((arrival, TableState(angle, None, arrival)))
    return cell


class Run:
    """Feed a cell into a Pairer, poll regularly, collect batches, check the counters."""

    def __init__(self, pairer: Pairer) -> None:
        self.p = pairer
        self.batches: list[PairedBatch] = []

    def check(self) -> None:
        p = self.p
        assert p.received == p.paired + sum(p.dropped.values()) + p.pending

    def feed(self, records: list[object], poll_every: int = 10) -> None:
        for i, r in enumerate(records):
            if isinstance(r, Profile):
                self.p.add_profile(r)
            elif isinstance(r, RobotState):
                self.p.add_robot_state(r)
            elif isinstance(r, TableState):
                self.p.add_table_state(r)
            else:
                _, count, ct, host = r  # type: ignore[misc]
                self.p.add_encoder_sample(count, ct, host)
            self.check()
            if i % poll_every == 0:
                self.batches += self.p.poll()
                self.check()

    def finish(self, now_ns: int | None = None) -> None:
        self.batches += self.p.poll(now_ns)
        self.check()

    def frames(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        fc = np.concatenate([b.frame_counter for b in self.batches])
        ex = np.concatenate([b.exposure_ns for b in self.batches])
        F = np.concatenate([b.flange2base for b in self.batches])
        return fc, ex, F


def pose_errors(cell: Cell, fc: np.ndarray, F: np.ndarray) -> np.ndarray:
    e_true = np.array([cell.exposure[int(j)] for j in fc])
    F_true = kinematics.forward("UR5e", q_at(e_true))
    return np.linalg.norm(F[:, :3, 3] - F_true[:, :3, 3], axis=-1)


def config(**kw: object) -> PairerConfig:
    kw.setdefault("sensor_latency_ns", LATENCY)
    return PairerConfig(**kw)  # type: ignore[arg-type]


def test_pairs_match_truth() -> None:
    cell = make_cell()
    run = Run(Pairer(config()))
    run.feed(cell.sorted())
    run.finish()
    fc, ex, F = run.frames()
    assert run.p.received == 3000
    # Only the first few, waiting while the clocks lock, and the last ones still waiting.
    assert run.p.paired >= 2950, run.p.stats()
    assert sum(run.p.dropped.values()) == 0, run.p.dropped
    e_true = np.array([cell.exposure[int(j)] for j in fc])
    dt = np.abs(ex - e_true)
    assert np.max(dt) < 100_000  # ns; the first ones are mapped by clock fits of 0.1 s
    assert np.max(dt[e_true > T0 + S]) < 10_000
    err = pose_errors(cell, fc, F)
    assert np.max(err) < 30e-6  # m; the flange moves at ~0.3 m/s here


def test_batches_are_consistent() -> None:
    cell = make_cell(seconds=1.0, n_points=5)
    run = Run(Pairer(config(max_batch_profiles=7)))
    run.feed(cell.sorted(), poll_every=40)
    run.finish()
    assert run.batches
    for b in run.batches:
        assert 1 <= b.n_profiles <= 7
        assert np.all(np.diff(b.exposure_ns) >= 0)
        assert b.n_points == 5 * b.n_profiles == b.offsets[-1]
        assert np.array_equal(b.profile_index, np.repeat(np.arange(b.n_profiles), 5))
        assert b.intensity is not None
        np.testing.assert_array_equal(b.intensity[b.offsets[:-1]], b.frame_counter % 256)
        np.testing.assert_allclose(b.z[b.offsets[:-1]], 0.1 + b.frame_counter * 1e-6)
        assert b.flange2base.shape == (b.n_profiles, 4, 4) and b.table_angle is None


def test_arrival_order_between_streams_does_not_matter() -> None:
    cell = make_cell(seconds=2.0, seed=1)
    records = cell.sorted()
    profiles = [r for r in records if isinstance(r, Profile)]
    states = [r for r in records if isinstance(r, RobotState)]
    run = Run(Pairer(config()))
    # Bursts of 80 ms: all profiles of a burst first, then the robot states (or the reverse).
    for k, t in enumerate(range(T0, T0 + 2 * S, 80 * MS)):
        burst_p = [p for p in profiles if t <= p.host_time_ns < t + 80 * MS]
        burst_r = [s for s in states if t <= s.host_time_ns < t + 80 * MS]
        first, second = (burst_p, burst_r) if k % 2 else (burst_r, burst_p)
        run.feed(first, poll_every=10_000)
        run.feed(second, poll_every=10_000)
        run.finish()
    assert sum(run.p.dropped.values()) == 0, run.p.dropped
    assert run.p.paired >= 1950
    fc, _, F = run.frames()
    assert np.max(pose_errors(cell, fc, F)) < 30e-6


def test_gap_in_robot_states_drops_instead_of_guessing() -> None:
    cell = make_cell(robot_gap=(1.0, 1.1))
    run = Run(Pairer(config()))
    run.feed(cell.sorted())
    run.finish()
    fc, _, F = run.frames()
    assert run.p.dropped["gap_too_large"] >= 90
    e_true = np.array([cell.exposure[int(j)] for j in fc])
    in_gap = (e_true >= T0 + 1.0 * S) & (e_true < T0 + 1.1 * S - 100_000)
    assert not np.any(in_gap)
    assert np.max(pose_errors(cell, fc, F)) < 30e-6


def test_robot_stream_stopping_times_out() -> None:
    cell = make_cell(seconds=2.0, robot_stop=1.5)
    run = Run(Pairer(config()))
    run.feed(cell.sorted())
    run.finish()
    dropped = run.p.dropped["no_robot_state_timeout"]
    # Profiles exposed after the last robot sample, and received more than 200 ms before the end.
    assert 250 <= dropped <= 310, run.p.stats()
    assert run.p.pending > 100  # the last 200 ms still wait
    fc, _, F = run.frames()
    assert np.max(pose_errors(cell, fc, F)) < 30e-6
    run.finish(now_ns=T0 + 5 * S)
    assert run.p.pending == 0
    assert run.p.dropped["no_robot_state_timeout"] == dropped + (
        run.p.received - run.p.paired - dropped
    )


def test_profile_older_than_robot_buffer() -> None:
    cell = make_cell(seconds=2.0)
    records = cell.sorted()
    # One profile held up for 700 ms on its way (a delay spike); the robot buffer keeps 0.4 s.
    late = next(r for r in records if isinstance(r, Profile) and r.frame_counter == 1000)
    records.remove(late)
    late.host_time_ns += 700 * MS
    at = next(i for i, r in enumerate(records) if r.host_time_ns > late.host_time_ns)
    records.insert(at, late)
    run = Run(Pairer(config(robot_capacity=200)))
    run.feed(records)
    run.finish()
    assert run.p.dropped["before_buffer"] == 1
    assert 1000 not in set(run.frames()[0].tolist())


def test_sensor_clock_never_locking_drops_as_clock_unlocked() -> None:
    cell = make_cell(seconds=1.0)
    run = Run(Pairer(config(sensor_clock=ClockConfig(min_points=10**9))))
    run.feed(cell.sorted())
    run.finish(now_ns=T0 + 3 * S)
    assert run.p.paired == 0
    assert run.p.dropped["clock_unlocked"] == run.p.received


def test_pending_is_bounded() -> None:
    cell = make_cell(seconds=1.0)
    run = Run(Pairer(config(max_pending=50)))
    run.feed([r for r in cell.sorted() if isinstance(r, Profile)], poll_every=10**9)
    assert run.p.pending == 50
    assert run.p.dropped["pending_overflow"] == run.p.received - 50


def test_flush_drops_everything_left() -> None:
    cell = make_cell(seconds=0.5)
    run = Run(Pairer(config()))
    run.feed([r for r in cell.sorted() if isinstance(r, Profile)])
    assert run.p.pending > 0
    run.p.flush()
    run.check()
    assert run.p.pending == 0 and run.p.dropped["flushed"] > 0


def test_table_angle_at_exposure() -> None:
    cell = make_cell(seconds=2.0, table=True)
    run = Run(Pairer(config(use_table=True, table_latency_ns=2 * MS)))
    run.feed(cell.sorted())
    run.finish()
    assert run.p.paired >= 1900, run.p.stats()
    fc = np.concatenate([b.frame_counter for b in run.batches])
    ang = np.concatenate([b.table_angle for b in run.batches if b.table_angle is not None])
    e_true = np.array([cell.exposure[int(j)] for j in fc])
    truth = TABLE_RATE * (e_true - T0) * 1e-9
    diff = np.remainder(ang - truth + math.pi, 2 * math.pi) - math.pi
    assert np.max(np.abs(diff)) < TABLE_RATE * 50e-6  # 50 us of table motion


def test_encoder_mode_pairs_by_count_across_wrap() -> None:
    cell = make_cell(seconds=2.0, encoder=True, jitter_ns=1e6)
    run = Run(Pairer(config(mode="encoder", encoder_modulus=65_536, sensor_latency_ns=0)))
    run.feed(cell.sorted())
    run.finish()
    assert sum(run.p.dropped.values()) == 0, run.p.dropped
    assert run.p.paired >= 1950  # 20k counts/s, one trigger every 10 counts
    fc, ex, F = run.frames()
    e_true = np.array([cell.exposure[int(j)] for j in fc])
    # The pose needs no clock fit here; the reported host time does (robot clock, 1 ms jitter).
    assert np.max(pose_errors(cell, fc, F)) < 1e-6
    assert np.max(np.abs(ex - e_true)[e_true > T0 + S // 2]) < 30_000


def test_encoder_mode_profile_without_count() -> None:
    p = Pairer(config(mode="encoder"))
    p.add_profile(
        Profile(1, 0, 0, T0, np.zeros(2), np.zeros(2), np.ones(2, dtype=bool), encoder=None)
    )
    assert p.dropped["no_encoder_count"] == 1 and p.pending == 0
    assert p.received == p.paired + sum(p.dropped.values()) + p.pending


def test_sensor_reset_and_wrap_lose_only_the_outage() -> None:
    m = 1 << 24  # a 24-bit microsecond counter: wraps every 16.8 s

    def sensor_clock(stamp: np.ndarray) -> np.ndarray:
        us = np.rint((stamp - T0) / (1 + 50e-6) / 1000).astype(np.int64) + (m - 1_000_000)
        reboot = stamp >= T0 + 2 * S
        us[reboot] = np.rint((stamp[reboot] - (T0 + 2 * S)) / 1000).astype(np.int64)
        return (us % m) * 1000

    cell = make_cell(seconds=3.5, seed=4, sensor_clock=sensor_clock)
    records = [
        r
        for r in cell.sorted()
        if not (
            isinstance(r, Profile)
            and T0 + 2 * S - 50 * MS <= cell.exposure[r.frame_counter] < T0 + 2 * S
        )
    ]
    outage = 3500 - sum(isinstance(r, Profile) for r in records)
    run = Run(Pairer(config(sensor_time_modulus_ns=m * 1000)))
    run.feed(records)
    run.finish()
    clk = run.p.sensor_clock(1)
    unw = run.p.sensor_unwrapper(1)
    assert clk.n_resets == 1 and unw is not None and unw.n_wraps == 1
    assert sum(run.p.dropped.values()) == 0, run.p.dropped
    # All received profiles are paired except the last few still waiting for the robot.
    assert run.p.paired >= 3500 - outage - 30
    fc, _, F = run.frames()
    err = pose_errors(cell, fc, F)
    assert np.sqrt(np.mean(err**2)) < 20e-6


def starve(
    cell: Cell,
    stalls: tuple[tuple[float, float], ...],
    loads: tuple[tuple[float, float], ...],
    seed: int = 0,
) -> None:
    """Re-time the profiles and robot states as read by one process short of CPU: each stream in
    order, one record at a time; nothing read during a stall (then a burst), 1-5 ms late
    wake-ups under load. Episodes in seconds after T0, shared by both streams."""
    rng = np.random.default_rng(seed)

    def within(t: int, episodes: tuple[tuple[float, float], ...]) -> int:
        for a, b in episodes:
            if T0 + a * S <= t < T0 + b * S:
                return int(T0 + b * S)
        return -1

    for kind in (Profile, RobotState):
        stream = sorted((e for e in cell.events if isinstance(e[1], kind)), key=lambda e: e[0])
        done = T0
        for arrival, rec in stream:
            t = max(arrival, done)
            if arrival > done and within(arrival, loads) >= 0:
                t += int(rng.uniform(1 * MS, 5 * MS))
            while (end := within(t, stalls)) >= 0:
                t = end
            rec.host_time_ns = t  # type: ignore[attr-defined]
            done = t + 30_000
    cell.events = [(r.host_time_ns, r) for _, r in cell.events]  # type: ignore[attr-defined]


def test_receiver_short_of_cpu_loses_no_profile_to_the_clocks() -> None:
    # 0.3 s of records queued before reading starts, a 0.7 s stall during 2 s of load, another
    # stall: the clocks lock within the wait bound and stay locked; nothing is dropped.
    cell = make_cell(seconds=4.0, seed=5)
    starve(cell, stalls=((-1.0, 0.3), (0.8, 1.5), (2.2, 2.3)), loads=((1.2, 3.2),))
    run = Run(Pairer(config()))
    run.feed(cell.sorted())
    run.finish(now_ns=T0 + 6 * S)
    p = run.p
    assert p.sensor_clock(1).n_resets == 0 and p.robot_clock.n_resets == 0
    clock_drops = ("clock_unlocked", "robot_clock_unlocked")
    assert all(p.dropped[k] == 0 for k in clock_drops), p.dropped
    # Only the last ones, exposed after the last robot sample, are dropped (timeout).
    assert p.received == 4000 and p.paired >= 3995, p.dropped
    fc, ex, F = run.frames()
    e_true = np.array([cell.exposure[int(j)] for j in fc])
    # Through 2 s of load the lines rest on the drift learnt in the 1 s before: tens of us.
    dt = (ex - e_true)[e_true > T0 + S // 2].astype(np.float64)
    assert np.sqrt(np.mean(dt**2)) < 50_000 and np.max(np.abs(dt)) < 150_000
    assert np.max(pose_errors(cell, fc, F)) < 60e-6


@pytest.mark.parametrize("reason", DROP_REASONS)
def test_drop_reasons_are_counted_from_zero(reason: str) -> None:
    assert Pairer().dropped[reason] == 0


def test_latency_window_keeps_the_latest_profiles_per_stage() -> None:
    from wristscan.daemon.service.instruments import LatencyWindow

    w = LatencyWindow(size=5)
    assert w.summary() == {}
    ms = 1_000_000
    # Three profiles exposed at 0, 1, 2 ms, received 2 ms later, ticked at 10, done at 12 ms.
    e = np.array([0, 1, 2]) * ms
    w.add(e, e + 2 * ms, 10 * ms, 12 * ms)
    s = w.summary()
    assert s["transport"]["max"] == 2.0 and s["process"]["p50"] == 2.0
    assert s["wait"]["max"] == 8.0 and s["total"]["max"] == 12.0
    # Four more overwrite the oldest two: only the latest five count.
    e = np.array([100, 101, 102, 103]) * ms
    w.add(e, e + 5 * ms, 110 * ms, 111 * ms)
    s = w.summary()
    assert s["transport"]["p50"] == 5.0 and s["total"]["max"] == 11.0


def test_merge_joins_batches_in_order_up_to_the_profile_limit() -> None:
    from wristscan.daemon.sync.batch import PairedBatch
    from wristscan.daemon.sync.pairing import Pairer, PairerConfig

    def batch(first: int, sizes: list[int]) -> PairedBatch:
        p = len(sizes)
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        n = int(offsets[-1])
        return PairedBatch(
            sensor_id=np.ones(p, np.int64),
            frame_counter=np.arange(first, first + p),
            exposure_ns=np.arange(first, first + p) * 1000,
            clock_uncertainty_ns=np.zeros(p),
            flange2base=np.broadcast_to(np.eye(4), (p, 4, 4)).copy(),
            table_angle=None,
            y=np.arange(n, dtype=float) + 100 * first,
            z=np.zeros(n),
            valid=np.ones(n, bool),
            intensity=None,
            profile_index=np.repeat(np.arange(p, dtype=np.uint32), sizes),
            offsets=offsets,
            arrival_ns=np.arange(first, first + p) * 1000 + 5,
        )

    pairer = Pairer(PairerConfig(max_batch_profiles=5))
    merged = pairer.merge([batch(0, [2, 3]), batch(2, [1]), batch(3, [4, 1, 2])])
    # 2 + 1 profiles fit in one batch; the next three would exceed 5.
    assert [m.n_profiles for m in merged] == [3, 3]
    m = merged[0]
    assert m.frame_counter.tolist() == [0, 1, 2] and m.arrival_ns.tolist() == [5, 1005, 2005]
    assert m.offsets.tolist() == [0, 2, 5, 6]
    assert m.profile_index.tolist() == [0, 0, 1, 1, 1, 2]
    assert m.y.tolist() == [0, 1, 2, 3, 4, 200]
    assert merged[1].offsets.tolist() == [0, 4, 5, 7]


def test_states_cover_waiting_tells_when_a_poll_can_release_the_waiting_profiles() -> None:
    cell = make_cell(seconds=1.0, seed=3)
    records = cell.sorted()
    profiles = [r for r in records if isinstance(r, Profile)]
    states = [r for r in records if isinstance(r, RobotState)]
    p = Pairer(config())
    # Everything up to 0.6 s, then the profiles up to 0.8 s without their robot states.
    cut, later = T0 + 600 * MS, T0 + 800 * MS
    for r in records:
        if r.host_time_ns < cut or (isinstance(r, Profile) and r.host_time_ns < later):
            if isinstance(r, Profile):
                p.add_profile(r)
            else:
                p.add_robot_state(r)  # type: ignore[arg-type]
    p.poll()
    assert p.waiting_for_states > 0
    assert not p.states_cover_waiting()
    waiting = p.waiting_for_states
    # The states of the next 0.1 s release some profiles, not all: still not covered.
    for s in (s for s in states if cut <= s.host_time_ns < cut + 100 * MS):
        p.add_robot_state(s)
    assert not p.states_cover_waiting()
    # Those up to 0.8 s and a little beyond (the state after the last exposure) cover them.
    for s in (s for s in states if cut + 100 * MS <= s.host_time_ns < later + 10 * MS):
        p.add_robot_state(s)
    assert p.states_cover_waiting()
    released = sum(b.n_profiles for b in p.poll())
    assert released >= waiting and p.waiting_for_states == 0
    assert len([q for q in profiles if q.host_time_ns < later]) == p.paired
