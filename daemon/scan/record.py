"""Recording the passes of a scan: linear moves through a pass's poses while the acquisition
pairs profiles with the robot poses, checks that the table stood still, and a repeat of a pass
during which a clock fit of the synchroniser restarted (its profiles may be milliseconds off).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import se3
from wristscan.daemon.scan.errors import ScanError
from wristscan.daemon.scan.plan import CellGeometry, ResolvedPass

if TYPE_CHECKING:
    from wristscan.daemon.procedure.acquisition import Acquisition, Sweep

__all__ = ["TABLE_STILL_RAD", "RecordedPass", "angle_diff", "record_clean_pass", "ur_pose"]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

TABLE_STILL_RAD = 2e-4
"""The table angle before and after a pass may differ by this much (encoder noise)."""
_PASS_TRIES = 3


@dataclass(frozen=True)
class RecordedPass:
    """The profiles of one pass, paired with the robot poses (base frame)."""

    index: int
    label: str
    kind: str
    sweep: Sweep
    table_angle_rad: float | None
    """Encoder angle of the table during the pass (rad); None without a table."""
    duration_s: float
    repeats: int = 0
    """How often the pass was recorded again because a clock fit restarted during it."""
    clock_clean: bool = True
    """False: every try saw a clock fit restart; the timing of this pass is suspect."""


def angle_diff(a: float, b: float) -> float:
    """Angle between two table angles (rad, 0..pi)."""
    return abs((a - b + math.pi) % (2.0 * math.pi) - math.pi)


def ur_pose(geom: CellGeometry, sensor2base: FloatArray) -> FloatArray:
    """The UR pose ``p[x, y, z, rx, ry, rz]`` of the TCP that puts the sensor at
    ``sensor2base``."""
    return np.asarray(se3.matrix_to_pose(geom.tcp_of(sensor2base)))


def _clock_state(acq: Acquisition) -> tuple[Any, ...]:
    """Epoch, resets and re-anchorings of every clock fit of the synchroniser: a change means
    that a fit restarted, and profiles paired around it may be milliseconds off."""
    p = acq.stats().get("pairing", {})
    clocks = [p.get("robot_clock", {}), *p.get("sensor_clocks", {}).values()]
    return tuple((c.get("epoch"), c.get("resets"), c.get("reanchors")) for c in clocks)


def record_clean_pass(
    acq: Acquisition, geom: CellGeometry, rp: ResolvedPass, back_to_start: Callable[[], None]
) -> RecordedPass:
    """Record a pass; repeat it (up to ``_PASS_TRIES`` times, going back to the start the way
    the plan came) when a clock fit of the synchroniser restarted meanwhile. The last try is
    kept and marked when none was clean."""
    for attempt in range(1, _PASS_TRIES + 1):
        before = _clock_state(acq)
        rec = _record_pass(acq, geom, rp)
        if _clock_state(acq) == before:
            return dataclasses.replace(rec, repeats=attempt - 1)
        log.warning("%s: a clock fit restarted during the pass (try %d)", rp.label, attempt)
        if attempt < _PASS_TRIES:
            back_to_start()
    return dataclasses.replace(rec, repeats=_PASS_TRIES - 1, clock_clean=False)


def _record_pass(acq: Acquisition, geom: CellGeometry, rp: ResolvedPass) -> RecordedPass:
    """Record the linear moves of one pass; the table must not turn meanwhile."""
    robot = acq.robot
    accel = acq.cfg.robot.max_accel_m_s2
    table = acq.table
    before = float(table.angle()) if table is not None else None
    t0 = time.monotonic()
    with acq.record() as rec:
        for pose in rp.sensor2base[1:]:
            robot.move_l(ur_pose(geom, pose), rp.speed_m_s, accel)
    sweep = rec.result()
    angle: float | None = None
    if table is not None and before is not None:
        after = float(table.angle())
        if angle_diff(before, after) > TABLE_STILL_RAD:
            raise ScanError(
                f"{rp.label}: the table turned during the pass "
                f"({math.degrees(before):.4f} -> {math.degrees(after):.4f} deg)"
            )
        angle = before + 0.5 * math.remainder(after - before, 2.0 * math.pi)
    if sweep.n_profiles == 0:
        raise ScanError(f"{rp.label}: no profile was paired with the robot during the pass")
    log.info("%s: %d profiles, %d valid points", rp.label, sweep.n_profiles, sweep.valid.sum())
    return RecordedPass(rp.index, rp.label, rp.kind, sweep, angle, time.monotonic() - t0)
