"""Sensor latency procedure (``wristscan calibrate latency``).

The sensor sweeps over a fixed tooling ball along its own X axis, forward and backward, at
several speeds (default 25, 50 and 100 mm/s, capped by ``[robot] max_speed_m_s``). Each sweep is
paired by the synchroniser with the latency in force (``[sensor] latency_s``) and gives one ball
centre in the base frame (sphere fit of the known radius, through the sensor calibration in
force). If the true latency exceeds the configured one by ``dt``, every point of a sweep lies
displaced by the sensor's motion during ``dt``: the centre seen by a sweep at velocity ``v`` is
``p* + v dt``. :func:`wristscan.calib.latency.estimate_latency` solves for ``p*`` and ``dt``
over all sweeps; the latency to configure is ``latency_s + dt``.

* The velocity of each sweep is measured, not assumed: the least-squares slope of the sensor
  position over the profiles that saw the ball (robot poses at the paired instants).
* Each sweep reaches its speed before the ball (the run-up is ``v^2 / 2a`` plus a margin), so
  the ball is seen at constant velocity; the speed spread over the ball is reported.
* A sweep during which a clock fit of the synchroniser restarted is repeated (its pairing may be
  off by milliseconds).
* The repeatability of the robot (its true position wanders by some micrometres between sweeps)
  is what limits the result; ``repeats`` pairs of sweeps per speed average it down. The
  uncertainty comes from the residuals of the fit, so it includes it.

The result is a correction that the operator puts into the configuration (``latency_s = ...``
under ``[sensor]``); the procedure never rewrites the configuration. Safety as for the table
procedure (:mod:`.table`); the ball scanning is shared with it (:mod:`.ball`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib.latency import LatencyEstimate, estimate_latency
from wristscan.daemon.calibrate.ball import BallMeasurement, BallScanner, ball_scanner
from wristscan.daemon.config import Config
from wristscan.daemon.io.atomic import write_atomic
from wristscan.daemon.procedure.errors import ProcedureError
from wristscan.daemon.procedure.in_force import load_sensor_calibration, procedure_acquisition
from wristscan.daemon.procedure.motion import guarded_motion, require_motion
from wristscan.daemon.procedure.progress import Progress, StepReport, stage_reporter

if TYPE_CHECKING:
    from wristscan.daemon.procedure.acquisition import Acquisition
__all__ = [
    "RESULT_FORMAT",
    "LatencyOptions",
    "LatencyResult",
    "LatencySweep",
    "calibrate_latency",
    "latency_report",
    "outlier_sweeps",
    "write_latency_result",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

RESULT_FORMAT = "wristscan-latency"


@dataclass(frozen=True)
class LatencyOptions:
    """Settings of :func:`calibrate_latency` (SI units)."""

    speeds_m_s: tuple[float, ...] = (0.025, 0.05, 0.1)
    """Sweep speeds; each is capped by ``[robot] max_speed_m_s``."""
    repeats: int = 1
    """Forward + backward pairs per speed."""
    ball_guess_m: tuple[float, float, float] | None = None
    """Approximate ball centre (base frame); None: ``standoff_m`` in front of the sensor."""
    ball_radius_m: float = 0.0127
    standoff_m: float = 0.10
    margin_m: float = 0.004
    """Sweep length beyond the ball on each side (after the run-up)."""
    locate_speed_m_s: float = 0.02
    search_margin_m: float = 0.02
    recentre_tol_m: float = 0.002
    travel_speed_m_s: float = 0.1
    accel_m_s2: float | None = None
    """Acceleration of the sweeps (None: ``[robot] max_accel_m_s2``)."""

    def __post_init__(self) -> None:
        if not self.speeds_m_s or any(v <= 0 for v in self.speeds_m_s):
            raise ValueError("speeds_m_s: one or more speeds > 0 needed")
        if self.repeats < 1:
            raise ValueError("repeats must be >= 1")
        if self.ball_radius_m <= 0 or self.standoff_m <= 0:
            raise ValueError("ball_radius_m and standoff_m must be > 0")


@dataclass(frozen=True)
class LatencySweep:
    """One recorded sweep: its commanded speed and direction, and what it saw."""

    speed_m_s: float
    direction: int
    """+1 forward (along the sensor's +X), -1 backward."""
    ball: BallMeasurement

    def to_dict(self) -> dict[str, Any]:
        return {"speed_m_s": self.speed_m_s, "direction": self.direction, **self.ball.to_dict()}


@dataclass(frozen=True)
class LatencyResult:
    """What :func:`calibrate_latency` found (seconds, metres)."""

    configured_latency_s: float
    """``[sensor] latency_s`` the sweeps were paired with."""
    estimate: LatencyEstimate
    """The correction ``dt`` (``latency_s``) and its standard deviation (``std_s``)."""
    sweeps: tuple[LatencySweep, ...]
    ball_centre_m: FloatArray
    """(3,) ball centre corrected for the latency (base frame)."""
    sweep_axis: FloatArray
    """(3,) unit direction of the forward sweeps (base frame)."""
    speed_cap_m_s: float
    sensor_calibration: str
    duration_s: float
    config_source: str = ""
    created_utc: datetime = field(default_factory=lambda: datetime.now(UTC))

    @property
    def latency_s(self) -> float:
        """The latency to configure: configured plus the correction."""
        return self.configured_latency_s + self.estimate.latency_s

    @property
    def std_s(self) -> float:
        return self.estimate.std_s

    def toml_line(self) -> str:
        """The line to put under ``[sensor]`` (microsecond resolution)."""
        return f"latency_s = {max(self.latency_s, 0.0):.6f}"

    def along_motion_m(self) -> FloatArray:
        """(n,) apparent ball position of each sweep along the forward direction, relative to
        the corrected centre (m): ``~ v dt`` with ``v`` the signed speed."""
        c = np.stack([s.ball.centre for s in self.sweeps])
        return np.asarray((c - self.ball_centre_m) @ self.sweep_axis)

    def signed_speeds_m_s(self) -> FloatArray:
        """(n,) measured velocity of each sweep along the forward direction (m/s)."""
        v = np.stack([s.ball.velocity_m_s for s in self.sweeps])
        return np.asarray(v @ self.sweep_axis)

    def to_dict(self) -> dict[str, Any]:
        e = self.estimate
        return {
            "format": RESULT_FORMAT,
            "version": 1,
            "latency_s": self.latency_s,
            "std_s": e.std_s,
            "configured_latency_s": self.configured_latency_s,
            "correction_s": e.latency_s,
            "toml": f"[sensor] {self.toml_line()}",
            "rms_m": e.rms_m,
            "n_sweeps": e.n_sweeps,
            "ball_centre_m": self.ball_centre_m.tolist(),
            "sweep_axis": self.sweep_axis.tolist(),
            "speed_cap_m_s": self.speed_cap_m_s,
            "sweeps": [s.to_dict() for s in self.sweeps],
            "residuals_m": e.residuals.tolist(),
            "sensor_calibration": self.sensor_calibration,
            "config": self.config_source,
            "duration_s": self.duration_s,
            "created_utc": self.created_utc.isoformat(timespec="seconds").replace("+00:00", "Z"),
        }


def calibrate_latency(
    cfg: Config,
    options: LatencyOptions | None = None,
    *,
    confirmed: bool = False,
    progress: Progress | None = None,
    acquisition: Acquisition | None = None,
) -> LatencyResult:
    """Run the latency procedure on the devices of ``cfg`` (see the module docstring).
    ``acquisition``: an already built, unopened one (tests, benchmarks); default: one on the
    devices of ``cfg``.

    Raises (all from :mod:`wristscan.daemon.procedure.errors`) :class:`MotionNotConfirmed`
    before anything moves, :class:`ProcedureError` without a sensor calibration or when the
    sweeps cannot separate the latency, :class:`ProcedureAborted` when the run stopped part way.
    """
    opts = options or LatencyOptions()
    require_motion(cfg, confirmed)
    calib = load_sensor_calibration(cfg)
    s2f = np.asarray(calib.transform, dtype=np.float64)
    cap = float(cfg.robot.max_speed_m_s)
    speeds = _capped(opts.speeds_m_s, cap)
    plan = [(v, d) for v in speeds for _ in range(opts.repeats) for d in (1, -1)]
    total = len(plan) + 3
    report = stage_reporter(progress, "latency")
    t_start = time.monotonic()
    report(0, total, "connecting, waiting for paired profiles")

    with procedure_acquisition(cfg, acquisition) as acq:
        with guarded_motion(acq, "latency calibration"):
            scanner, guess = ball_scanner(acq, s2f, opts, opts.accel_m_s2)
            report(1, total, "locating the ball")
            first = scanner.locate(
                guess,
                speed_m_s=opts.locate_speed_m_s,
                margin_m=opts.search_margin_m,
                recentre_tol_m=opts.recentre_tol_m,
                strict_clock=False,
            )
            centre = first.centre
            sweeps = _sweep_plan(scanner, centre, plan, opts, report)
            report(len(plan) + 2, total, "fitting the latency")
            est = _fit(sweeps)
            bad = outlier_sweeps(est)
            if bad:
                _sweep_again(scanner, centre, sweeps, bad, est, opts, report)
                est = _fit(sweeps)
                still = outlier_sweeps(est)
                if still:
                    log.warning("sweeps %s stay off the others", [i + 1 for i in still])
            scanner.move_to(centre, 0.0)
        report(total, total, "done")
        return LatencyResult(
            configured_latency_s=float(cfg.sensor.latency_s),
            estimate=est,
            sweeps=tuple(sweeps),
            ball_centre_m=np.asarray(est.feature_position, dtype=np.float64),
            sweep_axis=scanner.sweep_axis,
            speed_cap_m_s=cap,
            sensor_calibration=str(cfg.calibration.file),
            duration_s=time.monotonic() - t_start,
            config_source=cfg.source,
        )


def _sweep_plan(
    scanner: BallScanner,
    centre: FloatArray,
    plan: Sequence[tuple[float, int]],
    opts: LatencyOptions,
    report: StepReport,
) -> list[LatencySweep]:
    """One sweep over the ball at ``centre`` per ``(speed, direction)`` of ``plan``."""
    total = len(plan) + 3
    sweeps: list[LatencySweep] = []
    for i, (v, d) in enumerate(plan):
        way = "forward" if d > 0 else "backward"
        report(2 + i, total, f"sweep {i + 1}/{len(plan)}: {way} at {v * 1e3:.0f} mm/s")
        ball = scanner.measure(centre, speed_m_s=v, margin_m=opts.margin_m, direction=d, seed=i)
        if ball.speed_spread > 0.05:
            log.warning(
                "sweep %d: the speed varied by %.0f %% over the ball (too short a run-up?)",
                i + 1,
                100 * ball.speed_spread,
            )
        sweeps.append(LatencySweep(v, d, ball))
    return sweeps


def _sweep_again(
    scanner: BallScanner,
    centre: FloatArray,
    sweeps: list[LatencySweep],
    bad: Sequence[int],
    est: LatencyEstimate,
    opts: LatencyOptions,
    report: StepReport,
) -> None:
    """Measure the sweeps ``bad`` (indices into ``sweeps``) again, replacing them in place."""
    step = len(sweeps) + 2
    total = len(sweeps) + 3
    for i in bad:
        # One sweep far off the others: its poses were wrong for part of it (a stalled
        # stream, a clock hiccup); measure it again rather than let it pull the fit.
        s = sweeps[i]
        off = float(np.linalg.norm(est.residuals[i])) * 1e6
        report(step, total, f"sweep {i + 1} is {off:.0f} um off: sweeping again")
        ball = scanner.measure(
            centre,
            speed_m_s=s.speed_m_s,
            margin_m=opts.margin_m,
            direction=s.direction,
            seed=1000 + i,
        )
        ball = dataclasses.replace(ball, rescans=s.ball.rescans + ball.rescans + 1)
        sweeps[i] = LatencySweep(s.speed_m_s, s.direction, ball)


def _fit(sweeps: Sequence[LatencySweep]) -> LatencyEstimate:
    P = np.stack([s.ball.centre for s in sweeps])
    V = np.stack([s.ball.velocity_m_s for s in sweeps])
    try:
        return estimate_latency(P, V)
    except ValueError as exc:
        raise ProcedureError(f"latency fit failed: {exc}") from None


def outlier_sweeps(est: LatencyEstimate, k: float = 5.0) -> list[int]:
    """Sweeps whose residual (norm) exceeds ``median + k * robust sigma`` and three times the
    median: one bad sweep among many."""
    r = np.linalg.norm(est.residuals, axis=1)
    if r.shape[0] < 4:
        return []
    med = float(np.median(r))
    sigma = 1.4826 * float(np.median(np.abs(r - med)))
    limit = max(med + k * sigma, 3.0 * med)
    return [int(i) for i in np.flatnonzero(r > limit)]


def _capped(speeds: Sequence[float], cap: float) -> list[float]:
    out = []
    for v in speeds:
        if v > cap:
            log.warning("sweep speed %.3f m/s capped to max_speed_m_s %.3f", v, cap)
        out.append(min(float(v), cap))
    if len(set(out)) < len(out):
        log.warning("speeds coincide after capping: %s m/s", out)
    return out


def write_latency_result(path: str | Path, result: LatencyResult) -> Path:
    """Write the JSON result file atomically (the configuration is never rewritten)."""
    return write_atomic(path, json.dumps(result.to_dict(), indent=2) + "\n")


# --------------------------------------------------------------------------------------------
# Report


def latency_report(result: LatencyResult, subtitle: str = "") -> Any:
    """A :class:`~wristscan.daemon.io.report.Report` of ``result``: the latency with its
    uncertainty, every sweep, and (with matplotlib) the apparent ball position against the
    sweep velocity."""
    from wristscan.daemon.io.report import Report, have_matplotlib

    e = result.estimate
    rep = Report("Sensor latency calibration", subtitle)
    rep.section(
        "Result",
        f"{e.n_sweeps} sweeps over the ball ({result.duration_s:.0f} s). The sweeps were paired "
        f"with the configured latency {result.configured_latency_s * 1e3:.4f} ms; the fit gives "
        "the correction to add. Uncertainties are one sigma from the residuals (they include "
        "the robot's repeatability).",
    )
    c = result.ball_centre_m
    rep.table(
        ["parameter", "value", "1 sigma", "unit"],
        [
            ["sensor latency", f"{result.latency_s * 1e3:.4f}", f"{e.std_s * 1e3:.4f}", "ms"],
            [
                "correction to the configured",
                f"{e.latency_s * 1e3:.4f}",
                f"{e.std_s * 1e3:.4f}",
                "ms",
            ],
            ["ball centre x", f"{c[0] * 1e3:.4f}", "", "mm"],
            ["ball centre y", f"{c[1] * 1e3:.4f}", "", "mm"],
            ["ball centre z", f"{c[2] * 1e3:.4f}", "", "mm"],
            ["RMS residual", f"{e.rms_m * 1e6:.2f}", "", "um"],
        ],
    )
    rep.text(
        "Put this line under [sensor] in the configuration:\n" + result.toml_line(),
        preformatted=True,
    )
    if result.latency_s < 0:
        rep.text(
            "The measured latency is negative: the sensor's timestamps run ahead of the robot's. "
            "Configure latency_s = 0 and the rest as [sync] robot_latency_s."
        )
    rep.section("Sweeps", "Apparent ball position along the forward direction, per sweep.")
    along = result.along_motion_m()
    speeds = result.signed_speeds_m_s()
    rows = []
    for s, a, v, r in zip(result.sweeps, along, speeds, e.residuals, strict=True):
        rows.append(
            [
                f"{s.speed_m_s * 1e3:.0f}",
                "forward" if s.direction > 0 else "backward",
                f"{v * 1e3:.2f}",
                f"{a * 1e6:.2f}",
                f"{float(np.linalg.norm(r)) * 1e6:.2f}",
                f"{100 * s.ball.speed_spread:.1f}",
                str(s.ball.n_points),
                str(s.ball.rescans),
            ]
        )
    rep.table(
        [
            "speed (mm/s)",
            "direction",
            "measured (mm/s)",
            "along motion (um)",
            "residual (um)",
            "speed spread (%)",
            "points",
            "rescans",
        ],
        rows,
    )
    if have_matplotlib():
        _latency_figure(rep, result)
    else:
        rep.text("(figures need matplotlib: pip install 'wristscan[plot]')")
    return rep


def _latency_figure(rep: Any, result: LatencyResult) -> None:
    """The apparent ball position of every sweep against its velocity, with the fitted line."""
    from wristscan.daemon.io.report import new_figure

    e = result.estimate
    along = result.along_motion_m()
    speeds = result.signed_speeds_m_s()
    fig, ax = new_figure(1, 1, figsize=(6.5, 4.2))
    ax.plot(1e3 * speeds, 1e6 * along, "o", label="sweeps")
    vmax = float(np.max(np.abs(speeds))) * 1.1
    vv = np.linspace(-vmax, vmax, 3)
    ax.plot(
        1e3 * vv,
        1e6 * vv * e.latency_s,
        "-",
        label=f"fit: {e.latency_s * 1e3:.3f} +- {e.std_s * 1e3:.3f} ms",
    )
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("sweep velocity along the forward direction (mm/s)")
    ax.set_ylabel("apparent ball position (um)")
    ax.legend(fontsize=8)
    rep.figure(fig, "Apparent ball position against sweep velocity: the slope is the latency")
