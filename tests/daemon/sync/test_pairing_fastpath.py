"""The pairer's shortcuts for the usual tick (every pending profile ready: ``Pairer.poll``'s
``_poll_all_ready``; one block released in order: ``PendingProfiles._gather_run``) give the
batches of the general path, to the last bit, on a stream where both kinds of tick occur."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from wristscan.daemon.sync.batch import PairedBatch
from wristscan.daemon.sync.pairing import Pairer, PairerConfig
from wristscan.daemon.sync.pending import PendingProfiles
from wristscan.drivers.records import ProfileBlock, RobotState

MS = 1_000_000


def _run(pairer: Pairer, seed: int = 4) -> list[PairedBatch]:
    """2 kHz x 64 points and 500 Hz states in 10 ms ticks; every 7th tick the states come late
    (profiles wait), the profiles of every 5th arrive out of exposure order."""
    rng = np.random.default_rng(seed)
    t0, per, n = 10**12, 20, 64
    q0 = np.array([0.3, -1.2, 1.4, -1.8, -1.57, 0.2])
    out: list[PairedBatch] = []
    for k in range(150):
        tick = t0 + k * 10 * MS
        lag = 6 * MS if k % 7 == 3 else 0
        for j in range(5):
            t = tick - 9 * MS + 2 * j * MS - lag
            q = q0 + 1e-3 * (t - t0) / MS
            pairer.add_robot_state(RobotState(t * 1e-9, t + 300_000, q, np.zeros(6)))
        t_exp = tick - 12 * MS + np.arange(per) * (MS // 2)
        if k % 5 == 2:
            t_exp = t_exp[rng.permutation(per)]
        host = t_exp + 2 * MS + rng.integers(50_000, 400_000, per)
        z = rng.normal(0.15, 1e-4, (per, n))
        block = ProfileBlock(
            np.zeros(per, np.int64),
            np.arange(k * per, (k + 1) * per),
            t_exp + 2 * MS,
            host,
            np.linspace(-0.02, 0.02, n),
            z,
            np.ones(z.shape, bool),
        )
        pairer.add_block(block)
        out += pairer.poll()
    return out


def _digest(b: PairedBatch) -> tuple[Any, ...]:
    return (
        b.exposure_ns.tobytes(),
        b.flange2base.tobytes(),
        b.clock_uncertainty_ns.tobytes(),
        b.frame_counter.tobytes(),
        b.sensor_id.tobytes(),
        b.arrival_ns.tobytes(),
        b.offsets.tobytes(),
        b.z.tobytes(),
        b.y.tobytes(),
        b.valid.tobytes(),
    )


def test_shortcuts_equal_the_general_path(monkeypatch: pytest.MonkeyPatch) -> None:
    fast = Pairer(PairerConfig(sensor_latency_ns=2 * MS))
    taken = []
    shortcut = Pairer._poll_all_ready

    def counted(self: Pairer) -> list[PairedBatch] | None:
        got = shortcut(self)
        taken.append(got is not None)
        return got

    monkeypatch.setattr(Pairer, "_poll_all_ready", counted)
    got = _run(fast)
    monkeypatch.setattr(Pairer, "_poll_all_ready", lambda self: None)
    monkeypatch.setattr(PendingProfiles, "_gather_run", lambda self, sel, p: None)
    ref = _run(general := Pairer(PairerConfig(sensor_latency_ns=2 * MS)))
    assert 50 < sum(taken) < len(taken)  # both kinds of tick were seen
    assert [_digest(b) for b in got] == [_digest(b) for b in ref]
    assert fast.stats() == general.stats()
    assert fast.paired > 2000
