"""Generating a scan plan that covers a box (``wristscan scan plan``; the plan model is in
:mod:`.plan_file`).

Generation (:func:`generate_plan`): from a bounding box, the width of the laser line (field of
view), an overlap fraction and a standoff, for each table angle and each view (tilt): parallel
linear passes, serpentine, spaced so that neighbouring strips share at least ``overlap`` of the
line width. The strips are laid out across the box's projection along the view direction, so
every point of the box that the laser can see from that direction lies in a strip (see
``docs/scan.md``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import ValidationError

from wristscan.daemon.scan.plan_file import (
    Crop,
    LinearPass,
    Orientation,
    PlanError,
    ScanPlan,
    Vec3,
    problem_lines,
)

__all__ = ["StripLayout", "generate_plan", "strip_layout"]

FloatArray = NDArray[np.float64]


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
    _check_request(lo, hi, fov_width_m, overlap, standoff_m, frame, table_angles_deg, tilts_deg)
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
                _check_depth(lay, depth_range_m, tilt, standoff_m)
            overlaps.append(lay.overlap_fraction)
            strips, forward = _strip_passes(lay, o, theta, tilt, forward)
            passes += strips
    gen = {
        "bbox_min_m": [float(x) for x in lo],
        "bbox_max_m": [float(x) for x in hi],
        **_request_doc(fov_width_m, overlap, standoff_m, tilts_deg, yaw_deg, table_angles_deg),
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
        raise PlanError("\n".join(problem_lines(exc, "generated plan"))) from None


def _request_doc(
    fov_width_m: float,
    overlap: float,
    standoff_m: float,
    tilts_deg: Sequence[float],
    yaw_deg: float,
    table_angles_deg: Sequence[float | None],
) -> dict[str, Any]:
    """The generation settings as the plan's ``generator`` table keeps them (for the report)."""
    return {
        "fov_width_m": float(fov_width_m),
        "overlap": float(overlap),
        "standoff_m": float(standoff_m),
        "tilts_deg": [float(t) for t in tilts_deg],
        "yaw_deg": float(yaw_deg),
        "table_angles_deg": [float(a) for a in table_angles_deg if a is not None],
    }


def _check_request(
    lo: FloatArray,
    hi: FloatArray,
    fov_width_m: float,
    overlap: float,
    standoff_m: float,
    frame: str,
    table_angles_deg: Sequence[float | None],
    tilts_deg: Sequence[float],
) -> None:
    """:class:`PlanError` for a generation request that cannot make a plan."""
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


def _check_depth(
    lay: StripLayout, depth_range_m: tuple[float, float], tilt: float, standoff_m: float
) -> None:
    """:class:`PlanError` when the box does not fit in the measuring range ``depth_range_m``
    at the standoff, seen from the view ``tilt``."""
    near, far = lay.depth_span_m
    if near < depth_range_m[0] or far > depth_range_m[1]:
        raise PlanError(
            f"view tilt {tilt:g} deg: the box spans {near * 1e3:.1f} .. "
            f"{far * 1e3:.1f} mm from the sensor at standoff {standoff_m * 1e3:g} mm,"
            f" outside the measuring range {depth_range_m[0] * 1e3:g} .. "
            f"{depth_range_m[1] * 1e3:g} mm (smaller box, other standoff or tilt)"
        )


def _strip_passes(
    lay: StripLayout, o: Orientation, theta: float | None, tilt: float, forward: bool
) -> tuple[list[LinearPass], bool]:
    """The linear passes of one view's strips, in alternate directions starting ``forward``
    (serpentine), and the direction the next strip starts with."""
    R = o.matrix()
    passes: list[LinearPass] = []
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
    return passes, forward


def _wrap_deg(a: float) -> float:
    w = (a + 180.0) % 360.0 - 180.0
    return 0.0 if abs(w) < 1e-12 else float(w)


def _vec3(a: Iterable[float]) -> Vec3:
    x, y, z = (round(float(v), 9) for v in a)
    return (x, y, z)
