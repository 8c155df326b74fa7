"""Scan plans: what a scan job does (the plan model, validated here) and the plan file (TOML or
JSON, read by :func:`load_plan`; :func:`plan_to_toml` writes it back). The plan's generation is
in :mod:`.plan_generate`, the checks before motion in :mod:`.plan`.

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
"""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    model_validator,
)

from wristscan.calib import se3

__all__ = [
    "SCHEMA_VERSION",
    "Crop",
    "LinearPass",
    "Orientation",
    "PathPass",
    "PlanError",
    "ScanPlan",
    "Vec3",
    "Waypoint",
    "down_matrix",
    "load_plan",
    "parse_plan",
    "plan_to_toml",
    "problem_lines",
]

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


def problem_lines(exc: ValidationError, source: str) -> list[str]:
    """One line per problem pydantic found in a plan document, prefixed with ``source``."""
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
        raise PlanError("\n".join(problem_lines(exc, source))) from None


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
