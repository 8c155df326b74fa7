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
   anything moves (:class:`PlanRejected`).
3. For each pass: back off from the previous pass, turn the table if the pass asks for an angle,
   joint move to the approach pose, linear move in, record the pass (linear moves through its
   poses), and read the table angle before and after it (the table must stand still during a
   pass). Any failure stops the robot and the table (:class:`ScanAborted`).
4. :func:`align_passes`: each pass into the plan frame with the calibrations in force (Eq. (1)),
   cropped to the plan's box.
5. :func:`merge_passes`: point-to-plane ICP of every pass against the union of the others, in
   rounds; the corrections are reported per pass (mm, degrees) and those above the thresholds
   are **flagged** as a sign of a calibration or timing fault, never silently absorbed.
6. :func:`write_outputs`: binary PLY per pass and merged (voxel down-sampled, normals facing the
   sensor), an NPZ with everything, a JSON report, and optionally a Poisson surface (the
   ``surface`` extra: pymeshlab, MeshLab's own filters).

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

import dataclasses
import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from wristscan.calib import se3
from wristscan.calib.align import align_with_poses, sensor_poses
from wristscan.calib.icp import estimate_normals, icp_point_to_plane
from wristscan.daemon.calibrate.table import (
    MotionNotConfirmed,
    ProcedureAborted,
    ProcedureError,
    Progress,
    calibration_in_force,
    no_progress,
    procedure_acquisition,
    require_motion,
)
from wristscan.daemon.config import Config
from wristscan.daemon.scan.plan import (
    CellGeometry,
    PlanCheck,
    PlanError,
    ResolvedPass,
    ScanPlan,
    check_plan,
    resolve_plan,
)

if TYPE_CHECKING:
    from wristscan.daemon.procedure.acquisition import Acquisition, Sweep
__all__ = [
    "MergeOptions",
    "MergeResult",
    "MotionNotConfirmed",
    "PassCloud",
    "PassCorrection",
    "PlanRejected",
    "RecordedPass",
    "ScanAborted",
    "ScanCalibration",
    "ScanError",
    "ScanResult",
    "SurfaceUnavailable",
    "align_passes",
    "dry_run",
    "load_scan_calibration",
    "merge_passes",
    "poisson_surface",
    "run_scan",
    "voxel_mean",
    "write_outputs",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

_TABLE_STILL_RAD = 2e-4
"""The table angle before and after a pass may differ by this much (encoder noise)."""
_MIN_OVERLAP_POINTS = 200
_PASS_TRIES = 3
_JOINT_NEIGHBOURS = 12
"""Neighbours searched per point for one from another pass (voxelised passes: a few each)."""


class ScanError(ProcedureError):
    """A scan job cannot run or failed; the message says why."""


class PlanRejected(ScanError):
    """The plan failed its checks before anything moved; ``problems`` lists them."""

    def __init__(self, problems: Sequence[str]) -> None:
        self.problems = list(problems)
        super().__init__(
            "the plan was refused before anything moved:\n" + "\n".join(f"  {p}" for p in problems)
        )


class ScanAborted(ScanError, ProcedureAborted):
    """The scan stopped part way (protective stop, refused move, lost device, Ctrl-C); the robot
    and the table were stopped."""


class SurfaceUnavailable(ScanError):
    """The optional surface reconstruction library is not installed."""


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
            model = robot.kinematic_model() or model  # type: ignore[attr-defined]
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
                table_angle = float(devices.table.angle())  # type: ignore[attr-defined]
            finally:
                devices.table.close()
    else:
        q = np.asarray(q_start, dtype=np.float64)
    geom = _geometry(cfg, cal, tcp2flange, model)
    resolved = _resolve(plan, geom, table_angle)
    return resolved, check_plan(resolved, geom, q)


# --------------------------------------------------------------------------------------------
# Execution


@dataclass(frozen=True)
class RecordedPass:
    """The profiles of one pass, paired with the robot poses (base frame)."""

    index: int
    label: str
    kind: str
    sweep: Sweep
    table_angle_rad: float | None
    """Encoder angle of the table during the pass (rad); None without a table."""
    duration_s: float
    repeats: int = 0
    """How often the pass was recorded again because a clock fit restarted during it."""
    clock_clean: bool = True
    """False: every try saw a clock fit restart; the timing of this pass is suspect."""


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


def _angle_diff(a: float, b: float) -> float:
    return abs((a - b + math.pi) % (2.0 * math.pi) - math.pi)


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
    report = progress or no_progress
    t0 = time.monotonic()
    n = len(plan.passes)
    total = n + 2
    recorded: list[RecordedPass] = []
    report(0, total, "connecting, waiting for paired profiles")
    with procedure_acquisition(cfg) as acq:
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
        r = cfg.robot
        travel = min(plan.travel_speed_m_s, r.max_speed_m_s)
        accel = r.max_accel_m_s2
        jspeed = min(1.0, r.max_joint_speed_rad_s)
        jaccel = r.max_joint_accel_rad_s2
        with _guarded(acq):
            for rp, pc in zip(resolved, check.passes, strict=True):
                if recorded:
                    robot.move_l(_ur(geom, resolved[rp.index - 1].retreat), travel, accel)
                if rp.table_angle_rad is not None:
                    here = float(acq.table.angle())
                    if _angle_diff(here, rp.table_angle_rad) > _TABLE_STILL_RAD:
                        deg = math.degrees(rp.table_angle_rad)
                        report(rp.index + 1, total, f"turning the table to {deg:.1f} deg")
                        acq.table.move_to(rp.table_angle_rad, wait=True)
                        time.sleep(table_settle_s)
                report(rp.index + 1, total, f"{rp.label}: moving to the start")
                assert pc.q_approach is not None
                robot.move_j(pc.q_approach, jspeed, jaccel)
                robot.move_l(_ur(geom, rp.sensor2base[0]), travel, accel)
                report(
                    rp.index + 1,
                    total,
                    f"{rp.label}: recording {rp.length_m * 1e3:.0f} mm at "
                    f"{rp.speed_m_s * 1e3:g} mm/s",
                )

                def back_to_start(rp: ResolvedPass = rp, q: FloatArray = pc.q_approach) -> None:
                    robot.move_l(_ur(geom, rp.retreat), travel, accel)
                    robot.move_j(q, jspeed, jaccel)
                    robot.move_l(_ur(geom, rp.sensor2base[0]), travel, accel)

                recorded.append(_record_clean_pass(acq, geom, rp, back_to_start))
            robot.move_l(_ur(geom, resolved[-1].retreat), travel, accel)
    report(n + 1, total, "aligning and merging the passes")
    frame = plan.frame
    clouds = align_passes(recorded, cal, frame, plan)
    merge = merge_passes(clouds, opts) if opts.icp and len(clouds) > 1 else None
    duration = time.monotonic() - t0
    summary = scan_report(plan, recorded, clouds, merge, cal, opts, frame, duration)
    files: list[Path] = []
    if out_dir is not None:
        files = write_outputs(out_dir, clouds, merge, opts, summary)
    report(total, total, "done")
    return ScanResult(plan, recorded, clouds, merge, files, cal, duration, frame, summary)


def _ur(geom: CellGeometry, sensor2base: FloatArray) -> FloatArray:
    return np.asarray(se3.matrix_to_pose(geom.tcp_of(sensor2base)))


def _clock_state(acq: Acquisition) -> tuple[Any, ...]:
    """Epoch, resets and re-anchorings of every clock fit of the synchroniser: a change means
    that a fit restarted, and profiles paired around it may be milliseconds off."""
    p = acq.stats().get("pairing", {})
    clocks = [p.get("robot_clock", {}), *p.get("sensor_clocks", {}).values()]
    return tuple((c.get("epoch"), c.get("resets"), c.get("reanchors")) for c in clocks)


def _record_clean_pass(
    acq: Acquisition, geom: CellGeometry, rp: ResolvedPass, back_to_start: Callable[[], None]
) -> RecordedPass:
    """Record a pass; repeat it (up to ``_PASS_TRIES`` times, going back to the start the way
    the plan came) when a clock fit of the synchroniser restarted meanwhile. The last try is
    kept and marked when none was clean."""
    for attempt in range(1, _PASS_TRIES + 1):
        before = _clock_state(acq)
        rec = _record_pass(acq, geom, rp)
        if _clock_state(acq) == before:
            return dataclasses.replace(rec, repeats=attempt - 1)
        log.warning("%s: a clock fit restarted during the pass (try %d)", rp.label, attempt)
        if attempt < _PASS_TRIES:
            back_to_start()
    return dataclasses.replace(rec, repeats=_PASS_TRIES - 1, clock_clean=False)


def _record_pass(acq: Acquisition, geom: CellGeometry, rp: ResolvedPass) -> RecordedPass:
    """Record the linear moves of one pass; the table must not turn meanwhile."""
    robot = acq.robot
    accel = acq.cfg.robot.max_accel_m_s2
    before = float(acq.table.angle()) if acq.table is not None else None
    t0 = time.monotonic()
    with acq.record() as rec:
        for pose in rp.sensor2base[1:]:
            robot.move_l(_ur(geom, pose), rp.speed_m_s, accel)
    sweep = rec.result()
    angle: float | None = None
    if before is not None:
        after = float(acq.table.angle())
        if _angle_diff(before, after) > _TABLE_STILL_RAD:
            raise ScanError(
                f"{rp.label}: the table turned during the pass "
                f"({math.degrees(before):.4f} -> {math.degrees(after):.4f} deg)"
            )
        angle = before + 0.5 * math.remainder(after - before, 2.0 * math.pi)
    if sweep.n_profiles == 0:
        raise ScanError(f"{rp.label}: no profile was paired with the robot during the pass")
    log.info("%s: %d profiles, %d valid points", rp.label, sweep.n_profiles, sweep.valid.sum())
    return RecordedPass(rp.index, rp.label, rp.kind, sweep, angle, time.monotonic() - t0)


def _guarded(acq: Acquisition) -> AbstractContextManager[None]:
    """Stop the robot and the table when anything goes wrong while moving; re-raise as
    :class:`ScanAborted` (driver errors, failed checks of a pass, Ctrl-C)."""
    from wristscan.daemon.procedure.acquisition import stop_on_failure

    def abort(reason: str) -> ScanAborted:
        return ScanAborted(f"scan aborted: {reason}; the robot and the table were stopped")

    return stop_on_failure(acq, abort, (ScanError,))


# --------------------------------------------------------------------------------------------
# Alignment


@dataclass
class PassCloud:
    """One pass in the plan frame: points and, per point, the sensor origin that saw it."""

    index: int
    label: str
    xyz: FloatArray
    origins: FloatArray

    @property
    def n_points(self) -> int:
        return int(self.xyz.shape[0])


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
# Down-sampling and normals


def voxel_mean(xyz: FloatArray, voxel_m: float, *extra: FloatArray) -> tuple[FloatArray, ...]:
    """One point per occupied voxel of edge ``voxel_m`` (m): the mean of its points, and the
    mean of each ``extra`` (N, k) array over the same points. ``voxel_m <= 0`` returns copies."""
    if voxel_m <= 0.0 or xyz.shape[0] == 0:
        return (xyz.copy(), *(e.copy() for e in extra))
    ijk = np.floor((xyz - xyz.min(axis=0)) / voxel_m).astype(np.int64)
    dims = ijk.max(axis=0) + 1
    key = np.ravel_multi_index(ijk.T, tuple(int(d) for d in dims))
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    out = []
    for a in (xyz, *extra):
        s = np.zeros((counts.size, a.shape[1]))
        for j in range(a.shape[1]):  # bincount per column: much faster than np.add.at
            s[:, j] = np.bincount(inverse, weights=a[:, j], minlength=counts.size)
        out.append(s / counts[:, None])
    return tuple(out)


def oriented_normals(xyz: FloatArray, origins: FloatArray, k: int = 12) -> FloatArray:
    """Unit normals of ``xyz`` (PCA of ``k`` neighbours), each turned towards the sensor origin
    that saw its point."""
    if xyz.shape[0] < k:
        return np.tile([0.0, 0.0, 1.0], (xyz.shape[0], 1))
    n = estimate_normals(xyz, k)
    flip = np.einsum("ij,ij->i", n, origins - xyz) < 0.0
    n[flip] *= -1.0
    return n


# --------------------------------------------------------------------------------------------
# Merging


@dataclass(frozen=True)
class MergeOptions:
    """Settings of :func:`merge_passes` and :func:`write_outputs` (SI units)."""

    icp: bool = True
    icp_voxel_m: float = 0.0005
    """Voxel of the clouds that ICP works on (m)."""
    max_distance_m: float = 0.002
    """Farthest pair ICP uses (m): the paper saw up to 0.5 mm between passes."""
    fine_distance_m: float = 0.001
    """Pairing distance of the overlap once the passes are close (m)."""
    trim_fraction: float = 0.9
    normal_agreement_deg: float = 30.0
    """A source point belongs to the overlap when the nearest point of the others is within
    the pairing distance and their normals agree within this angle (so that points of a face
    that only this pass sees are not pulled onto a neighbouring face)."""
    rounds: int = 8
    """Most joint refinement steps after the coarse round."""
    converged_m: float = 0.5e-6
    """The refinement stops when no pass moves by more than this (m)."""
    weak_ratio: float = 1e-2
    """Coarse round: directions of a pass's correction stiffer than this fraction of its
    stiffest are corrected, the others are left as calibrated."""
    joint_ratio: float = 1e-4
    """Joint refinement: the same, relative to each pass's mean stiffness; the 1-sigma limit
    below is what usually decides there."""
    weak_sigma_m: float = 1e-5
    """... and only directions whose 1-sigma from the fit is at most this (m)."""
    flag_translation_m: float = 5e-5
    """A pass whose correction moves its centroid by more than this is flagged (m)."""
    flag_rotation_deg: float = 0.05
    """A pass whose correction turns it by more than this is flagged (degrees)."""
    normals_k: int = 12
    voxel_m: float = 0.00025
    """Voxel of the written clouds (m); 0 keeps every point."""
    surface: bool = False
    """Also write a Poisson surface (needs the ``surface`` extra)."""
    surface_depth: int = 9
    surface_trim_m: float = 0.001
    """Surface triangles farther than this from the merged cloud are removed (m)."""

    def __post_init__(self) -> None:
        if not 0.0 < self.trim_fraction <= 1.0:
            raise ValueError("trim_fraction must be in (0, 1]")
        if self.icp_voxel_m < 0 or self.voxel_m < 0:
            raise ValueError("voxel sizes must be >= 0")
        if self.max_distance_m <= 0 or self.fine_distance_m <= 0:
            raise ValueError("pairing distances must be > 0")
        if self.rounds < 1:
            raise ValueError("rounds must be >= 1")


@dataclass(frozen=True)
class PassCorrection:
    """The ICP correction of one pass relative to the consensus of all passes."""

    index: int
    label: str
    transform: FloatArray
    """(4, 4) maps the pass as aligned by the calibration onto the merged cloud."""
    shift_m: float
    """Displacement of the pass's centroid (m)."""
    rotation_deg: float
    max_displacement_m: float
    """Largest displacement of any of its points (m)."""
    sigma_m: float
    """Largest 1-sigma (m of displacement) of the corrected directions, from the fit."""
    free_directions: int
    """Directions (of 6) the overlap did not constrain: not corrected."""
    overlap_points: int
    rms_before_m: float
    """Point-to-plane RMS against the others before ICP (m)."""
    rms_after_m: float
    status: str
    """``"ok"``, ``"flagged"`` (correction above a threshold) or ``"not measured"``."""
    note: str = ""

    @property
    def flagged(self) -> bool:
        return self.status == "flagged"


@dataclass
class MergeResult:
    corrections: list[PassCorrection]
    rounds: int
    options: MergeOptions

    @property
    def flagged(self) -> list[PassCorrection]:
        return [c for c in self.corrections if c.flagged]

    def transform(self, index: int) -> FloatArray:
        for c in self.corrections:
            if c.index == index:
                return c.transform
        return np.eye(4)


def _apply(T: FloatArray, p: FloatArray) -> FloatArray:
    return np.asarray(p @ T[:3, :3].T + T[:3, 3])


@dataclass
class _IcpCloud:
    xyz: FloatArray
    normals: FloatArray


def _overlap(
    src: _IcpCloud, tgt: _IcpCloud, tree: cKDTree, max_d: float, cos_agree: float
) -> tuple[NDArray[np.bool_], NDArray[np.intp]]:
    d, j = tree.query(src.xyz, k=1, distance_upper_bound=max_d)
    ok = np.isfinite(d)
    jj = np.where(ok, j, 0)
    ok &= np.einsum("ij,ij->i", src.normals, tgt.normals[jj]) > cos_agree
    return ok, jj


@dataclass(frozen=True)
class _Constraint:
    """How well an overlap constrains a rigid correction: the information matrix of the
    point-to-plane pairs (rotations scaled by ``scale_m`` about ``pivot``)."""

    H: FloatArray
    rms_m: float
    pivot: FloatArray
    scale_m: float
    n_pairs: int


def _constraint(src: FloatArray, tgt: _IcpCloud, tree: cKDTree, max_d: float) -> _Constraint | None:
    d, j = tree.query(src, k=1, distance_upper_bound=max_d)
    ok = np.isfinite(d)
    if ok.sum() < _MIN_OVERLAP_POINTS:
        return None
    p = src[ok]
    n = tgt.normals[j[ok]]
    r = np.einsum("ij,ij->i", n, p - tgt.xyz[j[ok]])
    pivot = p.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((p - pivot) ** 2, axis=1))))
    J = np.concatenate([np.cross(p - pivot, n) / scale, n], axis=1)
    return _Constraint(J.T @ J, float(np.sqrt(np.mean(r * r))), pivot, scale, int(ok.sum()))


def _twist(T: FloatArray, pivot: FloatArray, scale: float) -> FloatArray:
    """``[w * scale, v]``: rotation vector (scaled to metres at ``scale``) and displacement of
    ``pivot`` of a small rigid motion ``T``."""
    w = se3.matrix_to_rotvec(T[:3, :3])
    v = T[:3, :3] @ pivot + T[:3, 3] - pivot
    return np.concatenate([w * scale, v])


def _from_twist(x: FloatArray, pivot: FloatArray, scale: float) -> FloatArray:
    R = se3.rotvec_to_matrix(x[:3] / scale)
    return np.asarray(se3.make(R, pivot + x[3:] - R @ pivot))


def _strong_directions(c: _Constraint, o: MergeOptions) -> tuple[FloatArray, float]:
    """Eigenvectors (6, k) of the directions the overlap constrains (stiffness at least
    ``weak_ratio`` of the stiffest and 1-sigma at most ``weak_sigma_m``), and the largest
    1-sigma among them (m)."""
    ev, V = np.linalg.eigh(c.H)
    ev = np.maximum(ev, 1e-300)
    sigma = c.rms_m / np.sqrt(ev)
    strong = (ev >= o.weak_ratio * ev[-1]) & (sigma <= o.weak_sigma_m)
    return V[:, strong], float(sigma[strong].max()) if strong.any() else math.inf


def _restrict(step: FloatArray, c: _Constraint, o: MergeOptions) -> tuple[FloatArray, int, float]:
    """``step`` without its components along directions the overlap does not constrain (a
    rotation about the axis of a cylinder, a slide along a groove): those are left as the
    calibration put them. Returns (step, free directions, 1-sigma of the kept ones)."""
    E, sig = _strong_directions(c, o)
    x = _twist(step, c.pivot, c.scale_m)
    return _from_twist(E @ (E.T @ x), c.pivot, c.scale_m), 6 - E.shape[1], sig


def _rms_against(src: FloatArray, tgt: _IcpCloud, tree: cKDTree, max_d: float) -> float:
    d, j = tree.query(src, k=1, distance_upper_bound=max_d)
    ok = np.isfinite(d)
    if not ok.any():
        return math.inf
    r = np.einsum("ij,ij->i", tgt.normals[j[ok]], src[ok] - tgt.xyz[j[ok]])
    return float(np.sqrt(np.mean(r * r)))


def _union(ds: Sequence[_IcpCloud], T: Sequence[FloatArray], idx: Sequence[int]) -> _IcpCloud:
    return _IcpCloud(
        np.concatenate([_apply(T[j], ds[j].xyz) for j in idx]),
        np.concatenate([ds[j].normals @ T[j][:3, :3].T for j in idx]),
    )


def _joint_step(
    ds: Sequence[_IcpCloud], T: list[FloatArray], max_d: float, cos_agree: float, o: MergeOptions
) -> float:
    """One linearised least-squares step of all passes at once (multi-view point-to-plane):
    every point is paired with the nearest point of another pass (within ``max_d``, normals
    agreeing), the residuals are Tukey-weighted, and the 6n x 6n normal equations are solved in
    the subspace the pairs constrain (eigen-directions stiff and certain enough). The gauge (a
    motion of all passes together) is in the null space, so the minimum-norm step keeps the
    consensus as the reference. Updates ``T`` in place; returns the largest displacement (m)."""
    n = len(ds)
    X = np.concatenate([_apply(T[i], ds[i].xyz) for i in range(n)])
    M = np.concatenate([ds[i].normals @ T[i][:3, :3].T for i in range(n)])
    owner = np.concatenate([np.full(ds[i].xyz.shape[0], i) for i in range(n)])
    if X.shape[0] < 2 * _MIN_OVERLAP_POINTS:
        return 0.0
    k = min(_JOINT_NEIGHBOURS, X.shape[0])
    dist, nb = cKDTree(X).query(X, k=k, distance_upper_bound=max_d)
    ok = np.isfinite(dist)
    nb = np.where(ok, nb, 0)
    ok &= owner[nb] != owner[:, None]
    ok &= np.einsum("ij,ikj->ik", M, M[nb]) > cos_agree
    has = ok.any(axis=1)
    src = np.flatnonzero(has)
    tgt = nb[src, ok[src].argmax(axis=1)]  # nearest neighbour from another pass
    if src.size < _MIN_OVERLAP_POINTS:
        return 0.0
    c = X.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((X - c) ** 2, axis=1))))
    m = M[tgt]
    r = np.einsum("ij,ij->i", m, X[src] - X[tgt])
    mad = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    u = r / max(4.685 * mad, 1e-9)
    w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
    A = np.concatenate([np.cross(X[src] - c, m) / scale, m], axis=1)
    B = -np.concatenate([np.cross(X[tgt] - c, m) / scale, m], axis=1)
    H = np.zeros((6 * n, 6 * n))
    g = np.zeros(6 * n)
    key = owner[src] * n + owner[tgt]
    order = np.argsort(key, kind="stable")
    bounds = np.flatnonzero(np.diff(key[order])) + 1
    for grp in np.split(order, bounds):
        i, j = divmod(int(key[grp[0]]), n)
        a, b, wr, ww = A[grp], B[grp], w[grp] * r[grp], w[grp][:, None]
        si, sj = slice(6 * i, 6 * i + 6), slice(6 * j, 6 * j + 6)
        H[si, si] += (a * ww).T @ a
        H[sj, sj] += (b * ww).T @ b
        H[si, sj] += (a * ww).T @ b
        H[sj, si] += (b * ww).T @ a
        g[si] += a.T @ wr
        g[sj] += b.T @ wr
    sigma_r = float(np.sqrt(np.sum(w * r * r) / max(float(w.sum()), 1e-12)))
    # Each pass's block scaled to unit mean stiffness, so that "weak" means weak for that pass
    # (a pass that sees little is not drowned by the stiffness of the others).
    stiff = np.array([np.trace(H[6 * i : 6 * i + 6, 6 * i : 6 * i + 6]) / 6.0 for i in range(n)])
    scl = np.repeat(np.where(stiff > 0, 1.0 / np.sqrt(np.maximum(stiff, 1e-300)), 0.0), 6)
    ev, V = np.linalg.eigh(H * scl[:, None] * scl[None, :])
    if float(ev[-1]) <= 0.0:
        return 0.0
    ev_safe = np.maximum(ev, 1e-300)
    sigma = sigma_r * np.linalg.norm(V * scl[:, None], axis=0) / np.sqrt(ev_safe)
    keep = (ev > o.joint_ratio * float(ev[-1])) & (sigma <= o.weak_sigma_m)
    Vs = V[:, keep]
    x = -scl * (Vs @ ((Vs.T @ (scl * g)) / ev[keep]))
    biggest = 0.0
    for i in range(n):
        xi = x[6 * i : 6 * i + 6]
        biggest = max(biggest, float(np.linalg.norm(xi[:3])) + float(np.linalg.norm(xi[3:])))
        T[i] = _from_twist(xi, c, scale) @ T[i]
    return biggest


def merge_passes(clouds: Sequence[PassCloud], options: MergeOptions | None = None) -> MergeResult:
    """Refine the alignment of the passes with point-to-plane ICP and measure the corrections.

    Every pass is down-sampled (``icp_voxel_m``) and given sensor-facing normals once.

    1. Coarse: every pass is registered onto the union of the others as they stand
       (:func:`~wristscan.calib.icp.icp_point_to_plane`, pairs within ``max_distance_m``,
       trimmed: robust to partial overlap) after selecting its overlap (nearest point of the
       others close enough, normals agreeing). The step keeps only the directions that the
       overlap constrains (a cylinder leaves a rotation about its axis free, which noise alone
       would otherwise drive); the mean correction is removed.
    2. Fine: all passes at once (:func:`_joint_step`, pairs within ``fine_distance_m``), which
       also settles groups of passes that only loosely hold each other, until the steps are
       below ``converged_m`` or after ``rounds`` steps.

    The consensus of all passes is the reference. A pass whose overlap is too small or
    constrains almost nothing is left as the calibration put it and reported as
    ``"not measured"``.
    """
    o = options or MergeOptions()
    n = len(clouds)
    ds: list[_IcpCloud] = []
    for c in clouds:
        xyz, org = voxel_mean(c.xyz, o.icp_voxel_m, c.origins)
        ds.append(_IcpCloud(xyz, oriented_normals(xyz, org, o.normals_k)))
    T = [np.eye(4) for _ in range(n)]
    notes: list[str] = [""] * n
    cos_agree = math.cos(math.radians(o.normal_agreement_deg))
    pts = [d.xyz for d in ds if d.xyz.shape[0]]
    centre = np.concatenate(pts).mean(axis=0) if pts else np.zeros(3)
    coarse = [False] * n
    for i in range(n):
        if ds[i].xyz.shape[0] < _MIN_OVERLAP_POINTS:
            notes[i] = f"only {ds[i].xyz.shape[0]} points after down-sampling"
            continue
        others = [j for j in range(n) if j != i and ds[j].xyz.shape[0]]
        if not others:
            notes[i] = "no other pass to compare with"
            continue
        tgt = _union(ds, T, others)
        src = _union(ds, T, [i])
        tree = cKDTree(tgt.xyz)
        ok, _ = _overlap(src, tgt, tree, o.max_distance_m, cos_agree)
        if ok.sum() < _MIN_OVERLAP_POINTS:
            notes[i] = f"overlap with the other passes too small ({int(ok.sum())} points)"
            continue
        try:
            res = icp_point_to_plane(
                src.xyz[ok],
                tgt.xyz,
                tgt.normals,
                max_distance=o.max_distance_m,
                trim_fraction=o.trim_fraction,
                max_iter=30,
                tol=1e-8,
            )
        except ValueError as exc:
            notes[i] = f"ICP: {exc}"
            continue
        con = _constraint(_apply(res.source2target, src.xyz[ok]), tgt, tree, o.max_distance_m)
        if con is None:
            notes[i] = "overlap lost during ICP"
            continue
        step, free, _ = _restrict(res.source2target, con, o)
        if free < 6:
            T[i] = step @ T[i]
            coarse[i] = True
    idx = [i for i in range(n) if coarse[i]]
    if idx:
        w = np.mean([se3.matrix_to_rotvec(T[i][:3, :3]) for i in idx], axis=0)
        dc = np.mean([_apply(T[i], centre[None])[0] - centre for i in idx], axis=0)
        Rm = se3.rotvec_to_matrix(w)
        Gi = se3.invert(se3.make(Rm, centre + dc - Rm @ centre))
        for i in idx:
            T[i] = Gi @ T[i]
    rounds_done = 1
    for _ in range(o.rounds):
        step_m = _joint_step(ds, T, o.fine_distance_m, cos_agree, o)
        rounds_done += 1
        log.debug("merge step %d: largest step %.2g m", rounds_done, step_m)
        if step_m < o.converged_m:
            break

    measured = [False] * n
    free_dirs = [6] * n
    sigmas = [math.inf] * n
    corrections: list[PassCorrection] = []
    for i, c in enumerate(clouds):
        d = ds[i]
        others = [j for j in range(n) if j != i and ds[j].xyz.shape[0]]
        if d.xyz.shape[0] < _MIN_OVERLAP_POINTS or not others:
            corrections.append(_unmeasured(c, notes[i] or "no points"))
            continue
        ci = d.xyz.mean(axis=0)
        moved = _apply(T[i], d.xyz)
        # Before: every pass as the calibration put it; after: as merged.
        before = _union(ds, [np.eye(4)] * n, others)
        after = _union(ds, T, others)
        tb, ta = cKDTree(before.xyz), cKDTree(after.xyz)
        ok_b, _ = _overlap(d, before, tb, o.fine_distance_m, cos_agree)
        src_a = _IcpCloud(moved, d.normals @ T[i][:3, :3].T)
        ok_a, _ = _overlap(src_a, after, ta, o.fine_distance_m, cos_agree)
        con = _constraint(moved[ok_a], after, ta, o.fine_distance_m)
        if con is not None:
            E, sigmas[i] = _strong_directions(con, o)
            free_dirs[i] = 6 - E.shape[1]
            measured[i] = free_dirs[i] < 6
        if not measured[i]:
            why = notes[i] or (
                "overlap with the other passes too small"
                if con is None
                else "the overlap constrains no direction well enough"
            )
            corrections.append(_unmeasured(c, why))
            continue
        disp = np.linalg.norm(moved - d.xyz, axis=1)
        shift = float(np.linalg.norm(_apply(T[i], ci[None])[0] - ci))
        rot = math.degrees(float(se3.rotation_angle(T[i][:3, :3])))
        flagged = shift > o.flag_translation_m or rot > o.flag_rotation_deg
        note = ""
        if flagged:
            note = (
                f"correction {shift * 1e3:.3f} mm / {rot:.4f} deg above the thresholds "
                f"{o.flag_translation_m * 1e3:g} mm / {o.flag_rotation_deg:g} deg: calibration "
                "or timing fault suspected"
            )
        elif free_dirs[i]:
            note = f"{free_dirs[i]} of 6 directions weakly constrained by the overlap"
        corrections.append(
            PassCorrection(
                index=c.index,
                label=c.label,
                transform=T[i],
                shift_m=shift,
                rotation_deg=rot,
                max_displacement_m=float(disp.max()),
                sigma_m=sigmas[i],
                free_directions=free_dirs[i],
                overlap_points=int(ok_a.sum()),
                rms_before_m=_rms_against(d.xyz[ok_b], before, tb, o.fine_distance_m),
                rms_after_m=_rms_against(moved[ok_a], after, ta, o.fine_distance_m),
                status="flagged" if flagged else "ok",
                note=note,
            )
        )
    return MergeResult(corrections, rounds_done, o)


def _unmeasured(c: PassCloud, note: str) -> PassCorrection:
    return PassCorrection(
        index=c.index,
        label=c.label,
        transform=np.eye(4),
        shift_m=math.nan,
        rotation_deg=math.nan,
        max_displacement_m=math.nan,
        sigma_m=math.nan,
        free_directions=6,
        overlap_points=0,
        rms_before_m=math.nan,
        rms_after_m=math.nan,
        status="not measured",
        note=note,
    )


# --------------------------------------------------------------------------------------------
# Report and outputs


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


def corrected_clouds(clouds: Sequence[PassCloud], merge: MergeResult | None) -> list[PassCloud]:
    """The passes moved by their ICP corrections (unchanged without a merge)."""
    if merge is None:
        return list(clouds)
    out = []
    for c in clouds:
        T = merge.transform(c.index)
        out.append(PassCloud(c.index, c.label, _apply(T, c.xyz), _apply(T, c.origins)))
    return out


def merged_cloud(
    clouds: Sequence[PassCloud], voxel_m: float, normals_k: int = 12
) -> tuple[FloatArray, FloatArray]:
    """Union of ``clouds`` down-sampled to ``voxel_m`` (m): points and sensor-facing normals."""
    if not clouds:
        return np.zeros((0, 3)), np.zeros((0, 3))
    xyz = np.concatenate([c.xyz for c in clouds])
    org = np.concatenate([c.origins for c in clouds])
    v, o = voxel_mean(xyz, voxel_m, org)
    return v, oriented_normals(v, o, normals_k)


def write_outputs(
    out_dir: Path,
    clouds: Sequence[PassCloud],
    merge: MergeResult | None,
    opts: MergeOptions,
    report: dict[str, Any],
) -> list[Path]:
    """Write ``pass_NN.ply`` (each pass, corrected), ``merged.ply``, ``scan.npz``,
    ``report.json`` and, with ``opts.surface``, ``surface.ply`` into ``out_dir``."""
    from wristscan.daemon.io.ply import write_ply

    out_dir.mkdir(parents=True, exist_ok=True)
    files: list[Path] = []
    fixed = corrected_clouds(clouds, merge)
    frame = report.get("frame", "?")
    npz: dict[str, Any] = {}
    for c in fixed:
        v, o = voxel_mean(c.xyz, opts.voxel_m, c.origins)
        nrm = oriented_normals(v, o, opts.normals_k)
        path = out_dir / f"pass_{c.index + 1:02d}.ply"
        write_ply(
            path,
            v,
            normals=nrm,
            comments=[f"wristscan scan pass {c.index + 1}: {c.label}", f"frame {frame}, metres"],
        )
        files.append(path)
        npz[f"pass_{c.index + 1:02d}_xyz"] = v.astype(np.float32)
        npz[f"pass_{c.index + 1:02d}_normals"] = nrm.astype(np.float32)
    xyz, normals = merged_cloud(fixed, opts.voxel_m, opts.normals_k)
    path = out_dir / "merged.ply"
    write_ply(
        path,
        xyz,
        normals=normals,
        comments=[
            f"wristscan scan: {len(fixed)} passes merged, frame {frame}, metres",
            f"voxel {opts.voxel_m * 1e3:g} mm, ICP {'on' if merge is not None else 'off'}",
        ],
    )
    files.append(path)
    npz["merged_xyz"] = xyz.astype(np.float32)
    npz["merged_normals"] = normals.astype(np.float32)
    if merge is not None:
        npz["corrections"] = np.stack([c.transform for c in merge.corrections])
        npz["correction_pass"] = np.array([c.index + 1 for c in merge.corrections])
    npz["report_json"] = np.array(json.dumps(report))
    path = out_dir / "scan.npz"
    np.savez_compressed(path, **npz)
    files.append(path)
    if opts.surface:
        path = out_dir / "surface.ply"
        faces = poisson_surface(xyz, normals, path, opts.surface_depth, opts.surface_trim_m)
        report["surface"] = {"file": path.name, "faces": faces, "depth": opts.surface_depth}
        files.append(path)
    path = out_dir / "report.json"
    path.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    files.append(path)
    return files


def poisson_surface(
    xyz: FloatArray,
    normals: FloatArray,
    path: Path,
    depth: int = 9,
    trim_m: float = 0.001,
) -> int:
    """Screened Poisson surface of an oriented cloud (MeshLab's filter, through pymeshlab),
    with the triangles farther than ``trim_m`` from the cloud removed (Poisson closes the
    surface where there are no points); written as binary PLY. Returns the face count.
    Raises :class:`SurfaceUnavailable` when pymeshlab is not installed."""
    try:
        import pymeshlab  # type: ignore[import-not-found,unused-ignore]
    except ImportError:
        raise SurfaceUnavailable(
            "the surface model needs the optional dependency pymeshlab: "
            "pip install 'wristscan[surface]'"
        ) from None
    if xyz.shape[0] < 100:
        raise ScanError(f"too few points for a surface ({xyz.shape[0]})")
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=xyz, v_normals_matrix=normals))
    ms.generate_surface_reconstruction_screened_poisson(depth=depth, preclean=True)
    mesh = ms.current_mesh()
    verts = np.asarray(mesh.vertex_matrix(), dtype=np.float64)
    faces = np.asarray(mesh.face_matrix(), dtype=np.int64)
    dist, _ = cKDTree(xyz).query(verts, k=1)
    near = dist <= trim_m
    keep = near[faces].all(axis=1)
    faces = faces[keep]
    used = np.unique(faces)
    remap = np.full(verts.shape[0], -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    out = pymeshlab.MeshSet()
    out.add_mesh(pymeshlab.Mesh(vertex_matrix=verts[used], face_matrix=remap[faces]))
    path.parent.mkdir(parents=True, exist_ok=True)
    out.save_current_mesh(str(path), binary=True, save_vertex_normal=False)
    return int(faces.shape[0])
