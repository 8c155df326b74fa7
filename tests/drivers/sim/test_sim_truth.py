"""TruthRing: the shared-memory ground truth read by the simulated sensors in other processes."""

from __future__ import annotations

import multiprocessing as mp

import numpy as np
import pytest

from wristscan.drivers.sim.truth import TruthRing


def _reader(name: str, queue: mp.Queue) -> None:  # type: ignore[type-arg]
    ring = TruthRing.attach(name)
    try:
        queue.put(ring.sample(np.array([1500, 2500, 99999], dtype=np.int64)).tolist())
    finally:
        ring.close()


def test_interpolates_and_never_extrapolates() -> None:
    with TruthRing.create(width=2, capacity=8) as ring:
        assert ring.latest() is None
        assert np.isnan(ring.sample([0])).all()
        for k in range(5):
            ring.append(1000 * k, [k, 10.0 * k])
        got = ring.sample([500, 1000, 3250, 4000, 4001, -1])
        np.testing.assert_allclose(got[:4], [[0.5, 5.0], [1.0, 10.0], [3.25, 32.5], [4.0, 40.0]])
        assert np.isnan(got[4:]).all()
        latest = ring.latest()
        assert latest is not None and latest[0] == 4000


def test_wraps_and_keeps_the_newest_capacity_samples() -> None:
    with TruthRing.create(width=1, capacity=4) as ring:
        for k in range(10):
            ring.append(k, [float(k)])
        assert len(ring) == 4
        assert np.isnan(ring.sample([5])).all()  # overwritten
        np.testing.assert_allclose(ring.sample([6, 7.0, 9]), [[6.0], [7.0], [9.0]])


def test_reader_in_another_process() -> None:
    ctx = mp.get_context("spawn")
    with TruthRing.create(width=3) as ring:
        for k in range(4):
            ring.append(1000 * k, [k, 2 * k, 3 * k])
        queue = ctx.Queue()
        proc = ctx.Process(target=_reader, args=(ring.name, queue))
        proc.start()
        try:
            rows = queue.get(timeout=30)
        finally:
            proc.join(timeout=10)
        assert proc.exitcode == 0
        np.testing.assert_allclose(rows[0], [1.5, 3.0, 4.5])
        np.testing.assert_allclose(rows[1], [2.5, 5.0, 7.5])
        assert np.isnan(rows[2]).all()
        # The reader's exit must not have unlinked the segment.
        again = TruthRing.attach(ring.name)
        again.close()


def test_rejects_bad_shape() -> None:
    with pytest.raises(ValueError):
        TruthRing.create(width=0)
