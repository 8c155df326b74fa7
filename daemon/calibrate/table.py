"""Rotary-table calibration procedure (``wristscan calibrate table``). The ball-scanning
machinery it shares with the latency procedure (:mod:`.latency`) is in :mod:`.ball`, its report
in :mod:`.table_report`.

Procedure
---------
A tooling ball is fixed on the table top, away from the axis. For each of ``n >= 6`` table
angles the table turns, the sensor sweeps along its own X axis over the ball (Borangiu et al.
2009, section 2: "a sweep on the X direction of the tool reference frame, from -R to +R"), the
profiles are paired with the robot poses and put into the base frame through the sensor
calibration in force, and a sphere of the known radius is fitted: one ball centre per angle.
:func:`wristscan.calib.table.fit_table_axis` turns the centres and the encoder angles into the
axis direction, a point on it and the encoder offset, with their covariance.

* The sensor keeps one orientation for every sweep (the one it has when the procedure starts)
  and sees the ball at the same place in its field of view: an error of the sensor calibration
  then moves every centre by the same vector, which shifts the axis point but neither tilts the
  axis nor changes the encoder offset.
* The ball is found, not taught: the first sweep searches around the given (or assumed) ball
  position with a wide margin; the table then turns in two small steps (the ball stays within
  the search window whatever the axis), and from three centres on the circle fitted so far
  predicts where the ball goes next. A sweep that finds the ball off the planned centre by more
  than ``recentre_tol_m`` is repeated centred on it.
* Every sweep runs in the same direction at the same speed, so a latency error shifts every
  centre by the same vector too.

Safety: nothing moves unless ``[robot] motion_enabled`` is set and the caller confirmed
(``confirmed=True``; the CLI's ``--yes``); speeds are capped by the configuration and the robot
driver refuses targets outside the workspace box. Any failure while moving (protective stop,
refused move, lost link, Ctrl-C) stops the robot and the table and raises
:class:`ProcedureAborted`; nothing is written, so the calibration in force stays in force.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import se3
from wristscan.calib.table import COV_ORDER, TableAxis, fit_table_axis, table_rotation
from wristscan.daemon.calibrate.ball import BallMeasurement, BallScanner, ball_scanner
from wristscan.daemon.config import Config
from wristscan.daemon.io.calibfile import Calibration, Residuals, identities
from wristscan.daemon.procedure.errors import (
    ProcedureError,
)
from wristscan.daemon.procedure.in_force import (
    load_sensor_calibration,
    procedure_acquisition,
)
from wristscan.daemon.procedure.motion import (
    guarded_motion,
    require_motion,
)
from wristscan.daemon.procedure.progress import Progress, StepReport, stage_reporter

if TYPE_CHECKING:
    from wristscan.daemon.procedure.acquisition import Acquisition

__all__ = [
    "TableOptions",
    "TableResult",
    "calibrate_table",
    "direction_cov",
    "table_calibration",
    "tilt_sigma_deg",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TableOptions:
    """Settings of :func:`calibrate_table` (SI units)."""

    n_angles: int = 8
    """Table angles of the main plan (>= 6 recommended; two small bootstrap steps come on top)."""
    span_rad: float | None = None
    """Angle range the plan covers from the current angle; None: a full turn, evenly spaced
    (``2 pi (n - 1) / n``)."""
    ball_guess_m: tuple[float, float, float] | None = None
    """Approximate ball centre at the current table angle (base frame); None: ``standoff_m``
    in front of the sensor as it stands."""
    ball_radius_m: float = 0.0127
    standoff_m: float = 0.10
    """Distance from the sensor origin to the ball centre along the sensor's Z axis."""
    scan_speed_m_s: float = 0.02
    search_margin_m: float = 0.02
    """How far along the sweep the ball may be from where it is expected, at first."""
    margin_m: float = 0.006
    """The same once the ball's circle is known."""
    recentre_tol_m: float = 0.002
    bootstrap_step_rad: float = math.radians(5.0)
    ball_height_m: float = 0.0
    """Height of the ball centre above the table top: the table frame's origin is put on the
    table top (0: in the plane of the ball centre)."""
    travel_speed_m_s: float = 0.1
    settle_s: float = 0.2
    """Wait after the table stopped (the table and the post settle)."""

    def __post_init__(self) -> None:
        if self.n_angles < 3:
            raise ValueError("n_angles must be >= 3 (>= 6 recommended)")
        if self.ball_radius_m <= 0 or self.standoff_m <= 0 or self.scan_speed_m_s <= 0:
            raise ValueError("ball_radius_m, standoff_m and scan_speed_m_s must be > 0")
        if self.span_rad is not None and not 0 < self.span_rad <= 2 * math.pi:
            raise ValueError("span_rad must be in (0, 2 pi]")

    def plan(self, theta0: float) -> list[float]:
        """Table angles in measuring order (rad): the start, two bootstrap steps, the plan."""
        n = self.n_angles
        span = self.span_rad if self.span_rad is not None else 2 * math.pi * (n - 1) / n
        main = [theta0 + span * j / (n - 1) for j in range(n)]
        b = self.bootstrap_step_rad
        extra = [theta0 + b, theta0 + 2 * b] if main[1] - main[0] > 2.5 * b else []
        return sorted([main[0], *extra, *main[1:]])


@dataclass(frozen=True)
class TableResult:
    """What :func:`calibrate_table` found (base frame, SI units)."""

    axis: TableAxis
    measurements: tuple[BallMeasurement, ...]
    angles_rad: FloatArray
    """(k,) encoder angles of the measurements."""
    ball_height_m: float
    tilt_sigma_deg: float
    """One-sigma uncertainty of the axis tilt from base Z (degrees)."""
    sensor_calibration: str
    duration_s: float
    sweeps: int
    options: TableOptions = field(default_factory=TableOptions)

    @property
    def centres(self) -> FloatArray:
        return np.stack([m.centre for m in self.measurements])

    @property
    def base2table(self) -> FloatArray:
        return self.axis.base2table(-self.ball_height_m)

    def parameters(self) -> list[tuple[str, float, float, str]]:
        """``(name, value, one-sigma, unit)`` of every estimated parameter, for reports."""
        a = self.axis
        s = a.sigma()
        sd = np.sqrt(np.diag(direction_cov(a)))
        out = [
            ("axis tilt from base Z", a.tilt_deg, self.tilt_sigma_deg, "deg"),
            ("axis direction x", float(a.direction[0]), float(sd[0]), "1"),
            ("axis direction y", float(a.direction[1]), float(sd[1]), "1"),
            ("axis direction z", float(a.direction[2]), float(sd[2]), "1"),
            ("axis point x", a.point[0], s["point_x_m"], "m"),
            ("axis point y", a.point[1], s["point_y_m"], "m"),
            ("axis point z", a.point[2], s["point_z_m"], "m"),
            ("ball circle radius", a.radius_m, s["radius_m"], "m"),
            ("encoder offset", a.encoder_offset_rad, s["phase_rad"], "rad"),
        ]
        return out

    def to_dict(self) -> dict[str, Any]:
        a = self.axis
        return {
            "axis_direction": a.direction.tolist(),
            "axis_point_m": a.point.tolist(),
            "tilt_deg": a.tilt_deg,
            "tilt_sigma_deg": self.tilt_sigma_deg,
            "encoder_offset_rad": a.encoder_offset_rad,
            "radius_m": a.radius_m,
            "rms_m": a.rms_m,
            "sigma": a.sigma(),
            "angles_rad": self.angles_rad.tolist(),
            "measurements": [m.to_dict() for m in self.measurements],
            "residuals_m": a.residuals_m.tolist(),
            "base2table": self.base2table.tolist(),
            "ball_height_m": self.ball_height_m,
            "sensor_calibration": self.sensor_calibration,
            "duration_s": self.duration_s,
            "sweeps": self.sweeps,
        }


def direction_cov(axis: TableAxis) -> FloatArray:
    """(3, 3) covariance of ``axis.direction`` from the fit's two tilt parameters (small
    rotations ``w_x, w_y`` about table X and Y move the direction by ``-w_x Y + w_y X``)."""
    from wristscan.calib.table import table_x_axis

    d = axis.direction
    tx = table_x_axis(d)
    ty = np.cross(d, tx)
    J = np.column_stack([-ty, tx])
    return np.asarray(J @ axis.cov[:2, :2] @ J.T)


def tilt_sigma_deg(axis: TableAxis) -> float:
    """One-sigma of ``axis.tilt_deg`` by linear propagation of the two tilt parameters."""
    from wristscan.calib.table import table_x_axis

    # The fit's tilt parameters are small rotations about the table X and Y axes.
    d = axis.direction
    tx = table_x_axis(d)
    ty = np.cross(d, tx)
    h = 1e-7

    def tilt(w: FloatArray) -> float:
        dd = se3.rotvec_to_matrix(w[0] * tx + w[1] * ty) @ d
        return math.degrees(math.acos(min(1.0, abs(float(dd[2])))))

    t0 = tilt(np.zeros(2))
    if t0 < 1e-6:  # at zero tilt the derivative vanishes: use the radial spread instead
        return math.degrees(math.sqrt(float(np.trace(axis.cov[:2, :2])) / 2.0))
    g = np.array([(tilt(np.array([h, 0.0])) - t0) / h, (tilt(np.array([0.0, h])) - t0) / h])
    return float(math.sqrt(max(float(g @ axis.cov[:2, :2] @ g), 0.0)))


def _predict(centres: list[FloatArray], angles: list[float], theta: float) -> FloatArray:
    """Where the ball should be at ``theta`` from what was measured so far."""
    if len(centres) == 1:
        return centres[0]
    if len(centres) >= 3:
        try:
            axis = fit_table_axis(np.stack(centres), np.asarray(angles), min_span_rad=1e-3)
            table2base = se3.invert(axis.base2table())
            ball = np.append(axis.ball_in_part, 1.0)
            return np.asarray(
                (table2base @ table_rotation(theta, axis.encoder_offset_rad) @ ball)[:3]
            )
        except ValueError as exc:
            log.debug("no circle yet (%s): extrapolating", exc)
    # Two points (or a failed circle): straight extrapolation along the last chord.
    c1, c2 = centres[-2], centres[-1]
    # Encoder angles may wrap between readings: compare them modulo a turn.
    d21 = math.remainder(angles[-1] - angles[-2], 2 * math.pi)
    step = math.remainder(theta - angles[-1], 2 * math.pi) / d21 if d21 != 0 else 0.0
    return np.asarray(c2 + step * (c2 - c1))


def _measure_angles(
    acq: Acquisition,
    scanner: BallScanner,
    guess: FloatArray,
    opts: TableOptions,
    report: StepReport,
) -> tuple[list[BallMeasurement], list[float]]:
    """Turn the table through ``opts.plan`` from where it stands and measure the ball at every
    angle: one measurement per angle and its encoder angle, in measuring order."""
    table = acq.require_table("the table calibration turns it")
    theta0 = float(table.angle())
    plan = opts.plan(theta0)
    total = len(plan) + 1
    centres: list[FloatArray] = []
    angles: list[float] = []
    found: list[BallMeasurement] = []
    for i, target in enumerate(plan):
        if i > 0:
            report(i, total, f"turning the table to {math.degrees(target):.1f} deg")
            table.move_to(target, wait=True)
            time.sleep(opts.settle_s)
        theta = float(table.angle())
        expected = guess if i == 0 else _predict(centres, angles, theta)
        margin = opts.search_margin_m if len(centres) < 3 else opts.margin_m
        report(i, total, f"sweeping over the ball at {math.degrees(theta):.1f} deg")
        ball = scanner.locate(
            expected,
            speed_m_s=opts.scan_speed_m_s,
            margin_m=margin,
            recentre_tol_m=opts.recentre_tol_m,
            seed=i,
            strict_clock=False,
        )
        ball = dataclasses.replace(ball, table_angle_rad=theta)
        log.info(
            "table %.2f deg: ball at %s m (rms %.1f um, %d points)",
            math.degrees(theta),
            np.round(ball.centre, 5).tolist(),
            ball.rms_m * 1e6,
            ball.n_points,
        )
        found.append(ball)
        centres.append(ball.centre)
        angles.append(theta)
    return found, angles


def calibrate_table(
    cfg: Config,
    options: TableOptions | None = None,
    *,
    confirmed: bool = False,
    progress: Progress | None = None,
    acquisition: Acquisition | None = None,
) -> TableResult:
    """Run the table procedure on the devices of ``cfg`` (see the module docstring).
    ``acquisition``: an already built, unopened one (tests, benchmarks); default: one on the
    devices of ``cfg`` with the points in the base frame.

    Raises :class:`MotionNotConfirmed` before anything moves (motion not enabled or not
    confirmed), :class:`ProcedureError` when the configuration lacks a table or the sensor
    calibration, :class:`ProcedureAborted` when the run stopped part way.
    """
    opts = options or TableOptions()
    require_motion(cfg, confirmed)
    if not cfg.table_enabled:
        raise ProcedureError(f"{cfg.source}: no enabled [table] section: nothing to calibrate")
    calib = load_sensor_calibration(cfg)
    s2f = np.asarray(calib.transform, dtype=np.float64)
    t_start = time.monotonic()
    report = stage_reporter(progress, "table")
    report(0, len(opts.plan(0.0)) + 2, "connecting, waiting for paired profiles")

    with procedure_acquisition(cfg, acquisition) as acq:
        with guarded_motion(acq, "table calibration"):
            scanner, guess = ball_scanner(acq, s2f, opts)
            found, angles = _measure_angles(acq, scanner, guess, opts, report)
            centres = [m.centre for m in found]
            # Leave the sensor where it can be taken out: back above the last ball position.
            scanner.move_to(centres[-1], 0.0)
        total = len(found) + 1
        report(len(found), total, "fitting the table axis")
        try:
            axis = fit_table_axis(np.stack(centres), np.asarray(angles))
        except ValueError as exc:
            raise ProcedureError(f"table axis fit failed: {exc}") from None
        report(total, total, "done")
        return TableResult(
            axis=axis,
            measurements=tuple(found),
            angles_rad=np.asarray(angles),
            ball_height_m=opts.ball_height_m,
            tilt_sigma_deg=tilt_sigma_deg(axis),
            sensor_calibration=str(cfg.calibration.file),
            duration_s=time.monotonic() - t_start,
            sweeps=scanner.sweeps,
            options=opts,
        )


def table_calibration(result: TableResult, cfg: Config) -> Calibration:
    """The ``kind = "table"`` calibration file content of ``result``."""
    robot_id, sensor_id = identities(cfg)
    a = result.axis
    names = tuple(COV_ORDER)  # the names carry their units
    per_angle = np.linalg.norm(a.residuals_m, axis=1)
    params = {
        "encoder_offset_rad": a.encoder_offset_rad,
        "axis_direction_x": float(a.direction[0]),
        "axis_direction_y": float(a.direction[1]),
        "axis_direction_z": float(a.direction[2]),
        "axis_point_x_m": float(a.point[0]),
        "axis_point_y_m": float(a.point[1]),
        "axis_point_z_m": float(a.point[2]),
        "tilt_deg": a.tilt_deg,
        "tilt_sigma_deg": result.tilt_sigma_deg,
        "ball_circle_radius_m": a.radius_m,
        "ball_height_m": result.ball_height_m,
        "n_angles": float(a.n_angles),
    }
    return Calibration(
        kind="table",
        transform=result.base2table,
        robot=robot_id,
        sensor=sensor_id,
        method="ball on the table at several angles, circle fit (wristscan calibrate table)",
        residuals=Residuals(float(np.sqrt(np.mean(per_angle**2))), tuple(per_angle.tolist())),
        covariance=0.5 * (np.asarray(a.cov) + np.asarray(a.cov).T),
        covariance_parameters=names,
        parameters=params,
        notes=(
            "table frame: origin on the axis at the ball-centre plane minus ball_height_m, Z "
            "along the axis; part2table = Rz(encoder angle + encoder_offset_rad); sensor "
            f"calibration used: {result.sensor_calibration}"
        ),
    )
