"""Distance sensing with the calibrated sensor (``wristscan measure``).

:func:`measure` records still profiles (or, with ``sweep_m``, a short move along the sensor's X
axis) and reports the standoff (distance along the sensor's Z axis to the surface at the middle
of the laser line), the surface normal under the sensor (the in-plane tilt only from a still
profile: the component along X needs the sweep), the surface point in the base frame, and the
sensor pose that would look at that point along the normal from a chosen standoff.
:func:`measure_surface` is the same measurement of a recorded sweep; plane teaching
(:mod:`.plane`) starts with it.

Safety as for every teaching procedure (:mod:`.kit`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import se3
from wristscan.calib.plane import fit_hyperplane, fit_plane
from wristscan.daemon.config import Config
from wristscan.daemon.procedure.in_force import load_sensor_calibration
from wristscan.daemon.procedure.motion import require_motion
from wristscan.daemon.teach.kit import (
    Mover,
    TeachError,
    guarded,
    mean_pose,
    points_in_base,
    record_still,
    teach_acquisition,
)

if TYPE_CHECKING:
    from wristscan.daemon.procedure.acquisition import Acquisition, Sweep

__all__ = ["MIN_SURFACE_POINTS", "SurfaceMeasurement", "measure", "measure_surface"]

FloatArray = NDArray[np.float64]

MIN_SURFACE_POINTS = 50
"""Fewer valid points than this: no surface in the measuring range (also per plane spot)."""


@dataclass(frozen=True)
class SurfaceMeasurement:
    """The surface under the sensor (SI units; base frame unless named ``_sensor``)."""

    standoff_m: float
    """Distance along the sensor's Z axis to the surface (at the middle of the laser line)."""
    point: FloatArray
    """(3,) that surface point."""
    normal: FloatArray
    """(3,) unit surface normal, towards the sensor."""
    normal_sensor: FloatArray
    """(3,) the same in the sensor frame."""
    full_normal: bool
    """False for a still measurement: the normal's component along the sensor's X axis is not
    observed (the normal is the one in the laser plane)."""
    incidence_deg: float
    """Angle between the sensor's Z axis and the normal (0: looking straight at the surface)."""
    rms_m: float
    n_points: int
    n_profiles: int
    sensor2base: FloatArray
    """(4, 4) sensor pose (the mean over the profiles used)."""

    def normal_view(self, standoff_m: float | None = None) -> FloatArray:
        """``sensor2base`` looking at :attr:`point` along the normal from ``standoff_m``
        (default: the current standoff), its X axis as close to the current one as possible."""
        d = self.standoff_m if standoff_m is None else float(standoff_m)
        z = -self.normal
        x0 = self.sensor2base[:3, 0]
        x = x0 - (x0 @ z) * z
        if np.linalg.norm(x) < 1e-6:
            x = self.sensor2base[:3, 1] - (self.sensor2base[:3, 1] @ z) * z
        x = x / np.linalg.norm(x)
        return np.asarray(se3.make(np.column_stack([x, np.cross(z, x), z]), self.point - d * z))

    def to_dict(self) -> dict[str, Any]:
        return {
            "standoff_m": self.standoff_m,
            "point_m": self.point.tolist(),
            "normal": self.normal.tolist(),
            "normal_sensor": self.normal_sensor.tolist(),
            "full_normal": self.full_normal,
            "incidence_deg": self.incidence_deg,
            "rms_m": self.rms_m,
            "n_points": self.n_points,
            "n_profiles": self.n_profiles,
            "sensor2base": self.sensor2base.tolist(),
            "sensor_pose_ur": se3.matrix_to_pose(self.sensor2base).tolist(),
        }


def measure_surface(
    sweep: Sweep,
    sensor2flange: ArrayLike,
    *,
    swept: bool = False,
    max_points: int = 20_000,
) -> SurfaceMeasurement:
    """The surface under the sensor from ``sweep`` (see the module doc). ``swept``: the
    profiles come from a move along the sensor's X axis, so the full normal is fitted (a plane);
    otherwise a line in the laser plane. Raises :class:`TeachError` without enough points."""
    s2f = np.asarray(sensor2flange, dtype=np.float64)
    pts, prof = points_in_base(sweep, s2f, max_points)
    if pts.shape[0] < MIN_SURFACE_POINTS:
        raise TeachError(f"only {pts.shape[0]} valid points: no surface within the measuring range")
    s2b_all = sweep.flange2base @ s2f
    S = mean_pose(s2b_all[np.unique(prof)])
    origin, zaxis = S[:3, 3], S[:3, 2]
    if swept:
        fit = fit_plane(pts)
        n = np.asarray(fit.normal)
        if float(n @ (origin - fit.point)) < 0:
            n = -n
        try:
            point = fit.intersect_line(origin, zaxis)
        except ValueError:
            raise TeachError("the sensor's Z axis runs parallel to the surface") from None
        rms, n_in = fit.rms, fit.n_inliers
        n_s = S[:3, :3].T @ n
    else:
        local = (pts - origin) @ S[:3, :3]  # sensor frame: x ~ 0, (y, z) in the laser plane
        line = fit_hyperplane(local[:, 1:3])
        nl = np.asarray(line.normal)
        if nl[1] > 0:
            nl = -nl  # towards the sensor (negative z)
        if abs(float(nl[1])) < 1e-9:
            raise TeachError("the laser line runs along the sensor's Z axis: no surface")
        z0 = line.offset / float(line.normal[1])
        n_s = np.array([0.0, nl[0], nl[1]])
        n = S[:3, :3] @ n_s
        point = origin + z0 * zaxis
        rms, n_in = line.rms, line.n_inliers
    standoff = float((point - origin) @ zaxis)
    incidence = math.degrees(math.acos(min(1.0, abs(float(n @ zaxis)))))
    return SurfaceMeasurement(
        standoff_m=standoff,
        point=np.asarray(point, dtype=np.float64),
        normal=np.asarray(n / np.linalg.norm(n), dtype=np.float64),
        normal_sensor=np.asarray(n_s / np.linalg.norm(n_s), dtype=np.float64),
        full_normal=swept,
        incidence_deg=incidence,
        rms_m=float(rms),
        n_points=int(n_in),
        n_profiles=int(np.unique(prof).size),
        sensor2base=S,
    )


def measure(
    cfg: Config,
    *,
    dwell_s: float = 0.2,
    sweep_m: float = 0.0,
    speed_m_s: float = 0.01,
    confirmed: bool = False,
    acquisition: Acquisition | None = None,
) -> SurfaceMeasurement:
    """Measure the surface under the sensor on the devices of ``cfg``. With ``sweep_m`` > 0 the
    sensor moves ``+-sweep_m / 2`` along its X axis and back (needs motion enabled and
    ``confirmed``); otherwise nothing moves. ``acquisition``: an already built one (tests),
    opened if need be and closed at the end, as by the other procedures."""
    if sweep_m > 0:
        require_motion(cfg, confirmed)
    calib = load_sensor_calibration(cfg)
    s2f = np.asarray(calib.transform, dtype=np.float64)
    with teach_acquisition(cfg, acquisition) as acq:
        still = record_still(acq, dwell_s, settle_s=0.0)
        if sweep_m <= 0:
            return measure_surface(still, s2f)
        with guarded(acq, "measurement sweep"):
            mover = Mover(acq, s2f, speed_m_s)
            S = mean_pose(still.flange2base @ s2f)
            half = 0.5 * sweep_m * S[:3, 0]
            start, end = S.copy(), S.copy()
            start[:3, 3] -= half
            end[:3, 3] += half
            mover.move_sensor(start)
            with acq.record() as rec:
                mover.move_sensor(end, speed_m_s)
            sweep = rec.result()
            mover.move_sensor(S)
        return measure_surface(sweep, s2f, swept=True)
