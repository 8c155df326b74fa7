"""Scan jobs: execute a scan plan on the robot, merge the passes, write the clouds.

The paper's first use of the calibrated probe (Borangiu et al. 2009, section 4): many scan
passes, "already almost aligned" by the calibration, refined with ICP and turned into a surface.

Steps of :func:`run_scan`
-------------------------
1. Refuse unless motion is enabled in the configuration and confirmed.
2. Open the devices (:class:`~wristscan.daemon.procedure.acquisition.Acquisition`, points paired
   in the base frame; this module reads the table itself, as the calibration procedures do),
   wait until profiles are being paired, read the joints, and check the whole plan from them
   (:func:`~wristscan.daemon.scan.plan.check_plan`): a plan with any problem is refused before
   anything moves (:class:`~wristscan.daemon.scan.errors.PlanRejected`).
3. For each pass: back off from the previous pass, turn the table if the pass asks for an angle,
   joint move to the approach pose, linear move in, record the pass (linear moves through its
   poses), and read the table angle before and after it (the table must stand still during a
   pass). Any failure stops the robot and the table
   (:class:`~wristscan.daemon.scan.errors.ScanAborted`).
4. :func:`align_passes`: each pass into the plan frame with the calibrations in force (Eq. (1)),
   cropped to the plan's box.
5. :func:`~wristscan.calib.merge.merge_passes`: point-to-plane ICP of every pass against the
   union of the others, in rounds; the corrections are reported per pass (mm, degrees) and those
   above the thresholds are **flagged** as a sign of a calibration or timing fault, never
   silently absorbed.
6. :func:`~wristscan.daemon.scan.output.write_outputs`: binary PLY per pass and merged (voxel
   down-sampled, normals facing the sensor), an NPZ with everything, a JSON report, and
   optionally a Poisson surface (the ``surface`` extra: pymeshlab, MeshLab's own filters).

The passes are recorded by :mod:`wristscan.daemon.scan.record`; the merge is pure maths in
:mod:`wristscan.calib.merge`.

What ICP can and cannot see
---------------------------
ICP measures how the passes disagree, not where they all are: an error that moves every pass
the same way (a calibration error seen through one robot orientation and one table angle) leaves
the passes consistent and goes unnoticed. Passes at several table angles and orientations turn a
sensor calibration error into different shifts per pass, which ICP then sees. The corrections
are reported relative to the consensus of all passes (their mean is removed), so a single bad
pass carries most of the disagreement.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import se3
from wristscan.calib.align import align_with_poses, sensor_poses
from wristscan.calib.merge import MergeOptions, MergeResult, PassCloud, merge_passes
from wristscan.daemon.config import Config
from wristscan.daemon.procedure.errors import MotionNotConfirmed
from wristscan.daemon.procedure.in_force import calibration_in_force, procedure_acquisition
from wristscan.daemon.procedure.motion import guarded_motion, require_motion
from wristscan.daemon.procedure.progress import Progress, StepReport, stage_reporter
from wristscan.daemon.scan.archive import keep_in_archive
from wristscan.daemon.scan.errors import PlanRejected, ScanAborted, ScanError
from wristscan.daemon.scan.output import write_outputs
from wristscan.daemon.scan.plan import (
    CellGeometry,
    PassCheck,
    PlanCheck,
    ResolvedPass,
    check_plan,
    resolve_plan,
)
from wristscan.daemon.scan.plan_file import PlanError, ScanPlan
from wristscan.daemon.scan.record import (
    TABLE_STILL_RAD,
    RecordedPass,
    angle_diff,
    record_clean_pass,
    ur_pose,
)

if TYPE_CHECKING:
    from wristscan.daemon.procedure.acquisition import Acquisition
__all__ = [
    "MergeOptions",
    "MotionNotConfirmed",
    "PlanRejected",
    "ScanAborted",
    "ScanCalibration",
    "ScanError",
    "ScanResult",
    "align_passes",
    "dry_run",
    "load_scan_calibration",
    "report_lines",
    "run_scan",
    "scan_report",
]

FloatArray = NDArray[np.float64]


# --------------------------------------------------------------------------------------------
# Calibrations in force


@dataclass(frozen=True)
class ScanCalibration:
    """The calibrations a scan uses (from the configuration's ``[calibration]`` files)."""

    sensor2flange: FloatArray
    base2table: FloatArray | None = None
    encoder_offset_rad: float = 0.0
    sources: dict[str, str] = field(default_factory=dict)


def load_scan_calibration(cfg: Config, plan: ScanPlan) -> ScanCalibration:
    """Read the sensor calibration (always needed) and the table calibration (needed by a
    part-frame plan or one that turns the table). Raises :class:`ScanError` saying what is
    missing."""
    c = cfg.calibration
    s2f = calibration_in_force(
        cfg,
        "sensor2flange",
        "a scan needs the sensor calibration (wristscan calibrate sensor writes it)",
        ScanError,
    )
    sources = {"sensor2flange": str(c.file)}
    needs_table = plan.frame == "part" or any(p.table_deg is not None for p in plan.passes)
    if not needs_table:
        return ScanCalibration(np.asarray(s2f.transform, dtype=np.float64), sources=sources)
    if not cfg.table_enabled:
        raise ScanError(
            f"{cfg.source}: the plan turns the table or is in the part frame, but the "
            "configuration has no enabled [table]"
        )
    tcal = calibration_in_force(
        cfg,
        "table",
        "a part-frame plan needs the table calibration (wristscan calibrate table writes it)",
        ScanError,
    )
    sources["table"] = str(c.table_file)
    return ScanCalibration(
        np.asarray(s2f.transform, dtype=np.float64),
        np.asarray(tcal.transform, dtype=np.float64),
        float(tcal.parameters.get("encoder_offset_rad", 0.0)),
        sources,
    )


def _geometry(
    cfg: Config, cal: ScanCalibration, tcp2flange: FloatArray, model: Any
) -> CellGeometry:
    r = cfg.robot
    return CellGeometry(
        model=model or r.model,
        sensor2flange=cal.sensor2flange,
        tcp2flange=tcp2flange,
        base2table=cal.base2table,
        encoder_offset_rad=cal.encoder_offset_rad,
        workspace_min_m=None if r.workspace_min_m is None else np.asarray(r.workspace_min_m),
        workspace_max_m=None if r.workspace_max_m is None else np.asarray(r.workspace_max_m),
        max_speed_m_s=float(r.max_speed_m_s),
    )


def _resolve(plan: ScanPlan, geom: CellGeometry, table_angle: float | None) -> list[ResolvedPass]:
    try:
        return resolve_plan(plan, geom, table_angle)
    except PlanError as exc:
        raise ScanError(str(exc)) from None


# --------------------------------------------------------------------------------------------
# Dry run


def dry_run(
    cfg: Config, plan: ScanPlan, q_start: ArrayLike | None = None
) -> tuple[list[ResolvedPass], PlanCheck]:
    """Resolve and check ``plan`` without moving anything. The joints come from ``q_start``
    (rad) or, when None, from the robot (read only: no control link is opened; the TCP offset
    is then taken from the reported TCP pose)."""
    from wristscan.calib import kinematics

    cal = load_scan_calibration(cfg, plan)
    model: Any = cfg.robot.model
    tcp2flange = np.eye(4)
    table_angle: float | None = None
    if q_start is None:
        from wristscan.daemon.devices import make_devices

        devices = make_devices(cfg)
        robot = devices.robot
        robot.open()
        try:
            state = robot.read(timeout=10.0)
            if state is None:
                raise ScanError(f"the robot at {cfg.robot.host} sends no state")
            model = robot.kinematic_model() or model
            q = np.asarray(state.q, dtype=np.float64)
            flange = kinematics.forward(model, q)
            tcp2flange = se3.invert(flange) @ se3.pose_to_matrix(np.asarray(state.tcp_pose))
            if float(np.linalg.norm(tcp2flange[:3, 3])) < 1e-4:
                tcp2flange = np.eye(4)  # kinematic model differences, not a TCP offset
        finally:
            robot.close()
        if devices.table is not None and cal.base2table is not None:
            devices.table.open()
            try:
                table_angle = float(devices.table.angle())
            finally:
                devices.table.close()
    else:
        q = np.asarray(q_start, dtype=np.float64)
    geom = _geometry(cfg, cal, tcp2flange, model)
    resolved = _resolve(plan, geom, table_angle)
    return resolved, check_plan(resolved, geom, q)


# --------------------------------------------------------------------------------------------
# Execution


@dataclass
class ScanResult:
    """What :func:`run_scan` did and produced."""

    plan: ScanPlan
    recorded: list[RecordedPass]
    clouds: list[PassCloud]
    merge: MergeResult | None
    files: list[Path]
    calibration: ScanCalibration
    duration_s: float
    frame: str
    report: dict[str, Any]


def run_scan(
    cfg: Config,
    plan: ScanPlan,
    *,
    confirmed: bool,
    out_dir: Path | None = None,
    options: MergeOptions | None = None,
    progress: Progress | None = None,
    table_settle_s: float = 0.2,
) -> ScanResult:
    """Execute ``plan`` on the devices of ``cfg`` and merge the passes (see the module doc).

    Raises :class:`MotionNotConfirmed` (nothing moved), :class:`ScanError` for a missing
    calibration or table, :class:`PlanRejected` when a check fails (nothing moved),
    :class:`ScanAborted` when the scan stopped part way. Writes the outputs into ``out_dir``
    when given.
    """
    require_motion(cfg, confirmed)
    opts = options or MergeOptions()
    cal = load_scan_calibration(cfg, plan)
    report = stage_reporter(progress, "scan")
    t0 = time.monotonic()
    n = len(plan.passes)
    total = n + 2
    report(0, total, "connecting, waiting for paired profiles")
    with procedure_acquisition(cfg) as acq:
        geom, resolved, check = _checked_plan(cfg, plan, cal, acq)
        recorded = _record_passes(
            cfg, acq, plan, geom, resolved, check.passes, report, total, table_settle_s
        )
    report(n + 1, total, "aligning and merging the passes")
    frame = plan.frame
    clouds = align_passes(recorded, cal, frame, plan)
    merge = merge_passes(clouds, opts) if opts.icp and len(clouds) > 1 else None
    duration = time.monotonic() - t0
    summary = scan_report(plan, recorded, clouds, merge, cal, opts, frame, duration)
    files: list[Path] = []
    if out_dir is not None:
        files = write_outputs(out_dir, clouds, merge, opts, summary)
    archived = keep_in_archive(cfg, plan.name, files, clouds, merge, opts, summary)
    if archived is not None:
        summary["archived_as"] = archived.name
    report(total, total, "done")
    return ScanResult(plan, recorded, clouds, merge, files, cal, duration, frame, summary)


def _checked_plan(
    cfg: Config, plan: ScanPlan, cal: ScanCalibration, acq: Acquisition
) -> tuple[CellGeometry, list[ResolvedPass], PlanCheck]:
    """The plan resolved for the cell as it stands (robot joints, TCP offset, table angle) and
    checked from the joints now; raises :class:`PlanRejected` when a check fails."""
    robot = acq.robot
    state = robot.latest_state()
    if state is None:
        raise ScanError("the robot sends no state")
    q_now = np.asarray(state.q, dtype=np.float64)
    model = robot.kinematic_model() or cfg.robot.model
    tcp2flange = se3.pose_to_matrix(np.asarray(robot.tcp_offset(), dtype=np.float64))
    geom = _geometry(cfg, cal, tcp2flange, model)
    table_angle = float(acq.table.angle()) if acq.table is not None else None
    resolved = _resolve(plan, geom, table_angle)
    check = check_plan(resolved, geom, q_now)
    if not check.ok:
        raise PlanRejected(check.all_problems())
    return geom, resolved, check


def _record_passes(
    cfg: Config,
    acq: Acquisition,
    plan: ScanPlan,
    geom: CellGeometry,
    resolved: list[ResolvedPass],
    checks: Sequence[PassCheck],
    report: StepReport,
    total: int,
    table_settle_s: float,
) -> list[RecordedPass]:
    """Move through the passes and record them (step 3 of the module doc), guarded: any
    failure stops the robot and the table."""
    robot = acq.robot
    r = cfg.robot
    travel = min(plan.travel_speed_m_s, r.max_speed_m_s)
    accel = r.max_accel_m_s2
    jspeed = min(1.0, r.max_joint_speed_rad_s)
    jaccel = r.max_joint_accel_rad_s2
    recorded: list[RecordedPass] = []
    with _guarded(acq):
        for rp, pc in zip(resolved, checks, strict=True):
            if recorded:
                robot.move_l(ur_pose(geom, resolved[rp.index - 1].retreat), travel, accel)
            if rp.table_angle_rad is not None:
                _turn_table(acq, rp, report, total, table_settle_s)
            report(rp.index + 1, total, f"{rp.label}: moving to the start")
            assert pc.q_approach is not None
            robot.move_j(pc.q_approach, jspeed, jaccel)
            robot.move_l(ur_pose(geom, rp.sensor2base[0]), travel, accel)
            report(
                rp.index + 1,
                total,
                f"{rp.label}: recording {rp.length_m * 1e3:.0f} mm at {rp.speed_m_s * 1e3:g} mm/s",
            )

            def back_to_start(rp: ResolvedPass = rp, q: FloatArray = pc.q_approach) -> None:
                robot.move_l(ur_pose(geom, rp.retreat), travel, accel)
                robot.move_j(q, jspeed, jaccel)
                robot.move_l(ur_pose(geom, rp.sensor2base[0]), travel, accel)

            recorded.append(record_clean_pass(acq, geom, rp, back_to_start))
        robot.move_l(ur_pose(geom, resolved[-1].retreat), travel, accel)
    return recorded


def _turn_table(
    acq: Acquisition, rp: ResolvedPass, report: StepReport, total: int, settle_s: float
) -> None:
    """Turn the table to the pass's angle unless it stands there already."""
    assert rp.table_angle_rad is not None
    table = acq.require_table(f"{rp.label} is at a table angle")
    here = float(table.angle())
    if angle_diff(here, rp.table_angle_rad) > TABLE_STILL_RAD:
        deg = math.degrees(rp.table_angle_rad)
        report(rp.index + 1, total, f"turning the table to {deg:.1f} deg")
        table.move_to(rp.table_angle_rad, wait=True)
        time.sleep(settle_s)


def _guarded(acq: Acquisition) -> AbstractContextManager[None]:
    """The procedures' guard for a scan: stop the robot and the table when anything goes wrong
    while moving; driver errors, failed checks of a pass and Ctrl-C become :class:`ScanAborted`."""
    return guarded_motion(
        acq,
        "scan",
        error=ScanAborted,
        also=(ScanError,),
        consequence="the robot and the table were stopped",
    )


# --------------------------------------------------------------------------------------------
# Alignment


def align_passes(
    recorded: Sequence[RecordedPass],
    cal: ScanCalibration,
    frame: str,
    plan: ScanPlan | None = None,
) -> list[PassCloud]:
    """Each pass into ``frame`` ("base" or "part") with the calibrations ``cal`` (Eq. (1)),
    cropped to ``plan.crop`` when given."""
    out: list[PassCloud] = []
    for rec in recorded:
        sw = rec.sweep
        if frame == "part":
            if cal.base2table is None or rec.table_angle_rad is None:
                raise ScanError("part-frame clouds need the table calibration and angle")
            poses = sensor_poses(
                sw.flange2base,
                cal.sensor2flange,
                cal.base2table,
                rec.table_angle_rad,
                cal.encoder_offset_rad,
                frame="part",
            )
        else:
            poses = sensor_poses(sw.flange2base, cal.sensor2flange)
        m = sw.valid & np.isfinite(sw.y) & np.isfinite(sw.z)
        xyz = align_with_poses(sw.y, sw.z, sw.profile_index, poses, mask=m)
        origins = np.asarray(poses[sw.profile_index[m], :3, 3])
        if plan is not None and plan.crop is not None:
            lo, hi = np.asarray(plan.crop.min_m), np.asarray(plan.crop.max_m)
            keep = np.all((xyz >= lo) & (xyz <= hi), axis=1)
            xyz, origins = xyz[keep], origins[keep]
        out.append(PassCloud(rec.index, rec.label, xyz, origins))
    return out


# --------------------------------------------------------------------------------------------
# Report


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def scan_report(
    plan: ScanPlan,
    recorded: Sequence[RecordedPass],
    clouds: Sequence[PassCloud],
    merge: MergeResult | None,
    cal: ScanCalibration,
    opts: MergeOptions,
    frame: str,
    duration_s: float,
) -> dict[str, Any]:
    """The job report (JSON-ready; lengths in mm, angles in degrees, as named)."""
    passes = []
    for rec, c in zip(recorded, clouds, strict=True):
        row: dict[str, Any] = {
            "pass": rec.index + 1,
            "label": rec.label,
            "kind": rec.kind,
            "table_deg": None
            if rec.table_angle_rad is None
            else round(math.degrees(rec.table_angle_rad), 4),
            "profiles": rec.sweep.n_profiles,
            "points": c.n_points,
            "duration_s": round(rec.duration_s, 3),
            "repeats": rec.repeats,
            "clock_clean": rec.clock_clean,
        }
        if merge is not None:
            k = merge.corrections[[x.index for x in merge.corrections].index(c.index)]
            row.update(
                {
                    "correction_mm": _finite(k.shift_m * 1e3),
                    "correction_deg": _finite(k.rotation_deg),
                    "max_displacement_mm": _finite(k.max_displacement_m * 1e3),
                    "sigma_mm": _finite(k.sigma_m * 1e3),
                    "free_directions": k.free_directions,
                    "overlap_points": k.overlap_points,
                    "rms_before_mm": _finite(k.rms_before_m * 1e3),
                    "rms_after_mm": _finite(k.rms_after_m * 1e3),
                    "status": k.status,
                    "note": k.note,
                }
            )
        passes.append(row)
    flagged = [] if merge is None else [c.index + 1 for c in merge.flagged]
    return {
        "plan": plan.name,
        "frame": frame,
        "passes": passes,
        "icp": None
        if merge is None
        else {
            "rounds": merge.rounds,
            "flag_translation_mm": opts.flag_translation_m * 1e3,
            "flag_rotation_deg": opts.flag_rotation_deg,
            "flagged_passes": flagged,
        },
        "fault_suspected": bool(flagged),
        "calibration": cal.sources,
        "duration_s": round(duration_s, 2),
    }


def report_lines(report: dict[str, Any]) -> list[str]:
    """The report as readable lines (the CLI prints them)."""
    lines = [
        f"{'pass':>4} {'table':>7} {'points':>8} {'corr mm':>8} {'deg':>7} {'+-mm':>6} "
        f"{'rms before/after um':>19}  status",
    ]
    for p in report["passes"]:

        def f(key: str, scale: float = 1.0, fmt: str = ".4f", row: dict[str, Any] = p) -> str:
            v = row.get(key)
            return "-" if v is None else format(v * scale, fmt)

        table = "-" if p["table_deg"] is None else f"{p['table_deg']:.1f}"
        rms = f"{f('rms_before_mm', 1e3, '.1f')}/{f('rms_after_mm', 1e3, '.1f')}"
        lines.append(
            f"{p['pass']:>4} {table:>7} {p['points']:>8} {f('correction_mm'):>8} "
            f"{f('correction_deg'):>7} {f('sigma_mm'):>6} {rms:>19}  {p.get('status', '-')}"
            f"  {p['label']}"
        )
        if p.get("note"):
            lines.append(f"       {p['note']}")
        if not p.get("clock_clean", True):
            lines.append(
                f"       a clock fit of the synchroniser restarted during each of its "
                f"{p['repeats'] + 1} tries: its timing is suspect"
            )
        elif p.get("repeats"):
            lines.append(f"       recorded again {p['repeats']}x after a clock fit restart")
    icp = report.get("icp")
    if icp is None:
        lines.append("ICP: not run; the passes are merged as the calibration aligned them")
    elif icp["flagged_passes"]:
        lines.append(
            f"WARNING: pass(es) {', '.join(map(str, icp['flagged_passes']))} needed corrections "
            f"above {icp['flag_translation_mm']:g} mm / {icp['flag_rotation_deg']:g} deg: a "
            "calibration or timing fault is suspected (wristscan calibrate sensor / latency)"
        )
    else:
        lines.append(
            f"ICP: every correction within {icp['flag_translation_mm']:g} mm / "
            f"{icp['flag_rotation_deg']:g} deg ({icp['rounds']} rounds)"
        )
    return lines
