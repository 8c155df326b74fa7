"""``wristscan calibrate kinematics``: the arm's kinematic errors identified with the probe
(:mod:`wristscan.calib.kinematic_ident`) on the cell.

The ball sweeps are those of ``calibrate sensor``'s automatic mode (:mod:`.sensor`: the find
sweep, the field-of-view grid, the orientations around the ball), with more orientations in two
tilts so that the arm's joints move more; the sensor calibration's joint solution on them is the
start. Each profile's joints are recovered from its flange pose with the model the synchroniser
paired it with (:func:`~wristscan.calib.kinematic_ident_synthetic.path_joints`: one inverse
kinematics per sweep, then Newton steps), and the DH deviations are identified jointly with
sensor2flange and the ball centre. The result is written as a kinematics file
(:mod:`.kinematics_file`; ``[robot] kinematics_file`` names it) and, with ``sensor_out``, the
sensor2flange identified with it as a sensor calibration file: the two belong together.

The report says, without any truth, what the identification changed: the residual RMS of the
points to the ball and the ball-centre scatter across the sweeps (each sweep's own sphere fit)
with the model in use and with the identified one, and which parameters could not be observed.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import kinematic_ident as ki
from wristscan.calib import kinematics
from wristscan.calib.handeye_kinematic import prior_sigma
from wristscan.calib.kinematic_ident_synthetic import centre_scatter, path_joints
from wristscan.daemon.calibrate.sensor import (
    CalibrationFailed,
    RecordedSweep,
    RobotCell,
    SensorCalibration,
    SensorCalibrationResult,
    Settings,
    settings_for,
)
from wristscan.daemon.devices import robot_model
from wristscan.daemon.io.kinematics_file import KinematicsFile, write_kinematics
from wristscan.daemon.procedure.acquisition import Acquisition
from wristscan.daemon.procedure.progress import Progress, stage_reporter
from wristscan.drivers.base import MotionNotEnabled

if TYPE_CHECKING:
    from wristscan.daemon.config import Config

__all__ = [
    "KinematicsCalibrationResult",
    "ball_scans",
    "identify_on",
    "run",
    "settings_for_kinematics",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class KinematicsCalibrationResult:
    """The identification, the sensor calibration whose sweeps it used, the ball-centre scatter
    across sweeps (m) before and after, and how long the procedure took (s)."""

    ident: ki.KinematicIdentification
    sensor: SensorCalibrationResult
    scatter_before_m: float
    scatter_after_m: float
    duration_s: float

    def summary(self) -> list[str]:
        """The report's lines."""
        r = self.ident
        lines = [
            f"{r.n_scans} sweeps, {r.n_points} points; residual RMS {r.rms_before_m * 1e6:.1f} um "
            f"with {r.base_model.name}, {r.rms_m * 1e6:.1f} um identified",
            f"ball-centre scatter across sweeps: {self.scatter_before_m * 1e6:.1f} um before, "
            f"{self.scatter_after_m * 1e6:.1f} um after",
            f"robot time {self.sensor.robot_time_s:.0f} s ({self.sensor.motion_time_s:.0f} s "
            "moving)",
        ]
        for i, name in enumerate(ki.PARAM_NAMES):
            if i in r.ident.fixed:
                continue
            k, j = divmod(i, 6)
            d, s = r.delta[k, j], r.sigma[k, j]
            if k in (1, 2):
                lines.append(f"  {name:7s} {d * 1e6:+8.1f} um  (1 sigma {s * 1e6:.1f} um)")
            else:
                lines.append(
                    f"  {name:7s} {math.degrees(d):+9.5f} deg (1 sigma {math.degrees(s):.5f} deg)"
                )
        lines += [f"not observable: {u}" for u in r.ident.unobservable]
        lines += [f"weakly observed (held by the prior): {w}" for w in r.ident.weak]
        return lines


def settings_for_kinematics(cfg: Config, **overrides: Any) -> Settings:
    """The sensor calibration's settings for ``cfg`` with more orientations (12 at 40 degrees:
    the joints move more), no check scan and no leave-one-out; ``overrides`` win."""
    kw: dict[str, Any] = {"n_orientations": 12, "tilt_deg": 40.0, "min_tilt_deg": 30.0}
    kw.update({"check_scan": False, "leave_one_out": False})
    kw.update({k: v for k, v in overrides.items() if v is not None})
    return settings_for(cfg, **kw)


def ball_scans(
    sweeps: Sequence[RecordedSweep],
    model: kinematics.DHParams,
    seed_q: FloatArray,
    inliers: Sequence[NDArray[np.bool_]] | None = None,
) -> list[ki.BallScan]:
    """The recorded sweeps (their ``inliers``: the points on the ball, when given) with each
    profile's joints, recovered from its flange pose with ``model`` (the synchroniser's) on the
    branch nearest ``seed_q``; one ball place. Sweeps whose joints cannot be recovered are left
    out."""
    out = []
    for k, w in enumerate(sweeps):  # tens of sweeps; each is vectorised over its profiles
        try:
            q = path_joints(model, w.sweep.flange2base, seed_q)
        except (kinematics.Unreachable, ValueError, np.linalg.LinAlgError) as exc:
            log.warning("%s: joints not recovered (%s); left out", w.label, exc)
            continue
        sw = w.sweep if inliers is None else w.sweep.subset(inliers[k])
        out.append(ki.BallScan(sw, q, 0))
    return out


def identify_on(
    sres: SensorCalibrationResult,
    model: kinematics.DHParams,
    nominal_model: str,
    seed_q: FloatArray,
) -> tuple[ki.KinematicIdentification, float, float]:
    """The identification on a sensor calibration's sweeps: the result and the ball-centre
    scatter before and after (m). The prior: a real arm's full deviations when ``model`` is the
    nominal table, 15 % of them for a factory (or an earlier) calibration."""
    j = sres.joint
    masks = j.inliers if len(j.inliers) == len(sres.sweeps) else None
    scans = ball_scans(sres.sweeps, model, seed_q, masks)
    if len(scans) < 6:
        raise CalibrationFailed(f"only {len(scans)} sweeps could be used; at least 6 are needed")
    table = kinematics.get_model(nominal_model)
    on_table = np.allclose(np.array(model.arrays()), np.array(table.arrays()), 0.0, 1e-12)
    prior = prior_sigma("none" if on_table else "partial")
    try:
        res = ki.identify(
            scans, model, j.sensor2flange, sres.settings.ball_radius_m, prior,
            centres=np.asarray(j.ball_centre_base)[None],
        )  # fmt: skip
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise CalibrationFailed(f"the identification failed: {exc}") from None
    R = sres.settings.ball_radius_m
    before = centre_scatter(scans, model, res.sensor2flange_before, R)
    after = centre_scatter(scans, res.model, res.sensor2flange, R)
    return res, before, after


def run(
    cfg: Config,
    settings: Settings,
    *,
    nominal: FloatArray | None,
    out: str | Path | None,
    progress: Progress | None = None,
    acquisition: Acquisition | None = None,
) -> KinematicsCalibrationResult:
    """Open the configured devices, sweep the ball (the sensor calibration's automatic mode with
    ``settings``), identify the arm's kinematics and write the kinematics file ``out`` (None: the
    caller writes it, :func:`kinematics_file_of`). Nothing is written unless every stage
    completes. Raises ``MotionNotEnabled``,
    :class:`CalibrationFailed`, :class:`CalibrationAborted` or ``DriverError``."""
    if not cfg.robot.motion_enabled:
        raise MotionNotEnabled(
            f"motion is not enabled in {cfg.source}: set [robot] motion_enabled = true"
        )
    t0 = time.monotonic()
    connect = stage_reporter(progress, "connect")
    connect(0, 0, f"opening {cfg.robot.driver} at {cfg.robot.host} and {cfg.sensor.driver}")
    acq = acquisition or Acquisition(cfg)
    with acq:
        model = kinematics.get_model(robot_model(cfg, acq.devices))
        cell = RobotCell(acq, kinematics.get_model(cfg.robot.model))
        seed_q = cell.joints()
        proc = SensorCalibration(
            cell, settings, nominal, progress=progress,
            configured_latency_s=float(cfg.sensor.latency_s),
        )  # fmt: skip
        sres = proc.run()
    say = stage_reporter(progress, "identify")
    say(0, 0, f"identifying the arm's kinematics on {len(sres.sweeps)} sweeps ({model.name})")
    res, before, after = identify_on(sres, model, cfg.robot.model, seed_q)
    result = KinematicsCalibrationResult(res, sres, before, after, time.monotonic() - t0)
    for line in result.summary():
        say(0, 0, line)
    if out is not None:
        path = write_kinematics(out, kinematics_file_of(cfg, result))
        stage_reporter(progress, "write")(0, 0, f"kinematics written to {path}")
    return result


def kinematics_file_of(cfg: Config, result: KinematicsCalibrationResult) -> KinematicsFile:
    """The kinematics file of a result, for the robot of ``cfg``."""
    from wristscan.daemon.io.calibfile import identities

    robot_id, _ = identities(cfg)
    r = result.ident
    return KinematicsFile(
        robot_model=cfg.robot.model,
        serial=robot_id.serial,
        model=r.model,
        base_model=r.base_model,
        delta=r.delta,
        sigma=r.sigma,
        fixed=r.ident.fixed_names,
        unobservable=r.ident.unobservable,
        weak=r.ident.weak,
        sensor2flange=r.sensor2flange,
        sensor2flange_before=r.sensor2flange_before,
        figures={
            "rms_before_m": r.rms_before_m,
            "rms_after_m": r.rms_m,
            "scatter_before_m": result.scatter_before_m,
            "scatter_after_m": result.scatter_after_m,
            "n_scans": float(r.n_scans),
            "n_points": float(r.n_points),
            "duration_s": result.duration_s,
            "robot_time_s": result.sensor.robot_time_s,
        },
    )
