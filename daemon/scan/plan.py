"""Scan plans: what a scan job does, how a plan is generated, and the checks that run before
anything moves.

A plan (TOML or JSON, validated here) lists **passes**. Every pose in it is the pose of the
*sensor* (its origin and axes; +Z looks at the part, the laser plane is the sensor's Y-Z plane)
in the plan's ``frame``:

* ``frame = "part"``: the rotary table's part frame (Eq. (1): ``base2part = table2part(theta) @
  base2table``). A pass there follows the part whatever the table angle, and the calibrations in
  force turn it into robot poses at run time.
* ``frame = "base"``: the robot base frame (no table needed).

Pass kinds (the two modes of Borangiu et al. 2009, section 4):

* ``linear``: the sensor moves from ``start_m`` to ``end_m`` at constant orientation (the paper's
  best mode: "a sequence of simple linear sweep motions, keeping its orientation constant").
* ``path``: a free 3D path through ``waypoints`` whose position and orientation change together
  (the paper's first mode); executed as linear moves through the waypoints, recorded as one pass.

Each pass may name a rotary-table angle ``table_deg``; the table turns there before the pass.

An orientation is either ``"down"`` (sensor +Z along the frame's -Z, sensor X along the frame's
X), ``{yaw_deg, pitch_deg, tilt_deg}`` (``Rz(yaw) @ down @ Ry(pitch) @ Rx(tilt)``: ``yaw`` turns
the pass direction about the vertical, ``tilt`` leans the laser plane sideways about the pass
direction so that it sees side faces, ``pitch`` leans it forwards or backwards along the pass), or
``{rotvec = [rx, ry, rz]}``, the sensor-to-frame rotation as a UR rotation vector (rad).

Example::

    schema_version = 1
    frame = "part"
    speed_m_s = 0.04            # pass speed
    travel_speed_m_s = 0.15     # moves between passes
    retract_m = 0.03            # back off along the sensor's -Z before and after each pass

    [[passes]]
    kind = "linear"
    table_deg = 0.0
    start_m = [-0.10, 0.01, 0.16]
    end_m = [0.08, 0.01, 0.16]
    orientation = { tilt_deg = 25.0 }

    [[passes]]
    kind = "path"
    table_deg = 90.0
    waypoints = [
      { position_m = [0.0, -0.05, 0.17], orientation = "down" },
      { position_m = [0.0, 0.05, 0.15], orientation = { pitch_deg = 20.0 } },
    ]

Checks before motion (:func:`check_plan`): from the robot's current joints, the whole job is
followed with the inverse kinematics: the joint move to each pass's approach pose, the linear
moves in, along the pass (samples every ``step_m`` / ``step_rad``, each solved from the previous
one as the controller does) and out. A pose out of reach, a branch flip or singularity (a joint
turning more than ``max_joint_step_rad`` between neighbouring samples), a TCP outside the
workspace box (also along the joint moves) or a speed above the configured cap rejects the plan
with one line per problem, and nothing moves.

Generation (:func:`generate_plan`): from a bounding box, the width of the laser line (field of
view), an overlap fraction and a standoff, for each table angle and each view (tilt): parallel
linear passes, serpentine, spaced so that neighbouring strips share at least ``overlap`` of the
line width. The strips are laid out across the box's projection along the view direction, so
every point of the box that the laser can see from that direction lies in a strip (see
``docs/scan.md``).
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import tomllib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    model_validator,
)

from wristscan.calib import kinematics, se3
from wristscan.calib import table as table_math

__all__ = [
    "CellGeometry",
    "LinearPass",
    "Orientation",
    "PassCheck",
    "PathPass",
    "PlanCheck",
    "PlanError",
    "ResolvedPass",
    "ScanPlan",
    "Waypoint",
    "check_plan",
    "describe_plan",
    "generate_plan",
    "load_plan",
    "parse_plan",
    "plan_to_toml",
    "resolve_plan",
    "strip_layout",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

SCHEMA_VERSION = 1


class PlanError(ValueError):
    """A plan that cannot be used (invalid file, impossible generation request, missing
    calibration for its frame); the message says why in one line per problem."""


# --------------------------------------------------------------------------------------------
# The plan model


def _down_alias(v: Any) -> Any:
    if isinstance(v, str):
        if v.strip().lower() == "down":
            return {}
        raise ValueError(f'an orientation is "down" or a table, not {v!r}')
    return v


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


Vec3 = tuple[float, float, float]


class Orientation(_Model):
    """Sensor orientation in the plan frame (see the module doc)."""

    yaw_deg: float = 0.0
    pitch_deg: Annotated[float, Field(ge=-89.0, le=89.0)] = 0.0
    tilt_deg: Annotated[float, Field(ge=-89.0, le=89.0)] = 0.0
    rotvec: Vec3 | None = None
    """The sensor-to-frame rotation as a UR rotation vector (rad); excludes the angles."""

    @model_validator(mode="after")
    def _one_form(self) -> Orientation:
        if self.rotvec is not None and (self.yaw_deg or self.pitch_deg or self.tilt_deg):
            raise ValueError("give either rotvec or yaw_deg/pitch_deg/tilt_deg, not both")
        return self

    def matrix(self) -> FloatArray:
        """The rotation ``sensor2frame`` (3, 3)."""
        if self.rotvec is not None:
            return np.asarray(se3.rotvec_to_matrix(np.asarray(self.rotvec, dtype=np.float64)))
        return down_matrix(self.yaw_deg, self.pitch_deg, self.tilt_deg)

    def is_down(self) -> bool:
        return self.rotvec is None and not (self.yaw_deg or self.pitch_deg or self.tilt_deg)


OrientationField = Annotated[Orientation, BeforeValidator(_down_alias)]


def down_matrix(yaw_deg: float = 0.0, pitch_deg: float = 0.0, tilt_deg: float = 0.0) -> FloatArray:
    """``Rz(yaw) @ Rx(pi) @ Ry(pitch) @ Rx(tilt)``: the sensor looking down (its +Z along the
    frame's -Z, its X along the frame's X turned by ``yaw``), leaned by ``pitch`` about its Y and
    ``tilt`` about its X axis (degrees). A positive tilt turns the view towards the frame's +Y
    (for yaw 0)."""
    y, p, t = (math.radians(a) for a in (yaw_deg, pitch_deg, tilt_deg))
    return np.asarray(se3.rot_z(y) @ se3.rot_x(math.pi) @ se3.rot_y(p) @ se3.rot_x(t))


class LinearPass(_Model):
    """The sensor from ``start_m`` to ``end_m`` (its origin, plan frame, m) at one orientation."""

    kind: Literal["linear"]
    label: str = ""
    start_m: Vec3
    end_m: Vec3
    orientation: OrientationField = Orientation()
    speed_m_s: Annotated[float, Field(gt=0.0, le=2.0)] | None = None
    """Pass speed (m/s); None: the plan's ``speed_m_s``."""
    table_deg: float | None = None
    """Rotary-table angle for the pass (degrees); None: leave the table where it is."""

    @model_validator(mode="after")
    def _length(self) -> LinearPass:
        if math.dist(self.start_m, self.end_m) < 1e-4:
            raise ValueError("start_m and end_m must be at least 0.1 mm apart")
        return self


class Waypoint(_Model):
    position_m: Vec3
    orientation: OrientationField = Orientation()


class PathPass(_Model):
    """A free 3D path: linear moves through ``waypoints`` (position and orientation together)."""

    kind: Literal["path"]
    label: str = ""
    waypoints: Annotated[list[Waypoint], Field(min_length=2, max_length=1000)]
    speed_m_s: Annotated[float, Field(gt=0.0, le=2.0)] | None = None
    table_deg: float | None = None


Pass = Annotated[LinearPass | PathPass, Field(discriminator="kind")]


class Crop(_Model):
    """Box kept of the clouds, in the plan frame (the frame of the clouds too), m."""

    min_m: Vec3
    max_m: Vec3

    @model_validator(mode="after")
    def _order(self) -> Crop:
        if any(a >= b for a, b in zip(self.min_m, self.max_m, strict=True)):
            raise ValueError("crop: every min_m value must be below its max_m value")
        return self


class ScanPlan(_Model):
    """A scan job (see the module doc). SI units: metres, m/s; angles in degrees by name."""

    schema_version: Literal[1] = 1
    name: str = ""
    frame: Literal["base", "part"] = "part"
    speed_m_s: Annotated[float, Field(gt=0.0, le=2.0)] = 0.04
    travel_speed_m_s: Annotated[float, Field(gt=0.0, le=2.0)] = 0.15
    retract_m: Annotated[float, Field(ge=0.0, le=0.5)] = 0.03
    crop: Crop | None = None
    passes: Annotated[list[Pass], Field(min_length=1, max_length=10_000)]
    generator: dict[str, Any] | None = None
    """How a generated plan was made (bbox, field of view, overlap, standoff): for the report."""


def _problem_lines(exc: ValidationError, source: str) -> list[str]:
    out = []
    for e in exc.errors(include_url=False):
        # Drop the union tags ("linear", "path") that pydantic puts into the location.
        loc = [str(p) for p in e["loc"] if p not in ("linear", "path")]
        where = ".".join(loc) if loc else "plan"
        msg = str(e["msg"]).removeprefix("Value error, ")
        got = e.get("input")
        extra = f" (got {json.dumps(got)[:60]})" if isinstance(got, int | float | str) else ""
        out.append(f"{source}: {where}: {msg}{extra}")
    return out


def parse_plan(data: dict[str, Any], source: str = "<plan>") -> ScanPlan:
    """Validate a plan document; :class:`PlanError` with one line per problem."""
    if not isinstance(data, dict):
        raise PlanError(f"{source}: a plan is a table of settings with a passes list")
    if data.get("schema_version", SCHEMA_VERSION) != SCHEMA_VERSION:
        raise PlanError(
            f"{source}: schema_version {data.get('schema_version')!r} is not supported "
            f"(this wristscan reads {SCHEMA_VERSION})"
        )
    try:
        return ScanPlan.model_validate(data)
    except ValidationError as exc:
        raise PlanError("\n".join(_problem_lines(exc, source))) from None


def load_plan(path: str | Path) -> ScanPlan:
    """Read a plan from a ``.toml`` or ``.json`` file; :class:`PlanError` says what is wrong."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise PlanError(f"{p}: cannot read the plan: {exc}") from None
    try:
        if p.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            data = tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise PlanError(f"{p}: not valid {p.suffix.lstrip('.').upper() or 'TOML'}: {exc}") from None
    return parse_plan(data, str(p))


# --------------------------------------------------------------------------------------------
# Writing plans (TOML)


def _toml_scalar(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        r = repr(round(v, 9))
        return r if ("." in r or "e" in r or "n" in r) else r + ".0"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_scalar(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_scalar(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _orientation_doc(o: Orientation) -> Any:
    if o.is_down():
        return "down"
    if o.rotvec is not None:
        return {"rotvec": list(o.rotvec)}
    return {
        k: v
        for k, v in (("yaw_deg", o.yaw_deg), ("pitch_deg", o.pitch_deg), ("tilt_deg", o.tilt_deg))
        if v
    }


def plan_to_toml(plan: ScanPlan) -> str:
    """The plan as a TOML document that :func:`load_plan` reads back to an equal plan."""
    lines = [
        "# wristscan scan plan: sensor poses (origin, axes) in the plan frame; metres, m/s, deg",
        f"schema_version = {SCHEMA_VERSION}",
    ]
    if plan.name:
        lines.append(f"name = {_toml_scalar(plan.name)}")
    lines += [
        f"frame = {_toml_scalar(plan.frame)}",
        f"speed_m_s = {_toml_scalar(plan.speed_m_s)}",
        f"travel_speed_m_s = {_toml_scalar(plan.travel_speed_m_s)}",
        f"retract_m = {_toml_scalar(plan.retract_m)}",
    ]
    if plan.crop is not None:
        lines.append(
            f"crop = {{ min_m = {_toml_scalar(plan.crop.min_m)}, "
            f"max_m = {_toml_scalar(plan.crop.max_m)} }}"
        )
    if plan.generator:
        lines.append("")
        lines.append("[generator]")
        for k, v in plan.generator.items():
            lines.append(f"{k} = {_toml_scalar(v)}")
    for p in plan.passes:
        lines.append("")
        lines.append("[[passes]]")
        lines.append(f"kind = {_toml_scalar(p.kind)}")
        if p.label:
            lines.append(f"label = {_toml_scalar(p.label)}")
        if p.table_deg is not None:
            lines.append(f"table_deg = {_toml_scalar(p.table_deg)}")
        if p.speed_m_s is not None:
            lines.append(f"speed_m_s = {_toml_scalar(p.speed_m_s)}")
        if isinstance(p, LinearPass):
            lines.append(f"start_m = {_toml_scalar(p.start_m)}")
            lines.append(f"end_m = {_toml_scalar(p.end_m)}")
            lines.append(f"orientation = {_toml_scalar(_orientation_doc(p.orientation))}")
        else:
            lines.append("waypoints = [")
            for w in p.waypoints:
                doc = {
                    "position_m": list(w.position_m),
                    "orientation": _orientation_doc(w.orientation),
                }
                lines.append(f"  {_toml_scalar(doc)},")
            lines.append("]")
    return "\n".join(lines) + "\n"


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
# Generation


@dataclass(frozen=True)
class StripLayout:
    """Strips of one view over a box: centres across the line, extent along the pass."""

    centres_v_m: FloatArray
    """Lateral centre of each strip along the laser line (the view's v axis, m)."""
    u_range_m: tuple[float, float]
    """Extent along the pass direction (m), margins included."""
    depth_m: float
    """Position of the sensor origins along the view direction (m)."""
    depth_span_m: tuple[float, float]
    """Nearest and farthest box corner seen from the sensor along its Z (m)."""
    step_m: float
    """Distance between neighbouring strip centres (m); 0 for one strip."""
    overlap_fraction: float
    """Shared width of neighbouring strips over the line width (1 for one strip)."""


def strip_layout(
    rotation: ArrayLike,
    bbox_min_m: ArrayLike,
    bbox_max_m: ArrayLike,
    *,
    fov_width_m: float,
    overlap: float,
    standoff_m: float,
    margin_m: float = 0.003,
) -> StripLayout:
    """Lay strips of a laser line ``fov_width_m`` wide over a box seen with the sensor rotation
    ``rotation`` (sensor2frame, 3x3): u = sensor X (pass direction), v = sensor Y (the line),
    d = sensor Z (view). The box corners projected on v span ``[v0, v1]``; strips of width W are
    spread evenly with at most ``W (1 - overlap)`` between centres, the first and last flush
    with the ends. The sensor origins lie ``standoff_m`` before the middle of the box along d.
    """
    R = np.asarray(rotation, dtype=np.float64)
    lo = np.asarray(bbox_min_m, dtype=np.float64)
    hi = np.asarray(bbox_max_m, dtype=np.float64)
    corners = np.array(
        [
            [(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]]
            for i in (0, 1)
            for j in (0, 1)
            for k in (0, 1)
        ]
    )
    proj = corners @ R  # columns: u, v, d
    u0, v0, d0 = proj.min(axis=0)
    u1, v1, d1 = proj.max(axis=0)
    width = float(v1 - v0)
    W = float(fov_width_m)
    if width <= W:
        centres = np.array([0.5 * (v0 + v1)])
        step = 0.0
        frac = 1.0
    else:
        n = math.ceil((width - W) / (W * (1.0 - overlap)) - 1e-9) + 1
        step = (width - W) / (n - 1)
        centres = v0 + 0.5 * W + step * np.arange(n)
        frac = (W - step) / W
    depth = 0.5 * float(d0 + d1) - standoff_m
    return StripLayout(
        centres_v_m=np.asarray(centres, dtype=np.float64),
        u_range_m=(float(u0) - margin_m, float(u1) + margin_m),
        depth_m=depth,
        depth_span_m=(float(d0) - depth, float(d1) - depth),
        step_m=float(step),
        overlap_fraction=float(frac),
    )


def generate_plan(
    bbox_min_m: ArrayLike,
    bbox_max_m: ArrayLike,
    *,
    fov_width_m: float,
    overlap: float,
    standoff_m: float,
    table_angles_deg: Sequence[float | None] = (None,),
    tilts_deg: Sequence[float] = (0.0,),
    yaw_deg: float = 0.0,
    frame: Literal["base", "part"] = "part",
    depth_range_m: tuple[float, float] | None = None,
    speed_m_s: float = 0.04,
    travel_speed_m_s: float = 0.15,
    retract_m: float = 0.03,
    margin_m: float = 0.003,
    crop_margin_m: float = 0.002,
    name: str = "",
) -> ScanPlan:
    """Linear passes covering the box ``bbox_min_m .. bbox_max_m`` (plan frame, m).

    For each table angle and each view (``tilt`` about the pass direction, degrees; the pass
    direction is ``yaw_deg`` in the *base* frame, so that turning the table shows the sensor
    other faces of the part), strips as :func:`strip_layout` lays them, run in alternate
    directions. In the part frame the view at table angle ``theta`` is yawed by ``-theta``:
    the robot keeps its orientation and the part turns under it (the table axis is the part
    frame's Z). ``depth_range_m``: the sensor's measuring range (m); the box must fit in it at
    the standoff. Raises :class:`PlanError` for an impossible request.
    """
    lo = np.asarray(bbox_min_m, dtype=np.float64)
    hi = np.asarray(bbox_max_m, dtype=np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or np.any(hi <= lo):
        raise PlanError("bbox: give min and max corners (3 values each) with min < max")
    if not 0.0 < fov_width_m <= 2.0:
        raise PlanError(f"fov width must be in (0, 2] m, got {fov_width_m}")
    if not 0.0 <= overlap < 0.95:
        raise PlanError(f"overlap must be a fraction in [0, 0.95), got {overlap}")
    if standoff_m <= 0.0:
        raise PlanError(f"standoff must be positive, got {standoff_m}")
    if frame == "base" and any(a is not None for a in table_angles_deg):
        # Base-frame passes do not follow the part: turning the table would move it away.
        raise PlanError("table angles need a part-frame plan (frame = part)")
    if not tilts_deg:
        raise PlanError("give at least one view (tilt)")
    passes: list[LinearPass] = []
    overlaps: list[float] = []
    forward = True
    for theta in table_angles_deg:
        part_yaw = yaw_deg - (theta or 0.0) if frame == "part" else yaw_deg
        for tilt in tilts_deg:
            o = Orientation(yaw_deg=_wrap_deg(part_yaw), tilt_deg=float(tilt))
            R = o.matrix()
            lay = strip_layout(
                R,
                lo,
                hi,
                fov_width_m=fov_width_m,
                overlap=overlap,
                standoff_m=standoff_m,
                margin_m=margin_m,
            )
            if depth_range_m is not None:
                near, far = lay.depth_span_m
                if near < depth_range_m[0] or far > depth_range_m[1]:
                    raise PlanError(
                        f"view tilt {tilt:g} deg: the box spans {near * 1e3:.1f} .. "
                        f"{far * 1e3:.1f} mm from the sensor at standoff {standoff_m * 1e3:g} mm,"
                        f" outside the measuring range {depth_range_m[0] * 1e3:g} .. "
                        f"{depth_range_m[1] * 1e3:g} mm (smaller box, other standoff or tilt)"
                    )
            overlaps.append(lay.overlap_fraction)
            for k, v in enumerate(lay.centres_v_m):
                ua, ub = lay.u_range_m if forward else lay.u_range_m[::-1]
                forward = not forward
                start = R @ np.array([ua, v, lay.depth_m])
                end = R @ np.array([ub, v, lay.depth_m])
                where = "" if theta is None else f"table {theta:g} deg, "
                passes.append(
                    LinearPass(
                        kind="linear",
                        label=f"{where}tilt {tilt:g} deg, strip {k + 1}/{lay.centres_v_m.size}",
                        start_m=_vec3(start),
                        end_m=_vec3(end),
                        orientation=o,
                        table_deg=None if theta is None else float(theta),
                    )
                )
    gen = {
        "bbox_min_m": [float(x) for x in lo],
        "bbox_max_m": [float(x) for x in hi],
        "fov_width_m": float(fov_width_m),
        "overlap": float(overlap),
        "standoff_m": float(standoff_m),
        "tilts_deg": [float(t) for t in tilts_deg],
        "yaw_deg": float(yaw_deg),
        "table_angles_deg": [float(a) for a in table_angles_deg if a is not None],
        "min_overlap": round(float(min(overlaps)), 6),
    }
    if depth_range_m is not None:
        gen["depth_range_m"] = [float(depth_range_m[0]), float(depth_range_m[1])]
    try:
        return ScanPlan(
            name=name,
            frame=frame,
            speed_m_s=speed_m_s,
            travel_speed_m_s=travel_speed_m_s,
            retract_m=retract_m,
            crop=Crop(min_m=_vec3(lo - crop_margin_m), max_m=_vec3(hi + crop_margin_m)),
            passes=list(passes),
            generator=gen,
        )
    except ValidationError as exc:
        raise PlanError("\n".join(_problem_lines(exc, "generated plan"))) from None


def _wrap_deg(a: float) -> float:
    w = (a + 180.0) % 360.0 - 180.0
    return 0.0 if abs(w) < 1e-12 else float(w)


def _vec3(a: Iterable[float]) -> Vec3:
    x, y, z = (round(float(v), 9) for v in a)
    return (x, y, z)


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
