"""Moving the robot and recording sweeps for the sensor calibration.

:class:`RobotCell` commands flange poses through an open acquisition and records the profiles
paired with robot states meanwhile; :class:`SweepRecorder` turns a recorded move into a checked
:class:`~.sweeps.RecordedSweep` (repeated when it came out with gaps), numbers the places swept
and reports the procedure's progress and notes. The two modes drive them: :mod:`.automatic`
(the procedure moves the robot) and :mod:`.manual` (the operator does).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import handeye, kinematics, se3
from wristscan.daemon.calibrate.sensor.errors import CalibrationAborted, CalibrationFailed
from wristscan.daemon.calibrate.sensor.plan import Settings
from wristscan.daemon.calibrate.sensor.reach import Reachability
from wristscan.daemon.calibrate.sensor.sweeps import (
    MIN_BALL_POINTS,
    RecordedData,
    RecordedSweep,
    SweepStage,
    ball_coverage,
    reduce_sweep,
)
from wristscan.daemon.procedure.progress import Progress, ProgressEvent
from wristscan.drivers.base import (
    DriverError,
    MotionNotEnabled,
    ProtectiveStop,
    Robot,
    WorkspaceViolation,
)

if TYPE_CHECKING:
    from wristscan.daemon.procedure.acquisition import Acquisition
    from wristscan.drivers.records import RobotState

__all__ = ["MAX_GAP_R", "RobotCell", "SweepRecorder"]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
T = TypeVar("T")

_PAIRED_SHARE = 0.5
"""Share of a sweep's profiles that must be paired with robot states (else it is repeated)."""
_MIN_SPAN_R = 1.4
"""A sweep must see the ball over at least this many radii along its travel ..."""
MAX_GAP_R = 0.25
"""... with no gap between paired profiles longer than this many radii."""


class RobotCell:
    """Motion and recording through an open :class:`Acquisition`.

    Flange poses come from the joint positions through the kinematic model the synchroniser
    uses, so planned and recorded poses agree. Motion commands take *flange* poses and are sent
    for the controller's active TCP. Every driver failure becomes :class:`CalibrationAborted`
    (a protective stop says so)."""

    def __init__(self, acq: Acquisition, model: kinematics.DHParams) -> None:
        self.acq = acq
        self.model = model
        self._tcp2flange: FloatArray | None = None
        self.motion_s = 0.0
        """Seconds spent in motion commands so far."""
        self._first_motion: float | None = None
        self._last_motion_end = 0.0

    @property
    def robot_time_s(self) -> float:
        """Seconds from the start of the first motion to the end of the last one: the time the
        procedure keeps the robot (0 before any motion)."""
        if self._first_motion is None:
            return 0.0
        return self._last_motion_end - self._first_motion

    def _timed(self, fn: Callable[..., T], *args: Any) -> T:
        t0 = time.monotonic()
        if self._first_motion is None:
            self._first_motion = t0
        try:
            return self._call(fn, *args)
        finally:
            self._last_motion_end = time.monotonic()
            self.motion_s += self._last_motion_end - t0

    @property
    def robot(self) -> Robot:
        return self.acq.robot

    # --- state -------------------------------------------------------------------------------
    def state(self, timeout_s: float = 3.0) -> RobotState:
        deadline = time.monotonic() + timeout_s
        while True:
            st = self.robot.latest_state()
            if st is not None:
                return st
            if time.monotonic() > deadline:
                raise CalibrationFailed(
                    "no robot state received: check the robot connection (wristscan status)"
                )
            time.sleep(0.02)

    def joints(self) -> FloatArray:
        return np.asarray(self.state().q, dtype=np.float64).copy()

    def flange2base(self) -> FloatArray:
        return np.asarray(kinematics.forward(self.model, self.joints()), dtype=np.float64)

    def check_safety(self) -> None:
        st = self.state()
        if st.protective_stop:
            raise CalibrationAborted("the robot is in a protective stop")

    def tcp2flange(self) -> FloatArray:
        if self._tcp2flange is None:
            self._tcp2flange = se3.pose_to_matrix(self._call(self.robot.tcp_offset))
        return self._tcp2flange

    def workspace(self) -> tuple[FloatArray, FloatArray] | None:
        lo, hi = self.robot.workspace_min_m, self.robot.workspace_max_m
        if lo is None or hi is None:
            return None
        return np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)

    def planner(self, reference_q: FloatArray | None = None) -> Reachability:
        return Reachability(self.model, self.tcp2flange(), self.workspace(), reference_q)

    # --- motion ------------------------------------------------------------------------------
    def _call(self, fn: Callable[..., T], *args: Any) -> T:
        # Not procedure.motion.guarded_motion: each robot call's driver error is told apart here
        # (protective stop, refused, failed) in the CalibrationAborted the operator reads, and
        # the robot is stopped once, by SensorCalibration.run around the whole procedure
        # (through Acquisition.stop_motion, see stop()).
        try:
            return fn(*args)
        except ProtectiveStop as exc:
            raise CalibrationAborted(f"protective stop: {exc}") from None
        except (MotionNotEnabled, WorkspaceViolation) as exc:
            raise CalibrationAborted(f"motion refused: {exc}") from None
        except DriverError as exc:
            raise CalibrationAborted(f"motion failed: {exc}") from None

    def move_l(self, flange2base: FloatArray, speed: float, accel: float) -> None:
        pose = se3.matrix_to_pose(np.asarray(flange2base) @ self.tcp2flange())
        self._timed(self.robot.move_l, pose, speed, accel)

    def move_j(self, q: FloatArray, speed: float, accel: float) -> None:
        self._timed(self.robot.move_j, np.asarray(q, dtype=np.float64), speed, accel)

    def stop(self) -> None:
        """Best-effort stop of the robot (after an error or an interrupt): a stop that fails is
        logged, never raised over the error that led here."""
        self.acq.stop_motion(table=False)

    # --- recording ---------------------------------------------------------------------------
    @contextmanager
    def _recording(self) -> Iterator[list[RecordedData]]:
        out: list[RecordedData] = []
        with self.acq.record() as rec:
            yield out
        out.append(rec.result())

    def sweep_to(
        self, flange2base: FloatArray, speed: float, accel: float
    ) -> tuple[RecordedData, float]:
        """Record while moving linearly to ``flange2base``; returns the recording and how long
        the move took (s)."""
        t0 = time.monotonic()
        with self._recording() as box:
            self.move_l(flange2base, speed, accel)
            took = time.monotonic() - t0
        return box[0], took

    def record_for(self, seconds: float) -> RecordedData:
        with self._recording() as box:
            time.sleep(seconds)
        return box[0]

    def record_while(self, fn: Callable[[], T]) -> tuple[RecordedData, T]:
        """Record while ``fn`` runs (manual mode: the operator moves the robot)."""
        with self._recording() as box:
            value = fn()
        return box[0], value


class SweepRecorder:
    """The recording side of one run of the procedure on a :class:`RobotCell`: places numbered
    in the order they are swept, recordings reduced and checked (:meth:`sweep` repeats one that
    came out with gaps), the paired profile rate (:meth:`wait_for_data`); and what the run tells
    the operator on the way (``progress`` events, ``notes`` for the report), which both modes
    and the solution report through it."""

    def __init__(self, cell: RobotCell, settings: Settings, progress: Progress | None) -> None:
        self.cell = cell
        self.s = settings
        self.progress = progress
        self.notes: list[str] = []
        self.repeated = 0
        """Sweeps repeated because they came out with gaps."""
        self._location = 0
        self._rate_hz = 0.0

    def say(self, stage: str, message: str, step: int = 0, total: int = 0) -> None:
        log.info("%s", ProgressEvent(stage, step, total, message))
        if self.progress is not None:
            self.progress(ProgressEvent(stage, step, total, message))

    def note(self, stage: str, text: str) -> None:
        """A note for the report, also said as progress."""
        self.notes.append(text)
        self.say(stage, "note: " + text)

    def next_location(self) -> int:
        self._location += 1
        return self._location

    def reduce(
        self,
        data: RecordedData,
        stage: SweepStage,
        group: int,
        location: int,
        direction: int,
        label: str,
        keep: Callable[[handeye.Sweep], BoolArray] | None = None,
    ) -> RecordedSweep:
        """``data`` as a :class:`RecordedSweep`; :class:`CalibrationFailed` (its message starts
        with ``label``) when too few profiles were paired or too few points are near the ball."""
        sw, n_valid = reduce_sweep(data, self.s.max_points_per_sweep, keep)
        if data.n_profiles < 10:
            raise CalibrationFailed(
                f"{label}: only {data.n_profiles} profiles were paired with robot states; check "
                "the sensor stream and the [sync] settings (wristscan status)"
            )
        if sw.n_points < MIN_BALL_POINTS:
            raise CalibrationFailed(
                f"{label}: only {sw.n_points} points near the ball; the ball left the field of "
                "view (check the ball radius, the nominal sensor2flange and the FOV settings)"
            )
        return RecordedSweep(
            stage, group, location, direction, label, sw, data.exposure_ns.copy(), n_valid
        )

    def sweep(
        self,
        frm: FloatArray,
        to: FloatArray,
        stage: SweepStage,
        group: int,
        location: int,
        direction: int,
        label: str,
        keep: Callable[[handeye.Sweep], BoolArray] | None = None,
        coverage: bool = True,
    ) -> RecordedSweep:
        """Sweep from ``frm`` (where the robot is) to ``to``. A sweep with gaps is repeated, up
        to ``sweep_retries`` times: fewer than half of its profiles paired (a host too busy for
        the synchroniser, a stream gap), or the ball not seen over most of its width along the
        travel (:func:`~.sweeps.ball_coverage`)."""
        s = self.s
        R = s.ball_radius_m
        for attempt in range(s.sweep_retries + 1):
            data, took = self.cell.sweep_to(to, s.sweep_speed_m_s, s.sweep_accel_m_s2)
            expected = self._rate_hz * took
            why = ""
            if data.n_profiles < max(_PAIRED_SHARE * expected, 20):
                why = f"only {data.n_profiles} of ~{expected:.0f} profiles paired"
            else:
                try:
                    rs = self.reduce(data, stage, group, location, direction, label, keep)
                except CalibrationFailed as exc:
                    why = str(exc).removeprefix(f"{label}: ")
                else:
                    span, gap = ball_coverage(rs)
                    if not coverage or (span >= _MIN_SPAN_R * R and gap <= MAX_GAP_R * R):
                        return rs
                    why = (
                        f"the ball was seen over {span * 1e3:.1f} mm of travel with a "
                        f"{gap * 1e3:.1f} mm gap"
                    )
            if attempt == s.sweep_retries:
                break
            self.repeated += 1
            self.say(stage, f"{label}: {why}; repeating")
            self.wait_for_data(quiet=True)
            self.cell.move_l(frm, s.travel_speed_m_s, s.travel_accel_m_s2)
        raise CalibrationFailed(
            f"{label}: {why} after {s.sweep_retries + 1} attempts; check the sensor stream and the "
            "synchroniser (wristscan status), and that the ball is in view"
        )

    def wait_for_data(self, quiet: bool = False) -> None:
        """Until profiles are paired (at the start), or paired again after a long computation
        (which can hold up the synchroniser); measures the paired profile rate. At the start,
        no paired profiles within ``lock_timeout_s`` is a failure; later the sweeps' own checks
        take over after the timeout.

        Not :func:`~wristscan.daemon.procedure.motion.wait_until_pairing`: the sweeps need the
        paired profile rate this measures, and after the start it gives up quietly."""
        if not quiet:
            self.say("connect", "waiting for profiles paired with robot states")
        deadline = time.monotonic() + self.s.lock_timeout_s
        window_s = 0.4
        while True:
            data = self.cell.record_for(window_s)
            # The rate: profiles over their time span (a lower bound: profiles over the window).
            self._rate_hz = max(self._rate_hz, data.n_profiles / window_s)
            if data.n_profiles >= 2:
                span = (int(data.exposure_ns[-1]) - int(data.exposure_ns[0])) * 1e-9
                if span > 0.5 * window_s:
                    self._rate_hz = max(self._rate_hz, (data.n_profiles - 1) / span)
            if data.n_profiles >= max(20.0, _PAIRED_SHARE * self._rate_hz * window_s):
                if not quiet:
                    self.say("connect", f"paired profiles at {self._rate_hz:.0f} Hz")
                return
            if time.monotonic() > deadline:
                if quiet and self._rate_hz > 0:
                    log.warning("pairing has not recovered; going on")
                    return
                raise CalibrationFailed(
                    f"no profiles were paired with robot states within {self.s.lock_timeout_s:g} "
                    "s: check the sensor stream, the robot connection and [sync] (wristscan "
                    "status)"
                )
