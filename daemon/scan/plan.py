"""Scan plans in robot terms: the plan's sensor poses resolved to the base frame through the
calibrations in force (:func:`resolve_plan`), the checks that run before anything moves
(:func:`check_plan`) and the readable summary of a plan with both (:func:`describe_plan`). The
plan model and its file are in :mod:`.plan_file`, its generation in :mod:`.plan_generate`.

Checks before motion (:func:`check_plan`): from the robot's current joints, the whole job is
followed with the inverse kinematics: the joint move to each pass's approach pose, the linear
moves in, along the pass (samples every ``step_m`` / ``step_rad``, each solved from the previous
one as the controller does) and out. A pose out of reach, a branch flip or singularity (a joint
turning more than ``max_joint_step_rad`` between neighbouring samples), a TCP outside the
workspace box (also along the joint moves) or a speed above the configured cap rejects the plan
with one line per problem, and nothing moves.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import kinematics, se3
from wristscan.calib import table as table_math
from wristscan.daemon.scan.plan_file import (
    LinearPass,
    Orientation,
    PlanError,
    ScanPlan,
)

__all__ = [
    "CellGeometry",
    "PassCheck",
    "PlanCheck",
    "ResolvedPass",
    "check_plan",
    "describe_plan",
    "resolve_plan",
]

FloatArray = NDArray[np.float64]


# --------------------------------------------------------------------------------------------
# From the plan to robot poses


@dataclass(frozen=True)
class CellGeometry:
    """What turns plan poses into robot targets: kinematics and the calibrations in force."""

    model: str | kinematics.DHParams
    sensor2flange: FloatArray
    tcp2flange: FloatArray = field(default_factory=lambda: np.eye(4))
    base2table: FloatArray | None = None
    encoder_offset_rad: float = 0.0
    workspace_min_m: FloatArray | None = None
    workspace_max_m: FloatArray | None = None
    max_speed_m_s: float = math.inf

    def part2base(self, table_angle_rad: float) -> FloatArray:
        """Pose of the part frame in the base frame at a table (encoder) angle."""
        if self.base2table is None:
            raise PlanError(
                "the plan is in the part frame (or turns the table): it needs the table "
                "calibration ([calibration] table_file; wristscan calibrate table writes it)"
            )
        b2p = table_math.table2part(table_angle_rad, self.encoder_offset_rad) @ self.base2table
        return np.asarray(se3.invert(b2p))

    def flange_of(self, sensor2base: FloatArray) -> FloatArray:
        """``flange2base`` (..., 4, 4) that puts the sensor at ``sensor2base``."""
        return np.asarray(sensor2base @ se3.invert(self.sensor2flange))

    def tcp_of(self, sensor2base: FloatArray) -> FloatArray:
        """``tcp2base`` (..., 4, 4): what ``move_l`` is given (as a UR pose)."""
        return np.asarray(self.flange_of(sensor2base) @ self.tcp2flange)


@dataclass(frozen=True)
class ResolvedPass:
    """A pass in robot terms: sensor poses in the base frame and the moves around them."""

    index: int
    label: str
    kind: str
    table_angle_rad: float | None
    """Where the table turns before the pass (encoder angle, rad); None: it does not turn."""
    frame_angle_rad: float
    """Table angle used to put part-frame poses into the base frame (rad)."""
    sensor2base: FloatArray
    """(K, 4, 4) sensor poses the pass moves through (K = 2 for a linear pass)."""
    speed_m_s: float
    approach: FloatArray
    """(4, 4) sensor pose ``retract`` behind the start (reached by a joint move)."""
    retreat: FloatArray
    """(4, 4) sensor pose ``retract`` behind the end."""

    @property
    def length_m(self) -> float:
        p = self.sensor2base[:, :3, 3]
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())

    @property
    def duration_s(self) -> float:
        """Recording time at the pass speed (acceleration not counted)."""
        return self.length_m / self.speed_m_s


def _pose(position: Sequence[float], o: Orientation) -> FloatArray:
    return np.asarray(se3.make(o.matrix(), np.asarray(position, dtype=np.float64)))


def _backed_off(pose: FloatArray, distance_m: float) -> FloatArray:
    out = pose.copy()
    out[:3, 3] -= distance_m * pose[:3, 2]
    return out


def resolve_plan(
    plan: ScanPlan, geom: CellGeometry, current_table_rad: float | None = None
) -> list[ResolvedPass]:
    """Robot-side poses of every pass. Part-frame plans need the table calibration
    (``geom.base2table``) and an angle: the pass's ``table_deg`` or, when it has none, the
    angle the table has before it (``current_table_rad`` for the first)."""
    out: list[ResolvedPass] = []
    angle = current_table_rad
    needs_table = plan.frame == "part" or any(p.table_deg is not None for p in plan.passes)
    if needs_table and geom.base2table is None:
        geom.part2base(0.0)  # raises the explanation
    for i, p in enumerate(plan.passes):
        target = None if p.table_deg is None else math.radians(p.table_deg)
        if target is not None:
            angle = target
        if isinstance(p, LinearPass):
            local = np.stack([_pose(p.start_m, p.orientation), _pose(p.end_m, p.orientation)])
        else:
            local = np.stack([_pose(w.position_m, w.orientation) for w in p.waypoints])
        frame_angle = 0.0
        if plan.frame == "part":
            if angle is None:
                raise PlanError(
                    f"pass {i + 1}: a part-frame pass needs a table angle (table_deg) or a table "
                    "that reports its angle"
                )
            frame_angle = angle
            s2b = geom.part2base(angle) @ local
        else:
            s2b = local
        out.append(
            ResolvedPass(
                index=i,
                label=p.label or f"pass {i + 1}",
                kind=p.kind,
                table_angle_rad=target,
                frame_angle_rad=frame_angle,
                sensor2base=np.asarray(s2b),
                speed_m_s=float(p.speed_m_s or plan.speed_m_s),
                approach=_backed_off(s2b[0], plan.retract_m),
                retreat=_backed_off(s2b[-1], plan.retract_m),
            )
        )
    return out


# --------------------------------------------------------------------------------------------
# Checks before motion


@dataclass
class PassCheck:
    """The checks of one pass (and of the travel to it)."""

    index: int
    problems: list[str] = field(default_factory=list)
    q_approach: FloatArray | None = None
    """Joints (rad) of the approach pose, the target of the joint move."""
    q_end: FloatArray | None = None
    ik_samples: int = 0

    @property
    def ok(self) -> bool:
        return not self.problems


@dataclass
class PlanCheck:
    """Outcome of :func:`check_plan`: one :class:`PassCheck` per pass, plan-wide problems."""

    passes: list[PassCheck]
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems and all(p.ok for p in self.passes)

    def all_problems(self) -> list[str]:
        out = list(self.problems)
        for p in self.passes:
            out += [f"pass {p.index + 1}: {m}" for m in p.problems]
        return out


def _samples(poses: FloatArray, step_m: float, step_rad: float) -> FloatArray:
    """Poses along the linear moves through ``poses`` (K, 4, 4), neighbouring samples at most
    ``step_m`` / ``step_rad`` apart, ends included."""
    out = [poses[:1]]
    for a, b in itertools.pairwise(poses):
        dist = float(np.linalg.norm(b[:3, 3] - a[:3, 3]))
        ang = float(se3.rotation_angle(a[:3, :3].T @ b[:3, :3]))
        n = max(1, math.ceil(max(dist / step_m, ang / step_rad)))
        s = np.arange(1, n + 1) / n
        out.append(np.asarray(se3.interpolate(a, b, s)))
    return np.concatenate(out)


class _Follower:
    """Follows the joints along the job as the controller would (IK from the previous sample)."""

    def __init__(
        self,
        geom: CellGeometry,
        q: FloatArray,
        max_joint_step_rad: float,
        step_m: float,
        step_rad: float,
    ) -> None:
        self.geom = geom
        self.q = q
        self.max_step = max_joint_step_rad
        self.step_m = step_m
        self.step_rad = step_rad
        self.n_ik = 0

    def _inside(self, xyz: FloatArray) -> NDArray[np.bool_]:
        lo, hi = self.geom.workspace_min_m, self.geom.workspace_max_m
        if lo is None or hi is None:
            return np.ones(xyz.shape[0], dtype=bool)
        return np.asarray(np.all((xyz >= lo) & (xyz <= hi), axis=1))

    def _box_problem(self, xyz: FloatArray, what: str) -> str | None:
        inside = self._inside(xyz)
        if inside.all():
            return None
        i = int(np.argmin(inside))
        lo, hi = self.geom.workspace_min_m, self.geom.workspace_max_m
        assert lo is not None and hi is not None
        return (
            f"{what}: TCP at {np.round(xyz[i], 4).tolist()} m outside the workspace box "
            f"{np.round(lo, 4).tolist()} .. {np.round(hi, 4).tolist()} m"
        )

    def joint_move(
        self, sensor2base: FloatArray, what: str
    ) -> tuple[FloatArray | None, str | None]:
        """IK of the target nearest to the current joints, and the TCP along the joint-space
        line (as the robot driver checks it). Returns (joints, problem)."""
        flange = self.geom.flange_of(sensor2base)
        try:
            q = kinematics.inverse_nearest(self.geom.model, flange, self.q)
        except kinematics.Unreachable:
            return None, (
                f"{what}: sensor pose at {np.round(sensor2base[:3, 3], 4).tolist()} m (base) "
                "is out of the robot's reach"
            )
        self.n_ik += 1
        s = np.linspace(0.0, 1.0, 17)[:, None]
        qs = self.q[None, :] + s * (q - self.q)[None, :]
        tcp = kinematics.forward(self.geom.model, qs) @ self.geom.tcp2flange
        self.q = q
        return q, self._box_problem(np.asarray(tcp[:, :3, 3]), what)

    def linear(self, sensor2base: FloatArray, what: str) -> str | None:
        """Linear moves from the current pose through ``sensor2base`` (K, 4, 4)."""
        here = kinematics.forward(self.geom.model, self.q) @ self.geom.sensor2flange
        poses = _samples(np.concatenate([here[None], sensor2base]), self.step_m, self.step_rad)
        tcp = self.geom.tcp_of(poses)
        problem = self._box_problem(np.asarray(tcp[:, :3, 3]), what)
        if problem is not None:
            return problem
        q = self.q
        for k, pose in enumerate(poses[1:], start=1):
            try:
                q_next = kinematics.inverse_nearest(self.geom.model, self.geom.flange_of(pose), q)
            except kinematics.Unreachable:
                return (
                    f"{what}: sensor pose at {np.round(pose[:3, 3], 4).tolist()} m (base) is "
                    "out of the robot's reach"
                )
            self.n_ik += 1
            jump = float(np.max(np.abs(q_next - q)))
            if jump > self.max_step:
                return (
                    f"{what}: a joint turns {math.degrees(jump):.0f} deg between two samples "
                    f"near {np.round(pose[:3, 3], 4).tolist()} m (singularity or branch flip, "
                    f"sample {k}/{len(poses) - 1})"
                )
            q = q_next
        self.q = q
        return None


def check_plan(
    passes: Sequence[ResolvedPass],
    geom: CellGeometry,
    q_start: ArrayLike,
    *,
    max_joint_step_rad: float = 0.35,
    step_m: float = 0.01,
    step_rad: float = 0.05,
) -> PlanCheck:
    """Follow the whole job from the joints ``q_start`` (rad) with the inverse kinematics and
    report every problem (reach, singularity, workspace box, speed) before anything moves.

    The order of moves is that of :func:`wristscan.daemon.scan.job.run_scan`: joint move to the
    approach pose, linear move to the start, the pass, linear move to the retreat pose.
    """
    q0 = np.asarray(q_start, dtype=np.float64)
    if q0.shape != (6,) or not np.all(np.isfinite(q0)):
        raise ValueError(f"q_start: expected 6 finite joint angles, got {q0.tolist()}")
    follow = _Follower(geom, q0, max_joint_step_rad, step_m, step_rad)
    checks: list[PassCheck] = []
    plan_problems: list[str] = []
    for rp in passes:
        pc = PassCheck(rp.index)
        checks.append(pc)
        if rp.speed_m_s > geom.max_speed_m_s:
            pc.problems.append(
                f"speed {rp.speed_m_s * 1e3:g} mm/s above the configured cap "
                f"{geom.max_speed_m_s * 1e3:g} mm/s ([robot] max_speed_m_s)"
            )
        n0 = follow.n_ik
        q_app, problem = follow.joint_move(rp.approach, "joint move to the approach pose")
        pc.q_approach = q_app
        if problem:
            pc.problems.append(problem)
        if q_app is None:
            continue  # the rest of this pass cannot be followed; the next starts from here
        for what, target in (
            ("approach", rp.sensor2base[:1]),
            ("pass", rp.sensor2base[1:]),
            ("retreat", rp.retreat[None]),
        ):
            problem = follow.linear(target, what)
            if problem:
                pc.problems.append(problem)
                break
        pc.q_end = follow.q.copy()
        pc.ik_samples = follow.n_ik - n0
    return PlanCheck(checks, plan_problems)


# --------------------------------------------------------------------------------------------
# Showing a plan


def describe_plan(
    plan: ScanPlan,
    resolved: Sequence[ResolvedPass] | None = None,
    check: PlanCheck | None = None,
) -> list[str]:
    """Readable lines: the plan, each pass (base-frame start and end when resolved) and the
    outcome of the checks."""
    lines = [
        f"plan {plan.name or '(unnamed)'}: {len(plan.passes)} passes in the {plan.frame} frame, "
        f"pass speed {plan.speed_m_s * 1e3:g} mm/s, travel {plan.travel_speed_m_s * 1e3:g} mm/s, "
        f"retract {plan.retract_m * 1e3:g} mm"
    ]
    g = plan.generator
    if g:
        lines.append(
            f"generated over the box {_mm3(g.get('bbox_min_m'))} .. {_mm3(g.get('bbox_max_m'))} "
            f"mm: line width {g.get('fov_width_m', 0) * 1e3:g} mm, requested overlap "
            f"{g.get('overlap', 0) * 100:g} %, achieved >= {g.get('min_overlap', 0) * 100:.1f} %,"
            f" standoff {g.get('standoff_m', 0) * 1e3:g} mm"
        )
    total_len = 0.0
    total_t = 0.0
    for i, p in enumerate(plan.passes):
        head = f"  {i + 1:3d} {p.kind:6s} {p.label or ''}"
        if p.table_deg is not None:
            head += f" [table {p.table_deg:g} deg]"
        if resolved is not None:
            rp = resolved[i]
            a, b = rp.sensor2base[0, :3, 3], rp.sensor2base[-1, :3, 3]
            head += (
                f"  base {_mm3(a)} -> {_mm3(b)} mm, {rp.length_m * 1e3:.0f} mm at "
                f"{rp.speed_m_s * 1e3:g} mm/s"
            )
            total_len += rp.length_m
            total_t += rp.duration_s
        if check is not None:
            pc = check.passes[i]
            head += "  ok" if pc.ok else "  REJECTED"
        lines.append(head)
        if check is not None:
            lines += [f"        - {m}" for m in check.passes[i].problems]
    if resolved is not None:
        lines.append(f"recorded path {total_len * 1e3:.0f} mm, {total_t:.1f} s at pass speed")
    if check is not None:
        lines += [f"  - {m}" for m in check.problems]
        n_ik = sum(p.ik_samples for p in check.passes)
        lines.append(
            "checks: every pose reachable and inside the workspace box "
            f"({n_ik} inverse-kinematics samples)"
            if check.ok
            else f"checks: {len(check.all_problems())} problem(s): the plan would be refused"
        )
    return lines


def _mm3(v: Any) -> str:
    if v is None:
        return "?"
    return "(" + ", ".join(f"{float(x) * 1e3:.1f}" for x in v) + ")"
