"""``wristscan calibrate table`` and ``wristscan calibrate latency``: the rotary-table axis and the
sensor latency, measured with a tooling ball (procedures in :mod:`wristscan.daemon.calibrate.table`
and :mod:`wristscan.daemon.calibrate.latency`). Both move the robot: they need
``[robot] motion_enabled`` and ``--yes`` (or a yes at the prompt on a terminal). Exit codes as
for every ``calibrate`` procedure: 0 done, 1 aborted or failed (nothing written), 2 usage or
configuration error (nothing moved).

The ``calibrate`` group (:mod:`.calibrate`) adds these commands after ``sensor``; the options
every calibration procedure takes are declared here.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, TypeVar

import typer

from wristscan.daemon.cli._common import (
    EXIT_USAGE,
    QuietOpt,
    YesOpt,
    check_number,
    check_out_folder,
    confirm_motion,
    fail,
    load_config_or_exit,
    progress_printer,
    report_path,
)

if TYPE_CHECKING:
    from wristscan.daemon.calibrate.latency import LatencyResult
    from wristscan.daemon.calibrate.table import TableResult

__all__ = ["ConfigOpt", "latency", "table"]

T = TypeVar("T")

ConfigOpt = Annotated[Path, typer.Option("--config", "-c", help="Configuration file of the cell.")]
"""``--config`` of the calibration procedures."""
_BallRadiusOpt = Annotated[float, typer.Option("--ball-radius-mm", help="Tooling ball radius.")]
_StandoffOpt = Annotated[
    float,
    typer.Option("--standoff-mm", help="Sensor origin to ball centre along sensor Z."),
]


def _vec3(text: str | None, option: str) -> tuple[float, float, float] | None:
    """``X,Y,Z`` (m); exit 2 naming ``option`` unless three finite numbers."""
    if text is None:
        return None
    try:
        vals = [float(v) for v in text.replace(" ", "").strip("[]").split(",")]
    except ValueError:
        vals = []
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        fail(f"{option}: expected X,Y,Z in metres, got {text!r}", EXIT_USAGE)
    return (vals[0], vals[1], vals[2])


def _check_ball(ball_radius_mm: float, standoff_mm: float) -> None:
    check_number("--ball-radius-mm", ball_radius_mm, ge=1)
    check_number("--standoff-mm", standoff_mm, ge=1)


def _run(fn: Callable[[], T]) -> T:
    """Run a procedure; its errors become one line on stderr and the exit code."""
    from wristscan.daemon.procedure.errors import (
        MotionNotConfirmed,
        ProcedureAborted,
        ProcedureError,
    )
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
    try:
        return fn()
    except (OSError, ValueError) as exc:
        fail(f"cannot write the result: {exc}")


# ------------------------------------------------------------------------------ calibrate table

_SpanOpt = Annotated[
    float | None,
    typer.Option(
        "--span-deg",
        help="Angle range the plan covers from the current angle (default: a full turn, "
        "360 (n - 1) / n).",
    ),
]
_TableBallOpt = Annotated[
    str | None,
    typer.Option(
        "--ball-m",
        help="Approximate ball centre X,Y,Z (m, base frame) at the current table angle. "
        "Default: --standoff-mm in front of the sensor as it stands.",
    ),
]
_BallHeightOpt = Annotated[
    float,
    typer.Option(
        "--ball-height-mm",
        help="Ball centre above the table top: puts the table frame's origin on the top "
        "(0: in the plane of the ball centre).",
    ),
]
_TableOutOpt = Annotated[
    Path | None,
    typer.Option(
        "--out",
        "-o",
        help="Calibration file (default: calibration.table_file, else ./table.json).",
    ),
]
_TableReportOpt = Annotated[
    Path | None,
    typer.Option(
        "--report",
        help="Report: .html, or .md with a folder of PNG figures. Default: beside the "
        "calibration file, .html.",
    ),
]


def table(
    config: ConfigOpt,
    yes: YesOpt = False,
    angles: Annotated[
        int,
        typer.Option("--angles", help="Table angles of the plan (>= 6), evenly spread."),
    ] = 8,
    span_deg: _SpanOpt = None,
    ball: _TableBallOpt = None,
    ball_radius_mm: _BallRadiusOpt = 12.7,
    standoff_mm: _StandoffOpt = 100.0,
    speed_mm_s: Annotated[float, typer.Option("--speed-mm-s", help="Sweep speed.")] = 20.0,
    ball_height_mm: _BallHeightOpt = 0.0,
    out: _TableOutOpt = None,
    report: _TableReportOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Calibrate the rotary-table axis and encoder offset with a tooling ball on the table.

    Fix the ball on the table away from the axis and jog the robot so that the sensor looks at
    it from about --standoff-mm. The table turns to each angle, the sensor sweeps the ball, and
    the circle of ball centres gives the axis, its tilt and the encoder offset with their
    uncertainties. Nothing is written if it fails or is stopped.
    """
    from wristscan.daemon.calibrate.table import TableOptions, calibrate_table, table_calibration
    from wristscan.daemon.calibrate.table_report import table_report
    from wristscan.daemon.io.calibfile import write_calibration

    check_number("--angles", angles, ge=6, le=72)
    check_number("--span-deg", span_deg, ge=30, le=360)
    _check_ball(ball_radius_mm, standoff_mm)
    check_number("--speed-mm-s", speed_mm_s, ge=1)
    check_number("--ball-height-mm", ball_height_mm)
    ball_m = _vec3(ball, "--ball-m")
    cfg = load_config_or_exit(config)
    target = out or cfg.calibration.table_file or Path("table.json")
    check_out_folder(target, "--out")
    rep = report_path(target, report)
    try:
        options = TableOptions(
            n_angles=angles,
            span_rad=None if span_deg is None else math.radians(span_deg),
            ball_guess_m=ball_m,
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
    progress = progress_printer(quiet)
    result = _run(lambda: calibrate_table(cfg, options, confirmed=True, progress=progress))
    path = _write(lambda: write_calibration(target, table_calibration(result, cfg)))
    rep_path = _write(
        lambda: table_report(result, f"cell {cfg.cell.name}, configuration {cfg.source}").write(rep)
    )
    _print_table(result, path, rep_path)


def _print_table(result: TableResult, path: Path, rep_path: Path) -> None:
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


# ------------------------------------------------------------------------------ calibrate latency

_SpeedsOpt = Annotated[
    str,
    typer.Option(
        "--speeds-mm-s",
        "--speeds",
        help="Sweep speeds in mm/s, comma separated (capped by robot.max_speed_m_s).",
    ),
]
_LatencyBallOpt = Annotated[
    str | None,
    typer.Option(
        "--ball-m",
        help="Approximate ball centre X,Y,Z (m, base frame). Default: --standoff-mm in front "
        "of the sensor as it stands.",
    ),
]
_LatencyOutOpt = Annotated[
    Path,
    typer.Option(
        "--out",
        "-o",
        help="JSON result file (the configuration is never rewritten).",
    ),
]
_LatencyReportOpt = Annotated[
    Path | None,
    typer.Option(
        "--report",
        help="Report: .html, or .md with a folder of PNG figures. Default: beside --out, .html.",
    ),
]


def latency(
    config: ConfigOpt,
    yes: YesOpt = False,
    speeds: _SpeedsOpt = "25,50,100",
    repeats: Annotated[
        int,
        typer.Option("--repeats", help="Forward + backward sweep pairs per speed."),
    ] = 1,
    ball: _LatencyBallOpt = None,
    ball_radius_mm: _BallRadiusOpt = 12.7,
    standoff_mm: _StandoffOpt = 100.0,
    out: _LatencyOutOpt = Path("latency.json"),
    report: _LatencyReportOpt = None,
    quiet: QuietOpt = False,
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

    values = _speeds_m_s(speeds)
    check_number("--repeats", repeats, ge=1, le=20)
    _check_ball(ball_radius_mm, standoff_mm)
    ball_m = _vec3(ball, "--ball-m")
    cfg = load_config_or_exit(config)
    check_out_folder(out, "--out")
    rep = report_path(out, report)
    try:
        options = LatencyOptions(
            speeds_m_s=values,
            repeats=repeats,
            ball_guess_m=ball_m,
            ball_radius_m=ball_radius_mm * 1e-3,
            standoff_m=standoff_mm * 1e-3,
        )
    except ValueError as exc:
        fail(str(exc), EXIT_USAGE)
    confirm_motion(cfg, yes, "calibrate latency")
    progress = progress_printer(quiet)
    result = _run(lambda: calibrate_latency(cfg, options, confirmed=True, progress=progress))
    path = _write(lambda: write_latency_result(out, result))
    rep_path = _write(
        lambda: latency_report(result, f"cell {cfg.cell.name}, configuration {cfg.source}").write(
            rep
        )
    )
    _print_latency(result, path, rep_path)


def _speeds_m_s(speeds: str) -> tuple[float, ...]:
    """``--speeds-mm-s`` in m/s; a usage error (exit 2) unless positive finite numbers."""
    try:
        values = tuple(float(v) * 1e-3 for v in speeds.split(","))
        if not all(math.isfinite(v) and v > 0 for v in values):
            raise ValueError
    except ValueError:
        fail(
            f"--speeds-mm-s: expected speeds in mm/s such as 25,50,100, got {speeds!r}", EXIT_USAGE
        )
    return values


def _print_latency(result: LatencyResult, path: Path, rep_path: Path) -> None:
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
