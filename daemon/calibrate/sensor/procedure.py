"""The sensor calibration as one procedure: :class:`SensorCalibration` runs the stages on a
:class:`~.collect.RobotCell` (collection in the automatic or the manual mode, the solution with
the timing compensation and the consistency check, the check scan, leave-one-out), and
:func:`run` ties it to a configuration and writes the calibration file and the report; it is
what the command line calls."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import handeye, kinematics, se3
from wristscan.daemon.calibrate.sensor.automatic import AutomaticCollection
from wristscan.daemon.calibrate.sensor.collect import RobotCell, SweepRecorder
from wristscan.daemon.calibrate.sensor.manual import ManualCollection, Prompt
from wristscan.daemon.calibrate.sensor.plan import (
    OrientationPlan,
    Settings,
    min_pairwise,
    z_axis_angles_deg,
)
from wristscan.daemon.calibrate.sensor.report import build_report
from wristscan.daemon.calibrate.sensor.result import SensorCalibrationResult, calibration_of
from wristscan.daemon.calibrate.sensor.solve import (
    ApparentLatency,
    apparent_latency,
    can_drop,
    compensate_timing,
    inconsistent_locations,
    inlier_masks,
    kinematic_prior_for,
    location_offsets,
    observed_robot_sigma,
    quick_refine,
    solve,
)
from wristscan.daemon.calibrate.sensor.sweeps import RecordedSweep, base_label
from wristscan.daemon.calibrate.sensor.validate import (
    CheckScan,
    LeaveOneOut,
    check_scan_fit,
    leave_one_out,
)
from wristscan.daemon.io.calibfile import identities, write_calibration
from wristscan.daemon.procedure.acquisition import Acquisition
from wristscan.daemon.procedure.progress import Progress, stage_reporter
from wristscan.drivers.base import MotionNotEnabled

if TYPE_CHECKING:
    from wristscan.daemon.config import Config

__all__ = ["SensorCalibration", "run"]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


class _Collection(Protocol):
    """How the sweeps are made: :class:`AutomaticCollection` or :class:`ManualCollection`."""

    @property
    def estimate(self) -> FloatArray | None: ...

    def collect(self) -> tuple[list[RecordedSweep], list[OrientationPlan], FloatArray]: ...

    def check(self, joint: handeye.HandEyeResult | None) -> list[RecordedSweep]: ...


@dataclass(frozen=True)
class _Solution:
    """The final solutions, on ``sweeps`` (re-timed, inconsistent places left out)."""

    sweeps: list[RecordedSweep]
    two_step: handeye.HandEyeResult
    joint: handeye.HandEyeResult
    uncompensated: handeye.HandEyeResult | None
    latency: ApparentLatency | None


class SensorCalibration:
    """The procedure on a :class:`RobotCell` (see the package doc for the stages).

    ``nominal``: the sensor2flange the motions are planned with (automatic mode; not needed in
    manual mode). ``prompt`` (manual mode) shows a message and returns the operator's answer
    (default ``input``). ``progress`` receives a :class:`ProgressEvent` at every step."""

    def __init__(
        self,
        cell: RobotCell,
        settings: Settings,
        nominal: FloatArray | None = None,
        *,
        manual: bool = False,
        prompt: Prompt | None = None,
        progress: Progress | None = None,
        configured_latency_s: float = 0.0,
    ) -> None:
        settings.check()
        if not manual and nominal is None:
            raise ValueError("automatic mode needs a nominal sensor2flange to plan the motions")
        self.cell = cell
        self.s = settings
        self.nominal = None if nominal is None else se3.check_transform(nominal, "nominal")
        self.manual = manual
        self.prompt: Prompt = prompt or input
        self.progress = progress
        self.configured_latency_s = configured_latency_s
        self.recorder = SweepRecorder(cell, settings, progress)
        self._robot_sigma = (settings.robot_sigma_m, 0.0)
        self._collection: _Collection
        if manual:
            self._collection = ManualCollection(self.recorder, self.prompt)
        else:
            assert self.nominal is not None
            self._collection = AutomaticCollection(self.recorder, self.nominal)

    @property
    def notes(self) -> list[str]:
        """Notes for the report, in the order they were made."""
        return self.recorder.notes

    def _say(self, stage: str, message: str) -> None:
        self.recorder.say(stage, message)

    def _note(self, stage: str, text: str) -> None:
        self.recorder.note(stage, text)

    # --- entry point -------------------------------------------------------------------------
    def run(self) -> SensorCalibrationResult:
        """Run every stage; raises :class:`CalibrationFailed` or :class:`CalibrationAborted`."""
        t0 = time.monotonic()
        try:
            self.recorder.wait_for_data()
            sweeps, orientations, ref = self._collection.collect()
            early = self._check_early()
            sol = self._solve(sweeps)
            check_sweeps, check = self._check(sol.two_step, sol.joint, early)
            loo = self._leave_one_out(sol.sweeps, sol.joint)
        except BaseException:
            if not self.manual:
                self.cell.stop()
            raise
        if self.recorder.repeated:
            self.notes.append(
                f"{self.recorder.repeated} sweeps were repeated: too few of their profiles were "
                "paired with robot states (a host too busy for the synchroniser, or a stream gap)"
            )
        min_angle = self._min_z_angle(sol)
        return SensorCalibrationResult(
            settings=self.s,
            nominal=self.nominal,
            sweeps=tuple(sol.sweeps),
            two_step=sol.two_step,
            joint=sol.joint,
            uncompensated=sol.uncompensated,
            loo=loo,
            check=check,
            check_sweeps=tuple(check_sweeps),
            latency=sol.latency,
            orientations=tuple(orientations),
            fov_reference_flange2base=ref,
            min_z_angle_deg=min_angle,
            notes=tuple(self.notes),
            configured_latency_s=self.configured_latency_s,
            manual=self.manual,
            duration_s=time.monotonic() - t0,
            robot_sigma_m=self._robot_sigma[0],
            observed_robot_sigma_m=self._robot_sigma[1],
            robot_time_s=self.cell.robot_time_s,
            motion_time_s=self.cell.motion_s,
        )

    # --- (d) solve ---------------------------------------------------------------------------
    def _solve(self, sweeps: list[RecordedSweep]) -> _Solution:
        """A first solution, the passes re-timed by their apparent offsets, inconsistent places
        left out, then the two-step and joint solutions with the robot's repeatability."""
        R = self.s.ball_radius_m
        self._say("solve", f"first solution on {len(sweeps)} sweeps")
        estimate = self._collection.estimate
        if estimate is not None:
            first = quick_refine(sweeps, estimate, R)
        else:
            first = solve(sweeps, R, self.s.robot_sigma_m)[1]
        sweeps, first, latency, uncompensated = self._retimed(sweeps, first)
        offsets = location_offsets(sweeps, first, R)
        bad = inconsistent_locations(sweeps, first, R, offsets=offsets)
        if bad and can_drop(sweeps, set(bad)):
            for loc, dist in bad.items():
                name = base_label(next(w.label for w in sweeps if w.location == loc))
                self._note(
                    "solve",
                    f"{name}: its passes put the ball {dist * 1e6:.0f} um from the solution's; "
                    "left out (a pass with a timing slip or a robot error)",
                )
            sweeps = [w for w in sweeps if w.location not in bad]
        robot_sigma, observed = self._robot_sigma_for(sweeps, offsets, set(bad))
        self._say("solve", f"two-step and joint solution on {len(sweeps)} sweeps")
        prior = None
        if self.s.kinematic_prior and self.s.robot_model is not None:
            prior = kinematic_prior_for(self.cell.model, self.s.robot_model, self.cell.joints())
            if prior is not None:
                self._note(
                    "solve",
                    "the uncertainty includes the arm's kinematic error: DH parameters known to "
                    f"{prior.sigma[1:3].max() * 1e3:.3f} mm / "
                    f"{math.degrees(prior.sigma[[0, 3]].max()):.4f} deg (1 sigma; the nominal "
                    "table: a real arm's deviations, a factory calibration: 15 % of them)",
                )
        two, joint = solve(sweeps, R, robot_sigma, prior)
        self._robot_sigma = (robot_sigma, observed)
        if joint.advice:
            self._note(
                "solve", f"weakly constrained (condition {joint.condition:.1f}): {joint.advice}"
            )
        self._say(
            "solve",
            f"residual RMS {joint.rms * 1e6:.1f} um (two-step {two.rms * 1e6:.1f} um), "
            f"condition {joint.condition:.1f}",
        )
        return _Solution(sweeps, two, joint, uncompensated, latency)

    def _retimed(
        self, sweeps: list[RecordedSweep], first: handeye.HandEyeResult
    ) -> tuple[
        list[RecordedSweep],
        handeye.HandEyeResult,
        ApparentLatency | None,
        handeye.HandEyeResult | None,
    ]:
        """The apparent sensor time offset under ``first``; with ``compensate_timing``, the
        sweeps re-timed pair by pair and the solution refined on them. Returns the sweeps, the
        solution, the offset and the solution before the re-timing (None: not re-timed)."""
        R = self.s.ball_radius_m
        latency = apparent_latency(sweeps, first.sensor2flange, first.inliers, R)
        uncompensated = None
        if latency is not None:
            self._say(
                "solve",
                f"apparent sensor time offset {latency.offset_s * 1e3:+.3f} ms (+- "
                f"{latency.std_s * 1e3:.3f} ms, {latency.n_pairs} forward/backward pairs)",
            )
            if self.s.compensate_timing:
                uncompensated = first
                sweeps = compensate_timing(sweeps, latency)
                first = quick_refine(sweeps, first, R)
        return sweeps, first, latency, uncompensated

    def _robot_sigma_for(
        self, sweeps: list[RecordedSweep], offsets: dict[int, FloatArray], bad: set[int]
    ) -> tuple[float, float]:
        """The per-axis robot repeatability the covariance uses, and the observed one (m)."""
        s = self.s
        # The covariance takes the larger of the data sheet's repeatability and what the
        # places' scatter shows (the robot's error at the sensor includes its orientation
        # error times the sensor's distance from the flange).
        observed = observed_robot_sigma({k: v for k, v in offsets.items() if k not in bad})
        # The passes of a place share its error, while the solver's robot term takes every
        # sweep's as independent: scaled by sqrt(passes per place) for the same variance of
        # the place's mean.
        passes = len(sweeps) / max(1, len({w.location for w in sweeps}))
        robot_sigma = max(s.robot_sigma_m, observed * math.sqrt(passes))
        self._say(
            "solve",
            f"robot repeatability per axis: {s.robot_sigma_m * 1e6:.1f} um (data sheet), "
            f"{observed * 1e6:.1f} um (observed); the covariance uses "
            f"{robot_sigma * 1e6:.1f} um",
        )
        return robot_sigma, observed

    # --- (e) validate ------------------------------------------------------------------------
    def _check_early(self) -> list[RecordedSweep] | None:
        """Automatic mode: the check scan's sweeps right after the collection, aimed with its
        estimate (the robot does not wait for the solution); None otherwise."""
        if not self.s.check_scan or self.manual:
            return None
        self.recorder.wait_for_data(quiet=True)
        return self._collection.check(None)

    def _check(
        self,
        two: handeye.HandEyeResult,
        joint: handeye.HandEyeResult,
        early: list[RecordedSweep] | None = None,
    ) -> tuple[list[RecordedSweep], CheckScan | None]:
        """The check scan (when asked for): its sweeps (``early``: already recorded), re-timed,
        and their sphere fit."""
        s = self.s
        R = s.ball_radius_m
        if not s.check_scan:
            return [], None
        if early is not None:
            check_sweeps = early
        else:
            if not self.manual:
                self.recorder.wait_for_data(quiet=True)
            check_sweeps = self._collection.check(joint)
        if not check_sweeps:
            return check_sweeps, None
        band = max(5 * joint.rms, 0.2e-3)
        masks = inlier_masks(check_sweeps, joint.sensor2flange, joint.ball_centre_base, R, band)
        lat = apparent_latency(check_sweeps, joint.sensor2flange, masks, R)
        if lat is not None and s.compensate_timing:
            check_sweeps = compensate_timing(check_sweeps, lat)
        check = check_scan_fit(check_sweeps, joint, two, R)
        self._say(
            "check",
            f"check scan: centre {check.centre_error_m * 1e3:.4f} mm from the "
            f"calibrated ball, radius error {check.radius_error_m * 1e3:+.4f} mm",
        )
        return check_sweeps, check

    def _leave_one_out(
        self, sweeps: list[RecordedSweep], joint: handeye.HandEyeResult
    ) -> LeaveOneOut | None:
        if not self.s.leave_one_out:
            return None
        self._say("validate", "leave-one-out over the orientations")
        loo = leave_one_out(sweeps, joint, self.s.ball_radius_m)
        if loo is not None:
            self._say(
                "validate",
                f"leave-one-out: translation within {loo.max_translation_dev_m * 1e3:.4f}"
                f" mm, rotation within {math.degrees(loo.max_rotation_dev_rad):.4f} deg",
            )
        return loo

    def _min_z_angle(self, sol: _Solution) -> float:
        """Smallest angle (degrees) between the sensor Z axes of two orientations used; a note
        when it is below the minimum tilt."""
        groups: dict[int, FloatArray] = {}
        for w in sol.sweeps:
            groups.setdefault(w.group, w.sweep.flange2base[0] @ sol.joint.sensor2flange)
        min_angle = min_pairwise(z_axis_angles_deg(list(groups.values())))
        if math.isfinite(min_angle) and min_angle < self.s.min_tilt_deg - 0.5:
            self._note(
                "solve",
                f"two orientations are only {min_angle:.1f} deg apart (sensor Z axes); the paper "
                f"recommends >= {self.s.min_tilt_deg:.0f} deg",
            )
        return min_angle


# --------------------------------------------------------------------------------------------
# The whole thing on a configuration


def run(
    cfg: Config,
    settings: Settings,
    *,
    nominal: FloatArray | None,
    out: str | Path,
    report: str | Path | None = None,
    manual: bool = False,
    prompt: Prompt | None = None,
    progress: Progress | None = None,
    acquisition: Acquisition | None = None,
) -> SensorCalibrationResult:
    """Open the configured devices, run the procedure, write the calibration file ``out`` and the
    report. Nothing is written unless the procedure completes.

    Raises ``MotionNotEnabled`` (automatic mode without ``[robot] motion_enabled``),
    :class:`CalibrationFailed`, :class:`CalibrationAborted`, ``DriverError`` (devices cannot be
    opened). ``acquisition``: an already built (unopened) one, for tests."""
    # Not procedure.motion.require_motion: the confirmation is the command line's, manual mode
    # moves nothing, and the command line reports MotionNotEnabled as a usage error.
    if not manual and not cfg.robot.motion_enabled:
        raise MotionNotEnabled(
            f"motion is not enabled in {cfg.source}: set [robot] motion_enabled = true (or use "
            "--manual and move the robot from the teach pendant)"
        )
    connect, write = stage_reporter(progress, "connect"), stage_reporter(progress, "write")
    connect(0, 0, f"opening {cfg.robot.driver} at {cfg.robot.host} and {cfg.sensor.driver}")
    # Not procedure.in_force.procedure_acquisition: the procedure waits for paired profiles
    # itself (SweepRecorder.wait_for_data, which measures their rate), with its own error.
    acq = acquisition or Acquisition(cfg)
    model = kinematics.get_model(cfg.robot.model)
    with acq:
        cell = RobotCell(acq, model)
        proc = SensorCalibration(
            cell,
            settings,
            nominal,
            manual=manual,
            prompt=prompt,
            progress=progress,
            configured_latency_s=float(cfg.sensor.latency_s),
        )
        result = proc.run()
    robot_id, sensor_id = identities(cfg)
    calib = calibration_of(result, robot_id, sensor_id)
    path = write_calibration(out, calib)
    write(0, 0, f"calibration written to {path}: {calib.ur_pose_text}")
    if report is not None:
        try:
            rep = build_report(result, subtitle=f"cell {cfg.cell.name}, configuration {cfg.source}")
            write(0, 0, f"report written to {rep.write(report)}")
        except (OSError, ValueError) as exc:  # the calibration is written: do not fail for this
            log.warning("the report could not be written: %s", exc)
            write(0, 0, f"the report could not be written: {exc}")
    return result
