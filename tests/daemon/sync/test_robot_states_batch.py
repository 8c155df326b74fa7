"""``Pairer.add_robot_states`` (a tick's controller samples at once: the robot clock fed by
``clockfeed.feed_lists``, the buffer written by ``RobotStateBuffer.append_many``) against the
reference, one sample at a time: the robot clock's lines, epochs, counters, recent arrivals and
buckets equal to those of a ``ClockMapper`` fed by ``feed`` arrival by arrival, and the robot
buffer equal to one filled by ``add_robot_state``, to the last bit, after every tick; on a
stream with a controller restart, a forward clock jump, a reordered and a repeated sample."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from wristscan.daemon.sync.buffers import RobotStateBuffer
from wristscan.daemon.sync.clockmap import ClockMapper
from wristscan.daemon.sync.pairing import Pairer, PairerConfig
from wristscan.drivers.records import RobotState

MS = 1_000_000
S = 1_000_000_000


def _states(seconds: float = 6.0, seed: int = 8) -> list[RobotState]:
    """500 Hz samples (controller clock -30 ppm), gamma delays with 2 % spikes of 2-20 ms."""
    rng = np.random.default_rng(seed)
    n = int(seconds * 500)
    ctrl = 7200 * S + np.arange(n, dtype=np.int64) * 2 * MS
    host = 100 * S + np.rint((ctrl - 7200 * S) * (1.0 - 30e-6)).astype(np.int64)
    delay = 250_000 + rng.gamma(2.0, 70_000.0, n)
    spike = rng.random(n) < 0.02
    delay[spike] += rng.uniform(2 * MS, 20 * MS, int(spike.sum()))
    host = np.maximum.accumulate(host + np.rint(delay).astype(np.int64))
    ctrl[n // 3 :] -= 5 * S  # the controller restarts: its clock goes back
    ctrl[2 * n // 3 :] += 30 * MS  # its clock jumps forward
    ctrl[[700, 701]] = ctrl[[701, 700]]  # a reordered pair (the buffer refuses one)
    ctrl[900] = ctrl[899]  # a repeated time
    q0 = np.array([0.3, -1.2, 1.4, -1.8, -1.57, 0.2])
    return [
        RobotState(c / 1e9, h, q0 + 1e-3 * k, np.full(6, 1e-4 * k))
        for k, (c, h) in enumerate(zip(ctrl.tolist(), host.tolist(), strict=True))
    ]


def _same_clock(a: ClockMapper, b: ClockMapper) -> None:
    assert a._line == b._line
    assert a.status() == b.status()
    assert list(a._recent) == list(b._recent)
    assert np.array_equal(a._bx[a._b0 : a._b1], b._bx[b._b0 : b._b1])
    assert np.array_equal(a._br[a._b0 : a._b1], b._br[b._b0 : b._b1])
    assert (a._ob, a._ox, a._or, a._x_last, a.n_fed) == (b._ob, b._ox, b._or, b._x_last, b.n_fed)


def _same_buffer(a: RobotStateBuffer, b: RobotStateBuffer) -> None:
    assert np.array_equal(a.buffer.times, b.buffer.times)
    assert np.array_equal(a.buffer.values, b.buffer.values)
    assert a.buffer.n_rejected == b.buffer.n_rejected


def test_states_at_once_equal_one_by_one(monkeypatch: pytest.MonkeyPatch) -> None:
    states = _states()
    cfg = PairerConfig(robot_capacity=1000)  # the buffer also fills up and makes room
    one, many = Pairer(cfg), Pairer(cfg)
    ref = ClockMapper(replace(cfg.robot_clock, latency_ns=cfg.robot_latency_ns), "robot clock")
    appended = [0]
    append = RobotStateBuffer.append

    def counted(self: RobotStateBuffer, *args: object) -> bool:
        appended[0] += 1
        return append(self, *args)  # type: ignore[arg-type]

    monkeypatch.setattr(RobotStateBuffer, "append", counted)
    sizes = [5, 1, 13, 60, 2, 49, 5, 5, 0, 7]
    i = k = 0
    while i < len(states):
        tick = states[i : i + sizes[k % len(sizes)]]
        for s in tick:
            one.add_robot_state(s)
            ref.feed(round(s.controller_time_s * 1e9), s.host_time_ns)
        many.add_robot_states(tick)
        _same_clock(many.robot_clock, ref)
        _same_clock(one.robot_clock, ref)
        _same_buffer(many.robot, one.robot)
        assert many.latest_host_ns == one.latest_host_ns
        i += len(tick)
        k += 1
    assert ref.n_resets >= 2  # the stream does restart the fit (back, then forward)
    assert one.robot.buffer.n_rejected == 2  # the reordered sample and the repeated time
    assert many.robot_states == one.robot_states == len(states)
    # One append per sample one by one (len(states)); the ticks written at once add few more.
    assert appended[0] < 1.2 * len(states)
