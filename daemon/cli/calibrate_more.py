"""``wristscan calibrate table`` and ``wristscan calibrate latency``: the rotary-table axis and the
sensor latency, measured with a tooling ball (procedures in :mod:`.calib_table` and
:mod:`.calib_latency`). Both move the robot: they need ``[robot] motion_enabled`` and ``--yes``
(or a yes at the prompt on a terminal). Exit codes as for every ``calibrate`` procedure: 0 done,
1 aborted or failed (nothing written), 2 usage or configuration error (nothing moved)."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import typer

T = TypeVar("T")


def _vec3(text: str | None, option: str) -> tuple[float, float, float] | None:
    if text is None:
        return None
    try:
        vals = [float(v) for v in text.replace(" ", "").strip("[]").split(",")]
    except ValueError:
        vals = []
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise typer.BadParameter(f"expected X,Y,Z in metres, got {text!r}", param_hint=option)
    return (vals[0], vals[1], vals[2])


def _progress(quiet: bool) -> Callable[[int, int, str], None]:
    """One stage line per step on stderr."""

    def line(done: int, total: int, text: str) -> None:
        if not quiet:
            typer.echo(f"[{done}/{total}] {text}", err=True)

    return line


def _report_path(target: Path, report: Path | None) -> Path:
    from wristscan.daemon.cli.calibrate import EXIT_USAGE, fail

    rep = report if report is not None else target.with_name(target.stem + "-report.html")
    if rep.suffix.lower() not in (".html", ".htm", ".md"):
        fail("--report: the name must end in .html or .md", EXIT_USAGE)
    return rep


def _check_folder(target: Path, option: str) -> None:
    from wristscan.daemon.cli.calibrate import EXIT_USAGE, fail

    if not target.parent.is_dir():
        fail(f"{option}: folder {target.parent} does not exist", EXIT_USAGE)


def _run(fn: Callable[[], T]) -> T:
    """Run a procedure; its errors become one line on stderr and the exit code."""
    from wristscan.daemon.calibrate.table import (
        MotionNotConfirmed,
        ProcedureAborted,
        ProcedureError,
    )
    from wristscan.daemon.cli.calibrate import EXIT_USAGE, fail
    from wristscan.drivers.base import DriverError

    try:
        return fn()
    except MotionNotConfirmed as exc:
        fail(f"{exc}; nothing moved", EXIT_USAGE)
    except ProcedureAborted as exc:
        fail(str(exc))
    except ProcedureError as exc:
        fail(f"{exc}; nothing was written, the calibration in force is unchanged")
    except DriverError as exc:
        fail(f"device error: {exc}; nothing was written")
    except KeyboardInterrupt:
        fail("interrupted; nothing was written, the calibration in force is unchanged")


def _write(fn: Callable[[], T]) -> T:
    from wristscan.daemon.cli.calibrate import fail

    try:
        return fn()
    except (OSError, ValueError) as exc:
        fail(f"cannot write the result: {exc}")


def register(app: typer.Typer) -> None:
    from wristscan.daemon.cli.calibrate import calibrate_app

    calibrate_app.command("table")(table)
    calibrate_app.command("latency")(latency)


def table(
    config: Path = typer.Option(..., "--config", "-c", help="Configuration file of the cell."),
    yes: bool = typer.Option(
        False, "--yes", "-y", help="Confirm that the robot may move (needed without a terminal)."
    ),
    angles: int = typer.Option(
        8, "--angles", min=6, max=72, help="Table angles of the plan (>= 6), evenly spread."
    ),
    span_deg: float | None = typer.Option(
        None,
        "--span-deg",
        min=30.0,
        max=360.0,
        help="Angle range the plan covers from the current angle (default: a full turn, "
        "360 (n - 1) / n).",
    ),
    ball: str | None = typer.Option(
        None,
        "--ball-m",
        help="Approximate ball centre X,Y,Z (m, base frame) at the current table angle. "
        "Default: --standoff-mm in front of the sensor as it stands.",
    ),
    ball_radius_mm: float = typer.Option(12.7, "--ball-radius-mm", min=1.0),
    standoff_mm: float = typer.Option(
        100.0, "--standoff-mm", min=1.0, help="Sensor origin to ball centre along sensor Z."
    ),
    speed_mm_s: float = typer.Option(20.0, "--speed-mm-s", min=1.0, help="Sweep speed."),
    ball_height_mm: float = typer.Option(
        0.0,
        "--ball-height-mm",
        help="Ball centre above the table top: puts the table frame's origin on the top "
        "(0: in the plane of the ball centre).",
    ),
    out: Path | None = typer.Option(
        None,
        "--out",
        "-o",
        help="Calibration file (default: calibration.table_file, else ./table.json).",
    ),
    report: Path | None = typer.Option(
        None,
        "--report",
        help="Report: .html, or .md with a folder of PNG figures. Default: beside the "
        "calibration file, .html.",
    ),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress lines."),
) -> None:
    """Calibrate the rotary-table axis and encoder offset with a tooling ball on the table.

    Fix the ball on the table away from the axis and jog the robot so that the sensor looks at
    it from about --standoff-mm. The table turns to each angle, the sensor sweeps the ball, and
    the circle of ball centres gives the axis, its tilt and the encoder offset with their
    uncertainties. Nothing is written if it fails or is stopped.
    """
    from wristscan.daemon.calibrate.table import (
        TableOptions,
        calibrate_table,
        table_calibration,
        table_report,
    )
    from wristscan.daemon.cli.calibrate import EXIT_USAGE, confirm_motion, fail, load_config_or_exit
    from wristscan.daemon.io.calibfile import write_calibration

    cfg = load_config_or_exit(config)
    target = out or cfg.calibration.table_file or Path("table.json")
    _check_folder(target, "--out")
    rep = _report_path(target, report)
    try:
        options = TableOptions(
            n_angles=angles,
            span_rad=None if span_deg is None else math.radians(span_deg),
            ball_guess_m=_vec3(ball, "--ball-m"),
            ball_radius_m=ball_radius_mm * 1e-3,
            standoff_m=standoff_mm * 1e-3,
            scan_speed_m_s=speed_mm_s * 1e-3,
            ball_height_m=ball_height_mm * 1e-3,
        )
    except ValueError as exc:
        fail(str(exc), EXIT_USAGE)
    if not cfg.table_enabled:
        fail(f"{cfg.source}: no enabled [table] section: nothing to calibrate", EXIT_USAGE)
    confirm_motion(cfg, yes, "calibrate table")
    result = _run(lambda: calibrate_table(cfg, options, confirmed=True, progress=_progress(quiet)))
    path = _write(lambda: write_calibration(target, table_calibration(result, cfg)))
    rep_path = _write(
        lambda: table_report(result, f"cell {cfg.cell.name}, configuration {cfg.source}").write(rep)
    )
    a = result.axis
    s = a.sigma()
    typer.echo(
        f"table axis    tilt {a.tilt_deg:.4f} +- {result.tilt_sigma_deg:.4f} deg from base Z, "
        f"direction [{a.direction[0]:.6f}, {a.direction[1]:.6f}, {a.direction[2]:.6f}]"
    )
    typer.echo(
        f"  axis point  [{a.point[0]:.5f}, {a.point[1]:.5f}, {a.point[2]:.5f}] m "
        f"(1 sigma {1e3 * s['point_x_m']:.4f} {1e3 * s['point_y_m']:.4f} "
        f"{1e3 * s['point_z_m']:.4f} mm)"
    )
    typer.echo(
        f"  encoder offset {a.encoder_offset_rad:.6f} +- {s['phase_rad']:.6f} rad; ball circle "
        f"radius {a.radius_m * 1e3:.4f} mm; residual RMS {a.rms_m * 1e6:.1f} um over "
        f"{a.n_angles} angles"
    )
    typer.echo(f"calibration file {path}")
    typer.echo(f"report           {rep_path}")


def latency(
    config: Path = typer.Option(..., "--config", "-c", help="Configuration file of the cell."),
    yes: bool = typer.Option(
        False, "--yes", "-y", help="Confirm that the robot may move (needed without a terminal)."
    ),
    speeds: str = typer.Option(
        "25,50,100",
        "--speeds-mm-s",
        "--speeds",
        help="Sweep speeds in mm/s, comma separated (capped by robot.max_speed_m_s).",
    ),
    repeats: int = typer.Option(
        1, "--repeats", min=1, max=20, help="Forward + backward sweep pairs per speed."
    ),
    ball: str | None = typer.Option(
        None,
        "--ball-m",
        help="Approximate ball centre X,Y,Z (m, base frame). Default: --standoff-mm in front "
        "of the sensor as it stands.",
    ),
    ball_radius_mm: float = typer.Option(12.7, "--ball-radius-mm", min=1.0),
    standoff_mm: float = typer.Option(
        100.0, "--standoff-mm", min=1.0, help="Sensor origin to ball centre along sensor Z."
    ),
    out: Path = typer.Option(
        Path("latency.json"),
        "--out",
        "-o",
        help="JSON result file (the configuration is never rewritten).",
    ),
    report: Path | None = typer.Option(
        None,
        "--report",
        help="Report: .html, or .md with a folder of PNG figures. Default: beside --out, .html.",
    ),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress lines."),
) -> None:
    """Measure the sensor latency: sweeps over a fixed ball, both ways, at three speeds.

    Jog the robot so that the sensor looks at the ball from about --standoff-mm. Prints the
    latency_s line for the sensor section of the configuration and writes a JSON result and a
    report.
    """
    from wristscan.daemon.calibrate.latency import (
        LatencyOptions,
        calibrate_latency,
        latency_report,
        write_latency_result,
    )
    from wristscan.daemon.cli.calibrate import EXIT_USAGE, confirm_motion, fail, load_config_or_exit

    try:
        values = tuple(float(v) * 1e-3 for v in speeds.split(","))
        if not all(math.isfinite(v) and v > 0 for v in values):
            raise ValueError
    except ValueError:
        raise typer.BadParameter(
            f"expected speeds in mm/s such as 25,50,100, got {speeds!r}",
            param_hint="--speeds-mm-s",
        ) from None
    cfg = load_config_or_exit(config)
    _check_folder(out, "--out")
    rep = _report_path(out, report)
    try:
        options = LatencyOptions(
            speeds_m_s=values,
            repeats=repeats,
            ball_guess_m=_vec3(ball, "--ball-m"),
            ball_radius_m=ball_radius_mm * 1e-3,
            standoff_m=standoff_mm * 1e-3,
        )
    except ValueError as exc:
        fail(str(exc), EXIT_USAGE)
    confirm_motion(cfg, yes, "calibrate latency")
    result = _run(
        lambda: calibrate_latency(cfg, options, confirmed=True, progress=_progress(quiet))
    )
    path = _write(lambda: write_latency_result(out, result))
    rep_path = _write(
        lambda: latency_report(result, f"cell {cfg.cell.name}, configuration {cfg.source}").write(
            rep
        )
    )
    e = result.estimate
    typer.echo(
        f"sensor latency {result.latency_s * 1e3:.4f} +- {result.std_s * 1e3:.4f} ms "
        f"(configured {result.configured_latency_s * 1e3:.4f} ms, correction "
        f"{e.latency_s * 1e3:+.4f} ms; {e.n_sweeps} sweeps, residual RMS {e.rms_m * 1e6:.1f} um)"
    )
    if result.latency_s < 0:
        typer.echo(
            "warning: the latency is negative (the sensor's stamps run ahead of the robot's): "
            "configure latency_s = 0 and the rest as [sync] robot_latency_s",
            err=True,
        )
    typer.echo(f"result file {path}")
    typer.echo(f"report      {rep_path}")
    typer.echo("put this line under [sensor] in the configuration:")
    typer.echo(result.toml_line())
