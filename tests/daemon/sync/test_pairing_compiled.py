"""The synchroniser's compiled kernels (:mod:`wristscan.calib.jit_clock`) against their numpy
twins, to the last bit: the usual tick's arithmetic (:mod:`wristscan.daemon.sync.readytick`)
and the clock fit's feed (``clockfeed``), slope searches (``envelope._searches``) and window
pruning."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import test_robot_states_batch
from test_clockfeed import streams, synth
from test_pairing_fastpath import _digest, _run

from wristscan.calib import jit
from wristscan.daemon.sync import envelope, readytick
from wristscan.daemon.sync.clockmap import ClockMapper
from wristscan.daemon.sync.envelope import EnvelopeLine
from wristscan.daemon.sync.pairing import Pairer, PairerConfig

MS = 1_000_000


def test_compiled_tick_equals_numpy_steps(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(jit, "enabled", True)
    assert jit.kernel("map_locate") is not None
    compiled = readytick._mapped_compiled
    taken: list[bool] = []

    def counted(*args: object) -> object:
        got = compiled(*args)  # type: ignore[arg-type]
        taken.append(got is not None)
        return got

    monkeypatch.setattr(readytick, "_mapped_compiled", counted)
    got = _run(fast := Pairer(PairerConfig(sensor_latency_ns=2 * MS)))
    monkeypatch.setattr(readytick, "_mapped_compiled", lambda *args: None)
    ref = _run(plain := Pairer(PairerConfig(sensor_latency_ns=2 * MS)))
    assert sum(taken) > 50
    assert [_digest(b) for b in got] == [_digest(b) for b in ref]
    assert fast.stats() == plain.stats()


def test_compiled_slope_searches_equal_numpy(monkeypatch: pytest.MonkeyPatch) -> None:
    """The clock fit's five slope searches compiled (``fit_slopes``) against
    ``support_slope``: the same floats on windows of 6 to 3000 points, clean and with spikes
    or tied values, from a previous slope near the edge, far from it or none."""
    rng = np.random.default_rng(1)
    for trial in range(300):
        m = int(rng.integers(6, 3000))
        X = np.arange(m) * 1e7 + rng.uniform(0, 1e6, m)
        d_true = rng.uniform(-2e-4, 2e-4)
        delay = rng.gamma(2.0, rng.uniform(1e3, 1e6), m)
        if trial % 3 == 1:
            delay[rng.random(m) < 0.1] += 1e7
        if trial % 3 == 2:
            delay = np.round(delay, -3)
        R = 5e5 + d_true * X + delay
        x0, span = float(X[0]), float(X[-1] - X[0])
        x_e, xq = x0 + 0.5 * span, (x0 + 0.25 * span, x0 + 0.75 * span)
        guess = d_true + rng.normal(0.0, 1e-6 if trial % 2 else 1e-4)
        line = None if trial % 5 == 0 else EnvelopeLine(0, 0, 0.0, guess, 0.0, 0.0, 0.0, True)
        got = []
        for on in (True, False):
            monkeypatch.setattr(jit, "enabled", on)
            got.append(repr(envelope._searches(X, R, x_e, xq, -1e-3, 1e-3, line, span)))
        assert got[0] == got[1], trial


def test_compiled_clock_fits_equal_numpy(monkeypatch: pytest.MonkeyPatch) -> None:
    """Whole clock fits with the compiled feed, searches and window pruning against numpy's,
    tick by tick, on test_clockfeed's streams (bursts that pruning removes, reboots, jumps, a
    late sender): the same epochs, lines and windows."""
    cases = streams()
    dev, host = synth(3.0, 2000.0, 6)
    down = np.arange(dev.shape[0]) < 3000  # the delay floor comes down by 1.5 ms: re-anchored
    cases["floor down"] = (dev, np.where(down, host + 1_500_000, host))
    for (name, (dev, host)), tick in itertools.product(cases.items(), (100, 20)):
        fits = []
        for on in (True, False):  # ticks of 20: numpy's path feeds them as Python numbers
            monkeypatch.setattr(jit, "enabled", on)
            cm = ClockMapper()
            ticks = []
            for i in range(0, dev.shape[0], tick):
                epochs = cm.feed_many(dev[i : i + tick], host[i : i + tick])
                window = (cm._bx[cm._b0 : cm._b1].tobytes(), cm._br[cm._b0 : cm._b1].tobytes())
                ticks.append((epochs.tobytes(), cm._line, window))
            fits.append((ticks, cm.status()))
            assert name != "floor down" or cm.n_reanchors == 1
        assert fits[0] == fits[1], (name, tick)


def test_robot_states_at_once_without_kernels(monkeypatch: pytest.MonkeyPatch) -> None:
    """test_robot_states_batch's check on numpy's path (``feed_lists`` in Python numbers), the
    default run taking the compiled one."""
    monkeypatch.setattr(jit, "enabled", False)
    test_robot_states_batch.test_states_at_once_equal_one_by_one(monkeypatch)
