"""The robot read by the pipeline's worker at its ticks (``InlineReader``): the real UR driver
against the simulated UR5e controller over loopback RTDE, no reader thread."""

from __future__ import annotations

import time
from collections import deque

import numpy as np
import pytest

from wristscan.daemon.service.readers import InlineReader
from wristscan.drivers.records import RobotState
from wristscan.drivers.sim.ur.controller import (
    ControllerConfig,
    SimulatedController,
    pick_free_loopback_host,
)
from wristscan.drivers.ur.robot import URRobot

pytestmark = pytest.mark.timeout(120)


def test_ticks_read_every_state_and_a_wait_returns_with_the_next() -> None:
    cfg = ControllerConfig(host=pick_free_loopback_host())
    with SimulatedController(cfg) as sim, URRobot(sim.host, receive_backend="native") as robot:
        assert robot.stamped_on_receipt  # what makes the pipeline read it inline
        sink: deque[RobotState] = deque()
        drops: list[int] = []
        reader = InlineReader("robot", robot, sink, 10_000, lambda: drops.append(1))
        assert reader.pump(5.0) >= 1  # waits for the first (and takes what came since open)
        skipped0 = sim.state()["skipped_cycles"]
        sink.clear()
        deadline = time.monotonic() + 20.0
        while len(sink) < 100 and time.monotonic() < deadline:
            time.sleep(0.01)  # 10 ms ticks: the states of each come in one pump
            reader.pump()
        skipped = sim.state()["skipped_cycles"] - skipped0
        t = np.array([s.controller_time_s for s in sink])
        assert t.shape[0] >= 100
        steps = np.round(np.diff(t) / 0.002).astype(int)
        assert steps.min() == 1 and int((steps - 1).sum()) <= skipped  # none lost or repeated
        assert not drops and robot.counters.lost == 0
        # Drained: a wait returns as soon as the next state is in, not at its timeout.
        reader.pump()
        t0 = time.monotonic()
        assert reader.pump(1.0) >= 1
        assert time.monotonic() - t0 < 0.5
        # A full sink drops what does not fit, counted.
        sink.clear()
        reader.maxsize = 3
        time.sleep(0.05)
        n = reader.pump()
        assert len(sink) == 3 and len(drops) == n - 3 > 0
