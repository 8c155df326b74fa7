"""``wristscan scan``: scan jobs (execute a plan, merge the passes) and plan authoring.

::

    wristscan scan plan --bbox-mm -90 -20 30 60 40 90 --fov-mm 50 --overlap 0.3 \\
        --standoff-mm 100 --table-deg 0 --table-deg 90 --tilt-deg 15 --tilt-deg -15 > plan.toml
    wristscan scan --plan plan.toml --config cell.toml --dry-run     # show and check, no motion
    wristscan scan --plan plan.toml --config cell.toml --yes --out part-scan

Exit codes: 0 done; 1 the scan failed or was aborted, or ICP flagged a pass (a calibration or
timing fault is suspected; the outputs are written); 2 usage, configuration or plan error, or
the plan was refused by its checks (nothing moved).
"""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from wristscan.daemon.cli._common import (
    EXIT_FAILED,
    EXIT_OK,
    EXIT_USAGE,
    YesOpt,
    check_number,
    confirm_motion,
    fail,
    load_config_or_exit,
    progress_printer,
)

scan_app = typer.Typer(
    name="scan",
    help="Scan jobs: run a scan plan and merge the passes (ICP), or author a plan.",
    invoke_without_command=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def register(app: typer.Typer) -> None:
    app.add_typer(scan_app, name="scan")


@scan_app.callback()
def scan(
    ctx: typer.Context,
    plan: Path | None = typer.Option(None, "--plan", "-p", help="Scan plan (TOML or JSON)."),
    config: Path | None = typer.Option(None, "--config", "-c", help="Configuration of the cell."),
    yes: YesOpt = False,
    dry_run: bool = typer.Option(
        False, "--dry-run", help="Show the plan and run every check; nothing moves."
    ),
    joints_deg: tuple[float, float, float, float, float, float] | None = typer.Option(
        None,
        "--joints-deg",
        help="Dry run from these joints (deg) instead of reading the robot.",
    ),
    out: Path = typer.Option(
        Path("scan"),
        "--out",
        "-o",
        help="Output folder; or NAME.e57 / NAME.mcap: the scan as that file (one scan or cloud "
        "per pass), and the other outputs in the folder NAME.",
    ),
    voxel_mm: float = typer.Option(
        0.25, "--voxel-mm", help="Voxel of the written clouds (mm); 0 keeps all points."
    ),
    icp: bool = typer.Option(True, "--icp/--no-icp", help="Refine the passes with ICP."),
    max_correction_mm: float = typer.Option(
        0.05, "--max-correction-mm", help="Flag passes whose ICP correction is larger."
    ),
    max_correction_deg: float = typer.Option(
        0.05, "--max-correction-deg", help="Flag passes turned more than this by ICP."
    ),
    surface: bool = typer.Option(
        False, "--surface", help="Also write a Poisson surface (needs wristscan[surface])."
    ),
) -> None:
    """Run a scan plan on the robot and merge the passes into one cloud in the plan frame."""
    check_number("--joints-deg", joints_deg, ge=-360, le=360)
    check_number("--voxel-mm", voxel_mm, ge=0)
    check_number("--max-correction-mm", max_correction_mm, ge=0)
    check_number("--max-correction-deg", max_correction_deg, ge=0)
    if ctx.invoked_subcommand is not None:
        return
    if plan is None or config is None:
        fail("give --plan FILE and --config FILE (or: wristscan scan plan --help)", EXIT_USAGE)
    from wristscan.daemon.scan.plan_file import PlanError, load_plan

    try:
        scan_plan = load_plan(plan)
    except PlanError as exc:
        typer.echo(str(exc), err=True)
        raise typer.Exit(EXIT_USAGE) from None
    cfg = load_config_or_exit(config)
    if dry_run or joints_deg is not None:
        _dry_run(cfg, scan_plan, joints_deg)
        return
    out, cloud_file = _split_out(out)
    if surface:
        import importlib.util

        if importlib.util.find_spec("pymeshlab") is None:
            fail(
                "--surface needs the optional dependency pymeshlab: pip install "
                "'wristscan[surface]' (nothing moved)",
                EXIT_USAGE,
            )
    confirm_motion(cfg, yes, "wristscan scan")
    _run(
        cfg,
        scan_plan,
        out,
        voxel_mm,
        icp,
        max_correction_mm,
        max_correction_deg,
        surface,
        cloud_file,
    )


def _split_out(out: Path) -> tuple[Path, Path | None]:
    """The output folder and the scan file: ``NAME.e57`` or ``NAME.mcap`` is that file and the
    folder ``NAME``; anything else is the folder. Fails (nothing moved) on a cloud extension
    the scan does not write or a missing extra."""
    from wristscan.daemon.io.cloudfile import FORMATS, CloudFormatError, cloud_format
    from wristscan.daemon.scan.output import SCAN_FILE_FORMATS

    if out.suffix.lower() not in FORMATS:
        return out, None
    try:
        cloud_format(out, allowed=SCAN_FILE_FORMATS)
    except CloudFormatError as exc:
        fail(f"--out: {exc} (or a folder name) (nothing moved)", EXIT_USAGE)
    return out.with_suffix(""), out


def _dry_run(cfg: object, scan_plan: object, joints_deg: tuple[float, ...] | None) -> None:
    import math

    from wristscan.daemon.config import Config
    from wristscan.daemon.scan.job import ScanError, dry_run
    from wristscan.daemon.scan.plan import describe_plan
    from wristscan.daemon.scan.plan_file import ScanPlan

    assert isinstance(cfg, Config) and isinstance(scan_plan, ScanPlan)
    q = None if joints_deg is None else [math.radians(a) for a in joints_deg]
    try:
        resolved, check = dry_run(cfg, scan_plan, q)
    except ScanError as exc:
        fail(str(exc), EXIT_USAGE)
    except Exception as exc:  # the robot could not be read: a device problem
        from wristscan.drivers.base import DriverError

        if not isinstance(exc, DriverError):
            raise
        fail(f"cannot read the robot's joints: {exc} (or give --joints-deg)", EXIT_FAILED)
    for line in describe_plan(scan_plan, resolved, check):
        typer.echo(line)
    typer.echo("dry run: nothing moved")
    raise typer.Exit(EXIT_OK if check.ok else EXIT_USAGE)


def _run(
    cfg: object,
    scan_plan: object,
    out: Path,
    voxel_mm: float,
    icp: bool,
    max_mm: float,
    max_deg: float,
    surface: bool,
    cloud_file: Path | None = None,
) -> None:

    from wristscan.daemon.config import Config
    from wristscan.daemon.procedure.errors import ProcedureError
    from wristscan.daemon.scan.job import (
        MergeOptions,
        MotionNotConfirmed,
        PlanRejected,
        ScanAborted,
        ScanError,
        report_lines,
        run_scan,
    )
    from wristscan.daemon.scan.plan import describe_plan
    from wristscan.daemon.scan.plan_file import ScanPlan
    from wristscan.drivers.base import DriverError

    assert isinstance(cfg, Config) and isinstance(scan_plan, ScanPlan)
    opts = MergeOptions(
        icp=icp,
        voxel_m=voxel_mm * 1e-3,
        flag_translation_m=max_mm * 1e-3,
        flag_rotation_deg=max_deg,
        surface=surface,
    )
    for line in describe_plan(scan_plan):
        typer.echo(line)
    progress = progress_printer(err=False, elapsed=True)
    try:
        result = run_scan(
            cfg, scan_plan, confirmed=True, out_dir=out, options=opts, progress=progress
        )
    except MotionNotConfirmed as exc:
        fail(str(exc), EXIT_USAGE)
    except PlanRejected as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(EXIT_USAGE) from None
    except ScanAborted as exc:
        fail(str(exc), EXIT_FAILED)
    except ScanError as exc:
        fail(str(exc), EXIT_USAGE if "calibration" in str(exc) else EXIT_FAILED)
    except ProcedureError as exc:  # the shared acquisition steps (no paired profiles, ...)
        fail(str(exc), EXIT_FAILED)
    except DriverError as exc:
        fail(f"device error: {exc}", EXIT_FAILED)
    if cloud_file is not None:
        from wristscan.daemon.scan.output import write_scan_file

        files = (result.clouds, result.merge, result.recorded, result.frame, result.calibration)
        result.files.append(write_scan_file(cloud_file, *files))
    typer.echo("")
    for line in report_lines(result.report):
        typer.echo(line)
    for f in result.files:
        typer.echo(f"wrote {f}")
    typer.echo(
        f"done in {result.duration_s:.0f} s ({len(result.recorded)} passes, {result.frame} frame)"
    )
    if result.report.get("fault_suspected"):
        fail(
            "ICP corrections above the thresholds: a calibration or timing fault is suspected "
            "(see the report); the outputs were written with the corrections applied"
        )


@scan_app.command("plan")
def plan_cmd(
    bbox_mm: tuple[float, float, float, float, float, float] = typer.Option(
        ..., "--bbox-mm", help="Box to cover: xmin ymin zmin xmax ymax zmax (mm, plan frame)."
    ),
    fov_mm: float = typer.Option(..., "--fov-mm", help="Width of the laser line (mm)."),
    overlap: float = typer.Option(
        0.3, "--overlap", help="Shared width of neighbouring strips (fraction of the line)."
    ),
    standoff_mm: float = typer.Option(
        ..., "--standoff-mm", help="Sensor origin to the middle of the box along the view (mm)."
    ),
    table_deg: list[float] = typer.Option(
        [], "--table-deg", help="Table angle (deg); repeat for several. None: the table stays."
    ),
    tilt_deg: list[float] = typer.Option(
        [], "--tilt-deg", help="View tilt about the pass direction (deg); repeat. Default 0."
    ),
    yaw_deg: float = typer.Option(0.0, "--yaw-deg", help="Pass direction in the base frame."),
    frame: str = typer.Option("part", "--frame", help="Plan frame: part or base."),
    depth_range_mm: tuple[float, float] | None = typer.Option(
        None, "--depth-range-mm", help="Sensor measuring range (mm): the box must fit in it."
    ),
    speed_mm_s: float = typer.Option(40.0, "--speed-mm-s", help="Pass speed (mm/s)."),
    travel_mm_s: float = typer.Option(150.0, "--travel-mm-s", help="Travel speed (mm/s)."),
    retract_mm: float = typer.Option(30.0, "--retract-mm", help="Back-off before/after a pass."),
    name: str = typer.Option("", "--name", help="Name of the plan."),
    out: Path | None = typer.Option(None, "--out", "-o", help="Write here (default: stdout)."),
) -> None:
    """Generate a plan of parallel linear passes over a box (prints TOML)."""
    from wristscan.daemon.scan.plan import describe_plan
    from wristscan.daemon.scan.plan_file import PlanError, plan_to_toml
    from wristscan.daemon.scan.plan_generate import generate_plan

    if frame not in ("part", "base"):
        fail(f"--frame must be part or base, not {frame!r}", EXIT_USAGE)
    check_number("--bbox-mm", bbox_mm)
    check_number("--fov-mm", fov_mm, gt=0)
    check_number("--overlap", overlap, ge=0, lt=0.95)
    check_number("--standoff-mm", standoff_mm, gt=0)
    check_number("--table-deg", table_deg)
    check_number("--tilt-deg", tilt_deg, gt=-90, lt=90)
    check_number("--yaw-deg", yaw_deg)
    check_number("--depth-range-mm", depth_range_mm, gt=0)
    check_number("--speed-mm-s", speed_mm_s, gt=0)
    check_number("--travel-mm-s", travel_mm_s, gt=0)
    check_number("--retract-mm", retract_mm, ge=0)
    lo, hi = bbox_mm[:3], bbox_mm[3:]
    try:
        plan = generate_plan(
            [v * 1e-3 for v in lo],
            [v * 1e-3 for v in hi],
            fov_width_m=fov_mm * 1e-3,
            overlap=overlap,
            standoff_m=standoff_mm * 1e-3,
            table_angles_deg=list(table_deg) or [None],
            tilts_deg=list(tilt_deg) or [0.0],
            yaw_deg=yaw_deg,
            frame="part" if frame == "part" else "base",
            depth_range_m=None
            if depth_range_mm is None
            else (depth_range_mm[0] * 1e-3, depth_range_mm[1] * 1e-3),
            speed_m_s=speed_mm_s * 1e-3,
            travel_speed_m_s=travel_mm_s * 1e-3,
            retract_m=retract_mm * 1e-3,
            name=name,
        )
    except (PlanError, ValueError) as exc:
        fail(str(exc).splitlines()[0], EXIT_USAGE)
    text = plan_to_toml(plan)
    if out is None:
        sys.stdout.write(text)
    else:
        out.write_text(text, encoding="utf-8")
    for line in describe_plan(plan):
        typer.echo(line, err=True)
