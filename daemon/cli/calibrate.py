"""``wristscan calibrate ...``: calibration procedures run at the cell.

``calibrate_app`` is the typer group: ``sensor`` (sensor2flange with a tooling ball) and
``import`` (sensor2flange from a stop-and-go data set on disk, docs/calibration_import.md) are
here, ``table`` (the rotary-table axis) and ``latency`` (the sensor latency) are in
:mod:`._calibrate_table`.

Exit codes of every procedure: 0 done, 1 aborted or failed (nothing written; the calibration in
force is unchanged), 2 usage or configuration error (nothing moved).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from wristscan.daemon.cli._calibrate_kinematics import kinematics
from wristscan.daemon.cli._calibrate_table import ConfigOpt, latency, table
from wristscan.daemon.cli._common import (
    EXIT_USAGE,
    QuietOpt,
    YesOpt,
    check_number,
    check_out_folder,
    confirm_motion,
    fail,
    load_config_or_exit,
    mm,
    progress_printer,
    report_path,
)

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from wristscan.daemon.calibrate.sensor import SensorCalibrationResult, Settings
    from wristscan.daemon.config import Config

__all__ = ["calibrate_app", "register"]

calibrate_app = typer.Typer(
    name="calibrate",
    help="Calibration procedures at the cell (sensor2flange with a tooling ball, ...).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def register(app: typer.Typer) -> None:
    app.add_typer(calibrate_app, name="calibrate")


# ------------------------------------------------------------------------------ calibrate sensor

_OutOpt = Annotated[
    Path | None,
    typer.Option(
        "--out",
        "-o",
        help="Calibration file (default: the configured calibration file, else "
        "./sensor2flange.json).",
    ),
]
_ReportOpt = Annotated[
    Path | None,
    typer.Option(
        "--report",
        help="Report file: .html (one self-contained file) or .md (with a "
        "folder of PNG figures). Default: beside the calibration file, .html.",
    ),
]
_ManualOpt = Annotated[
    bool,
    typer.Option(
        "--manual",
        help="Record while you move the robot from the teach pendant; the "
        "procedure commands no motion.",
    ),
]
_NominalOpt = Annotated[
    str | None,
    typer.Option(
        "--nominal",
        help='Starting sensor2flange "p[x, y, z, rx, ry, rz]" (m, rad), e.g. '
        "from the mounting drawing. Default: the calibration in force, or the simulated "
        "sensor's drawing value.",
    ),
]
_BallRadiusOpt = Annotated[
    float | None,
    typer.Option(
        "--ball-radius-mm",
        help="Tooling ball radius (default: the simulated ball, or 12.7 mm).",
    ),
]
_FovWidthOpt = Annotated[
    float | None,
    typer.Option(
        "--fov-width-mm", help="Length of the laser line (default: the simulated sensor's)."
    ),
]
_DepthMinOpt = Annotated[
    float | None, typer.Option("--depth-min-mm", help="Measuring range start.")
]
_DepthMaxOpt = Annotated[float | None, typer.Option("--depth-max-mm", help="Measuring range end.")]
_OrientationsOpt = Annotated[
    int,
    typer.Option("--orientations", help="Tilted orientations around the ball."),
]
_TiltOpt = Annotated[
    float,
    typer.Option("--tilt-deg", help="Tilt of the orientations (>= 45 deg)."),
]
_LateralPlacesOpt = Annotated[
    int,
    typer.Option(
        "--lateral-places",
        help="Ball places along the laser line per tilted "
        "orientation (2: both ends; the rotation about the sensor Z axis needs the lever).",
    ),
]
_OneWayOpt = Annotated[
    bool,
    typer.Option("--one-way", help="Sweep each place once (faster; a latency error then biases)."),
]


@calibrate_app.command("sensor")
def sensor(
    config: ConfigOpt,
    yes: YesOpt = False,
    out: _OutOpt = None,
    report: _ReportOpt = None,
    manual: _ManualOpt = False,
    speed_mm_s: Annotated[float, typer.Option("--speed-mm-s", help="Sweep speed.")] = 50.0,
    nominal: _NominalOpt = None,
    ball_radius_mm: _BallRadiusOpt = None,
    fov_width_mm: _FovWidthOpt = None,
    depth_min_mm: _DepthMinOpt = None,
    depth_max_mm: _DepthMaxOpt = None,
    grid: Annotated[int, typer.Option("--grid", help="Field-of-view grid (n x n).")] = 4,
    orientations: _OrientationsOpt = 6,
    tilt_deg: _TiltOpt = 52.0,
    lateral_places: _LateralPlacesOpt = 2,
    one_way: _OneWayOpt = False,
    no_check: Annotated[
        bool, typer.Option("--no-check", help="Skip the final check scan.")
    ] = False,
    no_loo: Annotated[
        bool, typer.Option("--no-loo", help="Skip the leave-one-out validation.")
    ] = False,
    quiet: QuietOpt = False,
) -> None:
    """Calibrate sensor2flange with a tooling ball (Borangiu et al. 2009, refined jointly).

    Jog the robot so that the laser line crosses the ball, then run this. The robot sweeps the
    ball at a grid of places in the field of view and from tilted orientations, solves the
    paper's two-step method and the joint refinement, validates (leave-one-out, a check scan)
    and writes the calibration file and a report. Nothing is written if it fails or is stopped.
    """
    from wristscan.calib import kinematics

    check_number("--speed-mm-s", speed_mm_s, ge=1)
    check_number("--ball-radius-mm", ball_radius_mm, ge=1)
    check_number("--fov-width-mm", fov_width_mm, gt=0)
    check_number("--depth-min-mm", depth_min_mm, gt=0)
    check_number("--depth-max-mm", depth_max_mm, gt=0)
    check_number("--grid", grid, ge=2, le=5)
    check_number("--orientations", orientations, ge=2, le=12)
    check_number("--tilt-deg", tilt_deg, ge=45, le=80)
    check_number("--lateral-places", lateral_places, ge=1, le=2)
    cfg = load_config_or_exit(config)
    if cfg.sim is None and (fov_width_mm is None or depth_min_mm is None or depth_max_mm is None):
        fail(
            "give the sensor's field of view: --fov-width-mm, --depth-min-mm and --depth-max-mm",
            EXIT_USAGE,
        )
    settings = _sensor_settings(
        cfg,
        ball_radius_m=mm(ball_radius_mm),
        fov_width_m=mm(fov_width_mm),
        depth_min_m=mm(depth_min_mm),
        depth_max_m=mm(depth_max_mm),
        sweep_speed_m_s=speed_mm_s * 1e-3,
        fov_grid=grid,
        n_orientations=orientations,
        tilt_deg=tilt_deg,
        bidirectional=not one_way,
        lateral_places=lateral_places,
        check_scan=not no_check,
        leave_one_out=not no_loo,
    )
    x0 = _nominal_pose(cfg, nominal, manual, quiet)
    if kinematics.UR_MODELS.get(cfg.robot.model) is None:
        fail(f"robot model {cfg.robot.model!r} has no kinematic model", EXIT_USAGE)
    target = out or cfg.calibration.file or Path("sensor2flange.json")
    check_out_folder(target, "--out")
    rep = report_path(target, report)
    if not manual:
        confirm_motion(cfg, yes, "calibrate sensor")
    result = _run_sensor(cfg, settings, x0, target, rep, manual, quiet)
    _print_result(result, target, rep)


def _sensor_settings(cfg: Config, **options: Any) -> Settings:
    """The procedure's settings from the options; exit 2 when they do not fit together."""
    from wristscan.daemon.calibrate import sensor as cs

    try:
        return cs.settings_for(cfg, **options)
    except ValueError as exc:
        fail(str(exc), EXIT_USAGE)


def _nominal_pose(
    cfg: Config, nominal: str | None, manual: bool, quiet: bool
) -> NDArray[np.float64] | None:
    """The starting sensor2flange: ``--nominal``, else (unless ``--manual``) the calibration in
    force or the simulated sensor's; exit 2 when motions must be planned without one."""
    from wristscan.calib import se3
    from wristscan.daemon.calibrate import sensor as cs
    from wristscan.daemon.io.urpose import parse_ur_pose

    if nominal is not None:
        try:
            return se3.pose_to_matrix(parse_ur_pose(nominal))
        except ValueError as exc:
            fail(f"--nominal: {exc}", EXIT_USAGE)
    if manual:
        return None
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
    return x0


def _run_sensor(
    cfg: Config,
    settings: Settings,
    x0: NDArray[np.float64] | None,
    target: Path,
    rep: Path,
    manual: bool,
    quiet: bool,
) -> SensorCalibrationResult:
    """Run the procedure; its errors become one line on stderr and the exit code."""
    from wristscan.daemon.calibrate import sensor as cs
    from wristscan.drivers.base import DriverError, MotionNotEnabled

    progress = progress_printer(quiet)
    try:
        return cs.run(
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


def _print_result(result: SensorCalibrationResult, out: Path, report: Path | None) -> None:
    import math

    import numpy as np

    from wristscan.calib import se3
    from wristscan.daemon.io.urpose import ur_pose_text

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


# The procedures of _calibrate_table, after sensor: ``calibrate --help`` lists them in this order.
calibrate_app.command("table")(table)
calibrate_app.command("latency")(latency)
calibrate_app.command("kinematics")(kinematics)


# ------------------------------------------------------------------------------ calibrate import


_FolderArg = Annotated[
    Path, typer.Argument(help="Data set folder: poses.csv and profiles/<pose>.csv.")
]
_RadiusOpt = Annotated[
    str, typer.Option("--ball-radius", help="Ball radius with its unit: 40mm, 0.04m.")
]
_PosesOpt = Annotated[
    str,
    typer.Option(
        "--poses",
        help="Pose convention of poses.csv: ur-rotvec, fanuc-xyzwpr, kuka-abc, "
        "abb-quaternion or matrix.",
    ),
]
_UnitsOpt = Annotated[
    str, typer.Option("--units", help="Units of positions and profile points: mm or m.")
]
_ImportOutOpt = Annotated[
    Path | None,
    typer.Option("--out", "-o", help="Calibration file (default: ./sensor2flange.json)."),
]
_IdentityOpt = Annotated[
    Path | None,
    typer.Option(
        "--config", "-c", help="Cell configuration: the robot and sensor the file is for."
    ),
]
_RobotSigmaOpt = Annotated[
    float,
    typer.Option(
        "--robot-sigma-mm",
        help="Per-axis flange position error of a pose from the data sheet (the floor of the "
        "one estimated from the residuals).",
    ),
]
_SideOpt = Annotated[
    str,
    typer.Option(
        "--ball-side", help="Side of the laser plane the ball centre is on: auto, +x, -x."
    ),
]


@calibrate_app.command("import")
def import_(
    folder: _FolderArg,
    ball_radius: _RadiusOpt,
    poses: _PosesOpt,
    units: _UnitsOpt = "mm",
    out: _ImportOutOpt = None,
    report: _ReportOpt = None,
    config: _IdentityOpt = None,
    robot_sigma_mm: _RobotSigmaOpt = 0.02,
    side: _SideOpt = "auto",
) -> None:
    """Calibrate sensor2flange from a stop-and-go data set on disk (one profile per pose).

    Reads FOLDER/poses.csv (a header, then pose,x,y,z and the orientation columns of
    --poses) and FOLDER/profiles/<pose>.csv (y,z and an optional valid column), solves in
    closed form (no initial guess), chooses the side of the laser plane the ball is on, refines
    jointly on every point, and writes the same calibration file and report as `calibrate
    sensor`. See docs/calibration_import.md.
    """
    from wristscan.calib import pose_conventions as pc
    from wristscan.daemon.calibrate import imported

    check_number("--robot-sigma-mm", robot_sigma_mm, ge=0)
    if poses not in pc.CONVENTIONS:
        fail(f"--poses: {poses!r} is not one of {', '.join(pc.CONVENTIONS)}", EXIT_USAGE)
    if units not in imported.UNITS:
        fail(f"--units: {units!r} is not mm or m", EXIT_USAGE)
    sides: dict[str, Any] = {"auto": "auto", "+x": 1, "-x": -1}
    if side not in sides:
        fail(f"--ball-side: {side!r} is not auto, +x or -x", EXIT_USAGE)
    try:
        radius_m = imported.parse_length(ball_radius, units)
    except ValueError as exc:
        fail(f"--ball-radius: {exc}", EXIT_USAGE)
    target = out or Path("sensor2flange.json")
    check_out_folder(target, "--out")
    rep = report_path(target, report)
    robot = sensor_id = None
    if config is not None:
        from wristscan.daemon.io.calibfile import identities

        robot, sensor_id = identities(load_config_or_exit(config))
    try:
        result = imported.run(
            folder, poses, radius_m, units=units, out=target, report=rep, robot=robot,
            sensor=sensor_id, robot_sigma_m=robot_sigma_mm * 1e-3, side=sides[side],
        )  # fmt: skip
    except imported.DatasetError as exc:
        fail(f"{exc}; nothing was written", EXIT_USAGE)
    except imported.ImportFailed as exc:
        fail(f"calibration failed: {exc}; nothing was written")
    except OSError as exc:
        fail(f"cannot write the result: {exc}")
    _print_import(result, target, rep)


def _print_import(result: Any, out: Path, report: Path) -> None:
    import math

    from wristscan.calib import se3
    from wristscan.daemon.io.urpose import ur_pose_text

    j = result.joint
    pose = se3.matrix_to_pose(j.sensor2flange)
    st = j.sigma_translation_m * 1e3
    echo = typer.echo
    echo(f"sensor2flange  {ur_pose_text(pose)}")
    echo(
        f"  translation   x {pose[0] * 1e3:.4f}  y {pose[1] * 1e3:.4f}  z {pose[2] * 1e3:.4f} mm"
        f"   (1 sigma {st[0]:.4f} {st[1]:.4f} {st[2]:.4f} mm)"
    )
    if result.jackknife is not None:
        jt = result.jackknife.sigma_translation_m * 1e3
        echo(f"  jackknife     1 sigma over poses {jt[0]:.4f} {jt[1]:.4f} {jt[2]:.4f} mm")
    side = {1: "+x", -1: "-x", 0: "mixed"}[result.solution.side]
    echo(
        f"  residual RMS  {j.rms * 1e6:.1f} um, {len(result.dataset.names)} poses, "
        f"{j.n_points} points, ball side {side}, condition {j.condition:.1f}"
    )
    ps = float(getattr(j, "point_sigma_m", math.nan))
    if math.isfinite(ps):
        echo(f"  point error   up to {ps * 1e3:.4f} mm (1 sigma) from the calibration")
    for n in result.notes:
        echo(f"  note: {n}")
    echo(f"calibration file {out}")
    if report.exists():
        echo(f"report           {report}")
