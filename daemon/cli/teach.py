"""``wristscan teach ...`` and ``wristscan measure``: the calibrated sensor used as a teaching
and guidance tool (Borangiu et al. 2009, section 5; docs/teach.md).

* ``teach plane``  - a plane frame from spots above a tilted surface (:mod:`.teach_plane`);
* ``teach edge-model`` - an edge model taught from an example edge under the sensor;
* ``teach edge``   - learn a 3D path along an edge under closed-loop guidance (:mod:`.teach_edge`);
* ``teach replay`` - the learned path as waypoints and a URScript program for another tool, and
  optionally run it (:mod:`.replay`);
* ``measure``      - standoff and surface normal under the sensor.

Exit codes: 0 done, 1 aborted or failed (nothing written), 2 usage or configuration error
(nothing moved).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from wristscan.daemon.cli._common import (
    EXIT_FAILED,
    EXIT_USAGE,
    CellConfigOpt,
    YesOpt,
    check_number,
    confirm_motion,
    fail,
    load_config_or_exit,
    mm,
    progress_printer,
)

if TYPE_CHECKING:
    from wristscan.calib.edge import EdgeModel
    from wristscan.daemon.config import Config
    from wristscan.daemon.teach.edge_path import LearnedPath
    from wristscan.daemon.teach.replay import ReplayOptions, ReplayPlan, ToolDef
__all__ = ["register", "teach_app"]

teach_app = typer.Typer(
    name="teach",
    help="Teach with the calibrated sensor: plane frames, edge paths, replay with another tool.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def register(app: typer.Typer) -> None:
    app.add_typer(teach_app, name="teach")
    app.command("measure")(measure_cmd)


_progress = progress_printer()


# --------------------------------------------------------------------------------------------
# teach plane


@teach_app.command("plane")
def plane_cmd(
    config: CellConfigOpt,
    yes: YesOpt = False,
    spacing_mm: float = typer.Option(30.0, "--spacing-mm", help="Distance between the spots."),
    spots: int = typer.Option(3, "--spots", help="3 (triangle) or 4 (square)."),
    dwell_s: float = typer.Option(0.25, "--dwell-s", help="Recording time at each spot."),
    speed_mm_s: float = typer.Option(50.0, "--speed-mm-s", help="Speed between the spots."),
    flatness_mm: float = typer.Option(
        0.1, "--max-form-error-mm", help="Flatness tolerance (form error, noise averaged out)."
    ),
    out: Path = typer.Option(Path("plane-frame.json"), "--out", "-o", help="Frame file (JSON)."),
) -> None:
    """Teach the frame of a tilted work surface: the robot visits spots above it from where the
    sensor is now, a robust plane fit gives the surface, the frame is saved and printed as a UR
    pose to enter as a plane feature."""
    from wristscan.daemon.procedure.errors import MotionNotConfirmed, ProcedureError
    from wristscan.daemon.teach.plane import PlaneOptions, teach_plane, write_plane_frame

    check_number("--spacing-mm", spacing_mm, gt=0)
    check_number("--spots", spots, ge=3, le=4)
    check_number("--dwell-s", dwell_s, gt=0)
    check_number("--speed-mm-s", speed_mm_s, gt=0)
    check_number("--max-form-error-mm", flatness_mm, gt=0)
    try:
        options = PlaneOptions(
            spacing_m=mm(spacing_mm),
            n_spots=spots,
            dwell_s=dwell_s,
            speed_m_s=mm(speed_mm_s),
            max_form_error_m=mm(flatness_mm),
        )
    except ValueError as exc:
        fail(str(exc), EXIT_USAGE)
    cfg = load_config_or_exit(config)
    confirm_motion(cfg, yes, "plane teaching")
    try:
        result = teach_plane(cfg, options, confirmed=True, progress=_progress)
    except MotionNotConfirmed as exc:
        fail(str(exc), EXIT_USAGE)
    except ProcedureError as exc:
        fail(str(exc), EXIT_FAILED)
    for line in result.summary_lines():
        typer.echo(line)
    if not result.flat:
        fail(
            f"the surface is not flat enough: form error {result.fit.form_error * 1e3:.3f} mm > "
            f"{flatness_mm:g} mm (--max-form-error-mm); nothing written",
            EXIT_FAILED,
        )
    path = write_plane_frame(out, result)
    typer.echo(f"frame file    {path}")


# --------------------------------------------------------------------------------------------
# measure


def measure_cmd(
    config: CellConfigOpt,
    dwell_s: float = typer.Option(0.2, "--dwell-s", help="Recording time (still)."),
    sweep_mm: float = typer.Option(
        0.0,
        "--sweep-mm",
        help="Move this far along the sensor's X axis to measure the full normal (moves the "
        "robot: needs --yes).",
    ),
    standoff_mm: float | None = typer.Option(
        None, "--standoff-mm", help="Also print the sensor pose normal to the surface from here."
    ),
    yes: bool = typer.Option(False, "--yes", "-y", help="Confirm the sweep's motion."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON instead of text."),
) -> None:
    """Standoff and surface normal under the sensor (distance sensing for guidance and for
    teaching locations precisely)."""
    from wristscan.calib import se3
    from wristscan.daemon.io.urpose import ur_pose_text
    from wristscan.daemon.procedure.errors import MotionNotConfirmed, ProcedureError
    from wristscan.daemon.teach.measure import measure

    check_number("--dwell-s", dwell_s, gt=0)
    check_number("--sweep-mm", sweep_mm, ge=0)
    check_number("--standoff-mm", standoff_mm, gt=0)
    cfg = load_config_or_exit(config)
    if sweep_mm > 0:
        confirm_motion(cfg, yes, "the measurement sweep")
    try:
        m = measure(cfg, dwell_s=dwell_s, sweep_m=mm(sweep_mm), confirmed=True)
    except MotionNotConfirmed as exc:
        fail(str(exc), EXIT_USAGE)
    except ProcedureError as exc:
        fail(str(exc), EXIT_FAILED)
    view = m.normal_view(None if standoff_mm is None else mm(standoff_mm))
    if as_json:
        doc = m.to_dict()
        doc["normal_view_sensor2base"] = view.tolist()
        doc["normal_view_ur_pose"] = se3.matrix_to_pose(view).tolist()
        typer.echo(json.dumps(doc, indent=2))
        return
    n = m.normal
    ns = m.normal_sensor
    typer.echo(f"standoff      {m.standoff_m * 1e3:.4f} mm  (sensor Z axis to the surface)")
    typer.echo("surface point " + " ".join(f"{v * 1e3:.4f}" for v in m.point) + " mm (base)")
    what = "" if m.full_normal else "  (in the laser plane only: --sweep-mm for the full normal)"
    typer.echo("normal        " + " ".join(f"{v:+.6f}" for v in n) + " (base)" + what)
    typer.echo(
        "              " + " ".join(f"{v:+.6f}" for v in ns) + " (sensor)"
        f"; incidence {m.incidence_deg:.3f} deg"
    )
    typer.echo(
        f"fit           {m.n_points} points from {m.n_profiles} profiles, RMS "
        f"{m.rms_m * 1e6:.1f} um"
    )
    typer.echo(f"sensor pose   {ur_pose_text(se3.matrix_to_pose(m.sensor2base))} (base)")
    d = m.standoff_m if standoff_mm is None else mm(standoff_mm)
    typer.echo(
        f"normal view   {ur_pose_text(se3.matrix_to_pose(view))} "
        f"(sensor pose looking along the normal from {d * 1e3:.1f} mm)"
    )


# --------------------------------------------------------------------------------------------
# teach edge


def load_edge_model(path: Path) -> EdgeModel:
    """The edge model of a TOML (table ``[edge]``, or top level) or JSON file; exit 2 when it
    cannot be read."""
    import tomllib

    from wristscan.calib.edge import EdgeModel

    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        fail(f"cannot read the edge model {path}: {exc.strerror}", EXIT_USAGE)
    try:
        doc: Any = json.loads(text) if path.suffix.lower() == ".json" else tomllib.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        fail(f"{path}: {exc}", EXIT_USAGE)
    if isinstance(doc, dict) and isinstance(doc.get("edge"), dict):
        doc = doc["edge"]
    if not isinstance(doc, dict):
        fail(f"{path}: the edge model must be a table", EXIT_USAGE)
    try:
        return EdgeModel.from_mapping(doc)
    except (TypeError, ValueError) as exc:
        fail(f"{path}: {exc}", EXIT_USAGE)


@teach_app.command("edge-model")
def edge_model_cmd(
    config: CellConfigOpt,
    kind: str = typer.Option(
        ..., "--kind", "-k", help="step, lap_joint, v_groove or outer_corner."
    ),
    dwell_s: float = typer.Option(0.2, "--dwell-s", help="Recording time (still)."),
    out: Path = typer.Option(Path("edge.toml"), "--out", "-o", help="Edge model file (TOML)."),
) -> None:
    """Teach an edge model from an example edge under the sensor (the laser line across it;
    nothing moves): its kind, height or angle and side, for teach edge --edge-model."""
    from wristscan.calib.edge import EDGE_KINDS
    from wristscan.daemon.io.atomic import write_atomic
    from wristscan.daemon.procedure.errors import ProcedureError
    from wristscan.daemon.teach.edge_model import model_toml, teach_edge_model

    if kind not in EDGE_KINDS:
        fail(f"--kind must be one of {', '.join(EDGE_KINDS)}", EXIT_USAGE)
    check_number("--dwell-s", dwell_s, gt=0)
    cfg = load_config_or_exit(config)
    try:
        model = teach_edge_model(cfg, kind, dwell_s)
    except ProcedureError as exc:
        fail(str(exc), EXIT_FAILED)
    text = model_toml(model)
    typer.echo(text.rstrip())
    typer.echo(f"edge model    {write_atomic(out, text)}")


@teach_app.command("edge")
def edge_cmd(
    config: CellConfigOpt,
    edge_model: Path = typer.Option(
        ..., "--edge-model", "-m", help="Edge model (TOML [edge] table or JSON)."
    ),
    yes: YesOpt = False,
    resolution_mm: float = typer.Option(1.0, "--resolution-mm", help="Spacing of the path."),
    length_mm: float = typer.Option(200.0, "--length-mm", help="Stop after this much edge."),
    step_mm: float = typer.Option(2.0, "--step-mm", help="Guidance step along the edge."),
    standoff_mm: float | None = typer.Option(
        None, "--standoff-mm", help="Standoff kept above the edge (default: the one at start)."
    ),
    direction: int = typer.Option(
        1, "--direction", help="+1: along the sensor's +X axis at the start; -1: along -X."
    ),
    speed_mm_s: float = typer.Option(20.0, "--speed-mm-s", help="Speed of the guidance steps."),
    out: Path = typer.Option(Path("edge-path.json"), "--out", "-o", help="Path file (JSON)."),
) -> None:
    """Learn the 3D path of an edge: the robot follows it under closed-loop guidance (edge kept
    in the middle of the laser line at a set standoff, sensor normal to the surface) and records
    it in the base frame at the resolution asked, with the surface normal at each point."""
    from wristscan.daemon.procedure.errors import MotionNotConfirmed, ProcedureError
    from wristscan.daemon.teach.edge import EdgeOptions, learn_edge
    from wristscan.daemon.teach.edge_path import write_edge_path

    if direction not in (1, -1):
        fail("--direction must be 1 or -1", EXIT_USAGE)
    check_number("--resolution-mm", resolution_mm, gt=0)
    check_number("--length-mm", length_mm, gt=0)
    check_number("--step-mm", step_mm, gt=0, le=20)
    check_number("--standoff-mm", standoff_mm, gt=0)
    check_number("--speed-mm-s", speed_mm_s, gt=0)
    try:
        options = EdgeOptions(
            resolution_m=mm(resolution_mm),
            length_m=mm(length_mm),
            step_m=mm(step_mm),
            standoff_m=None if standoff_mm is None else mm(standoff_mm),
            direction=direction,
            speed_m_s=mm(speed_mm_s),
        )
    except ValueError as exc:
        fail(str(exc), EXIT_USAGE)
    model = load_edge_model(edge_model)
    cfg = load_config_or_exit(config)
    confirm_motion(cfg, yes, "edge learning")
    try:
        result = learn_edge(cfg, model, options, confirmed=True, progress=_progress)
    except MotionNotConfirmed as exc:
        fail(str(exc), EXIT_USAGE)
    except ProcedureError as exc:
        fail(str(exc), EXIT_FAILED)
    for line in result.summary_lines():
        typer.echo(line)
    path = write_edge_path(out, result, cfg)
    typer.echo(f"path file     {path}")


# --------------------------------------------------------------------------------------------
# teach replay


_ToolOpt = Annotated[
    str,
    typer.Option(
        "--tool",
        "-t",
        help='Tool transformation as a UR pose "p[x, y, z, rx, ry, rz]" (m, rad, flange frame)'
        " or the name of a tool in --tools.",
    ),
]
_ToolsOpt = Annotated[
    Path | None,
    typer.Option("--tools", help="Tool table (TOML [tools.<name>] with tcp = [...] and settings)."),
]
_OffsetOpt = Annotated[
    float | None,
    typer.Option("--offset-mm", help="Tool tip this far from the edge along the surface normal."),
]
_LeadOpt = Annotated[
    float | None,
    typer.Option("--lead-deg", help="Travel angle: tool tilted forward along the path."),
]
_TiltOpt = Annotated[
    float | None,
    typer.Option("--tilt-deg", help="Work angle: tool tilted sideways about the path."),
]
_BlendOpt = Annotated[
    float | None, typer.Option("--blend-mm", help="Largest blend radius between waypoints.")
]
_ToleranceOpt = Annotated[
    float | None,
    typer.Option(
        "--tolerance-mm", help="Drop waypoints while the path stays this close (0: keep all)."
    ),
]
_ApproachOpt = Annotated[
    float | None,
    typer.Option("--approach-mm", help="Approach and retract distance along the normal."),
]
_ReplayOutOpt = Annotated[Path, typer.Option("--out", "-o", help="Waypoints for the tool (JSON).")]


@teach_app.command("replay")
def replay_cmd(
    path: Annotated[Path, typer.Option("--path", "-p", help="Learned path (JSON of teach edge).")],
    tool: _ToolOpt,
    tools: _ToolsOpt = None,
    offset_mm: _OffsetOpt = None,
    lead_deg: _LeadOpt = None,
    tilt_deg: _TiltOpt = None,
    speed_mm_s: float | None = typer.Option(None, "--speed-mm-s", help="Process speed."),
    accel: float | None = typer.Option(None, "--accel-m-s2", help="Acceleration (m/s^2)."),
    blend_mm: _BlendOpt = None,
    tolerance_mm: _ToleranceOpt = None,
    approach_mm: _ApproachOpt = None,
    move: str = typer.Option("movel", "--move", help="movel or movep for the process moves."),
    out: _ReplayOutOpt = Path("replay.json"),
    csv: Path | None = typer.Option(None, "--csv", help="Also write the waypoints as CSV."),
    script: Path | None = typer.Option(None, "--script", help="Write the URScript program."),
    run: bool = typer.Option(False, "--run", help="Run the program on the robot of --config."),
    config: Path | None = typer.Option(None, "--config", "-c", help="Cell configuration (--run)."),
    yes: bool = typer.Option(False, "--yes", "-y", help="Confirm the motion of --run."),
    timeout_s: float = typer.Option(600.0, "--timeout-s", help="Longest run (--run)."),
) -> None:
    """Write a learned path as poses for another tool (waypoints JSON/CSV and a URScript program
    with blends) and optionally run it."""
    from wristscan.daemon.teach.replay import ReplayError, plan_replay, run_program

    if move not in ("movel", "movep"):
        fail("--move must be movel or movep", EXIT_USAGE)
    if run and config is None:
        fail("--run needs --config (the robot to run on)", EXIT_USAGE)
    _check_replay_numbers(
        offset_mm, lead_deg, tilt_deg, speed_mm_s, accel, blend_mm, tolerance_mm, approach_mm
    )
    check_number("--timeout-s", timeout_s, gt=0)
    overrides = _given(
        offset_m=(offset_mm, 1e-3),
        lead_rad=(lead_deg, math.pi / 180),
        tilt_rad=(tilt_deg, math.pi / 180),
        speed_m_s=(speed_mm_s, 1e-3),
        accel_m_s2=(accel, 1.0),
        blend_m=(blend_mm, 1e-3),
        tolerance_m=(tolerance_mm, 1e-3),
        approach_m=(approach_mm, 1e-3),
    )
    tool_def, options = _replay_options(tool, tools, move, overrides)
    learned = _read_learned(path)
    cfg = None
    if run:
        assert config is not None
        cfg = load_config_or_exit(config)
        confirm_motion(cfg, yes, "the replay")
    model = _replay_model(learned, cfg)
    try:
        plan = plan_replay(learned, tool_def.tcp, options, cfg=cfg, model=model)
    except ReplayError as exc:
        fail(str(exc), EXIT_FAILED)
    for line in plan.summary_lines():
        typer.echo(line)
    _write_replay(plan, out, csv, script)
    if run:
        assert cfg is not None
        try:
            outcome = run_program(cfg, plan, timeout_s=timeout_s, progress=_progress)
        except ReplayError as exc:
            fail(str(exc), EXIT_FAILED)
        typer.echo(f"run           {outcome}")


def _check_replay_numbers(
    offset_mm: float | None,
    lead_deg: float | None,
    tilt_deg: float | None,
    speed_mm_s: float | None,
    accel: float | None,
    blend_mm: float | None,
    tolerance_mm: float | None,
    approach_mm: float | None,
) -> None:
    check_number("--offset-mm", offset_mm)
    check_number("--lead-deg", lead_deg, gt=-90, lt=90)
    check_number("--tilt-deg", tilt_deg, gt=-90, lt=90)
    check_number("--speed-mm-s", speed_mm_s, gt=0)
    check_number("--accel-m-s2", accel, gt=0)
    check_number("--blend-mm", blend_mm, ge=0)
    check_number("--tolerance-mm", tolerance_mm, ge=0)
    check_number("--approach-mm", approach_mm, ge=0)


def _given(**values: tuple[float | None, float]) -> dict[str, float]:
    """The options given on the command line, each times its unit scale: ``name=(value,
    scale)``, None values left out (the tool's settings stay)."""
    return {key: value * scale for key, (value, scale) in values.items() if value is not None}


def _replay_options(
    tool: str, tools: Path | None, move: str, overrides: dict[str, float]
) -> tuple[ToolDef, ReplayOptions]:
    """The tool and the replay settings (its own, overridden by the options); exit 2 when they
    cannot be read or do not fit."""
    from wristscan.daemon.teach.replay import ReplayOptions, load_tool

    try:
        tool_def = load_tool(tool, tools)
    except ValueError as exc:
        fail(str(exc), EXIT_USAGE)
    try:
        options = ReplayOptions.from_tool(tool_def, move=move, **overrides)
    except ValueError as exc:
        fail(str(exc), EXIT_USAGE)
    return tool_def, options


def _read_learned(path: Path) -> LearnedPath:
    from wristscan.daemon.teach.edge_path import PathFileError, read_edge_path

    try:
        return read_edge_path(path)
    except (OSError, PathFileError) as exc:
        fail(f"cannot read the path {path}: {exc}", EXIT_USAGE)


def _replay_model(learned: LearnedPath, cfg: Config | None) -> Any:
    """The robot model the path was learned on, for a reachability check without a robot to
    ask (None: there is a robot, or the model is unknown)."""
    from wristscan.calib import kinematics

    if cfg is not None or learned.robot is None:
        return None
    try:
        return kinematics.get_model(learned.robot)
    except ValueError:
        return None  # an unknown model name: no reachability check


def _write_replay(plan: ReplayPlan, out: Path, csv: Path | None, script: Path | None) -> None:
    from wristscan.daemon.teach.replay import write_csv, write_script, write_waypoints

    typer.echo(f"waypoints     {write_waypoints(out, plan)}")
    if csv is not None:
        typer.echo(f"csv           {write_csv(csv, plan)}")
    if script is not None:
        typer.echo(f"script        {write_script(script, plan)}")
