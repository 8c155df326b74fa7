"""What the sensor calibration visits and how: its :class:`Settings` (from a configuration with
:func:`settings_for`), the starting sensor2flange (:func:`default_nominal`), the field-of-view
locations of the ball in the laser plane (:func:`fov_targets`) and the orientations around the
ball (:func:`orbit_pose`, :func:`plan_orientations`).

Pure geometry on the settings: nothing here moves the robot or records (see
:mod:`.collect`); whether a pose can be reached is asked of the caller (:mod:`.reach`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import se3

if TYPE_CHECKING:
    from wristscan.daemon.config import Config

__all__ = [
    "ISO9283_RP_PER_AXIS_SIGMA",
    "UR_REPEATABILITY_ISO9283_M",
    "OrientationPlan",
    "Settings",
    "default_nominal",
    "fov_targets",
    "iso9283_axis_sigma",
    "min_pairwise",
    "orbit_pose",
    "plan_orientations",
    "rotation_between",
    "settings_for",
    "tx",
    "tz",
    "z_axis_angles_deg",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

UR_REPEATABILITY_ISO9283_M: Mapping[str, float] = {
    "UR3": 1e-4,
    "UR5": 1e-4,
    "UR10": 1e-4,
    "UR3e": 3e-5,
    "UR5e": 3e-5,
    "UR10e": 5e-5,
    "UR16e": 5e-5,
    "UR20": 5e-5,
}
"""Pose repeatability per ISO 9283 from the UR data sheets (metres, the "+-" figure)."""

#: ISO 9283 pose repeatability RP = mean + 3 std of the 3-D distance to the mean position. For an
#: isotropic Gaussian error of per-axis std s the distance is chi(3)-distributed: mean s*sqrt(8/pi),
#: std s*sqrt(3 - 8/pi), so RP = 3.62 s.
ISO9283_RP_PER_AXIS_SIGMA = math.sqrt(8 / math.pi) + 3 * math.sqrt(3 - 8 / math.pi)


def iso9283_axis_sigma(rp_m: float) -> float:
    """Per-axis standard deviation (m) of the position error behind an ISO 9283 repeatability."""
    return float(rp_m) / ISO9283_RP_PER_AXIS_SIGMA


# --------------------------------------------------------------------------------------------
# Settings


@dataclass(frozen=True)
class Settings:
    """How the procedure runs (SI units). :func:`settings_for` fills them from a configuration."""

    ball_radius_m: float = 0.0127
    fov_width_m: float = 0.05
    """Length of the laser line (lateral field of view, sensor Y) at the working depths."""
    depth_min_m: float = 0.05
    """Measuring range along sensor Z."""
    depth_max_m: float = 0.15
    margin_m: float = 0.003
    """Clearance between the ball and the edges of the field of view, and the overshoot of each
    sweep beyond the ball."""
    fov_grid: int = 4
    """Field-of-view locations: ``fov_grid x fov_grid`` (lateral x depth): the lever that pins
    the sensor's rotation, and cheap (short moves between the places)."""
    sweep_speed_m_s: float = 0.05
    """At 1 kHz, 0.05 mm between profiles; the latency error this speed makes worse is measured
    and removed per forward/backward pair."""
    sweep_accel_m_s2: float = 0.5
    travel_speed_m_s: float = 0.25
    travel_accel_m_s2: float = 1.0
    joint_speed_rad_s: float = 1.0
    joint_accel_rad_s2: float = 1.5
    n_orientations: int = 6
    """Tilted orientations around the ball (besides the start orientation): six at 52 degrees
    keep every pair of sensor Z axes >= 45 degrees apart (the paper's rule); more add little
    information for their robot time."""
    tilt_deg: float = 52.0
    """Angle between the sensor Z axis of each tilted orientation and the start orientation's.
    Six azimuths at 52 degrees keep every pair of Z axes >= 46 degrees apart."""
    min_tilt_deg: float = 45.0
    """Smallest tilt a replacement orientation may have (paper sec. 3)."""
    clearance_m: float = 0.04
    """Retreat along sensor -Z before a reorientation (joint moves start and end there)."""
    bidirectional: bool = True
    """Sweep every location forwards and backwards (cancels a sensor latency error)."""
    lateral_places: int = 2
    """Places of the ball along the laser line at each tilted orientation: 2 (both ends of the
    line) or 1 (alternately one end): the rotation about the sensor Z axis is seen only through
    the ball's lateral offset."""
    sweep_retries: int = 4
    """Repeats of a sweep that came out with gaps (too few profiles paired)."""
    compensate_timing: bool = True
    """Remove the apparent time offset of every forward/backward pair before the final solution
    (:func:`~.solve.compensate_timing`)."""
    max_points_per_sweep: int = 6000
    """Points kept per sweep (a random subset): with tens of sweeps, far more than the
    robot's repeatability leaves to resolve, and it keeps the solutions fast."""
    robot_sigma_m: float = 0.0
    """Per-axis standard deviation of the robot's repeatability (m), propagated into the
    covariance (the error shared by all points of a sweep)."""
    robot_model: str | None = None
    """The configured (nominal) robot model: with ``kinematic_prior``, what the flange poses'
    model is judged against (a model other than the nominal table is a factory calibration)."""
    kinematic_prior: bool = True
    """Include the arm's kinematic error left by its factory calibration (or all of it, on the
    nominal table) in the reported uncertainty (:mod:`wristscan.calib.handeye_kinematic`); it
    needs ``robot_model``."""
    leave_one_out: bool = True
    check_scan: bool = True
    lock_timeout_s: float = 20.0
    """How long to wait for the first paired profiles."""

    @property
    def sweep_half_m(self) -> float:
        """Half the sweep length along sensor X: ``R + margin``."""
        return self.ball_radius_m + self.margin_m

    @property
    def lateral_half_m(self) -> float:
        """Largest lateral offset of the ball centre from the laser line's middle."""
        return self.fov_width_m / 2 - self.ball_radius_m - self.margin_m

    @property
    def depth_span_m(self) -> tuple[float, float]:
        """Nearest and farthest depth of the ball centre: its near cap stays beyond
        ``depth_min`` and its outline (at the centre's depth) within ``depth_max``."""
        return (
            self.depth_min_m + self.ball_radius_m + self.margin_m,
            self.depth_max_m - self.margin_m,
        )

    @property
    def working_depth_m(self) -> float:
        lo, hi = self.depth_span_m
        return (lo + hi) / 2

    def check(self) -> None:
        """Raise ``ValueError`` (one line, for the operator) when the settings cannot work."""
        R = self.ball_radius_m
        if not (math.isfinite(R) and R > 0):
            raise ValueError(f"ball radius must be positive, got {R * 1e3:g} mm")
        if self.lateral_half_m < 0:
            raise ValueError(
                f"the laser line ({self.fov_width_m * 1e3:g} mm) is too short for a ball of "
                f"radius {R * 1e3:g} mm with {self.margin_m * 1e3:g} mm margins"
            )
        lo, hi = self.depth_span_m
        if hi <= lo:
            raise ValueError(
                f"the measuring range {self.depth_min_m * 1e3:g}..{self.depth_max_m * 1e3:g} mm "
                f"is too short for a ball of radius {R * 1e3:g} mm"
            )
        if self.fov_grid < 2:
            raise ValueError("the FOV grid needs at least 2 x 2 locations")
        if self.lateral_places not in (1, 2):
            raise ValueError("lateral_places must be 1 or 2")
        if self.n_orientations < 2:
            raise ValueError("at least 2 tilted orientations are needed (6 recommended)")
        if not 0 < self.min_tilt_deg <= self.tilt_deg < 90:
            raise ValueError("tilt must be between the minimum tilt and 90 degrees")
        for name in (
            "sweep_speed_m_s",
            "sweep_accel_m_s2",
            "travel_speed_m_s",
            "travel_accel_m_s2",
            "joint_speed_rad_s",
            "joint_accel_rad_s2",
            "clearance_m",
            "margin_m",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be positive, got {v}")
        if self.max_points_per_sweep < 1000:
            raise ValueError("max_points_per_sweep must be at least 1000")


def settings_for(cfg: Config, **overrides: Any) -> Settings:
    """Settings for ``cfg``: the field of view of the simulated sensor when ``[sim]`` is there,
    the repeatability of the configured UR model (ISO 9283 data-sheet figure as a per-axis
    standard deviation), speeds within the configured caps; ``overrides`` (Settings fields, None
    values ignored) win. Raises ``ValueError`` when the result is inconsistent or above a cap."""
    kw: dict[str, Any] = {}
    if cfg.sim is not None:
        s = cfg.sim.sensor
        kw.update(fov_width_m=s.fov_lateral_m, depth_min_m=s.depth_min_m, depth_max_m=s.depth_max_m)
        kw["ball_radius_m"] = cfg.sim.scene.ball_radius_m
    rp = UR_REPEATABILITY_ISO9283_M.get(cfg.robot.model)
    if rp is not None:
        kw["robot_sigma_m"] = iso9283_axis_sigma(rp)
    r = cfg.robot
    kw["robot_model"] = r.model
    base = Settings()
    kw["travel_speed_m_s"] = min(base.travel_speed_m_s, r.max_speed_m_s)
    kw["travel_accel_m_s2"] = min(base.travel_accel_m_s2, r.max_accel_m_s2)
    kw["sweep_accel_m_s2"] = min(base.sweep_accel_m_s2, r.max_accel_m_s2)
    kw["joint_speed_rad_s"] = min(base.joint_speed_rad_s, r.max_joint_speed_rad_s)
    kw["joint_accel_rad_s2"] = min(base.joint_accel_rad_s2, r.max_joint_accel_rad_s2)
    kw.update({k: v for k, v in overrides.items() if v is not None})
    out = Settings(**kw)
    out.check()
    if out.sweep_speed_m_s > r.max_speed_m_s:
        raise ValueError(
            f"sweep speed {out.sweep_speed_m_s * 1e3:g} mm/s is above the configured "
            f"[robot] max_speed_m_s ({r.max_speed_m_s * 1e3:g} mm/s)"
        )
    for name, cap in (
        ("travel_speed_m_s", r.max_speed_m_s),
        ("joint_speed_rad_s", r.max_joint_speed_rad_s),
    ):
        if getattr(out, name) > cap:
            raise ValueError(f"{name} {getattr(out, name):g} is above the configured cap {cap:g}")
    return out


def default_nominal(cfg: Config) -> tuple[FloatArray, str] | None:
    """A starting sensor2flange when none is given: the calibration in force (if its file reads),
    else for a simulated cell the drawing value (the true pose rounded to 1 cm, no rotation).
    Returns the transform and where it came from, or None.

    Not :func:`~wristscan.daemon.procedure.in_force.calibration_in_force`: any start will do
    here, so the file is read without the identity check and one that does not read is passed
    over (with a warning), not an error."""
    from wristscan.daemon.io.calibfile import CalibrationFileError, read_calibration

    f = cfg.calibration.file
    if f is not None and Path(f).exists():
        try:
            c = read_calibration(f, kind="sensor2flange")
            return np.array(c.transform), f"the calibration in force ({f})"
        except CalibrationFileError as exc:
            log.warning("ignoring the calibration in force as a start: %s", exc)
    if cfg.sim is not None:
        t = np.round(np.asarray(cfg.sim.truth.sensor2flange_pose[:3]), 2)
        return se3.make(None, t), "the simulated sensor's drawing value (rounded, no rotation)"
    return None


# --------------------------------------------------------------------------------------------
# Geometry of the plan


def fov_targets(settings: Settings) -> FloatArray:
    """Ball-centre locations in the laser plane, sensor frame ``(n*n, 3)`` (x = 0), in a
    serpentine order (short moves): lateral across the line, depth across the range."""
    n = settings.fov_grid
    ys = np.linspace(-settings.lateral_half_m, settings.lateral_half_m, n)
    lo, hi = settings.depth_span_m
    zs = np.linspace(lo, hi, n)
    rows = []
    for i, z in enumerate(zs):
        for y in ys if i % 2 == 0 else ys[::-1]:
            rows.append((0.0, float(y), float(z)))
    return np.array(rows)


def tx(x: float) -> FloatArray:
    """A translation by ``x`` along X (along a sweep, in the sensor frame)."""
    return se3.make(None, (x, 0.0, 0.0))


def tz(z: float) -> FloatArray:
    """A translation by ``z`` along Z (towards or away from the ball, in the sensor frame)."""
    return se3.make(None, (0.0, 0.0, z))


def rotation_between(A: FloatArray, B: FloatArray) -> float:
    """Angle (rad) of the rotation between the orientations of the transforms ``A`` and ``B``."""
    return float(se3.rotation_angle(A[:3, :3].T @ B[:3, :3]))


def orbit_pose(
    reference_sensor2base: ArrayLike,
    ball_centre_base: ArrayLike,
    depth_m: float,
    azimuth_rad: float,
    tilt_rad: float,
    roll_rad: float = 0.0,
) -> FloatArray:
    """Sensor pose ``(4, 4)`` looking at the ball from ``depth_m`` (ball at ``(0, 0, depth)`` in
    the sensor frame), tilted by ``tilt_rad`` from the reference orientation about the axis at
    ``azimuth_rad`` in the reference sensor X-Y plane, then rolled by ``roll_rad`` about its own
    Z axis. The tilt pivots about the ball, so the ball stays in view."""
    Sref = np.asarray(reference_sensor2base, dtype=np.float64)
    c = np.asarray(ball_centre_base, dtype=np.float64)
    Rref = Sref[:3, :3]
    S0 = se3.make(Rref, c - Rref @ np.array([0.0, 0.0, depth_m]))
    axis = Rref @ np.array([math.cos(azimuth_rad), math.sin(azimuth_rad), 0.0])
    Rb = se3.rotvec_to_matrix(axis * tilt_rad)
    about_ball = se3.make(Rb, c - Rb @ c)
    return np.asarray(about_ball @ S0 @ se3.make(se3.rot_z(roll_rad)), dtype=np.float64)


def z_axis_angles_deg(sensor2base: Sequence[FloatArray]) -> FloatArray:
    """Pairwise angles (degrees) between the sensor Z axes of the poses, ``(n, n)``."""
    z = np.array([np.asarray(S)[:3, 2] for S in sensor2base])
    return np.degrees(np.arccos(np.clip(z @ z.T, -1.0, 1.0)))


def min_pairwise(angles: FloatArray) -> float:
    """Smallest off-diagonal entry of :func:`z_axis_angles_deg` (NaN for fewer than 2 poses)."""
    n = angles.shape[0]
    if n < 2:
        return float("nan")
    return float(angles[~np.eye(n, dtype=bool)].min())


@dataclass(frozen=True)
class OrientationPlan:
    """One orientation around the ball: where it is (degrees), where the ball sits along the laser
    line (``lateral_m``, sensor Y) and why."""

    label: str
    azimuth_deg: float
    tilt_deg: float
    roll_deg: float
    note: str = ""
    lateral_m: float = 0.0

    def sensor2base(self, reference: FloatArray, ball: FloatArray, depth_m: float) -> FloatArray:
        """Sensor pose with the ball at ``(0, lateral_m, depth_m)`` in the sensor frame."""
        S = orbit_pose(
            reference,
            ball,
            depth_m,
            math.radians(self.azimuth_deg),
            math.radians(self.tilt_deg),
            math.radians(self.roll_deg),
        )
        return np.asarray(S @ se3.make(None, (0.0, -self.lateral_m, 0.0)))


def _azimuth_order(n: int) -> list[int]:
    """Visit order of ``n`` evenly spread azimuths: each next tilt axis as far as possible (mod
    180 degrees) from those visited, so the sensor origin is determined early."""
    axes = np.array([(180.0 * 2 * i / n) % 180.0 for i in range(n)])
    order = [0]
    while len(order) < n:
        rest = [i for i in range(n) if i not in order]

        def gap(i: int) -> float:
            d = np.abs(axes[i] - axes[order])
            return float(np.min(np.minimum(d, 180.0 - d)))

        order.append(max(rest, key=lambda i: (gap(i), -i)))
    return order


def _candidates(settings: Settings, azimuth_deg: float) -> list[tuple[float, float]]:
    """(tilt, roll) in degrees to try for one azimuth, preferred first."""
    t = settings.tilt_deg
    tilts = [t, t + 10.0, max(settings.min_tilt_deg, t - 5.0)]
    rolls = [0.0, 90.0, -90.0, 180.0]
    out: list[tuple[float, float]] = []
    for tilt in tilts:
        for roll in rolls:
            if (tilt, roll) not in out and tilt < 85.0:
                out.append((tilt, roll))
    return out


def plan_orientations(
    settings: Settings,
    reach: Callable[[OrientationPlan], bool],
) -> tuple[list[OrientationPlan], list[str]]:
    """The tilted orientations to visit, in order, and notes on what was replaced or skipped.

    ``settings.n_orientations`` azimuths evenly spread; for each, the first reachable candidate
    (the planned tilt with roll 0, then rolls of 90, -90, 180 degrees, then 10 degrees more
    tilt, then less tilt down to ``min_tilt_deg``) is taken."""
    n = settings.n_orientations
    plans: list[OrientationPlan] = []
    notes: list[str] = []
    for k, i in enumerate(_azimuth_order(n)):
        az = 360.0 * i / n
        chosen = None
        for tilt, roll in _candidates(settings, az):
            # The ball alternately left and right of the line's middle: the rotation about the
            # sensor Z axis is seen only through the ball's lateral offset (the FOV stage's alone
            # is short).
            side = settings.lateral_half_m * (1.0 if k % 2 == 0 else -1.0)
            cand = OrientationPlan(f"tilt {k + 1} (az {az:.0f} deg)", az, tilt, roll, "", side)
            if reach(cand):
                chosen = cand
                break
        if chosen is None:
            notes.append(f"azimuth {az:.0f} deg: no reachable orientation; skipped")
            continue
        if (chosen.tilt_deg, chosen.roll_deg) != (settings.tilt_deg, 0.0):
            note = (
                f"azimuth {az:.0f} deg: planned tilt {settings.tilt_deg:.0f} deg unreachable; "
                f"using tilt {chosen.tilt_deg:.0f} deg, roll {chosen.roll_deg:.0f} deg"
            )
            notes.append(note)
            chosen = dataclasses.replace(chosen, note=note)
        plans.append(chosen)
    return plans, notes
