"""Plane frame teaching (``wristscan teach plane``) with the calibrated sensor (Borangiu et al.
2009, section 5). Distance sensing (``wristscan measure``), which it starts with, is in
:mod:`.measure`; the machinery every teaching procedure shares in :mod:`.kit`.

Plane teaching
--------------
"Instead of manually teaching at least 3 robot locations on the tilted plane, the laser sensor
can be used as a distance sensor in order to teach the location with an automatic procedure."

The operator places the sensor above the work surface (the laser line on it, anywhere in the
measuring range). The robot then visits ``n_spots`` spots (3: a triangle, 4: a square) of side
``spacing_m`` in the directions of the sensor's own X and Y axes, keeping its orientation; at each
it stands still for ``dwell_s`` while the profiles are recorded. The next spot's depth is
predicted from the surface seen so far, so the surface stays at the standoff of the first spot
however it is tilted. Every profile's points go through the calibration in force
(``flange2base @ sensor2flange``) into the base frame; :func:`wristscan.calib.plane.fit_plane`
fits the plane robustly. The frame (:func:`wristscan.calib.plane.plane_frame`):

* origin: where the sensor's Z axis at the first spot meets the plane;
* Z: the plane normal, on the robot's side (where the sensor measured from);
* X: towards the second spot (where its Z axis meets the plane), Y = Z x X.

It is written as JSON and printed as a UR pose ``p[x, y, z, rx, ry, rz]`` to enter as a plane
feature on the teach pendant. The fit statistics (residual RMS, peak-to-valley, the form error
without the noise, the normal's 1-sigma) say whether the surface was flat enough: with a form
error above ``max_form_error_m`` nothing is written and the procedure fails.

Safety as in the calibration procedures: no motion unless ``[robot] motion_enabled`` and
confirmed; speeds capped by the configuration; the driver refuses targets outside the workspace
box; any failure while moving stops the robot and raises :class:`~.kit.TeachAborted`.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import se3
from wristscan.calib.plane import PlaneFit, fit_plane, plane_frame
from wristscan.daemon.config import Config
from wristscan.daemon.io.atomic import write_atomic
from wristscan.daemon.io.urpose import ur_pose_text
from wristscan.daemon.procedure.in_force import load_sensor_calibration
from wristscan.daemon.procedure.motion import require_motion
from wristscan.daemon.procedure.progress import Progress, stage_reporter
from wristscan.daemon.teach.kit import (
    Mover,
    TeachError,
    guarded,
    mean_pose,
    points_in_base,
    record_still,
    teach_acquisition,
)
from wristscan.daemon.teach.measure import MIN_SURFACE_POINTS, measure_surface

if TYPE_CHECKING:
    from wristscan.daemon.procedure.acquisition import Sweep

__all__ = [
    "PlaneOptions",
    "PlaneResult",
    "Spot",
    "plane_from_spots",
    "read_plane_frame",
    "teach_plane",
    "write_plane_frame",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

FRAME_FORMAT = "wristscan-plane-frame"
FRAME_VERSION = 1
_MAX_DEPTH_CORRECTION = 2.0  # times the spacing


# --------------------------------------------------------------------------------------------
# Plane teaching


@dataclass(frozen=True)
class PlaneOptions:
    """Settings of the plane-teaching procedure (SI units)."""

    spacing_m: float = 0.03
    """Distance between the spots."""
    n_spots: int = 3
    """3 (a triangle) or 4 (a square)."""
    dwell_s: float = 0.25
    """Recording time at each spot, standing still."""
    speed_m_s: float = 0.05
    """Speed between the spots (capped by the configuration)."""
    max_form_error_m: float = 1e-4
    """Flatness tolerance: the largest form error (noise averaged out) accepted."""
    standoff_m: float | None = None
    """Standoff kept at the spots (None: the one found at the start)."""
    max_points_per_spot: int = 20_000
    return_to_start: bool = True

    def __post_init__(self) -> None:
        if not self.spacing_m > 0:
            raise ValueError("spacing_m must be positive")
        if self.n_spots not in (3, 4):
            raise ValueError("n_spots must be 3 or 4")
        if not self.dwell_s > 0:
            raise ValueError("dwell_s must be positive")
        if not self.max_form_error_m > 0:
            raise ValueError("max_form_error_m must be positive")

    def layout(self) -> FloatArray:
        """Spot offsets ``(n, 2)`` along the sensor's X and Y axes (m)."""
        s = self.spacing_m
        if self.n_spots == 3:
            return np.array([[0.0, 0.0], [s, 0.0], [0.5 * s, 0.5 * math.sqrt(3.0) * s]])
        return np.array([[0.0, 0.0], [s, 0.0], [s, s], [0.0, s]])


@dataclass(frozen=True)
class Spot:
    """What the sensor saw standing at one spot."""

    sensor2base: FloatArray
    """(4, 4) mean sensor pose over the spot's profiles."""
    points: FloatArray
    """(M, 3) surface points (base frame)."""
    n_profiles: int


@dataclass(frozen=True)
class PlaneResult:
    fit: PlaneFit
    frame2base: FloatArray
    spots: tuple[Spot, ...]
    max_form_error_m: float
    duration_s: float = 0.0
    sensor_calibration: str = ""
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def flat(self) -> bool:
        """The form error is within the tolerance."""
        return bool(self.fit.form_error <= self.max_form_error_m)

    @property
    def ur_pose(self) -> FloatArray:
        return np.asarray(se3.matrix_to_pose(self.frame2base))

    @property
    def origin(self) -> FloatArray:
        return np.asarray(self.frame2base[:3, 3])

    @property
    def normal(self) -> FloatArray:
        return np.asarray(self.frame2base[:3, 2])

    def to_dict(self) -> dict[str, Any]:
        f = self.fit
        return {
            "format": FRAME_FORMAT,
            "version": FRAME_VERSION,
            "frame": "base",
            "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "frame2base": self.frame2base.tolist(),
            "ur_pose": self.ur_pose.tolist(),
            "ur_pose_text": ur_pose_text(self.ur_pose),
            "origin_m": self.origin.tolist(),
            "normal": self.normal.tolist(),
            "flat": self.flat,
            "fit": {
                "n_points": int(f.residuals.shape[0]),
                "n_inliers": f.n_inliers,
                "rms_m": f.rms,
                "peak_to_valley_m": f.peak_to_valley,
                "form_error_m": f.form_error,
                "form_bin_m": f.form_bin_m,
                "max_form_error_m": self.max_form_error_m,
                "sigma_normal_deg": math.degrees(f.sigma_normal_rad),
                "sigma_offset_m": f.sigma_offset_m,
                "extent_m": list(f.extent_m),
            },
            "spots": [
                {
                    "sensor2base": s.sensor2base.tolist(),
                    "n_points": int(s.points.shape[0]),
                    "n_profiles": s.n_profiles,
                }
                for s in self.spots
            ],
            "sensor_calibration": self.sensor_calibration,
            "duration_s": self.duration_s,
            "notes": list(self.notes),
        }

    def summary_lines(self) -> list[str]:
        f = self.fit
        o = self.origin * 1e3
        rpy = np.degrees(_rpy(self.frame2base[:3, :3]))
        verdict = "flat" if self.flat else "NOT FLAT ENOUGH"
        return [
            f"plane frame   {ur_pose_text(self.ur_pose)}",
            f"  pendant     X {o[0]:.3f}  Y {o[1]:.3f}  Z {o[2]:.3f} mm   "
            f"RX {self.ur_pose[3]:.4f}  RY {self.ur_pose[4]:.4f}  RZ {self.ur_pose[5]:.4f} rad "
            f"(rotation vector; RPY {rpy[0]:.3f} {rpy[1]:.3f} {rpy[2]:.3f} deg)",
            "  normal      "
            + " ".join(f"{v:+.6f}" for v in self.normal)
            + f"  (1 sigma {math.degrees(f.sigma_normal_rad) * 1e3:.2f} mdeg, offset "
            f"{f.sigma_offset_m * 1e6:.2f} um)",
            f"  fit         {f.n_inliers} of {f.residuals.shape[0]} points, RMS "
            f"{f.rms * 1e6:.1f} um, peak-to-valley {f.peak_to_valley * 1e6:.1f} um, over "
            f"{f.extent_m[0] * 1e3:.0f} x {f.extent_m[1] * 1e3:.0f} mm",
            f"  flatness    form error {f.form_error * 1e6:.1f} um (tolerance "
            f"{self.max_form_error_m * 1e6:.0f} um): {verdict}",
        ]


def _rpy(R: FloatArray) -> FloatArray:
    """Roll, pitch, yaw (rad) with ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (the pendant's RPY)."""
    pitch = math.asin(max(-1.0, min(1.0, -float(R[2, 0]))))
    roll = math.atan2(float(R[2, 1]), float(R[2, 2]))
    yaw = math.atan2(float(R[1, 0]), float(R[0, 0]))
    return np.array([roll, pitch, yaw])


def plane_from_spots(
    spots: list[Spot] | tuple[Spot, ...],
    max_form_error_m: float = 1e-4,
    **extra: Any,
) -> PlaneResult:
    """Fit the plane to the spots' points and build its frame (see the module doc)."""
    if len(spots) < 2:
        raise TeachError("a plane needs at least two spots (three to check it)")
    # As many points from every spot: one spot's line must not outweigh the others.
    n = min(s.points.shape[0] for s in spots)
    rng = np.random.default_rng(0)
    pts = np.concatenate(
        [
            s.points
            if s.points.shape[0] == n
            else s.points[np.sort(rng.choice(s.points.shape[0], n, replace=False))]
            for s in spots
        ]
    )
    try:
        fit = fit_plane(pts)
    except ValueError as exc:
        raise TeachError(f"no plane fits the points: {exc}") from None
    s0, s1 = spots[0].sensor2base, spots[1].sensor2base
    try:
        o = fit.intersect_line(s0[:3, 3], s0[:3, 2])
        x_to = fit.intersect_line(s1[:3, 3], s1[:3, 2])
        frame = plane_frame(fit.normal, o, x_to, s0[:3, 3])
    except ValueError as exc:
        raise TeachError(f"cannot build the plane frame: {exc}") from None
    return PlaneResult(fit, frame, tuple(spots), max_form_error_m, **extra)


def _spot(sweep: Sweep, s2f: FloatArray, max_points: int) -> Spot:
    pts, prof = points_in_base(sweep, s2f, max_points)
    if pts.shape[0] < MIN_SURFACE_POINTS:
        raise TeachError(
            f"only {pts.shape[0]} valid points at a spot: the surface left the measuring range"
            " (use a smaller --spacing-mm or start closer to the middle of the range)"
        )
    S = mean_pose(sweep.flange2base[np.unique(prof)] @ s2f)
    return Spot(S, pts, int(np.unique(prof).size))


def teach_plane(
    cfg: Config,
    options: PlaneOptions | None = None,
    *,
    confirmed: bool = False,
    progress: Progress | None = None,
) -> PlaneResult:
    """Run the plane-teaching procedure on the devices of ``cfg`` (module doc).

    Raises :class:`~wristscan.daemon.procedure.errors.MotionNotConfirmed` before anything moves,
    :class:`TeachError` when it cannot run or the result is unusable, :class:`TeachAborted`
    when it stopped part way. The result may be not :attr:`~PlaneResult.flat`: the caller
    decides (the CLI writes nothing then)."""
    opts = options or PlaneOptions()
    require_motion(cfg, confirmed)
    calib = load_sensor_calibration(cfg)
    s2f = np.asarray(calib.transform, dtype=np.float64)
    report = stage_reporter(progress, "plane")
    layout = opts.layout()
    total = len(layout) + 1
    t0 = time.monotonic()
    report(0, total, "connecting, waiting for paired profiles")
    with teach_acquisition(cfg) as acq:
        with guarded(acq, "plane teaching"):
            mover = Mover(acq, s2f, opts.speed_m_s)
            spots: list[Spot] = []
            first_sweep = record_still(acq, opts.dwell_s, 0.0)
            first = measure_surface(first_sweep, s2f)
            start = first.sensor2base
            standoff = opts.standoff_m if opts.standoff_m is not None else first.standoff_m
            R = start[:3, :3]
            # Depth model of the surface so far, for the next spot: after the first spot the
            # in-plane tilt of its line, then the plane through every point so far.
            n_est, p_est = first.normal, first.point
            limit = _MAX_DEPTH_CORRECTION * opts.spacing_m
            for i, (dx, dy) in enumerate(layout):
                report(i + 1, total, f"spot {i + 1} of {len(layout)}")
                lateral = start[:3, 3] + dx * R[:, 0] + dy * R[:, 1]
                # Where the sensor's Z axis from there meets the surface estimate.
                den = float(n_est @ R[:, 2])
                depth = float((p_est - lateral) @ n_est) / den if abs(den) > 1e-6 else standoff
                shift = float(np.clip(depth - standoff, -limit, limit))
                if i == 0 and abs(shift) < 2e-4:
                    sweep = first_sweep
                else:
                    mover.move_sensor(se3.make(R, lateral + shift * R[:, 2]))
                    sweep = record_still(acq, opts.dwell_s)
                spots.append(_spot(sweep, s2f, opts.max_points_per_spot))
                if len(spots) >= 2:
                    pre = fit_plane(np.concatenate([s.points for s in spots]))
                    n_est, p_est = np.asarray(pre.normal), np.asarray(pre.point)
            if opts.return_to_start:
                report(total - 1, total, "back to the start")
                mover.move_sensor(start)
    result = plane_from_spots(
        spots,
        opts.max_form_error_m,
        duration_s=time.monotonic() - t0,
        sensor_calibration=str(cfg.calibration.file),
    )
    report(total, total, "done")
    return result


def write_plane_frame(path: str | Path, result: PlaneResult) -> Path:
    """Write the frame and its statistics as JSON (atomically)."""
    return write_atomic(path, json.dumps(result.to_dict(), indent=2) + "\n")


def read_plane_frame(path: str | Path) -> dict[str, Any]:
    """The JSON document of a plane frame file; ValueError when it is not one."""
    doc = json.loads(Path(path).read_text(encoding="utf-8"))
    if not isinstance(doc, dict) or doc.get("format") != FRAME_FORMAT:
        raise ValueError(f"{path}: not a wristscan plane frame file")
    return doc
