"""The ball-scanning machinery shared by the table and latency procedures
(:mod:`.table`, :mod:`.latency`): sweeping the sensor along its own X axis over a tooling ball
and fitting a sphere of the known radius to what it saw.

Both procedures need the same thing from a sweep (a ball centre in the base frame, with how
fast and how evenly the sensor moved while it saw the ball), and the same care around it (a
sweep during which a clock fit restarted or the synchroniser dropped profiles is repeated; a
ball found off the sweep's middle is swept again centred on it), so it lives here once.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import se3
from wristscan.calib.sphere import fit_sphere
from wristscan.daemon.procedure.errors import BallNotFound, ProcedureError
from wristscan.daemon.procedure.motion import clock_epochs

if TYPE_CHECKING:
    from wristscan.daemon.procedure.acquisition import Acquisition, Sweep

__all__ = [
    "BallMeasurement",
    "BallOptions",
    "BallScanner",
    "ball_from_sweep",
    "ball_scanner",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

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
    if not fit.plausible:
        raise BallNotFound(f"the points do not fit the ball: {fit.why}")
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
