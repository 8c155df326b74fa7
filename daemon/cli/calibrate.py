"""``wristscan calibrate ...``: calibration procedures run at the cell.

``calibrate_app`` is the typer group; other modules add their procedures to it (for example
``cmd_calibrate_more.py`` adds ``table`` and ``latency``)::

    from wristscan.daemon.cli.calibrate import calibrate_app
    @calibrate_app.command("table")
    def table(...): ...

Exit codes of every procedure: 0 done, 1 aborted or failed (nothing written; the calibration in
force is unchanged), 2 usage or configuration error (nothing moved).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

import typer

if TYPE_CHECKING:
    from wristscan.daemon.calibrate.sensor import SensorCalibrationResult
    from wristscan.daemon.config import Config
__all__ = ["calibrate_app", "confirm_motion", "fail", "load_config_or_exit", "register"]

calibrate_app = typer.Typer(
    name="calibrate",
    help="Calibration procedures at the cell (sensor2flange with a tooling ball, ...).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


def register(app: typer.Typer) -> None:
    app.add_typer(calibrate_app, name="calibrate")


def fail(message: str, code: int = EXIT_FAILED) -> NoReturn:
    """One line on stderr and the exit code (no traceback)."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


def load_config_or_exit(path: Path) -> Config:
    """The validated configuration, or exit 2 with the loader's message."""
    from wristscan.daemon.config import ConfigError, load_config

    try:
        return load_config(path)
    except ConfigError as exc:
        typer.echo(str(exc), err=True)
        raise typer.Exit(EXIT_USAGE) from None


def confirm_motion(cfg: Config, yes: bool, what: str) -> None:
    """Refuse (exit 2) unless motion is enabled in ``cfg`` and confirmed: ``--yes``, or an answer
    at a terminal. Nothing has moved when this exits."""
    if not cfg.robot.motion_enabled:
        fail(
            f"motion is not enabled in {cfg.source}: set [robot] motion_enabled = true to let "
            "the procedure move the robot",
            EXIT_USAGE,
        )
    if yes:
        return
    if not sys.stdin.isatty():
        fail(f"{what} moves the robot: confirm with --yes (no terminal to ask)", EXIT_USAGE)
    r = cfg.robot
    typer.echo(
        f"{what} will move the robot at {r.host} (TCP speed up to {r.max_speed_m_s * 1e3:g} "
        f"mm/s, inside the workspace box {list(r.workspace_min_m)} .. "
        f"{list(r.workspace_max_m)} m). Keep the emergency stop at hand.",
        err=True,
    )
    if not typer.confirm("Start?", default=False, err=True):
        fail("not confirmed; nothing moved", EXIT_USAGE)


def _mm(value: float | None) -> float | None:
    return None if value is None else value * 1e-3


def _print_result(result: SensorCalibrationResult, out: Path, report: Path | None) -> None:
    import math

    import numpy as np

    from wristscan.calib import se3
    from wristscan.daemon.io.calibfile import ur_pose_text

    j = result.joint
    pose = se3.matrix_to_pose(j.sensor2flange)
    st = j.sigma_translation_m * 1e3
    sr = np.degrees(j.sigma_rotation_rad)
    echo = typer.echo
    echo(f"sensor2flange  {ur_pose_text(pose)}")
    echo(
        f"  translation   x {pose[0] * 1e3:.4f}  y {pose[1] * 1e3:.4f}  z {pose[2] * 1e3:.4f} mm"
        f"   (1 sigma {st[0]:.4f} {st[1]:.4f} {st[2]:.4f} mm)"
    )
    echo(f"  rotation      1 sigma about sensor X Y Z: {sr[0]:.5f} {sr[1]:.5f} {sr[2]:.5f} deg")
    t = result.two_step
    d_t = float(np.linalg.norm(t.sensor2flange[:3, 3] - j.sensor2flange[:3, 3])) * 1e3
    d_r = math.degrees(
        float(se3.rotation_angle(t.sensor2flange[:3, :3].T @ j.sensor2flange[:3, :3]))
    )
    echo(
        f"  residual RMS  {j.rms * 1e6:.1f} um (paper's two-step: {t.rms * 1e6:.1f} um, "
        f"{d_t:.4f} mm / {d_r:.5f} deg away)"
    )
    if result.check is not None:
        c = result.check
        echo(
            f"  check scan    centre {c.centre_error_m * 1e3:.4f} mm from the calibrated ball, "
            f"radius {c.radius_error_m * 1e3:+.4f} mm"
        )
    if result.loo is not None:
        echo(
            f"  leave-one-out translation within {result.loo.max_translation_dev_m * 1e3:.4f} mm,"
            f" rotation within {math.degrees(result.loo.max_rotation_dev_rad):.5f} deg"
        )
    if result.latency is not None:
        lat = result.latency
        echo(
            f"  sensor timing apparent offset {lat.offset_s * 1e3:+.3f} ms (+- "
            f"{lat.std_s * 1e3:.3f}); [sensor] latency_s = "
            f"{result.configured_latency_s + lat.offset_s:.5f} would remove it"
        )
    for n in result.notes:
        echo(f"  note: {n}")
    echo(f"calibration file {out}")
    if report is not None and report.exists():
        echo(f"report           {report}")


@calibrate_app.command("sensor")
def sensor(
    config: Path = typer.Option(..., "--config", "-c", help="Configuration file of the cell."),
    yes: bool = typer.Option(
        False, "--yes", "-y", help="Confirm that the robot may move (needed without a terminal)."
    ),
    out: Path | None = typer.Option(
        None,
        "--out",
        "-o",
        help="Calibration file (default: the configured calibration file, else "
        "./sensor2flange.json).",
    ),
    report: Path | None = typer.Option(
        None,
        "--report",
        help="Report file: .html (one self-contained file) or .md (with a "
        "folder of PNG figures). Default: beside the calibration file, .html.",
    ),
    manual: bool = typer.Option(
        False,
        "--manual",
        help="Record while you move the robot from the teach pendant; the "
        "procedure commands no motion.",
    ),
    speed_mm_s: float = typer.Option(20.0, "--speed-mm-s", min=1.0, help="Sweep speed."),
    nominal: str | None = typer.Option(
        None,
        "--nominal",
        help='Starting sensor2flange "p[x, y, z, rx, ry, rz]" (m, rad), e.g. '
        "from the mounting drawing. Default: the calibration in force, or the simulated "
        "sensor's drawing value.",
    ),
    ball_radius_mm: float | None = typer.Option(
        None,
        "--ball-radius-mm",
        min=1.0,
        help="Tooling ball radius (default: the simulated ball, or 12.7 mm).",
    ),
    fov_width_mm: float | None = typer.Option(
        None, "--fov-width-mm", help="Length of the laser line (default: the simulated sensor's)."
    ),
    depth_min_mm: float | None = typer.Option(
        None, "--depth-min-mm", help="Measuring range start."
    ),
    depth_max_mm: float | None = typer.Option(None, "--depth-max-mm", help="Measuring range end."),
    grid: int = typer.Option(4, "--grid", min=2, max=5, help="Field-of-view grid (n x n)."),
    orientations: int = typer.Option(
        10, "--orientations", min=2, max=12, help="Tilted orientations around the ball."
    ),
    tilt_deg: float = typer.Option(
        52.0, "--tilt-deg", min=45.0, max=80.0, help="Tilt of the orientations (>= 45 deg)."
    ),
    lateral_places: int = typer.Option(
        2,
        "--lateral-places",
        min=1,
        max=2,
        help="Ball places along the laser line per tilted "
        "orientation (2: both ends; the rotation about the sensor Z axis needs the lever).",
    ),
    one_way: bool = typer.Option(
        False, "--one-way", help="Sweep each place once (faster; a latency error then biases)."
    ),
    no_check: bool = typer.Option(False, "--no-check", help="Skip the final check scan."),
    no_loo: bool = typer.Option(False, "--no-loo", help="Skip the leave-one-out validation."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress lines."),
) -> None:
    """Calibrate sensor2flange with a tooling ball (Borangiu et al. 2009, refined jointly).

    Jog the robot so that the laser line crosses the ball, then run this. The robot sweeps the
    ball at a grid of places in the field of view and from tilted orientations, solves the
    paper's two-step method and the joint refinement, validates (leave-one-out, a check scan)
    and writes the calibration file and a report. Nothing is written if it fails or is stopped.
    """
    from wristscan.calib import kinematics
    from wristscan.daemon.calibrate import sensor as cs
    from wristscan.drivers.base import DriverError, MotionNotEnabled

    cfg = load_config_or_exit(config)
    if cfg.sim is None and (fov_width_mm is None or depth_min_mm is None or depth_max_mm is None):
        fail(
            "give the sensor's field of view: --fov-width-mm, --depth-min-mm and --depth-max-mm",
            EXIT_USAGE,
        )
    try:
        settings = cs.settings_for(
            cfg,
            ball_radius_m=_mm(ball_radius_mm),
            fov_width_m=_mm(fov_width_mm),
            depth_min_m=_mm(depth_min_mm),
            depth_max_m=_mm(depth_max_mm),
            sweep_speed_m_s=speed_mm_s * 1e-3,
            fov_grid=grid,
            n_orientations=orientations,
            tilt_deg=tilt_deg,
            bidirectional=not one_way,
            lateral_places=lateral_places,
            check_scan=not no_check,
            leave_one_out=not no_loo,
        )
    except ValueError as exc:
        fail(str(exc), EXIT_USAGE)
    x0 = None
    if nominal is not None:
        try:
            x0 = cs.parse_ur_pose(nominal)
        except ValueError as exc:
            fail(f"--nominal: {exc}", EXIT_USAGE)
    elif not manual:
        found = cs.default_nominal(cfg)
        if found is None:
            fail(
                "the motions are planned with a nominal sensor2flange: give --nominal "
                '"p[x, y, z, rx, ry, rz]" (m, rad) from the mounting drawing',
                EXIT_USAGE,
            )
        x0, origin = found
        if not quiet:
            typer.echo(f"nominal sensor2flange: {origin}", err=True)
    if kinematics.UR_MODELS.get(cfg.robot.model) is None:
        fail(f"robot model {cfg.robot.model!r} has no kinematic model", EXIT_USAGE)
    target = out or cfg.calibration.file or Path("sensor2flange.json")
    if not target.parent.is_dir():
        fail(f"--out: folder {target.parent} does not exist", EXIT_USAGE)
    rep = report if report is not None else target.with_name(target.stem + "-report.html")
    if rep.suffix.lower() not in (".html", ".htm", ".md"):
        fail("--report: the name must end in .html or .md", EXIT_USAGE)
    if not manual:
        confirm_motion(cfg, yes, "calibrate sensor")

    def progress(event: cs.ProgressEvent) -> None:
        if not quiet:
            typer.echo(str(event), err=True)

    try:
        result = cs.run(
            cfg,
            settings,
            nominal=x0,
            out=target,
            report=rep,
            manual=manual,
            progress=progress,
        )
    except MotionNotEnabled as exc:
        fail(str(exc), EXIT_USAGE)
    except cs.CalibrationAborted as exc:
        fail(f"aborted: {exc}; nothing was written, the calibration in force is unchanged")
    except cs.CalibrationFailed as exc:
        fail(f"calibration failed: {exc}; nothing was written")
    except DriverError as exc:
        fail(f"device error: {exc}; nothing was written")
    except KeyboardInterrupt:
        fail("interrupted; nothing was written, the calibration in force is unchanged")
    except OSError as exc:
        fail(f"cannot write the result: {exc}")
    _print_result(result, target, rep)
