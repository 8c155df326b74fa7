"""Pairing whole blocks of profiles (``Pairer.add_block``) against the record-wise path: the same
records give bitwise identical batches and counters, whatever the block sizes."""

from __future__ import annotations

import numpy as np
import pytest
from test_pairing import MS, T0, Cell, S, config, make_cell, starve

from wristscan.daemon.sync import pending
from wristscan.daemon.sync.batch import PairedBatch, Segment, concat_batches
from wristscan.daemon.sync.counters import CounterUnwrapper
from wristscan.daemon.sync.pairing import Pairer, PairerConfig
from wristscan.drivers.records import Profile, ProfileBlock, RobotState, TableState

PER_PROFILE = ("sensor_id", "frame_counter", "exposure_ns", "arrival_ns", "clock_uncertainty_ns")
PER_POINT = ("y", "z", "valid", "intensity", "offsets", "profile_index")


def same_batch(a: PairedBatch, b: PairedBatch) -> None:
    for name in (*PER_PROFILE, *PER_POINT, "table_angle"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.dtype == y.dtype and np.array_equal(x, y), name
    assert np.array_equal(a.flange2base, b.flange2base, equal_nan=True)
    assert a.points_per_profile == b.points_per_profile


def counters(p: Pairer) -> tuple[object, ...]:
    assert p.received == p.paired + sum(p.dropped.values()) + p.pending
    return (p.received, p.paired, p.pending, dict(p.dropped), p.waiting_for_states)


def add_state(p: Pairer, r: object) -> None:
    if isinstance(r, RobotState):
        p.add_robot_state(r)
    elif isinstance(r, TableState):
        p.add_table_state(r)
    else:
        _, count, ct, host = r  # type: ignore[misc]
        p.add_encoder_sample(count, ct, host)


def compare(
    records: list[object],
    cfg: PairerConfig,
    seed: int,
    poll_every: int = 37,
    max_block: int = 60,
    final_now: int | None = None,
) -> tuple[Pairer, list[PairedBatch]]:
    """Feed ``records`` record by record into one pairer and, in blocks of random sizes, into
    another; poll both at the same points and compare everything."""
    rng = np.random.default_rng(seed)
    a, b = Pairer(cfg), Pairer(cfg)
    queued: list[Profile] = []
    out: list[PairedBatch] = []

    def flush() -> None:
        k = 0
        while k < len(queued):
            n = int(rng.integers(1, max_block + 1))
            for block in ProfileBlock.from_profiles(queued[k : k + n]):
                b.add_block(block)
                counters(b)
            k += n
        queued.clear()

    def poll(now: int | None = None) -> None:
        flush()
        got_a, got_b = a.poll(now), b.poll(now)
        assert [x.n_profiles for x in got_a] == [x.n_profiles for x in got_b]
        for x, y in zip(got_a, got_b, strict=True):
            same_batch(x, y)
        assert counters(a) == counters(b)
        out.extend(got_b)

    for i, r in enumerate(records):
        if isinstance(r, Profile):
            a.add_profile(r)
            queued.append(r)
        else:
            add_state(a, r)
            add_state(b, r)
        counters(a)
        if i % poll_every == 0:
            poll()
    poll(final_now)
    assert a.stats() == b.stats()
    return b, out


def shared_grid(cell: Cell) -> None:
    """Give every profile of the cell one read-only lateral grid (as drivers do)."""
    grids: dict[int, np.ndarray] = {}
    for _, r in cell.events:
        if isinstance(r, Profile):
            r.y = grids.setdefault(r.n_points, np.linspace(-0.02, 0.02, r.n_points))
            r.y.flags.writeable = False


def test_wrapping_counter_reboot_and_overflow_give_identical_batches() -> None:
    m = 1 << 24  # a 24-bit us counter: wraps 1 s in, the sensor reboots at 2 s

    def sensor_clock(stamp: np.ndarray) -> np.ndarray:
        us = np.rint((stamp - T0) / (1 + 50e-6) / 1000).astype(np.int64) + (m - 1_000_000)
        reboot = stamp >= T0 + 2 * S
        us[reboot] = np.rint((stamp[reboot] - (T0 + 2 * S)) / 1000).astype(np.int64)
        return (us % m) * 1000

    cell = make_cell(seconds=3.0, seed=4, sensor_clock=sensor_clock)
    shared_grid(cell)
    records = [
        r
        for r in cell.sorted()
        if not (
            isinstance(r, Profile)
            and T0 + 2 * S - 50 * MS <= cell.exposure[r.frame_counter] < T0 + 2 * S
        )
    ]
    cfg = config(sensor_time_modulus_ns=m * 1000)
    p, batches = compare(records, cfg, seed=1)
    assert p.sensor_clock(1).n_resets == 1 and p.sensor_unwrapper(1).n_wraps == 1  # type: ignore[union-attr]
    assert p.paired > 2800 and batches
    # The grid stayed shared: the batches never copied it.
    assert all(b.y_grid is not None for b in batches)
    # With few polls and a small bound, the oldest profiles overflow.
    p, _ = compare(records, config(sensor_time_modulus_ns=m * 1000, max_pending=40), 2, 150)
    assert p.dropped["pending_overflow"] > 0


def test_late_gapped_and_timed_out_profiles_give_identical_batches() -> None:
    cell = make_cell(seconds=2.5, seed=6, robot_gap=(1.0, 1.1), robot_stop=2.2, table=True)
    records = cell.sorted()
    # One profile held up for 700 ms (older than the robot buffer by then).
    late = next(r for r in records if isinstance(r, Profile) and r.frame_counter == 500)
    records.remove(late)
    late.host_time_ns += 700 * MS
    records.insert(
        next(i for i, r in enumerate(records) if r.host_time_ns > late.host_time_ns), late
    )  # type: ignore[attr-defined]
    cfg = config(robot_capacity=200, use_table=True, table_latency_ns=2 * MS, max_batch_profiles=9)
    p, batches = compare(records, cfg, seed=3, final_now=T0 + 5 * S)
    for reason in ("before_buffer", "gap_too_large", "no_robot_state_timeout"):
        assert p.dropped[reason] > 0, reason
    assert max(b.n_profiles for b in batches) == 9
    assert all(b.table_angle is not None for b in batches)


def test_starved_receiver_gives_identical_batches() -> None:
    cell = make_cell(seconds=2.5, seed=5)
    starve(cell, stalls=((-1.0, 0.3), (0.8, 1.3)), loads=((1.0, 2.0),))
    p, _ = compare(cell.sorted(), config(), seed=4, poll_every=23, max_block=200)
    assert p.paired > 2400


def test_encoder_mode_gives_identical_batches() -> None:
    cell = make_cell(seconds=1.5, encoder=True, jitter_ns=1e6)
    records = cell.sorted()
    for r in records:  # every 7th profile came without its count
        if isinstance(r, Profile) and r.frame_counter % 7 == 3:
            r.encoder = None
    cfg = config(mode="encoder", encoder_modulus=65_536, sensor_latency_ns=0)
    p, _ = compare(records, cfg, seed=5)
    assert p.dropped["no_encoder_count"] > 100 and p.paired > 1000


def test_two_sensors_interleaved_in_blocks(monkeypatch: pytest.MonkeyPatch) -> None:
    """Two sensors in the same blocks, the second's records reordered by its own jitter: the
    released profiles come in too many runs to be viewed, so they are copied; still identical."""
    copies = []
    original = pending._copy_rows
    monkeypatch.setattr(pending, "_copy_rows", lambda *a: copies.append(1) or original(*a))
    rng = np.random.default_rng(7)
    cell = make_cell(seconds=1.5, seed=7, n_points=4)
    twins = []
    for _, r in cell.events:
        if isinstance(r, Profile):
            host = r.host_time_ns + int(rng.exponential(2 * MS))
            twin = Profile(2, r.frame_counter, r.sensor_time_ns, host, r.y, r.z + 1.0, r.valid,
                           r.intensity)  # fmt: skip
            twins.append((host, twin))
    cell.events += twins
    _, batches = compare(cell.sorted(), config(), seed=6, poll_every=300, max_block=500)
    assert set(np.unique(np.concatenate([b.sensor_id for b in batches]))) == {1, 2}
    assert copies


def test_tick_blocks_are_released_without_copying_points() -> None:
    """A tick's block whose profiles are all released becomes the batch's points (views)."""
    cell = make_cell(seconds=1.0, seed=8, n_points=16)
    shared_grid(cell)
    p = Pairer(config())
    viewed = 0
    profiles: list[Profile] = []
    for r in cell.sorted():
        if isinstance(r, Profile):
            profiles.append(r)
            continue
        add_state(p, r)
        if len(profiles) >= 20:
            (block,) = ProfileBlock.from_profiles(profiles)
            profiles = []
            p.add_block(block)
            for b in p.poll():
                for s in b.segments():
                    viewed += int(np.shares_memory(s.z, block.z))
                assert b.points_per_profile == 16 and b.y_grid is not None
                y, z, valid = b.rows()
                assert y.shape == z.shape == valid.shape == (b.n_profiles, 16)
                np.testing.assert_array_equal(z.reshape(-1), b.z)
                np.testing.assert_array_equal(y[0], b.y_grid)
                np.testing.assert_array_equal(
                    b.profile_index, np.repeat(np.arange(b.n_profiles), 16)
                )
    assert viewed > 20
    # The pending store keeps only blocks with waiting profiles (bounded memory).
    assert len(p._pending.blocks) <= 2


def test_concat_joins_segments_without_copying() -> None:
    z = np.arange(12.0).reshape(4, 3)
    grid = np.array([-1.0, 0.0, 1.0])

    def batch(rows: slice, first: int) -> PairedBatch:
        n = rows.stop - rows.start
        return PairedBatch(
            sensor_id=np.ones(n, np.int64),
            frame_counter=np.arange(first, first + n),
            exposure_ns=np.arange(first, first + n),
            clock_uncertainty_ns=np.zeros(n),
            flange2base=np.zeros((n, 4, 4)),
            table_angle=None,
            offsets=np.arange(n + 1) * 3,
            y_grid=grid,
            segments=[Segment(0, grid, z[rows], np.ones((n, 3), bool), None)],
        )

    m = concat_batches([batch(slice(0, 1), 0), batch(slice(2, 4), 1)])
    assert [s.start for s in m.segments()] == [0, 1]
    assert all(np.shares_memory(s.z, z) for s in m.segments())
    assert m.z.tolist() == [0, 1, 2, 6, 7, 8, 9, 10, 11]
    assert m.y.tolist() == [-1, 0, 1] * 3 and m.intensity is None
    assert m.profile_index.tolist() == [0, 0, 0, 1, 1, 1, 2, 2, 2]
    assert m.points_per_profile == 3 and m.rows()[1].shape == (3, 3)


@pytest.mark.parametrize("modulus", [1000, 1 << 16, 1 << 24])
def test_counter_unwrapper_many_matches_one_at_a_time(modulus: int) -> None:
    rng = np.random.default_rng(modulus)
    for _ in range(40):
        n = 300
        host = np.cumsum(rng.integers(0, 3000, n)).astype(np.int64) + S
        dev = (host - S) // int(rng.choice([1, 10, 100])) + int(rng.integers(0, modulus))
        for _ in range(int(rng.integers(0, 4))):  # resets
            j = int(rng.integers(1, n))
            dev[j:] += int(rng.integers(0, modulus)) - dev[j]
        for j in rng.integers(0, n - 1, int(rng.integers(0, 8))):  # reordered pairs
            dev[[j, j + 1]] = dev[[j + 1, j]]
        slack = int(rng.choice([100, 10**8]))
        one, many = (
            CounterUnwrapper(modulus, slack_ns=slack),
            CounterUnwrapper(modulus, slack_ns=slack),
        )
        ref = [one(int(x), int(t)) for x, t in zip(dev, host, strict=True)]
        cuts = np.sort(rng.integers(0, n, int(rng.integers(0, 6))))
        parts = zip(np.split(dev, cuts), np.split(host, cuts), strict=True)
        got = np.concatenate([many.many(d, t) for d, t in parts])
        assert got.tolist() == ref
        assert (one.n_wraps, one.n_resets) == (many.n_wraps, many.n_resets)


def test_block_without_encoder_counts_is_dropped_and_counted() -> None:
    p = Pairer(config(mode="encoder"))
    rows = 3
    block = ProfileBlock(
        np.ones(rows, np.int64), np.arange(rows), np.zeros(rows, np.int64),
        np.full(rows, T0), np.zeros(2), np.zeros((rows, 2)), np.ones((rows, 2), bool),
    )  # fmt: skip
    p.add_block(block)
    assert p.dropped["no_encoder_count"] == rows and p.pending == 0 and p.received == rows


def test_pending_blocks_are_copied_down_when_mostly_released() -> None:
    """A big block of which a few profiles still wait is copied down to them (bounded memory);
    the waiting profiles keep their points."""
    rows, n = 3000, 4
    z = np.arange(rows * n, dtype=np.float64).reshape(rows, n)
    block = ProfileBlock(
        np.ones(rows, np.int64), np.arange(rows), np.arange(rows), np.arange(rows) + T0,
        np.zeros(n), z, np.ones((rows, n), bool),
    )  # fmt: skip
    pend = pending.PendingProfiles()
    pend.add_block(block, None, np.arange(rows), np.zeros(rows, np.int64), (1, 0))
    pend.consolidate()
    waiting = np.array([5, 17, 2999])
    pend.keep(waiting)
    assert len(pend) == 3 and [b.n_profiles for b in pend.blocks] == [3]
    g = pend.gather(np.arange(3))
    assert g.frame_counter.tolist() == waiting.tolist()
    got = np.concatenate([s.z for s in g.segments or []])
    np.testing.assert_array_equal(got, z[waiting])
    assert not any(np.shares_memory(s.z, z) for s in g.segments or [])
