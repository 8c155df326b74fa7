"""What the acquisition pipeline runs with: the calibration in force (:class:`AlignmentSetup`)
and its settings (:class:`PipelineSettings`); both are importable from
``wristscan.daemon.service.pipeline`` as well."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["AlignmentSetup", "PipelineSettings"]


@dataclass(frozen=True)
class AlignmentSetup:
    """The calibration in force, as the worker uses it (swapped atomically as one object)."""

    sensor2flange: NDArray[np.float64]
    frame: str = "base"
    base2table: NDArray[np.float64] | None = None
    encoder_offset_rad: float = 0.0
    calibrated: bool = True
    description: dict[str, Any] | None = None


@dataclass(frozen=True)
class PipelineSettings:
    batch_s: float = 0.010
    profile_queue: int = 4096
    batch_queue: int = 8
    """Aligned batches waiting for the publishing thread at most (then the worker waits)."""
    state_queue: int = 65536
    status_period_s: float = 1.0
    state_wait_s: float = 0.005
    """At a tick, wait up to this long for the robot (or table) states that profiles already
    received still need (the state after their exposure is a few ms away), and publish them in
    this tick's batch instead of one whole period later."""
    read_ahead_s: float = 0.002
    """Between ticks the worker reads, decodes and queues what has arrived every this long
    (0: only at ticks), so that a tick has only the newest profiles left to decode (the same
    CPU per profile, off the path from tick to publication)."""
    read_ahead_profiles: int = 100
    """...but a read-ahead pass waits until about this many profiles have arrived (at the
    arrival rate of the last ticks): a pass costs ~0.1 ms however few it decodes, so at 1 kHz
    five passes a tick cost more than the profiles; at 10 kHz a pass every ~3 ms."""
    publish_intensity: bool = False
    publish_profile_index: bool = False
    inline_sensor: bool | None = None
    """Read the sensor in the worker at each tick instead of in a reader thread (None: when the
    driver's records are ``stamped_on_receipt``, e.g. by the kernel; then reading late loses no
    timing, the socket buffer holds the tick's datagrams, and a thread woken per profile,
    competing for the GIL with the worker, is saved)."""
    inline_robot: bool | None = None
    """Read the robot in the worker at each tick (and while it waits for states) instead of in
    a reader thread (None: when its records are ``stamped_on_receipt``, e.g. by the UR driver's
    receive child; a thread woken for each of 500 states a second costs ~4 % of a core)."""
    shed_overload: bool = True
    """Shed whole profiles, evenly spread and counted (``overload``), when they arrive faster
    than the worker can process them (``daemon/service/overload.py``), instead of falling
    behind without bound."""
    overload_lag_s: float = 0.1
    """Shed only while the oldest profile at admission is older than this: the worker is
    behind (keeping up, the lag is one tick)."""
    gil_switch_interval_s: float | None = 0.0005
    """Python's thread switch interval while the pipeline runs, for sensor drivers that stamp
    a record when their thread gets the GIL back after the receive call: with Python's default
    5 ms a busy worker delays those stamps by up to 5 ms, which the sensor clock fit sees as
    transport jitter (its jump tolerance is 2 ms). Drivers whose stamps come from the kernel
    (``kernel_stamps``, the UDP drivers on Linux) do not need it, and the interval is left
    alone for them: every forced switch costs the worker a wake-up. None: always leave it."""
