"""Rotary-table calibration procedure (``wristscan calibrate table``), and the ball-scanning
machinery it shares with the latency procedure (:mod:`.calib_latency`).

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
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import se3
from wristscan.calib.sphere import fit_sphere
from wristscan.calib.table import COV_ORDER, TableAxis, fit_table_axis, table_rotation
from wristscan.daemon.config import Config
from wristscan.daemon.io.atomic import write_atomic
from wristscan.daemon.io.calibfile import Calibration, Residuals, identities
from wristscan.daemon.procedure.errors import (
    BallNotFound,
    MotionNotConfirmed,
    ProcedureAborted,
    ProcedureError,
)
from wristscan.daemon.procedure.in_force import (
    calibration_in_force,
    load_sensor_calibration,
    procedure_acquisition,
    procedure_config,
)
from wristscan.daemon.procedure.motion import (
    clock_epochs,
    guarded_motion,
    require_motion,
    wait_until_pairing,
)

if TYPE_CHECKING:
    from wristscan.daemon.procedure.acquisition import Acquisition, Sweep
__all__ = [
    "BallMeasurement",
    "BallNotFound",
    "BallOptions",
    "BallScanner",
    "MotionNotConfirmed",
    "ProcedureAborted",
    "ProcedureError",
    "Progress",
    "TableOptions",
    "TableResult",
    "ball_from_sweep",
    "ball_scanner",
    "calibrate_table",
    "calibration_in_force",
    "direction_cov",
    "guarded_motion",
    "identities",
    "load_sensor_calibration",
    "no_progress",
    "procedure_acquisition",
    "procedure_config",
    "require_motion",
    "residual_components",
    "table_calibration",
    "table_report",
    "tilt_sigma_deg",
    "wait_until_pairing",
    "write_json_atomic",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

Progress = Callable[[int, int, str], None]
"""Progress callback: ``(steps done, steps in total, what happens now)``."""


def no_progress(done: int, total: int, text: str) -> None:
    """The :data:`Progress` callback of a caller that does not follow the progress."""


_MIN_BALL_POINTS = 200
_SWEEP_TRIES = 3
_RMS_OUTLIER = 3.0
"""A sweep whose sphere-fit rms exceeds this many times the typical one is repeated."""


# --------------------------------------------------------------------------------------------
# One ball seen by one sweep


@dataclass(frozen=True)
class BallMeasurement:
    """A ball centre from one sweep (base frame, SI units)."""

    centre: FloatArray
    """(3,) fitted centre (m)."""
    cov: FloatArray
    """(3, 3) covariance of the centre from the fit (m^2): sensor noise only."""
    rms_m: float
    """RMS residual of the sphere fit over its inliers (m)."""
    n_points: int
    """Points on the ball (fit inliers)."""
    n_profiles: int
    """Profiles with points on the ball."""
    velocity_m_s: FloatArray
    """(3,) mean velocity of the sensor while it saw the ball (m/s)."""
    speed_spread: float
    """Relative spread (std / mean) of the sensor speed while it saw the ball."""
    t_mid_ns: int
    """Middle of the profiles that saw the ball (host monotonic ns)."""
    table_angle_rad: float | None = None
    """Encoder angle of the table during the sweep (table procedure)."""
    rescans: int = 0
    """Sweeps repeated to centre the ball or after a clock restart."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "centre_m": self.centre.tolist(),
            "sigma_m": np.sqrt(np.diag(self.cov)).tolist(),
            "rms_m": self.rms_m,
            "n_points": self.n_points,
            "n_profiles": self.n_profiles,
            "velocity_m_s": self.velocity_m_s.tolist(),
            "speed_spread": self.speed_spread,
            "table_angle_rad": self.table_angle_rad,
            "rescans": self.rescans,
        }


def ball_from_sweep(
    sweep: Sweep,
    sensor2flange: ArrayLike,
    radius_m: float,
    *,
    max_points: int = 10_000,
    seed: int = 0,
) -> BallMeasurement:
    """Fit the ball (known ``radius_m``) to the points of ``sweep`` in the base frame.

    At most ``max_points`` points (a seeded random subset) go into the fit: the centre is then
    already far more precise than the robot. Raises :class:`BallNotFound` when too few points
    lie on a sphere of that radius.
    """
    if sweep.n_profiles == 0:
        raise ProcedureError(
            "no profile of the sweep was paired with a robot pose (the synchroniser dropped "
            "them: wristscan run -v shows why)"
        )
    m = sweep.valid
    n_valid = int(m.sum())
    if n_valid < _MIN_BALL_POINTS:
        raise BallNotFound(f"the sweep's {sweep.n_profiles} profiles hold {n_valid} valid points")
    s2f = np.asarray(sensor2flange, dtype=np.float64)
    s2b = sweep.flange2base @ s2f  # (P, 4, 4)
    prof = sweep.profile_index[m]
    y, z = sweep.y[m], sweep.z[m]
    if n_valid > max_points:
        keep = np.sort(np.random.default_rng(seed).choice(n_valid, max_points, replace=False))
        prof, y, z = prof[keep], y[keep], z[keep]
    # The laser plane is the sensor's Y-Z plane: point (0, y, z).
    R = s2b[prof, :3, :3]
    pts = R[:, :, 1] * y[:, None] + R[:, :, 2] * z[:, None] + s2b[prof, :3, 3]
    try:
        fit = fit_sphere(pts, radius=radius_m)
    except ValueError as exc:
        raise BallNotFound(f"no sphere of radius {radius_m * 1e3:.2f} mm fits: {exc}") from None
    if fit.n_inliers < _MIN_BALL_POINTS:
        raise BallNotFound(f"only {fit.n_inliers} points lie on the ball")
    # Velocity: least-squares slope of the sensor position over the profiles on the ball,
    # weighted by their points (pure translation: every point moves with the sensor).
    counts = np.bincount(prof[fit.inliers], minlength=sweep.n_profiles).astype(np.float64)
    on = np.flatnonzero(counts > 0)
    w = counts[on]
    t = (sweep.exposure_ns[on] - sweep.exposure_ns[on[0]]).astype(np.float64) * 1e-9
    p = s2b[on, :3, 3]
    tm = float(w @ t / w.sum())
    pm = (w @ p) / w.sum()
    stt = float(w @ (t - tm) ** 2)
    v = (w @ ((t - tm)[:, None] * (p - pm))) / stt if stt > 0 else np.zeros(3)
    spread = 0.0
    if on.size >= 3:
        dt = np.diff(t)
        ok = dt > 0
        speeds = np.linalg.norm(np.diff(p, axis=0)[ok], axis=1) / dt[ok]
        mean = float(np.mean(speeds)) if speeds.size else 0.0
        spread = float(np.std(speeds) / mean) if mean > 0 else 0.0
    return BallMeasurement(
        centre=np.asarray(fit.centre, dtype=np.float64),
        cov=np.asarray(fit.cov_centre, dtype=np.float64),
        rms_m=float(fit.rms),
        n_points=int(fit.n_inliers),
        n_profiles=int(on.size),
        velocity_m_s=np.asarray(v, dtype=np.float64),
        speed_spread=spread,
        t_mid_ns=int(sweep.exposure_ns[on[0]]) + round(tm * 1e9),
    )


# --------------------------------------------------------------------------------------------
# Moving the sensor over a ball


def _dropped(stats: dict[str, Any]) -> int:
    """Profiles the synchroniser dropped so far (all reasons)."""
    return int(sum(stats.get("dropped", {}).values()))


class BallScanner:
    """Sweeps of the sensor along its own X axis over a ball, with a fixed sensor orientation.

    Scan coordinates: the sensor at offset ``s`` (m) along its X axis sees the ball centre ``c``
    at ``(-s, 0, standoff_m)`` in its own frame (the laser line's middle, ``standoff_m`` away),
    so ``s = 0`` puts the laser plane through the centre.
    """

    def __init__(
        self,
        acq: Acquisition,
        sensor2flange: ArrayLike,
        *,
        radius_m: float,
        standoff_m: float,
        orientation: ArrayLike | None = None,
        travel_speed_m_s: float = 0.1,
        accel_m_s2: float | None = None,
        max_points: int = 10_000,
    ) -> None:
        self.acq = acq
        self.robot = acq.robot
        self.s2f = np.asarray(sensor2flange, dtype=np.float64)
        self.f2s = se3.invert(self.s2f)
        self.radius_m = float(radius_m)
        self.standoff_m = float(standoff_m)
        r = acq.cfg.robot
        self.max_speed_m_s = float(r.max_speed_m_s)
        self.accel_m_s2 = float(min(accel_m_s2 or r.max_accel_m_s2, r.max_accel_m_s2))
        self.travel_speed_m_s = min(float(travel_speed_m_s), self.max_speed_m_s)
        self.max_points = max_points
        self.tcp2flange = se3.pose_to_matrix(np.asarray(self.robot.tcp_offset(), dtype=float))
        self.flange2tcp = se3.invert(self.tcp2flange)
        if orientation is None:
            orientation = self.current_sensor2base()[:3, :3]
        self.R = np.asarray(orientation, dtype=np.float64)
        self.sweeps = 0
        self._rms: list[float] = []

    # --- geometry ---------------------------------------------------------------------------
    def current_sensor2base(self) -> FloatArray:
        """The sensor pose now, from the controller's TCP pose."""
        state = self.robot.latest_state()
        if state is None:
            raise ProcedureError("the robot sends no state")
        tcp2base = se3.pose_to_matrix(np.asarray(state.tcp_pose, dtype=np.float64))
        return np.asarray(tcp2base @ self.flange2tcp @ self.s2f)

    def ball_in_front(self) -> FloatArray:
        """Where the ball is assumed when not given: ``standoff_m`` along the sensor's +Z."""
        s2b = self.current_sensor2base()
        return np.asarray(s2b[:3, 3] + self.standoff_m * s2b[:3, 2])

    @property
    def sweep_axis(self) -> FloatArray:
        """Unit sweep direction in the base frame (the sensor's X axis)."""
        return np.asarray(self.R[:, 0])

    def sensor_pose(self, centre: ArrayLike, s: float) -> FloatArray:
        c = np.asarray(centre, dtype=np.float64)
        return se3.make(self.R, c - self.R @ np.array([-s, 0.0, self.standoff_m]))

    def tcp_pose(self, sensor2base: FloatArray) -> FloatArray:
        """UR pose of the TCP that puts the sensor at ``sensor2base``."""
        return se3.matrix_to_pose(sensor2base @ self.f2s @ self.tcp2flange)

    def in_scan_frame(self, point: ArrayLike, centre: ArrayLike) -> FloatArray:
        """``point - centre`` along the sweep, the laser line and the depth (m)."""
        return np.asarray(self.R.T @ (np.asarray(point, dtype=np.float64) - np.asarray(centre)))

    def ramp_m(self, speed_m_s: float) -> float:
        """Distance to reach ``speed_m_s`` at the acceleration used (m)."""
        return speed_m_s * speed_m_s / (2.0 * self.accel_m_s2)

    # --- motion ---------------------------------------------------------------------------
    def move_to(self, centre: ArrayLike, s: float) -> None:
        """Travel (not recorded) to scan offset ``s`` of the ball at ``centre``."""
        self.robot.move_l(
            self.tcp_pose(self.sensor_pose(centre, s)), self.travel_speed_m_s, self.accel_m_s2
        )

    def sweep(self, centre: ArrayLike, s_from: float, s_to: float, speed_m_s: float) -> Sweep:
        """Go to ``s_from`` and record the move to ``s_to`` at ``speed_m_s`` (m/s)."""
        speed = min(float(speed_m_s), self.max_speed_m_s)
        self.move_to(centre, s_from)
        target = self.tcp_pose(self.sensor_pose(centre, s_to))
        with self.acq.record() as rec:
            self.robot.move_l(target, speed, self.accel_m_s2)
        self.sweeps += 1
        return rec.result()

    def measure(
        self,
        centre: ArrayLike,
        *,
        speed_m_s: float,
        margin_m: float,
        direction: int = 1,
        seed: int = 0,
        strict_clock: bool = True,
    ) -> BallMeasurement:
        """One sweep over the ball expected at ``centre``: from ``-L`` to ``+L`` (``direction``
        +1) or back, ``L = R + margin_m`` plus the distance to reach the speed.

        A sweep during which a clock fit of the synchroniser restarted may hold profiles paired
        milliseconds off: it is repeated (twice at most); then ``strict_clock`` raises
        :class:`ProcedureError`, otherwise the last sweep is used (a timing error moves the
        ball along the sweep only, which the table axis does not feel)."""
        half = self.radius_m + margin_m + self.ramp_m(speed_m_s) + 0.002
        s0, s1 = (-half, half) if direction > 0 else (half, -half)
        for attempt in range(_SWEEP_TRIES):
            last = attempt + 1 == _SWEEP_TRIES
            stats = self.acq.stats()
            epochs, dropped = clock_epochs(stats), _dropped(stats)
            sweep = self.sweep(centre, s0, s1, speed_m_s)
            stats = self.acq.stats()
            dropped = _dropped(stats) - dropped
            if clock_epochs(stats) != epochs:
                if not last:
                    log.warning("a clock fit restarted during a sweep: sweeping again")
                    continue
                if strict_clock:
                    raise ProcedureError(
                        f"the synchroniser's clock fits restarted during {_SWEEP_TRIES} sweeps "
                        "in a row: the host is overloaded or a device clock jumps (wristscan "
                        "run -v shows the clock messages)"
                    )
                log.warning("clock fits keep restarting: using the sweep anyway")
            try:
                ball = ball_from_sweep(
                    sweep, self.s2f, self.radius_m, max_points=self.max_points, seed=seed
                )
            except ProcedureError as exc:
                if not dropped:
                    raise
                if not last:
                    log.warning(
                        "%s; the synchroniser dropped %d profiles: sweeping again", exc, dropped
                    )
                    continue
                raise type(exc)(
                    f"{exc}; the synchroniser dropped {dropped} profiles during the sweep "
                    "(host overloaded, or the robot stream stalls)"
                ) from None
            typical = float(np.median(self._rms)) if len(self._rms) >= 2 else math.inf
            if ball.rms_m > _RMS_OUTLIER * typical and not last:
                # A distorted ball: the poses of part of the sweep were wrong (a stalled stream).
                log.warning(
                    "sphere fit rms %.1f um against %.1f um typical: sweeping again",
                    ball.rms_m * 1e6,
                    typical * 1e6,
                )
                continue
            self._rms.append(ball.rms_m)
            return dataclasses.replace(ball, rescans=attempt)
        raise AssertionError("unreachable")

    def locate(
        self,
        guess: ArrayLike,
        *,
        speed_m_s: float,
        margin_m: float,
        recentre_tol_m: float,
        seed: int = 0,
        strict_clock: bool = True,
    ) -> BallMeasurement:
        """Measure the ball near ``guess``; sweep again centred on it while it was found off the
        sweep's middle by more than ``recentre_tol_m`` (at most twice)."""
        centre = np.asarray(guess, dtype=np.float64)
        rescans = 0
        try:
            ball = self.measure(
                centre,
                speed_m_s=speed_m_s,
                margin_m=margin_m,
                seed=seed,
                strict_clock=strict_clock,
            )
        except BallNotFound as exc:
            raise BallNotFound(
                f"no ball near {np.round(centre, 4).tolist()} m ({exc}): place the sensor about "
                f"{self.standoff_m * 1e3:.0f} mm above the ball, or give its position"
            ) from None
        for _ in range(2):
            off = self.in_scan_frame(ball.centre, centre)
            if np.all(np.abs(off[:2]) <= recentre_tol_m):
                break
            log.info("ball %.1f mm off the sweep's middle: sweeping centred on it", 1e3 * off[0])
            centre = ball.centre
            rescans += ball.rescans + 1
            ball = self.measure(
                centre,
                speed_m_s=speed_m_s,
                margin_m=max(recentre_tol_m, 0.003),
                seed=seed,
                strict_clock=strict_clock,
            )
        return dataclasses.replace(ball, rescans=rescans + ball.rescans)


class BallOptions(Protocol):
    """The settings of a ball procedure that :func:`ball_scanner` reads (SI units)."""

    @property
    def ball_guess_m(self) -> tuple[float, float, float] | None: ...
    @property
    def ball_radius_m(self) -> float: ...
    @property
    def standoff_m(self) -> float: ...
    @property
    def travel_speed_m_s(self) -> float: ...


def ball_scanner(
    acq: Acquisition,
    sensor2flange: ArrayLike,
    opts: BallOptions,
    accel_m_s2: float | None = None,
) -> tuple[BallScanner, FloatArray]:
    """A :class:`BallScanner` with the settings of ``opts``, and where the ball is looked for
    first: ``opts.ball_guess_m`` or, when None, ``standoff_m`` in front of the sensor as it
    stands."""
    scanner = BallScanner(
        acq,
        sensor2flange,
        radius_m=opts.ball_radius_m,
        standoff_m=opts.standoff_m,
        travel_speed_m_s=opts.travel_speed_m_s,
        accel_m_s2=accel_m_s2,
    )
    if opts.ball_guess_m is not None:
        return scanner, np.asarray(opts.ball_guess_m, dtype=np.float64)
    return scanner, scanner.ball_in_front()


# --------------------------------------------------------------------------------------------
# The table procedure


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
    report = progress or no_progress
    report(0, len(opts.plan(0.0)) + 2, "connecting, waiting for paired profiles")

    with procedure_acquisition(cfg, acquisition) as acq:
        with guarded_motion(acq, "table calibration"):
            scanner, guess = ball_scanner(acq, s2f, opts)
            theta0 = float(acq.table.angle())
            plan = opts.plan(theta0)
            total = len(plan) + 1
            centres: list[FloatArray] = []
            angles: list[float] = []
            found: list[BallMeasurement] = []
            for i, target in enumerate(plan):
                if i > 0:
                    report(i, total, f"turning the table to {math.degrees(target):.1f} deg")
                    acq.table.move_to(target, wait=True)
                    time.sleep(opts.settle_s)
                theta = float(acq.table.angle())
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
            # Leave the sensor where it can be taken out: back above the last ball position.
            scanner.move_to(centres[-1], 0.0)
        report(len(plan), total, "fitting the table axis")
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


# --------------------------------------------------------------------------------------------
# Report


def _fmt(value: float, sigma: float, unit: str) -> tuple[str, str, str]:
    """Value, one-sigma and unit for the report, in convenient units."""
    if unit == "m":
        return f"{value * 1e3:.4f}", f"{sigma * 1e3:.4f}", "mm"
    if unit == "rad":
        return f"{value:.6f}", f"{sigma:.6f}", "rad"
    if unit == "1":
        return f"{value:.7f}", f"{sigma:.7f}", ""
    return f"{value:.5f}", f"{sigma:.5f}", unit


def table_report(result: TableResult, subtitle: str = "") -> Any:
    """A :class:`~.report.Report` of ``result``: parameters with their uncertainty, the centres
    and the residuals (figures when matplotlib is there)."""
    from wristscan.daemon.io.report import Report, have_matplotlib

    a = result.axis
    rep = Report("Rotary table calibration", subtitle)
    rep.section(
        "Result",
        f"Axis from the ball centre measured at {a.n_angles} table angles "
        f"({result.sweeps} sweeps, {result.duration_s:.0f} s). The uncertainties are one sigma "
        "from the residuals of the circle fit (they include the robot's repeatability).",
    )
    rows = [[name, *_fmt(v, s, unit)] for name, v, s, unit in result.parameters()]
    rep.table(["parameter", "value", "1 sigma", "unit"], rows)
    rep.text(
        f"axis direction (base frame): [{a.direction[0]:.7f}, {a.direction[1]:.7f}, "
        f"{a.direction[2]:.7f}]\nbase2table:\n"
        + np.array2string(result.base2table, precision=6, suppress_small=True),
        preformatted=True,
    )
    rep.section(
        "Measurements",
        f"RMS distance between measured and modelled centres: {a.rms_m * 1e6:.1f} um. "
        "Residuals: radial (away from the axis), tangential (direction of turning), axial.",
    )
    res_local = residual_components(result)
    rows = []
    for m, th, r in zip(result.measurements, result.angles_rad, res_local, strict=True):
        rows.append(
            [
                f"{math.degrees(th):.3f}",
                *(f"{1e3 * v:.4f}" for v in m.centre),
                *(f"{1e6 * v:.1f}" for v in r),
                str(m.n_points),
                str(m.rescans),
            ]
        )
    rep.table(
        [
            "angle (deg)",
            "x (mm)",
            "y (mm)",
            "z (mm)",
            "radial (um)",
            "tangential (um)",
            "axial (um)",
            "points",
            "rescans",
        ],
        rows,
    )
    if have_matplotlib():
        _table_figures(rep, result, res_local)
    else:
        rep.text("(figures need matplotlib: pip install 'wristscan[plot]')")
    return rep


def residual_components(result: TableResult) -> FloatArray:
    """(k, 3) circle-fit residuals as radial (away from the axis), tangential (direction of
    turning) and axial components (m)."""
    a = result.axis
    res = a.residuals_m
    model = result.centres - res
    d = a.direction
    rel = model - a.point
    radial = rel - np.outer(rel @ d, d)
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    tangential = np.cross(d, radial)
    return np.stack(
        [np.sum(res * radial, axis=1), np.sum(res * tangential, axis=1), res @ d], axis=1
    )


def _table_figures(rep: Any, result: TableResult, res_local: FloatArray) -> None:
    from wristscan.daemon.io.report import new_figure

    a = result.axis
    b2t = a.base2table()
    C = result.centres
    local = C @ b2t[:3, :3].T + b2t[:3, 3]  # centres in the table frame (origin on the axis)
    fig, ax = new_figure(1, 2, figsize=(10.0, 4.4))
    t = np.linspace(0, 2 * np.pi, 361)
    ax[0].plot(1e3 * a.radius_m * np.cos(t), 1e3 * a.radius_m * np.sin(t), lw=0.8, label="fit")
    ax[0].plot(1e3 * local[:, 0], 1e3 * local[:, 1], "o", label="ball centres")
    for (px, py, _), th in zip(local, result.angles_rad, strict=True):
        ax[0].annotate(f"{math.degrees(th):.0f}", (1e3 * px, 1e3 * py), fontsize=7)
    ax[0].plot([0], [0], "+k", ms=10, label="axis")
    ax[0].set_aspect("equal")
    ax[0].set_xlabel("table X (mm)")
    ax[0].set_ylabel("table Y (mm)")
    ax[0].legend(fontsize=8)
    ax[0].set_title("Ball centres seen along the axis")
    deg = np.degrees(result.angles_rad)
    labels = ("radial", "tangential", "axial")
    for j in range(3):
        ax[1].plot(deg, 1e6 * res_local[:, j], "o-", label=labels[j])
    ax[1].axhline(0, color="k", lw=0.5)
    ax[1].set_xlabel("table angle (deg)")
    ax[1].set_ylabel("residual (um)")
    ax[1].legend(fontsize=8)
    ax[1].set_title("Circle-fit residuals")
    rep.figure(fig, "Ball centres in the table frame and the residuals of the circle fit")


# TODO(lead): the kit's old homes, until every importer uses wristscan.daemon.procedure.
write_json_atomic = write_atomic
