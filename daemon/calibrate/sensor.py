"""``wristscan calibrate sensor``: the sensor-to-flange calibration as a procedure at the cell.

A tooling ball of known radius stands in the workspace; the operator jogs the robot so that the
laser line crosses the ball. Then, with motion enabled and confirmed (automatic mode):

a. **find** - the ball's arc in the live profiles is fitted with a circle (is it a ball of this
   radius?), then one sweep along the sensor X axis from ``-(R + margin)`` to ``+(R + margin)``
   (the paper's ball matching) gives the ball centre through the *nominal* sensor2flange;
b. **fov** - at the start orientation, the ball is placed at a ``n x n`` grid of field-of-view
   locations in the laser plane (lateral ``+-(FOV/2 - R - margin)``, depth across the measuring
   range) and swept along sensor X at each (Borangiu et al. 2009, sec. 1: ball matching). Step 1
   of the paper's solution (:func:`wristscan.calib.handeye.solve_orientation`) then gives the
   rotation of sensor2flange;
c. **orient** - the sensor orbits the ball: a balanced set of ``>= 6`` orientations tilted by
   ``>= 45`` degrees from the start orientation at evenly spread azimuths (paper sec. 3: at least
   45 degrees between tool Z axes, and a balanced set covering the orientations used later),
   each reached by a retreat along sensor -Z, a joint move and a linear approach, and swept along
   its sensor X. Unreachable orientations are replaced (more tilt, a roll about the sensor Z) or
   skipped, and the report says so. After two orientations the sensor origin is estimated (step
   2) and the remaining ones are aimed with it;
d. **solve** - the paper's two-step solution (:func:`~wristscan.calib.handeye.two_step`) and the
   joint refinement of all six parameters and the ball centre on every point of every sweep
   (:func:`~wristscan.calib.handeye.refine`, covariance including the robot's repeatability);
e. **validate** - leave-one-out over the orientations (the spread of the estimates), a check scan
   at an orientation that was not used (sphere fit of its points mapped with the new calibration:
   centre against the calibrated ball centre, radius against the known one), and the apparent
   sensor time offset from sweeps in both directions;
f. the calibration file is written (atomically; nothing is written when the procedure fails or
   is stopped, so the calibration in force stays) and a report.

Sweeps are recorded while the robot moves: every profile is paired with the robot state at its
exposure by the synchroniser (:class:`wristscan.daemon.procedure.acquisition.Acquisition`),
so a sweep gives hundreds of profiles, not one stop-and-go sample. Each location is swept
forwards and backwards:
an error in the configured sensor latency shifts the ball by ``speed * error`` along the travel,
in opposite directions for the two passes. Its size is measured (:class:`ApparentLatency`),
each pair is re-timed by its own offset before the final solution (:func:`compensate_timing`),
and a place whose passes still disagree with the solution is left out
(:func:`inconsistent_locations`).

Manual mode records each sweep while the operator moves the robot from the teach pendant (press
Enter to start and to stop); no motion is commanded.

Everything here is plain functions and classes; :func:`run` ties them to a configuration and is
what the command line calls. Units are SI throughout (metres, radians, seconds).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import handeye, kinematics, se3, sphere
from wristscan.daemon.io.calibfile import (
    Calibration,
    Residuals,
    RobotIdentity,
    SensorIdentity,
    write_calibration,
)
from wristscan.daemon.procedure.acquisition import Acquisition
from wristscan.daemon.procedure.acquisition import Sweep as RecordedData
from wristscan.drivers.base import DriverError, MotionNotEnabled, WorkspaceViolation

if TYPE_CHECKING:
    from wristscan.daemon.config import Config
    from wristscan.daemon.io.report import Report
    from wristscan.drivers.records import RobotState
__all__ = [
    "UR_REPEATABILITY_ISO9283_M",
    "ApparentLatency",
    "CalibrationAborted",
    "CalibrationFailed",
    "CheckScan",
    "LeaveOneOut",
    "OrientationPlan",
    "ProgressEvent",
    "RecordedSweep",
    "RobotCell",
    "SensorCalibration",
    "SensorCalibrationResult",
    "Settings",
    "apparent_latency",
    "build_report",
    "calibration_of",
    "check_scan_fit",
    "default_nominal",
    "fov_targets",
    "iso9283_axis_sigma",
    "leave_one_out",
    "orbit_pose",
    "parse_ur_pose",
    "plan_orientations",
    "run",
    "settings_for",
    "solve",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]
T = TypeVar("T")

METHOD = "ball-matching+joint-refinement"
"""``method`` of the calibration files written here."""

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

_ORIENTATION_TOL_RAD = 2e-3
_MIN_BALL_POINTS = 200
_MAX_JOINT_STEP_RAD = 0.6
"""Largest joint change allowed along a short linear move (a larger one means a branch flip or a
singularity on the way)."""
_MIN_WRIST_SIN = math.sin(math.radians(5.0))
_MAX_ARM_CHANGE_RAD = math.radians(75.0)
_LOO_MIN_GROUPS = 3
_FIGURE_POINTS = 4000
_BAND_WIDE_M = 8e-3
"""Points farther than this from the predicted ball surface are dropped while the sensor origin
is still the nominal one (clutter: the post, the table)."""
_BAND_NARROW_M = 4e-3
_PAIRED_SHARE = 0.5
_MIN_SPAN_R = 1.4
"""A sweep must see the ball over at least this many radii along its travel ..."""
_MAX_GAP_R = 0.25
"""... with no gap between paired profiles longer than this many radii."""
"""Share of a sweep's profiles that must be paired with robot states (else it is repeated)."""


def iso9283_axis_sigma(rp_m: float) -> float:
    """Per-axis standard deviation (m) of the position error behind an ISO 9283 repeatability."""
    return float(rp_m) / ISO9283_RP_PER_AXIS_SIGMA


# --------------------------------------------------------------------------------------------
# Errors and progress


class CalibrationFailed(RuntimeError):
    """The procedure cannot produce a calibration (the ball is not in view, too few reachable
    orientations, the data do not constrain the result...); the message says what to do."""


class CalibrationAborted(RuntimeError):
    """The procedure was stopped: a protective stop, a failed or refused motion, the operator.
    Nothing was written; the calibration in force is unchanged."""


@dataclass(frozen=True)
class ProgressEvent:
    """What the procedure is doing: ``stage`` (``connect``, ``find``, ``fov``, ``orient``,
    ``solve``, ``validate``, ``check``, ``write``), ``step`` of ``total`` within it (0 of 0 when
    not counted) and a one-line message."""

    stage: str
    step: int
    total: int
    message: str

    def __str__(self) -> str:
        count = f" {self.step}/{self.total}" if self.total else ""
        return f"[{self.stage}{count}] {self.message}"


Progress = Callable[[ProgressEvent], None]
Prompt = Callable[[str], str]


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
    """Field-of-view locations: ``fov_grid x fov_grid`` (lateral x depth)."""
    sweep_speed_m_s: float = 0.02
    sweep_accel_m_s2: float = 0.5
    travel_speed_m_s: float = 0.1
    travel_accel_m_s2: float = 0.5
    joint_speed_rad_s: float = 0.6
    joint_accel_rad_s2: float = 1.2
    n_orientations: int = 10
    """Tilted orientations around the ball (besides the start orientation)."""
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
    (:func:`compensate_timing`)."""
    max_points_per_sweep: int = 6000
    """Points kept per sweep (a random subset): with tens of sweeps, far more than the
    robot's repeatability leaves to resolve, and it keeps the solutions fast."""
    robot_sigma_m: float = 0.0
    """Per-axis standard deviation of the robot's repeatability (m), propagated into the
    covariance (the error shared by all points of a sweep)."""
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


_POSE_RE = re.compile(r"^\s*p?\s*\[(.*)\]\s*$")


def parse_ur_pose(text: str) -> FloatArray:
    """``"p[x, y, z, rx, ry, rz]"`` (metres, rotation vector in radians; the ``p`` and the
    brackets are optional) as a 4x4 transform. Raises ``ValueError`` with a one-line reason."""
    m = _POSE_RE.match(text)
    body = m.group(1) if m else text
    parts = [p for p in re.split(r"[,\s]+", body.strip()) if p]
    try:
        values = np.array([float(p) for p in parts], dtype=np.float64)
    except ValueError:
        raise ValueError(f"not a UR pose p[x, y, z, rx, ry, rz]: {text!r}") from None
    if values.shape != (6,) or not np.all(np.isfinite(values)):
        raise ValueError(f"a UR pose needs 6 finite numbers (m, rad), got {text!r}")
    if np.linalg.norm(values[:3]) > 2.0:
        raise ValueError(f"pose translation {values[:3].tolist()} is over 2 m: metres expected")
    return se3.pose_to_matrix(values)


def default_nominal(cfg: Config) -> tuple[FloatArray, str] | None:
    """A starting sensor2flange when none is given: the calibration in force (if its file reads),
    else for a simulated cell the drawing value (the true pose rounded to 1 cm, no rotation).
    Returns the transform and where it came from, or None."""
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


def _tx(x: float) -> FloatArray:
    return se3.make(None, (x, 0.0, 0.0))


def _tz(z: float) -> FloatArray:
    return se3.make(None, (0.0, 0.0, z))


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


def _min_pairwise(angles: FloatArray) -> float:
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


@dataclass(frozen=True)
class _Reach:
    """Joint solutions of the approach, sweep start and sweep end of one location, and of a pose
    to pass through on the way to the approach (None: straight there)."""

    approach: FloatArray
    start: FloatArray
    end: FloatArray
    via: FloatArray | None = None


class _Kin:
    """Reachability of flange poses for the plan: IK near a seed, in the arm configuration of the
    start pose (base, shoulder and elbow within ``_MAX_ARM_CHANGE_RAD`` of ``reference_q``: no
    swinging the arm over), away from the wrist singularity, joint continuity along short linear
    moves, TCP inside the workspace box (also along joint moves)."""

    def __init__(
        self,
        model: kinematics.DHParams,
        tcp2flange: FloatArray,
        workspace: tuple[FloatArray, FloatArray] | None,
        reference_q: FloatArray | None = None,
    ) -> None:
        self.model = model
        self.tcp2flange = tcp2flange
        self.workspace = workspace
        self.reference_q = None if reference_q is None else np.asarray(reference_q, float)

    def _arm_ok(self, q: FloatArray) -> bool:
        if self.reference_q is None:
            return True
        d = kinematics.wrap_angle(q[:3] - self.reference_q[:3])
        return float(np.max(np.abs(d))) <= _MAX_ARM_CHANGE_RAD

    def ik(self, flange2base: FloatArray, seed: FloatArray) -> FloatArray | None:
        try:
            q = kinematics.inverse_nearest(self.model, flange2base, seed)
            if not self._arm_ok(q) and self.reference_q is not None:
                q = kinematics.inverse_nearest(self.model, flange2base, self.reference_q)
        except kinematics.Unreachable:
            return None
        if not self._arm_ok(q):
            return None
        if abs(math.sin(float(q[4]))) < _MIN_WRIST_SIN:
            return None
        if self.workspace is not None:
            p = (flange2base @ self.tcp2flange)[:3, 3]
            lo, hi = self.workspace
            if np.any(p < lo) or np.any(p > hi):
                return None
        return np.asarray(q, dtype=np.float64)

    def linear(
        self, a: FloatArray, b: FloatArray, qa: FloatArray, steps: int = 4
    ) -> FloatArray | None:
        """Joints at ``b`` reached by a linear move from ``a`` (joints ``qa``), or None when the
        path leaves the reach, the workspace or the joint branch."""
        q = qa
        for s in np.linspace(0.0, 1.0, steps + 1)[1:]:
            nxt = self.ik(se3.interpolate(a, b, s), q)
            if nxt is None or float(np.max(np.abs(nxt - q))) > _MAX_JOINT_STEP_RAD:
                return None
            q = nxt
        return q

    def joint_path(self, q0: FloatArray, q1: FloatArray, samples: int = 16) -> bool:
        """Whether the TCP stays inside the workspace box along the joint move ``q0 -> q1`` (as
        the driver checks it: joints interpolated linearly)."""
        if self.workspace is None:
            return True
        t = np.linspace(0.0, 1.0, samples + 1)[1:, None]
        F = kinematics.forward(self.model, q0[None, :] + t * (q1 - q0)[None, :])
        p = (F @ self.tcp2flange)[:, :3, 3]
        lo, hi = self.workspace
        return not bool(np.any((p < lo) | (p > hi)))

    def sweep(
        self,
        start: FloatArray,
        end: FloatArray,
        clearance: FloatArray,
        seed: FloatArray,
        via: FloatArray | None = None,
    ) -> _Reach | None:
        """Approach (``start @ clearance``, joint move from ``seed``), start, end. When the
        joint move would leave the workspace box, through the flange pose ``via`` (a hub, e.g.
        above the ball), with the approach solved near it."""
        approach = start @ clearance
        qa = self.ik(approach, seed)
        qv = None
        if qa is None or not self.joint_path(seed, qa):
            qv = None if via is None else self.ik(via, seed)
            if qv is None or not self.joint_path(seed, qv):
                return None
            qa = self.ik(approach, qv)
            if qa is None or not self.joint_path(qv, qa):
                return None
        qs = self.linear(approach, start, qa)
        if qs is None:
            return None
        qe = self.linear(start, end, qs)
        if qe is None:
            return None
        return _Reach(qa, qs, qe, qv)


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


# --------------------------------------------------------------------------------------------
# Recorded sweeps


SweepStage = Literal["find", "fov", "tilt", "check"]


@dataclass(frozen=True, eq=False)
class RecordedSweep:
    """One recorded pass, reduced to what the solvers use.

    ``sweep`` holds the kept points (at most ``max_points_per_sweep``, spread over all profiles)
    with the flange pose of every profile, in time order. ``group`` numbers the orientation (0:
    the start orientation of the FOV stage, 1...: tilts, -1: check scan); ``location`` numbers the
    place swept (a forward and a backward pass share it); ``direction`` is +1 along sensor +X,
    -1 back, 0 unknown (manual)."""

    stage: SweepStage
    group: int
    location: int
    direction: int
    label: str
    sweep: handeye.Sweep
    exposure_ns: IntArray
    n_points_recorded: int

    @property
    def n_profiles(self) -> int:
        return self.sweep.n_poses

    @property
    def travel_m(self) -> float:
        F = self.sweep.flange2base
        return float(np.linalg.norm(F[-1, :3, 3] - F[0, :3, 3]))

    def for_solver(self) -> handeye.Sweep:
        """The sweep as the paper's two-step method wants it: a backward pass reversed in time
        (the solver takes the first pose as the reference and the travel along sensor +X)."""
        if self.direction >= 0:
            return self.sweep
        s = self.sweep
        return handeye.Sweep(s.flange2base[::-1], s.points_sensor, s.n_poses - 1 - s.pose_index)


def ball_coverage(rs: RecordedSweep) -> tuple[float, float]:
    """How much of the travel saw the ball: the extent (m) of the flange positions of the
    profiles with kept points along the sweep's direction, and the longest gap (m) between
    consecutive ones. A gap comes from profiles the synchroniser could not pair."""
    s = rs.sweep
    if s.n_points == 0:
        return 0.0, 0.0
    prof = np.unique(s.pose_index)
    T = s.flange2base[:, :3, 3]
    d = T[-1] - T[0]
    n = float(np.linalg.norm(d))
    if n == 0.0:
        return 0.0, 0.0
    pos = np.sort((T[prof] - T[0]) @ (d / n))
    gap = float(np.max(np.diff(pos))) if pos.size > 1 else 0.0
    return float(pos[-1] - pos[0]), gap


def _slice_recording(data: RecordedData, lo: int, hi: int) -> RecordedData:
    """Profiles ``lo`` to ``hi - 1`` of a recording, with their points."""
    keep = (data.profile_index >= lo) & (data.profile_index < hi)
    return RecordedData(
        y=data.y[keep],
        z=data.z[keep],
        valid=data.valid[keep],
        profile_index=data.profile_index[keep] - lo,
        flange2base=data.flange2base[lo:hi],
        exposure_ns=data.exposure_ns[lo:hi],
        table_angle=None if data.table_angle is None else data.table_angle[lo:hi],
    )


def split_round_trip(data: RecordedData, min_travel_m: float = 5e-3) -> list[RecordedData]:
    """A recording that went across and came back (manual mode: "across the ball and back") as
    its two legs, split where the travel along its main direction turns; any other recording
    as is. The legs of a round trip are a forward/backward pair (see :func:`apparent_latency`)."""
    P = data.n_profiles
    if P < 10:
        return [data]
    T = data.flange2base[:, :3, 3]
    d = T - T[0]
    _, _, Vt = np.linalg.svd(d - d.mean(axis=0), full_matrices=False)
    pos = d @ Vt[0]
    turn = int(np.argmax(np.abs(pos)))
    reach = abs(float(pos[turn]))
    if reach < min_travel_m or abs(float(pos[-1])) > 0.4 * reach or turn in (0, P - 1):
        return [data]
    return [_slice_recording(data, 0, turn + 1), _slice_recording(data, turn, P)]


def reduce_sweep(
    data: RecordedData,
    max_points: int,
    keep: Callable[[handeye.Sweep], BoolArray] | None = None,
) -> tuple[handeye.Sweep, int]:
    """The valid points of a recording as a :class:`handeye.Sweep` (at most ``max_points``, a
    seeded random subset) and how many valid points there were. ``keep`` may drop
    points first (e.g. those far from the predicted ball)."""
    ok = data.valid & np.isfinite(data.y) & np.isfinite(data.z)
    idx = np.flatnonzero(ok)
    n_valid = int(idx.size)
    full = handeye.Sweep.from_yz(
        data.flange2base, data.y[idx], data.z[idx], data.profile_index[idx]
    )
    if keep is not None and full.n_points:
        full = full.subset(keep(full))
    if full.n_points > max_points:
        pick = _sample(full.n_points, max_points)
        full = handeye.Sweep(full.flange2base, full.points_sensor[pick], full.pose_index[pick])
    return full, n_valid


def _sample(n: int, k: int, seed: int = 0) -> IntArray:
    """``k`` of ``n`` indices, sorted, drawn at random with a fixed seed. Not a stride: points
    come ordered by profile and ray, and a stride could keep the same rays of every profile."""
    if k >= n:
        return np.arange(n, dtype=np.int64)
    return np.sort(np.random.default_rng(seed).choice(n, size=k, replace=False)).astype(np.int64)


def _near_ball(
    X: FloatArray, centre: FloatArray, radius: float, band_m: float
) -> Callable[[handeye.Sweep], BoolArray]:
    def keep(s: handeye.Sweep) -> BoolArray:
        d = np.linalg.norm(s.points_base(X) - centre, axis=1)
        return np.asarray(np.abs(d - radius) <= band_m, dtype=bool)

    return keep


# --------------------------------------------------------------------------------------------
# Solution and validation (pure functions on recorded sweeps)


def solve(
    sweeps: Sequence[RecordedSweep], ball_radius_m: float, robot_sigma_m: float = 0.0
) -> tuple[handeye.HandEyeResult, handeye.HandEyeResult]:
    """The paper's two-step solution and the joint refinement started from it, on the same
    sweeps. ``sweeps`` must list the FOV sweeps first, then the tilted ones (the order of
    ``per_sweep_rms`` and ``inliers``). Raises :class:`CalibrationFailed` with advice."""
    fov = [s.for_solver() for s in sweeps if s.stage == "fov"]
    tilt = [s.for_solver() for s in sweeps if s.stage == "tilt"]
    if [s.stage for s in sweeps] != ["fov"] * len(fov) + ["tilt"] * len(tilt):
        raise ValueError("solve: list the FOV sweeps first, then the tilted ones")
    try:
        two = handeye.two_step(fov, tilt, ball_radius_m)
        joint = handeye.refine([*fov, *tilt], two, ball_radius_m, robot_sigma_m=robot_sigma_m)
    except handeye.PoorlyConstrained as exc:
        raise CalibrationFailed(f"the sweeps do not determine sensor2flange: {exc}") from None
    except ValueError as exc:
        raise CalibrationFailed(f"the calibration could not be solved: {exc}") from None
    return two, joint


def quick_refine(
    sweeps: Sequence[RecordedSweep],
    initial: handeye.HandEyeResult | FloatArray,
    ball_radius_m: float,
) -> handeye.HandEyeResult:
    """The joint refinement alone from ``initial`` (a result on the same sweeps, whose inlier
    masks are reused, or a sensor2flange estimate): a cheap solution for the intermediate steps
    (timing, consistency); no identifiability check. Raises :class:`CalibrationFailed`."""
    try:
        return handeye.refine([w.for_solver() for w in sweeps], initial, ball_radius_m, check=False)
    except ValueError as exc:
        raise CalibrationFailed(f"the calibration could not be solved: {exc}") from None


def _centre_at_start(rs: RecordedSweep, rotation: FloatArray, radius: float) -> FloatArray:
    """Ball centre (m) in the sensor frame at the first pose of ``rs.for_solver()``."""
    sw = rs.for_solver()
    pts = handeye.sweep_points_at_start(sw, rotation)
    try:
        return np.asarray(sphere.fit_sphere(pts, radius=radius, robust="tukey").centre)
    except ValueError:
        return np.full(3, np.nan)


def _origin_estimate(
    sweeps: Sequence[RecordedSweep], rotation: FloatArray, centres: Sequence[FloatArray]
) -> tuple[FloatArray, FloatArray] | None:
    """Step 2 (the paper's TCP least squares) on sweep centres already fitted: (sensor origin in
    the flange frame, ball centre in base), or None while the orientations do not determine it."""
    from wristscan.calib import tcp

    c = np.array(centres)
    ok = np.all(np.isfinite(c), axis=1)
    F = np.array([w.for_solver().flange2base[0] for w in sweeps])[ok]
    Ri, Ti = F[:, :3, :3], F[:, :3, 3]
    Tp = Ti + np.einsum("nij,jk,nk->ni", Ri, rotation, c[ok])
    try:
        p_tool, p_world = tcp.solve_tcp_batch(Ri, Tp)
    except (tcp.DegeneratePoses, ValueError):
        return None
    return np.asarray(p_tool, dtype=np.float64), np.asarray(p_world, dtype=np.float64)


def _relabel(w: RecordedSweep, label: str) -> RecordedSweep:
    suffix = {1: " fwd", -1: " bwd"}.get(w.direction, "")
    return dataclasses.replace(w, label=label + suffix)


def _base_label(label: str) -> str:
    return label.removesuffix(" fwd").removesuffix(" bwd")


def _rotation_between(A: FloatArray, B: FloatArray) -> float:
    return float(se3.rotation_angle(A[:3, :3].T @ B[:3, :3]))


@dataclass(frozen=True, eq=False)
class LeaveOneOut:
    """The joint refinement repeated without each tilted orientation (both passes).

    ``translation_dev_m`` / ``rotation_dev_rad``: distance of each estimate from the full one;
    ``prediction_rms_m``: RMS residual of the left-out sweeps under the estimate without them
    (how well the calibration predicts an orientation it did not see)."""

    labels: tuple[str, ...]
    sensor2flange: FloatArray
    translation_dev_m: FloatArray
    rotation_dev_rad: FloatArray
    prediction_rms_m: FloatArray

    @property
    def max_translation_dev_m(self) -> float:
        return float(self.translation_dev_m.max())

    @property
    def max_rotation_dev_rad(self) -> float:
        return float(self.rotation_dev_rad.max())

    @property
    def spread_translation_m(self) -> FloatArray:
        """Per-axis standard deviation of the estimates, scaled by ``(n-1)/sqrt(n)`` (the
        jackknife standard error of the full estimate), metres ``(3,)``."""
        t = self.sensor2flange[:, :3, 3]
        n = t.shape[0]
        return np.asarray(np.sqrt((n - 1) / n * np.sum((t - t.mean(0)) ** 2, axis=0)))


def leave_one_out(
    sweeps: Sequence[RecordedSweep],
    joint: handeye.HandEyeResult,
    ball_radius_m: float,
    max_points: int = 2000,
) -> LeaveOneOut | None:
    """Leave-one-out over the tilted orientation groups of ``sweeps`` (the order of ``joint``).
    None when there are fewer than 3 groups (leaving one out would leave too few)."""
    groups = sorted({s.group for s in sweeps if s.stage == "tilt"})
    if len(groups) < _LOO_MIN_GROUPS:
        return None
    # Each refit runs on a thinned copy of the sweeps: the spread it measures comes from the
    # orientations, not from the sensor noise, so a third of the points is plenty.
    solver, masks = [], []
    for w, m in zip(sweeps, joint.inliers, strict=True):
        pick = np.zeros(w.sweep.n_points, dtype=bool)
        pick[_sample(w.sweep.n_points, max_points)] = True
        solver.append(w.for_solver().subset(pick))
        masks.append(np.asarray(m)[pick])
    labels, Xs, dts, drs, preds = [], [], [], [], []
    X = joint.sensor2flange
    for g in groups:
        keep = [i for i, s in enumerate(sweeps) if s.group != g]
        out = [i for i, s in enumerate(sweeps) if s.group == g]
        init = dataclasses.replace(joint, inliers=tuple(masks[i] for i in keep))
        try:
            r = handeye.refine([solver[i] for i in keep], init, ball_radius_m, check=False)
        except ValueError as exc:
            log.warning("leave-one-out without group %d failed: %s", g, exc)
            continue
        res = handeye.sphere_residuals(
            [solver[i].subset(masks[i]) for i in out],
            r.sensor2flange,
            r.ball_centre_base,
            ball_radius_m,
        )
        allr = np.concatenate(res)
        labels.append(_base_label(sweeps[out[0]].label))
        Xs.append(r.sensor2flange)
        dts.append(float(np.linalg.norm(r.sensor2flange[:3, 3] - X[:3, 3])))
        drs.append(_rotation_between(r.sensor2flange, X))
        preds.append(float(np.sqrt(np.mean(allr**2))) if allr.size else float("nan"))
    if len(labels) < _LOO_MIN_GROUPS:
        return None
    return LeaveOneOut(tuple(labels), np.array(Xs), np.array(dts), np.array(drs), np.array(preds))


@dataclass(frozen=True, eq=False)
class ApparentLatency:
    """Sensor time offset seen in sweeps run both ways: the ball found in a forward pass minus
    the one found in the backward pass, along the travel, divided by the sum of their speeds.

    ``offset_s`` (mean over the pairs) is the true exposure-to-timestamp latency minus the
    configured one (positive: configure a larger ``[sensor] latency_s``); ``std_s`` its standard
    error; ``per_pair_s`` the offset of each pair, at ``locations``."""

    offset_s: float
    std_s: float
    per_pair_s: FloatArray
    locations: IntArray
    speed_m_s: float

    @property
    def n_pairs(self) -> int:
        return int(self.per_pair_s.size)

    def per_location(self) -> dict[int, float]:
        return {int(k): float(v) for k, v in zip(self.locations, self.per_pair_s, strict=True)}


def _ball_speed(rs: RecordedSweep, mask: BoolArray) -> tuple[float, FloatArray]:
    """Mean flange speed (m/s) over the profiles that saw the ball, and the travel direction."""
    s = rs.sweep
    prof = np.unique(s.pose_index[mask])
    if prof.size < 2:
        return float("nan"), np.zeros(3)
    a, b = int(prof[0]), int(prof[-1])
    d = s.flange2base[b, :3, 3] - s.flange2base[a, :3, 3]
    dt = (int(rs.exposure_ns[b]) - int(rs.exposure_ns[a])) * 1e-9
    dist = float(np.linalg.norm(d))
    if dt <= 0 or dist == 0:
        return float("nan"), np.zeros(3)
    return dist / dt, d / dist


def apparent_latency(
    sweeps: Sequence[RecordedSweep],
    sensor2flange: FloatArray,
    inliers: Sequence[BoolArray],
    ball_radius_m: float,
) -> ApparentLatency | None:
    """:class:`ApparentLatency` from the forward/backward pairs among ``sweeps`` (``inliers`` per
    sweep, e.g. as the joint refinement returned them). None without pairs."""
    by_loc: dict[int, dict[int, int]] = {}
    for i, s in enumerate(sweeps):
        if s.direction != 0:
            by_loc.setdefault(s.location, {})[s.direction] = i
    per, locs, speeds = [], [], []
    for loc, pair in by_loc.items():
        if 1 not in pair or -1 not in pair:
            continue
        centres, vs, dirs = [], [], []
        for i in (pair[1], pair[-1]):
            m = np.asarray(inliers[i], dtype=bool)
            pts = sweeps[i].sweep.points_base(sensor2flange)[m]
            if pts.shape[0] < _MIN_BALL_POINTS:
                break
            fit = sphere.fit_sphere(pts, radius=ball_radius_m, robust=None)
            v, u = _ball_speed(sweeps[i], m)
            centres.append(fit.centre)
            vs.append(v)
            dirs.append(u)
        if len(centres) < 2 or not all(np.isfinite(vs)):
            continue
        per.append(float(np.dot(centres[0] - centres[1], dirs[0])) / (vs[0] + vs[1]))
        locs.append(loc)
        speeds.extend(vs)
    if not per:
        return None
    p = np.array(per)
    std = float(p.std(ddof=1) / math.sqrt(p.size)) if p.size > 1 else float("nan")
    return ApparentLatency(
        float(p.mean()), std, p, np.array(locs, dtype=np.int64), float(np.mean(speeds))
    )


def retime(rs: RecordedSweep, offset_s: float) -> RecordedSweep:
    """The sweep with every profile's flange position taken ``offset_s`` earlier along its own
    path (interpolated in the recorded poses, clamped at the ends): what the synchroniser would
    have paired with a sensor latency larger by ``offset_s``. Orientations are kept (sweeps keep
    the orientation constant)."""
    t = (rs.exposure_ns - rs.exposure_ns[0]).astype(np.float64) * 1e-9
    order = np.argsort(t, kind="stable")
    ts = t[order]
    T = rs.sweep.flange2base[order, :3, 3]
    F = rs.sweep.flange2base.copy()
    moved = np.column_stack([np.interp(ts - offset_s, ts, T[:, k]) for k in range(3)])
    F[order, :3, 3] = moved
    sw = handeye.Sweep(F, rs.sweep.points_sensor, rs.sweep.pose_index)
    return dataclasses.replace(rs, sweep=sw)


def compensate_timing(
    sweeps: Sequence[RecordedSweep], latency: ApparentLatency
) -> list[RecordedSweep]:
    """Every forward/backward pair re-timed by its own apparent offset (:func:`retime`); sweeps
    without a pair by the mean offset. This treats the time offset as a nuisance parameter per
    location: a wrong configured latency, or a time base that wanders, then no longer shifts the
    ball between the passes."""
    per = latency.per_location()
    return [retime(w, per.get(w.location, latency.offset_s)) for w in sweeps]


def inlier_masks(
    sweeps: Sequence[RecordedSweep],
    sensor2flange: FloatArray,
    ball_centre_base: FloatArray,
    ball_radius_m: float,
    band_m: float,
) -> list[BoolArray]:
    """Per sweep, the points within ``band_m`` of the ball surface (mapped with the calibration)."""
    return [
        np.asarray(
            np.abs(
                np.linalg.norm(w.sweep.points_base(sensor2flange) - ball_centre_base, axis=1)
                - ball_radius_m
            )
            <= band_m,
            dtype=bool,
        )
        for w in sweeps
    ]


def location_offsets(
    sweeps: Sequence[RecordedSweep],
    joint: handeye.HandEyeResult,
    ball_radius_m: float,
) -> dict[int, FloatArray]:
    """For each location, the mean of its passes' ball centres (fitted with the known radius on
    the points mapped with the solution) minus the solution's ball centre: ``{location: (3,)}``
    in metres, base frame. What the robot's repeatability and timing slips leave per place."""
    X, c = joint.sensor2flange, joint.ball_centre_base
    by_loc: dict[int, list[FloatArray]] = {}
    for w, m in zip(sweeps, joint.inliers, strict=True):
        pts = w.sweep.points_base(X)[np.asarray(m, dtype=bool)]
        if pts.shape[0] < _MIN_BALL_POINTS:
            continue
        fit = sphere.fit_sphere(pts, radius=ball_radius_m, robust=None)
        by_loc.setdefault(w.location, []).append(np.asarray(fit.centre))
    return {k: np.mean(v, axis=0) - c for k, v in by_loc.items()}


def observed_robot_sigma(offsets: Mapping[int, FloatArray]) -> float:
    """Per-axis standard deviation (m) of the per-location offsets, robustly (from their median
    squared length): the robot's repeatability as the data show it at the sensor. 0 with fewer
    than 5 places."""
    if len(offsets) < 5:
        return 0.0
    d2 = np.array([float(v @ v) for v in offsets.values()])
    # For a 3-D Gaussian of per-axis sigma, |d|^2 / sigma^2 is chi-square(3): median 2.366.
    return math.sqrt(float(np.median(d2)) / 2.366)


def inconsistent_locations(
    sweeps: Sequence[RecordedSweep],
    joint: handeye.HandEyeResult,
    ball_radius_m: float,
    floor_m: float = 10e-6,
    offsets: Mapping[int, FloatArray] | None = None,
) -> dict[int, float]:
    """Places whose passes put the ball elsewhere than the solution does: the distance (m) of
    :func:`location_offsets`, returned when above ``max(median + 5 robust sigma, 2.5 median,
    floor_m)``: a pass whose time base slipped (a host too busy for the synchroniser) or a
    robot that did not stand where it said. ``{location: distance}``."""
    off = location_offsets(sweeps, joint, ball_radius_m) if offsets is None else offsets
    if len(off) < 5:
        return {}
    locs = list(off)
    d = np.array([float(np.linalg.norm(off[k])) for k in locs])
    med = float(np.median(d))
    mad = 1.4826 * float(np.median(np.abs(d - med)))
    limit = max(med + 5.0 * mad, 2.5 * med, floor_m)
    return {k: float(v) for k, v in zip(locs, d, strict=True) if v > limit}


def _can_drop(sweeps: Sequence[RecordedSweep], drop: set[int]) -> bool:
    """Whether enough remains without the locations ``drop`` (3 FOV places, 2 orientations)."""
    rest = [w for w in sweeps if w.location not in drop]
    fov = {w.location for w in rest if w.stage == "fov"}
    tilt = {w.group for w in rest if w.stage == "tilt"}
    return len(fov) >= 3 and len(tilt) >= 2


@dataclass(frozen=True, eq=False)
class CheckScan:
    """A sweep at an orientation not used by the solution, mapped with the new calibration and
    fitted with a sphere of free radius: its centre against the calibrated ball centre and its
    radius against the known one (metres). The ``two_step_*`` figures are the same check with
    the two-step calibration. ``points_base`` / ``residuals_m`` are a sample for the figure."""

    label: str
    centre_base_m: FloatArray
    radius_m: float
    rms_m: float
    centre_error_m: float
    radius_error_m: float
    n_points: int
    two_step_centre_error_m: float
    two_step_radius_error_m: float
    points_base: FloatArray = field(repr=False)
    residuals_m: FloatArray = field(repr=False)


def check_scan_fit(
    check: Sequence[RecordedSweep],
    joint: handeye.HandEyeResult,
    two_step: handeye.HandEyeResult,
    ball_radius_m: float,
) -> CheckScan:
    """:class:`CheckScan` of the check sweeps (all passes together). Raises
    :class:`CalibrationFailed` when no sphere can be fitted."""

    def fit(X: FloatArray) -> tuple[sphere.SphereFit, FloatArray]:
        pts = np.concatenate([s.sweep.points_base(X) for s in check])
        try:
            return sphere.fit_sphere(pts, radius=None, robust="tukey"), pts
        except ValueError as exc:
            raise CalibrationFailed(f"the check scan could not be fitted: {exc}") from None

    f, pts = fit(joint.sensor2flange)
    f2, _ = fit(two_step.sensor2flange)
    inl = np.flatnonzero(f.inliers)
    pick = inl[np.unique(np.linspace(0, inl.size - 1, min(_FIGURE_POINTS, inl.size)).astype(int))]
    return CheckScan(
        label=_base_label(check[0].label),
        centre_base_m=np.asarray(f.centre),
        radius_m=float(f.radius),
        rms_m=float(f.rms),
        centre_error_m=float(np.linalg.norm(f.centre - joint.ball_centre_base)),
        radius_error_m=float(f.radius - ball_radius_m),
        n_points=int(f.n_inliers),
        two_step_centre_error_m=float(np.linalg.norm(f2.centre - two_step.ball_centre_base)),
        two_step_radius_error_m=float(f2.radius - ball_radius_m),
        points_base=pts[pick],
        residuals_m=np.asarray(f.residuals)[pick],
    )


# --------------------------------------------------------------------------------------------
# The robot and the recorder


class RobotCell:
    """Motion and recording through an open :class:`Acquisition`.

    Flange poses come from the joint positions through the kinematic model the synchroniser
    uses, so planned and recorded poses agree. Motion commands take *flange* poses and are sent
    for the controller's active TCP. Every driver failure becomes :class:`CalibrationAborted`
    (a protective stop says so)."""

    def __init__(self, acq: Acquisition, model: kinematics.DHParams) -> None:
        self.acq = acq
        self.model = model
        self._tcp2flange: FloatArray | None = None

    @property
    def robot(self) -> Any:
        return self.acq.robot

    # --- state -------------------------------------------------------------------------------
    def state(self, timeout_s: float = 3.0) -> RobotState:
        deadline = time.monotonic() + timeout_s
        while True:
            st = self.robot.latest_state()
            if st is not None:
                return st
            if time.monotonic() > deadline:
                raise CalibrationFailed(
                    "no robot state received: check the robot connection (wristscan status)"
                )
            time.sleep(0.02)

    def joints(self) -> FloatArray:
        return np.asarray(self.state().q, dtype=np.float64).copy()

    def flange2base(self) -> FloatArray:
        return np.asarray(kinematics.forward(self.model, self.joints()), dtype=np.float64)

    def check_safety(self) -> None:
        st = self.state()
        if st.protective_stop:
            raise CalibrationAborted("the robot is in a protective stop")

    def tcp2flange(self) -> FloatArray:
        if self._tcp2flange is None:
            self._tcp2flange = se3.pose_to_matrix(self._call(self.robot.tcp_offset))
        return self._tcp2flange

    def workspace(self) -> tuple[FloatArray, FloatArray] | None:
        lo = getattr(self.robot, "workspace_min_m", None)
        hi = getattr(self.robot, "workspace_max_m", None)
        if lo is None or hi is None:
            return None
        return np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)

    def planner(self, reference_q: FloatArray | None = None) -> _Kin:
        return _Kin(self.model, self.tcp2flange(), self.workspace(), reference_q)

    # --- motion ------------------------------------------------------------------------------
    def _call(self, fn: Callable[..., T], *args: Any) -> T:
        from wristscan.drivers.ur.robot import ProtectiveStop

        try:
            return fn(*args)
        except ProtectiveStop as exc:
            raise CalibrationAborted(f"protective stop: {exc}") from None
        except (MotionNotEnabled, WorkspaceViolation) as exc:
            raise CalibrationAborted(f"motion refused: {exc}") from None
        except DriverError as exc:
            raise CalibrationAborted(f"motion failed: {exc}") from None

    def move_l(self, flange2base: FloatArray, speed: float, accel: float) -> None:
        pose = se3.matrix_to_pose(np.asarray(flange2base) @ self.tcp2flange())
        self._call(self.robot.move_l, pose, speed, accel)

    def move_j(self, q: FloatArray, speed: float, accel: float) -> None:
        self._call(self.robot.move_j, np.asarray(q, dtype=np.float64), speed, accel)

    def stop(self) -> None:
        """Best-effort stop (after an error or an interrupt)."""
        try:
            self.robot.stop()
        except Exception as exc:  # stopping must never raise over the error that led here
            log.warning("stopping the robot: %s", exc)

    # --- recording ---------------------------------------------------------------------------
    @contextmanager
    def _recording(self) -> Iterator[list[RecordedData]]:
        out: list[RecordedData] = []
        with self.acq.record() as rec:
            yield out
        out.append(rec.result())

    def sweep_to(
        self, flange2base: FloatArray, speed: float, accel: float
    ) -> tuple[RecordedData, float]:
        """Record while moving linearly to ``flange2base``; returns the recording and how long
        the move took (s)."""
        t0 = time.monotonic()
        with self._recording() as box:
            self.move_l(flange2base, speed, accel)
            took = time.monotonic() - t0
        return box[0], took

    def record_for(self, seconds: float) -> RecordedData:
        with self._recording() as box:
            time.sleep(seconds)
        return box[0]

    def record_while(self, fn: Callable[[], T]) -> tuple[RecordedData, T]:
        """Record while ``fn`` runs (manual mode: the operator moves the robot)."""
        with self._recording() as box:
            value = fn()
        return box[0], value


# --------------------------------------------------------------------------------------------
# The procedure


@dataclass(frozen=True, eq=False)
class SensorCalibrationResult:
    """Everything the procedure found; :func:`calibration_of` and :func:`build_report` use it."""

    settings: Settings
    nominal: FloatArray | None
    sweeps: tuple[RecordedSweep, ...]
    """The solved sweeps, FOV first, in the order of the solutions' per-sweep figures."""
    two_step: handeye.HandEyeResult
    joint: handeye.HandEyeResult
    uncompensated: handeye.HandEyeResult | None
    """The joint refinement before the per-pair time offsets were removed (None: not done)."""
    loo: LeaveOneOut | None
    check: CheckScan | None
    check_sweeps: tuple[RecordedSweep, ...]
    latency: ApparentLatency | None
    orientations: tuple[OrientationPlan, ...]
    fov_reference_flange2base: FloatArray
    min_z_angle_deg: float
    """Smallest angle between the sensor Z axes of any two orientations used (degrees)."""
    notes: tuple[str, ...]
    configured_latency_s: float
    manual: bool
    duration_s: float
    robot_sigma_m: float = 0.0
    """Per-axis robot repeatability the covariance used (m): the larger of the data sheet's and
    the observed one."""
    observed_robot_sigma_m: float = 0.0
    """Per-axis scatter of the places' ball centres (m), see :func:`observed_robot_sigma`."""

    @property
    def sensor2flange(self) -> FloatArray:
        return self.joint.sensor2flange


class SensorCalibration:
    """The procedure on a :class:`RobotCell` (see the module doc for the stages).

    ``nominal``: the sensor2flange the motions are planned with (automatic mode; not needed in
    manual mode). ``prompt`` (manual mode) shows a message and returns the operator's answer
    (default ``input``). ``progress`` receives a :class:`ProgressEvent` at every step."""

    def __init__(
        self,
        cell: RobotCell,
        settings: Settings,
        nominal: FloatArray | None = None,
        *,
        manual: bool = False,
        prompt: Prompt | None = None,
        progress: Progress | None = None,
        configured_latency_s: float = 0.0,
    ) -> None:
        settings.check()
        if not manual and nominal is None:
            raise ValueError("automatic mode needs a nominal sensor2flange to plan the motions")
        self.cell = cell
        self.s = settings
        self.nominal = None if nominal is None else se3.check_transform(nominal, "nominal")
        self.manual = manual
        self.prompt: Prompt = prompt or input
        self.progress = progress
        self.configured_latency_s = configured_latency_s
        self.notes: list[str] = []
        self._location = 0
        self._reference = np.eye(4)
        self._reference_q: FloatArray | None = None
        self._rate_hz = 0.0
        self._estimate: FloatArray | None = None
        self._repeated = 0
        self._robot_sigma = (settings.robot_sigma_m, 0.0)

    # --- helpers -----------------------------------------------------------------------------
    def _say(self, stage: str, message: str, step: int = 0, total: int = 0) -> None:
        log.info("%s", ProgressEvent(stage, step, total, message))
        if self.progress is not None:
            self.progress(ProgressEvent(stage, step, total, message))

    def _note(self, stage: str, text: str) -> None:
        self.notes.append(text)
        self._say(stage, "note: " + text)

    def _next_location(self) -> int:
        self._location += 1
        return self._location

    def _reduce(
        self,
        data: RecordedData,
        stage: SweepStage,
        group: int,
        location: int,
        direction: int,
        label: str,
        keep: Callable[[handeye.Sweep], BoolArray] | None = None,
    ) -> RecordedSweep:
        sw, n_valid = reduce_sweep(data, self.s.max_points_per_sweep, keep)
        if data.n_profiles < 10:
            raise CalibrationFailed(
                f"{label}: only {data.n_profiles} profiles were paired with robot states; check "
                "the sensor stream and the [sync] settings (wristscan status)"
            )
        if sw.n_points < _MIN_BALL_POINTS:
            raise CalibrationFailed(
                f"{label}: only {sw.n_points} points near the ball; the ball left the field of "
                "view (check the ball radius, the nominal sensor2flange and the FOV settings)"
            )
        return RecordedSweep(
            stage, group, location, direction, label, sw, data.exposure_ns.copy(), n_valid
        )

    def _sweep(
        self,
        frm: FloatArray,
        to: FloatArray,
        stage: SweepStage,
        group: int,
        location: int,
        direction: int,
        label: str,
        keep: Callable[[handeye.Sweep], BoolArray] | None = None,
        coverage: bool = True,
    ) -> RecordedSweep:
        """Sweep from ``frm`` (where the robot is) to ``to``. A sweep with gaps is repeated, up
        to ``sweep_retries`` times: fewer than half of its profiles paired (a host too busy for
        the synchroniser, a stream gap), or the ball not seen over most of its width along the
        travel (:func:`ball_coverage`)."""
        s = self.s
        R = s.ball_radius_m
        for attempt in range(s.sweep_retries + 1):
            data, took = self.cell.sweep_to(to, s.sweep_speed_m_s, s.sweep_accel_m_s2)
            expected = self._rate_hz * took
            why = ""
            if data.n_profiles < max(_PAIRED_SHARE * expected, 20):
                why = f"only {data.n_profiles} of ~{expected:.0f} profiles paired"
            else:
                try:
                    rs = self._reduce(data, stage, group, location, direction, label, keep)
                except CalibrationFailed as exc:
                    why = str(exc).removeprefix(f"{label}: ")
                else:
                    span, gap = ball_coverage(rs)
                    if not coverage or (span >= _MIN_SPAN_R * R and gap <= _MAX_GAP_R * R):
                        return rs
                    why = (
                        f"the ball was seen over {span * 1e3:.1f} mm of travel with a "
                        f"{gap * 1e3:.1f} mm gap"
                    )
            if attempt == s.sweep_retries:
                break
            self._repeated += 1
            self._say(stage, f"{label}: {why}; repeating")
            self._wait_for_data(quiet=True)
            self.cell.move_l(frm, s.travel_speed_m_s, s.travel_accel_m_s2)
        raise CalibrationFailed(
            f"{label}: {why} after {s.sweep_retries + 1} attempts; check the sensor stream and the "
            "synchroniser (wristscan status), and that the ball is in view"
        )

    def _wait_for_data(self, quiet: bool = False) -> None:
        """Until profiles are paired (at the start), or paired again after a long computation
        (which can hold up the synchroniser); measures the paired profile rate. At the start,
        no paired profiles within ``lock_timeout_s`` is a failure; later the sweeps' own checks
        take over after the timeout."""
        if not quiet:
            self._say("connect", "waiting for profiles paired with robot states")
        deadline = time.monotonic() + self.s.lock_timeout_s
        window_s = 0.4
        while True:
            data = self.cell.record_for(window_s)
            # The rate: profiles over their time span (a lower bound: profiles over the window).
            self._rate_hz = max(self._rate_hz, data.n_profiles / window_s)
            if data.n_profiles >= 2:
                span = (int(data.exposure_ns[-1]) - int(data.exposure_ns[0])) * 1e-9
                if span > 0.5 * window_s:
                    self._rate_hz = max(self._rate_hz, (data.n_profiles - 1) / span)
            if data.n_profiles >= max(20.0, _PAIRED_SHARE * self._rate_hz * window_s):
                if not quiet:
                    self._say("connect", f"paired profiles at {self._rate_hz:.0f} Hz")
                return
            if time.monotonic() > deadline:
                if quiet and self._rate_hz > 0:
                    log.warning("pairing has not recovered; going on")
                    return
                raise CalibrationFailed(
                    f"no profiles were paired with robot states within {self.s.lock_timeout_s:g} "
                    "s: check the sensor stream, the robot connection and [sync] (wristscan "
                    "status)"
                )

    # --- entry point -------------------------------------------------------------------------
    def run(self) -> SensorCalibrationResult:
        """Run every stage; raises :class:`CalibrationFailed` or :class:`CalibrationAborted`."""
        t0 = time.monotonic()
        s = self.s
        R = s.ball_radius_m
        try:
            self._wait_for_data()
            if self.manual:
                sweeps, orientations, ref = self._collect_manual()
            else:
                sweeps, orientations, ref = self._collect_automatic()
            self._say("solve", f"first solution on {len(sweeps)} sweeps")
            if self._estimate is not None:
                first = quick_refine(sweeps, self._estimate, R)
            else:
                first = solve(sweeps, R, s.robot_sigma_m)[1]
            latency = apparent_latency(sweeps, first.sensor2flange, first.inliers, R)
            uncompensated = None
            if latency is not None:
                self._say(
                    "solve",
                    f"apparent sensor time offset {latency.offset_s * 1e3:+.3f} ms (+- "
                    f"{latency.std_s * 1e3:.3f} ms, {latency.n_pairs} forward/backward pairs)",
                )
                if s.compensate_timing:
                    uncompensated = first
                    sweeps = compensate_timing(sweeps, latency)
                    first = quick_refine(sweeps, first, R)
            offsets = location_offsets(sweeps, first, R)
            bad = inconsistent_locations(sweeps, first, R, offsets=offsets)
            if bad and _can_drop(sweeps, set(bad)):
                for loc, dist in bad.items():
                    name = _base_label(next(w.label for w in sweeps if w.location == loc))
                    self._note(
                        "solve",
                        f"{name}: its passes put the ball {dist * 1e6:.0f} um from the solution's; "
                        "left out (a pass with a timing slip or a robot error)",
                    )
                sweeps = [w for w in sweeps if w.location not in bad]
            # The covariance takes the larger of the data sheet's repeatability and what the
            # places' scatter shows (the robot's error at the sensor includes its orientation
            # error times the sensor's distance from the flange).
            observed = observed_robot_sigma({k: v for k, v in offsets.items() if k not in bad})
            # The passes of a place share its error, while the solver's robot term takes every
            # sweep's as independent: scaled by sqrt(passes per place) for the same variance of
            # the place's mean.
            passes = len(sweeps) / max(1, len({w.location for w in sweeps}))
            robot_sigma = max(s.robot_sigma_m, observed * math.sqrt(passes))
            self._say(
                "solve",
                f"robot repeatability per axis: {s.robot_sigma_m * 1e6:.1f} um (data sheet), "
                f"{observed * 1e6:.1f} um (observed); the covariance uses "
                f"{robot_sigma * 1e6:.1f} um",
            )
            self._say("solve", f"two-step and joint solution on {len(sweeps)} sweeps")
            two, joint = solve(sweeps, R, robot_sigma)
            self._robot_sigma = (robot_sigma, observed)
            if joint.advice:
                self._note(
                    "solve", f"weakly constrained (condition {joint.condition:.1f}): {joint.advice}"
                )
            self._say(
                "solve",
                f"residual RMS {joint.rms * 1e6:.1f} um (two-step {two.rms * 1e6:.1f} um), "
                f"condition {joint.condition:.1f}",
            )
            check_sweeps: list[RecordedSweep] = []
            check = None
            if s.check_scan:
                if not self.manual:
                    self._wait_for_data(quiet=True)
                check_sweeps = (
                    self._check_manual(joint) if self.manual else self._check_automatic(joint)
                )
                if check_sweeps:
                    band = max(5 * joint.rms, 0.2e-3)
                    masks = inlier_masks(
                        check_sweeps, joint.sensor2flange, joint.ball_centre_base, R, band
                    )
                    lat = apparent_latency(check_sweeps, joint.sensor2flange, masks, R)
                    if lat is not None and s.compensate_timing:
                        check_sweeps = compensate_timing(check_sweeps, lat)
                    check = check_scan_fit(check_sweeps, joint, two, R)
                    self._say(
                        "check",
                        f"check scan: centre {check.centre_error_m * 1e3:.4f} mm from the "
                        f"calibrated ball, radius error {check.radius_error_m * 1e3:+.4f} mm",
                    )
            loo = None
            if s.leave_one_out:
                self._say("validate", "leave-one-out over the orientations")
                loo = leave_one_out(sweeps, joint, R)
                if loo is not None:
                    self._say(
                        "validate",
                        f"leave-one-out: translation within {loo.max_translation_dev_m * 1e3:.4f}"
                        f" mm, rotation within {math.degrees(loo.max_rotation_dev_rad):.4f} deg",
                    )
        except BaseException:
            if not self.manual:
                self.cell.stop()
            raise
        if self._repeated:
            self.notes.append(
                f"{self._repeated} sweeps were repeated: too few of their profiles were paired "
                "with robot states (a host too busy for the synchroniser, or a stream gap)"
            )
        groups: dict[int, FloatArray] = {}
        for w in sweeps:
            groups.setdefault(w.group, w.sweep.flange2base[0] @ joint.sensor2flange)
        min_angle = _min_pairwise(z_axis_angles_deg(list(groups.values())))
        if math.isfinite(min_angle) and min_angle < s.min_tilt_deg - 0.5:
            self._note(
                "solve",
                f"two orientations are only {min_angle:.1f} deg apart (sensor Z axes); the paper "
                f"recommends >= {s.min_tilt_deg:.0f} deg",
            )
        return SensorCalibrationResult(
            settings=s,
            nominal=self.nominal,
            sweeps=tuple(sweeps),
            two_step=two,
            joint=joint,
            uncompensated=uncompensated,
            loo=loo,
            check=check,
            check_sweeps=tuple(check_sweeps),
            latency=latency,
            orientations=tuple(orientations),
            fov_reference_flange2base=ref,
            min_z_angle_deg=min_angle,
            notes=tuple(self.notes),
            configured_latency_s=self.configured_latency_s,
            manual=self.manual,
            duration_s=time.monotonic() - t0,
            robot_sigma_m=self._robot_sigma[0],
            observed_robot_sigma_m=self._robot_sigma[1],
        )

    # --- automatic mode ----------------------------------------------------------------------
    def _find(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(a): the ball in view? Its centre in base through ``X``; returns it and the start
        flange pose (the reference orientation)."""
        s = self.s
        R = s.ball_radius_m
        self.cell.check_safety()
        F0 = self.cell.flange2base()
        data = self.cell.record_for(0.3)
        ok = data.valid & np.isfinite(data.y) & np.isfinite(data.z)
        yz = np.column_stack([data.y[ok], data.z[ok]])
        if yz.shape[0] < 20:
            raise CalibrationFailed(
                "the sensor sees nothing: jog the robot so that the laser line crosses the ball "
                f"at {s.depth_min_m * 1e3:.0f}-{s.depth_max_m * 1e3:.0f} mm"
            )
        try:
            circle = sphere.fit_circle(yz[-20000:], radius=None, robust="tukey")
        except ValueError:
            circle = None
        if circle is None or circle.n_inliers < 20 or circle.radius > 1.1 * R:
            got = "no arc" if circle is None else f"an arc of radius {circle.radius * 1e3:.1f} mm"
            raise CalibrationFailed(
                f"the sensor sees {got}, not a ball of radius {R * 1e3:.2f} mm: jog the robot so "
                "that the laser line crosses the ball (or check --ball-radius-mm)"
            )
        self._say(
            "find",
            f"ball arc in view: radius {circle.radius * 1e3:.2f} mm at y "
            f"{circle.centre[0] * 1e3:+.1f} mm, z {circle.centre[1] * 1e3:.1f} mm",
        )
        S0 = F0 @ X
        h = s.sweep_half_m
        invX = se3.invert(X)
        start, end = S0 @ _tx(-h) @ invX, S0 @ _tx(h) @ invX
        self._say("find", f"sweep across the ball along sensor X (+-{h * 1e3:.1f} mm)")
        self.cell.move_l(start, s.travel_speed_m_s, s.travel_accel_m_s2)
        # The ball may sit up to R off the plane: this sweep may see only part of it.
        rs = self._sweep(start, end, "find", 0, 0, 1, "find sweep", coverage=False)
        pts = handeye.sweep_points_at_start(rs.sweep, X[:3, :3])
        try:
            fit = sphere.fit_sphere(pts, radius=R, robust="tukey")
        except ValueError as exc:
            raise CalibrationFailed(
                f"the ball could not be fitted in the find sweep: {exc}"
            ) from None
        c = rs.sweep.flange2base[0] @ X @ np.append(fit.centre, 1.0)
        self._say("find", f"ball centre (nominal tool) at {np.round(c[:3] * 1e3, 1).tolist()} mm")
        return np.asarray(c[:3]), F0

    def _collect_automatic(
        self,
    ) -> tuple[list[RecordedSweep], list[OrientationPlan], FloatArray]:
        s = self.s
        assert self.nominal is not None
        X = self.nominal
        h = s.sweep_half_m
        q_start = self.cell.joints()
        ball, F0 = self._find(X)
        kin = self.cell.planner(q_start)
        depth = s.working_depth_m

        def clearance(Xe: FloatArray) -> FloatArray:
            # The approach pose is the sweep start moved back along sensor -Z, as a flange motion.
            return np.asarray(Xe @ _tz(-s.clearance_m) @ se3.invert(Xe))

        def ends(
            p: OrientationPlan, Xe: FloatArray, ball_e: FloatArray
        ) -> tuple[FloatArray, FloatArray]:
            inv = se3.invert(Xe)
            Sc = p.sensor2base(F0 @ Xe, ball_e, depth)
            return Sc @ _tx(-h) @ inv, Sc @ _tx(h) @ inv

        def hub(Xe: FloatArray, ball_e: FloatArray) -> FloatArray:
            # Above the ball at the start orientation, well back: joint moves that would leave
            # the workspace box go through here.
            Rref_e = (F0 @ Xe)[:3, :3]
            S = se3.make(Rref_e, ball_e - Rref_e @ np.array([0.0, 0.0, depth + 2 * s.clearance_m]))
            return np.asarray(S @ se3.invert(Xe))

        def reachable(Xe: FloatArray, ball_e: FloatArray) -> Callable[[OrientationPlan], bool]:
            seed = self.cell.joints()
            via = hub(Xe, ball_e)
            return lambda p: kin.sweep(*ends(p, Xe, ball_e), clearance(Xe), seed, via) is not None

        # (b) field-of-view locations at the start orientation
        Rref = (F0 @ X)[:3, :3]
        targets = fov_targets(s)
        plan: list[tuple[FloatArray, FloatArray]] = []
        q = self.cell.joints()
        invX = se3.invert(X)
        for g in targets:
            Sc = se3.make(Rref, ball - Rref @ g)
            start, end = Sc @ _tx(-h) @ invX, Sc @ _tx(h) @ invX
            q_at = kin.ik(start, q)
            q_end = None if q_at is None else kin.linear(start, end, q_at)
            if q_end is None:
                raise CalibrationFailed(
                    f"field-of-view location y {g[1] * 1e3:+.1f} mm, z {g[2] * 1e3:.1f} mm is out "
                    "of reach or outside the workspace box: jog the robot to a more central pose"
                )
            q = q_end
            plan.append((start, end))
        # A first look at the orientations with the nominal tool: fail before the long stage.
        pre, _ = plan_orientations(s, reachable(X, ball))
        if len(pre) < 2:
            raise CalibrationFailed(
                f"only {len(pre)} of {s.n_orientations} orientations around the ball are "
                "reachable: move the ball (or the robot's start pose) towards the middle of the "
                "workspace, or lower --tilt-deg"
            )
        n_fov = len(plan)
        total = n_fov + len(pre)
        self._say(
            "plan",
            f"{n_fov} field-of-view locations and {len(pre)} orientations "
            f"({'both directions' if s.bidirectional else 'one direction'}, "
            f"{s.sweep_speed_m_s * 1e3:g} mm/s)",
        )

        sweeps: list[RecordedSweep] = []
        keep = _near_ball(X, ball, s.ball_radius_m, _BAND_WIDE_M)
        for k, (start, end) in enumerate(plan):
            g = targets[k]
            loc = self._next_location()
            name = f"fov {k + 1} (y {g[1] * 1e3:+.0f}, z {g[2] * 1e3:.0f} mm)"
            self._say("fov", name, k + 1, total)
            self.cell.move_l(start, s.travel_speed_m_s, s.travel_accel_m_s2)
            sweeps.append(self._sweep(start, end, "fov", 0, loc, 1, f"{name} fwd", keep))
            if s.bidirectional:
                sweeps.append(self._sweep(end, start, "fov", 0, loc, -1, f"{name} bwd", keep))
        try:
            # A few iterations are enough to aim the orientations; the solution comes later.
            ori = handeye.solve_orientation(
                [w.for_solver() for w in sweeps], s.ball_radius_m, max_iter=4
            )
        except (handeye.PoorlyConstrained, ValueError) as exc:
            raise CalibrationFailed(f"step 1 (ball matching) failed: {exc}") from None
        Xe = se3.make(ori.rotation, X[:3, 3])
        in_base = [
            w.for_solver().flange2base[0] @ Xe @ np.append(c, 1.0)
            for w, c in zip(sweeps, ori.centres_sensor, strict=True)
        ]
        ball = np.mean(np.array(in_base)[:, :3], axis=0)
        centres = list(ori.centres_sensor)
        n_fov_sweeps = len(sweeps)
        self._wait_for_data(quiet=True)
        self._say(
            "fov",
            f"sensor rotation found (step 1), {math.degrees(_rotation_between(Xe, X)):.2f} deg "
            "from the nominal",
        )

        # (c) orientations around the ball
        S_now = self.cell.flange2base() @ Xe
        self.cell.move_l(
            S_now @ _tz(-s.clearance_m) @ se3.invert(Xe), s.travel_speed_m_s, s.travel_accel_m_s2
        )
        plans, notes = plan_orientations(s, reachable(Xe, ball))
        for n in notes:
            self._note("orient", n)
        visited: list[OrientationPlan] = []
        tilt_sweeps: list[RecordedSweep] = []
        band = _BAND_WIDE_M
        for j, p in enumerate(plans):
            group = j + 1
            self._say(
                "orient",
                f"{p.label}, tilt {p.tilt_deg:.0f} deg, roll {p.roll_deg:.0f} deg",
                n_fov + j + 1,
                total,
            )
            start, end = ends(p, Xe, ball)
            r = kin.sweep(start, end, clearance(Xe), self.cell.joints(), hub(Xe, ball))
            if r is None:
                self._note("orient", f"{p.label}: unreachable with the updated estimate; skipped")
                continue
            if r.via is not None:
                self.cell.move_j(r.via, s.joint_speed_rad_s, s.joint_accel_rad_s2)
            self.cell.move_j(r.approach, s.joint_speed_rad_s, s.joint_accel_rad_s2)
            self.cell.move_l(start, s.travel_speed_m_s, s.travel_accel_m_s2)
            keep = _near_ball(Xe, ball, s.ball_radius_m, band)
            places = [(p, start, end)]
            if s.lateral_places == 2:
                # The same orientation with the ball at the other end of the laser line: reached
                # by a lateral move at the sweep start, where the laser plane is clear of the ball.
                p2 = dataclasses.replace(p, lateral_m=-p.lateral_m)
                start2, end2 = ends(p2, Xe, ball)
                q2 = kin.linear(start, start2, r.start)
                if q2 is not None and kin.linear(start2, end2, q2) is not None:
                    places.append((p2, start2, end2))
                else:
                    self._note("orient", f"{p.label}: the second lateral place is unreachable")
            last = start
            for k, (pk, a, b) in enumerate(places):
                if k:
                    self.cell.move_l(a, s.travel_speed_m_s, s.travel_accel_m_s2)
                loc = self._next_location()
                name = f"{pk.label} y {pk.lateral_m * 1e3:+.0f} mm"
                tilt_sweeps.append(self._sweep(a, b, "tilt", group, loc, 1, f"{name} fwd", keep))
                last = b
                if s.bidirectional:
                    tilt_sweeps.append(
                        self._sweep(b, a, "tilt", group, loc, -1, f"{name} bwd", keep)
                    )
                    last = a
                elif k + 1 < len(places):
                    self.cell.move_l(a, s.travel_speed_m_s, s.travel_accel_m_s2)
                    last = a
            self.cell.move_l(last @ clearance(Xe), s.travel_speed_m_s, s.travel_accel_m_s2)
            visited.append(p)
            for w in tilt_sweeps[len(centres) - n_fov_sweeps :]:
                centres.append(_centre_at_start(w, ori.rotation, s.ball_radius_m))
            if len(visited) >= 2:
                # Step 2 with what is there aims the remaining orientations better.
                est = _origin_estimate([*sweeps, *tilt_sweeps], ori.rotation, centres)
                if est is not None:
                    Xe = se3.make(ori.rotation, est[0])
                    ball = est[1]
                    band = _BAND_NARROW_M
                self._wait_for_data(quiet=True)
        if len(visited) < 2:
            raise CalibrationFailed(
                f"only {len(visited)} orientations could be swept; at least 2 are needed"
            )
        self._reference = F0
        self._reference_q = q_start
        self._estimate = Xe
        return [*sweeps, *tilt_sweeps], visited, F0

    def _check_automatic(self, joint: handeye.HandEyeResult) -> list[RecordedSweep]:
        """(e) a sweep at an orientation the solution did not use."""
        s = self.s
        X = joint.sensor2flange
        ball = joint.ball_centre_base
        F0 = self._reference
        kin = self.cell.planner(self._reference_q)
        inv = se3.invert(X)
        clear = X @ _tz(-s.clearance_m) @ inv
        h = s.sweep_half_m
        for az, tilt, roll in ((30.0, 25.0, 45.0), (210.0, 25.0, 45.0), (90.0, 20.0, -45.0)):
            p = OrientationPlan(f"check (az {az:.0f} deg)", az, tilt, roll)
            Sc = p.sensor2base(F0 @ X, ball, s.working_depth_m)
            start, end = Sc @ _tx(-h) @ inv, Sc @ _tx(h) @ inv
            Rref = (F0 @ X)[:3, :3]
            via = (
                se3.make(
                    Rref, ball - Rref @ np.array([0.0, 0.0, s.working_depth_m + 2 * s.clearance_m])
                )
                @ inv
            )
            r = kin.sweep(start, end, clear, self.cell.joints(), via)
            if r is not None:
                break
        else:
            self._note("check", "no reachable orientation for the check scan; skipped")
            return []
        self._say("check", f"check scan: {p.label}, tilt {tilt:.0f} deg, roll {roll:.0f} deg")
        if r.via is not None:
            self.cell.move_j(r.via, s.joint_speed_rad_s, s.joint_accel_rad_s2)
        self.cell.move_j(r.approach, s.joint_speed_rad_s, s.joint_accel_rad_s2)
        self.cell.move_l(start, s.travel_speed_m_s, s.travel_accel_m_s2)
        keep = _near_ball(X, ball, s.ball_radius_m, 3e-3)
        loc = self._next_location()
        out = [self._sweep(start, end, "check", -1, loc, 1, f"{p.label} fwd", keep)]
        last = end
        if s.bidirectional:
            out.append(self._sweep(end, start, "check", -1, loc, -1, f"{p.label} bwd", keep))
            last = start
        self.cell.move_l(last @ clear, s.travel_speed_m_s, s.travel_accel_m_s2)
        return out

    # --- manual mode -------------------------------------------------------------------------
    def _ask(self, message: str) -> str:
        answer = self.prompt(message).strip().lower()
        if answer in ("q", "quit", "abort"):
            raise CalibrationAborted("stopped by the operator")
        return answer

    def _manual_sweep(
        self, stage: SweepStage, group: int, label: str, instruction: str
    ) -> list[RecordedSweep] | None:
        """Record one operator-driven sweep; None when the operator ends the stage. A sweep
        across the ball and back becomes a forward/backward pair. A recording without the ball,
        with gaps (profiles not paired), over less than the ball's radius or with its orientation
        changing is rejected and asked for again."""
        R = self.s.ball_radius_m
        while True:
            answer = self._ask(
                f"{label}: {instruction} Press Enter to start recording ('done' ends this stage, "
                "'quit' aborts)."
            )
            if answer in ("d", "done", "s", "skip"):
                return None
            data, _ = self.cell.record_while(
                lambda: self._ask(
                    "Recording: move the sensor along its X axis across the ball and back, at "
                    "constant orientation (there and back cancels a latency error), then press "
                    "Enter."
                )
            )
            legs = split_round_trip(data)
            loc = self._next_location()
            out: list[RecordedSweep] = []
            why = ""
            for leg, direction in zip(legs, (1, -1) if len(legs) == 2 else (0,), strict=True):
                name = label if direction == 0 else f"{label} {'fwd' if direction > 0 else 'bwd'}"
                try:
                    rs = self._reduce(leg, stage, group, loc, direction, name)
                except CalibrationFailed as exc:
                    why = str(exc).removeprefix(name + ": ")
                    break
                span, gap = ball_coverage(rs)
                if span < R or gap > _MAX_GAP_R * R:
                    why = (
                        f"the ball was seen over {span * 1e3:.1f} mm of travel with a "
                        f"{gap * 1e3:.1f} mm gap; sweep across the whole ball"
                    )
                    break
                if self._constant_orientation(rs) > _ORIENTATION_TOL_RAD:
                    why = "the orientation changed during the sweep"
                    break
                out.append(rs)
            if why:
                self._say(stage, f"rejected: {why}; repeat it")
                continue
            return out

    def _constant_orientation(self, rs: RecordedSweep) -> float:
        R = rs.sweep.flange2base[:, :3, :3]
        return float(np.max(se3.rotation_angle(np.swapaxes(R[:1], -1, -2) @ R)))

    def _collect_manual(
        self,
    ) -> tuple[list[RecordedSweep], list[OrientationPlan], FloatArray]:
        s = self.s
        h = s.sweep_half_m
        targets = fov_targets(s)
        sweeps: list[RecordedSweep] = []
        ref: FloatArray | None = None
        k = 0
        self._say(
            "fov",
            "manual mode: move the robot from the teach pendant; keep one "
            "orientation for the whole field-of-view stage",
        )
        while k < len(targets):
            g = targets[k]
            label = f"fov {k + 1}/{len(targets)}"
            self._say("fov", label, k + 1, len(targets))
            got = self._manual_sweep(
                "fov",
                0,
                label,
                f"place the ball at about y {g[1] * 1e3:+.0f} mm, z {g[2] * 1e3:.0f} mm in the "
                f"laser plane, then move {h * 1e3:.0f} mm back along the sensor X axis.",
            )
            if got is None:
                if k >= 3:
                    break
                self._say("fov", "at least 3 field-of-view sweeps are needed")
                continue
            F = got[0].sweep.flange2base[0]
            if ref is not None and _rotation_between(F, ref) > _ORIENTATION_TOL_RAD:
                self._say(
                    "fov", "rejected: the orientation differs from the first sweep's; repeat it"
                )
                continue
            ref = F if ref is None else ref
            sweeps += [_relabel(w, f"fov {k + 1}") for w in got]
            k += 1
        assert ref is not None
        tilts: list[RecordedSweep] = []
        plans: list[OrientationPlan] = []
        j = 0
        while j < s.n_orientations:
            label = f"orientation {j + 1}/{s.n_orientations}"
            self._say("orient", label, j + 1, s.n_orientations)
            got = self._manual_sweep(
                "tilt",
                j + 1,
                label,
                f"tilt the sensor by at least {s.min_tilt_deg:.0f} deg from the previous "
                "orientations (spread the tilts around the ball), keep the ball in view and "
                f"move {h * 1e3:.0f} mm back along the sensor X axis.",
            )
            if got is None:
                if j >= 2:
                    break
                self._say("orient", "at least 2 tilted orientations are needed")
                continue
            tilt = math.degrees(_rotation_between(got[0].sweep.flange2base[0], ref))
            tilts += [_relabel(w, f"orientation {j + 1}") for w in got]
            plans.append(OrientationPlan(f"orientation {j + 1}", float("nan"), tilt, 0.0))
            j += 1
        return [*sweeps, *tilts], plans, ref

    def _check_manual(self, joint: handeye.HandEyeResult) -> list[RecordedSweep]:
        del joint
        got = self._manual_sweep(
            "check",
            -1,
            "check scan",
            "choose an orientation not used so far, put the ball in view and move "
            f"{self.s.sweep_half_m * 1e3:.0f} mm back along the sensor X axis ('done' skips the "
            "check).",
        )
        return [] if got is None else got


# --------------------------------------------------------------------------------------------
# Results: calibration file and report


def _sym(C: FloatArray) -> FloatArray:
    return np.asarray((C + C.T) / 2)


COVARIANCE_PARAMETERS = (
    "rot_sensor_x_rad",
    "rot_sensor_y_rad",
    "rot_sensor_z_rad",
    "x_m",
    "y_m",
    "z_m",
)
"""Covariance order of the file: rotation increments about the sensor axes (right perturbation,
radians), then the sensor origin in the flange frame (metres)."""


def identities(cfg: Config) -> tuple[RobotIdentity, SensorIdentity]:
    """The identities the daemon checks a calibration against (see ``service``)."""
    sid = cfg.sensor.sensor_id
    return RobotIdentity(cfg.robot.model), SensorIdentity(
        cfg.sensor.driver, None if sid is None else str(sid)
    )


def calibration_of(
    result: SensorCalibrationResult, robot: RobotIdentity, sensor: SensorIdentity
) -> Calibration:
    """The calibration file's content: the joint solution with its covariance and residuals, the
    ball, the validation figures and the two-step figures as named parameters."""
    j, t = result.joint, result.two_step
    params: dict[str, float] = {
        "ball_radius_m": result.settings.ball_radius_m,
        "ball_centre_x_m": float(j.ball_centre_base[0]),
        "ball_centre_y_m": float(j.ball_centre_base[1]),
        "ball_centre_z_m": float(j.ball_centre_base[2]),
        "condition_number": float(j.condition),
        "n_sweeps": float(len(result.sweeps)),
        "n_points": float(j.n_points),
        "min_z_angle_deg": float(result.min_z_angle_deg),
        "robot_sigma_m": float(result.robot_sigma_m or result.settings.robot_sigma_m),
        "observed_robot_sigma_m": float(result.observed_robot_sigma_m),
        "two_step_rms_m": float(t.rms),
        "two_step_translation_diff_m": float(
            np.linalg.norm(t.sensor2flange[:3, 3] - j.sensor2flange[:3, 3])
        ),
        "two_step_rotation_diff_rad": _rotation_between(t.sensor2flange, j.sensor2flange),
    }
    if result.loo is not None:
        params["loo_max_translation_m"] = result.loo.max_translation_dev_m
        params["loo_max_rotation_rad"] = result.loo.max_rotation_dev_rad
    if result.check is not None:
        params["check_centre_error_m"] = result.check.centre_error_m
        params["check_radius_error_m"] = result.check.radius_error_m
        params["check_rms_m"] = result.check.rms_m
    if result.latency is not None and math.isfinite(result.latency.offset_s):
        params["apparent_latency_offset_s"] = result.latency.offset_s
    params = {k: v for k, v in params.items() if math.isfinite(v)}
    per = np.nan_to_num(np.asarray(j.per_sweep_rms, dtype=np.float64))
    notes = "; ".join(result.notes)
    return Calibration(
        kind="sensor2flange",
        transform=j.sensor2flange,
        robot=robot,
        sensor=sensor,
        method=METHOD,
        residuals=Residuals(float(j.rms), tuple(float(v) for v in per)),
        covariance=_sym(np.asarray(j.cov, dtype=np.float64)),
        covariance_parameters=COVARIANCE_PARAMETERS,
        parameters=params,
        notes=("manual mode; " if result.manual else "") + notes,
    )


def _fmt_um(v: float) -> str:
    return f"{v * 1e6:.1f}" if math.isfinite(v) else "-"


def _param_rows(result: SensorCalibrationResult) -> list[list[str]]:
    j, t = result.joint, result.two_step
    pj, pt = se3.matrix_to_pose(j.sensor2flange), se3.matrix_to_pose(t.sensor2flange)
    pn = None if result.nominal is None else se3.matrix_to_pose(result.nominal)
    sj_t, st_t = j.sigma_translation_m, t.sigma_translation_m
    sj_r, st_r = j.sigma_rotation_rad, t.sigma_rotation_rad
    loo_t = None if result.loo is None else result.loo.spread_translation_m
    rows: list[list[str]] = []
    for i, a in enumerate("xyz"):
        rows.append(
            [
                f"{a} (mm)",
                "-" if pn is None else f"{pn[i] * 1e3:.3f}",
                f"{pt[i] * 1e3:.4f}",
                f"{st_t[i] * 1e3:.4f}",
                f"{pj[i] * 1e3:.4f}",
                f"{sj_t[i] * 1e3:.4f}",
                "-" if loo_t is None else f"{loo_t[i] * 1e3:.4f}",
            ]
        )
    for i, a in enumerate("xyz"):
        rows.append(
            [
                f"r{a} (deg, rotation vector)",
                "-" if pn is None else f"{math.degrees(pn[3 + i]):.4f}",
                f"{math.degrees(pt[3 + i]):.5f}",
                "",
                f"{math.degrees(pj[3 + i]):.5f}",
                "",
                "",
            ]
        )
    for i, a in enumerate("XYZ"):
        rows.append(
            [
                f"rotation about sensor {a} (deg)",
                "",
                "0",
                f"{math.degrees(st_r[i]):.5f}",
                "0",
                f"{math.degrees(sj_r[i]):.5f}",
                "",
            ]
        )
    return rows


def build_report(
    result: SensorCalibrationResult, title: str = "Sensor-to-flange calibration", subtitle: str = ""
) -> Report:
    """The procedure's report: results, uncertainties, two-step vs joint, validation, figures
    (when matplotlib is available)."""
    from wristscan.daemon.io.calibfile import ur_pose_text
    from wristscan.daemon.io.report import Report, have_matplotlib

    s = result.settings
    j, t = result.joint, result.two_step
    rep = Report(title, subtitle)
    rep.section("Result")
    pose = se3.matrix_to_pose(j.sensor2flange)
    rep.text(
        f"sensor2flange (joint refinement): {ur_pose_text(pose)}  (metres, rotation vector in "
        f"radians; on the teach pendant the TCP is x {pose[0] * 1e3:.3f} mm, y "
        f"{pose[1] * 1e3:.3f} mm, z {pose[2] * 1e3:.3f} mm, rx {pose[3]:.5f}, ry {pose[4]:.5f},"
        f" rz {pose[5]:.5f} rad)."
    )
    summary = [
        ["residual RMS (um)", _fmt_um(t.rms), _fmt_um(j.rms)],
        ["points used", str(t.n_points), str(j.n_points)],
        ["condition number", f"{t.condition:.1f}", f"{j.condition:.1f}"],
        [
            "ball centre (mm)",
            str(np.round(t.ball_centre_base * 1e3, 3).tolist()),
            str(np.round(j.ball_centre_base * 1e3, 3).tolist()),
        ],
    ]
    if result.check is not None:
        c = result.check
        summary += [
            [
                "check scan: centre error (um)",
                _fmt_um(c.two_step_centre_error_m),
                _fmt_um(c.centre_error_m),
            ],
            [
                "check scan: radius error (um)",
                _fmt_um(c.two_step_radius_error_m),
                _fmt_um(c.radius_error_m),
            ],
        ]
    d_t = float(np.linalg.norm(t.sensor2flange[:3, 3] - j.sensor2flange[:3, 3]))
    d_r = math.degrees(_rotation_between(t.sensor2flange, j.sensor2flange))
    rep.table(
        ["", "two-step (paper)", "joint refinement"],
        summary,
        "The paper's two-step solution beside the joint refinement, on the same sweeps",
    )
    rep.text(
        f"The two solutions differ by {d_t * 1e3:.4f} mm and {d_r:.5f} deg. "
        f"{len(result.sweeps)} sweeps ({sum(w.stage == 'fov' for w in result.sweeps)} at "
        f"field-of-view locations), {sum(w.n_profiles for w in result.sweeps)} profiles; "
        f"smallest angle between sensor Z axes of two orientations "
        f"{result.min_z_angle_deg:.1f} deg; {result.duration_s:.0f} s."
    )
    rep.section("Parameters and uncertainty")
    rep.table(
        ["parameter", "nominal", "two-step", "1 sigma", "joint", "1 sigma", "LOO jackknife"],
        _param_rows(result),
        "Translation of the sensor origin in the flange frame; rotation uncertainty about the "
        "sensor axes. 1 sigma from the covariance (joint: sensor noise and the robot's "
        f"repeatability, {(result.robot_sigma_m or s.robot_sigma_m) * 1e6:.1f} um per axis: the "
        f"larger of the data sheet's {s.robot_sigma_m * 1e6:.1f} um and the "
        f"{result.observed_robot_sigma_m * 1e6:.1f} um the places' scatter shows, per pass).",
    )
    rep.section("Validation")
    if result.loo is not None:
        loo = result.loo
        rep.table(
            [
                "left out",
                "translation change (um)",
                "rotation change (mdeg)",
                "prediction RMS (um)",
            ],
            [
                [lab, _fmt_um(a), f"{math.degrees(b) * 1e3:.2f}", _fmt_um(c)]
                for lab, a, b, c in zip(
                    loo.labels,
                    loo.translation_dev_m,
                    loo.rotation_dev_rad,
                    loo.prediction_rms_m,
                    strict=True,
                )
            ],
            "Leave-one-out over the orientations: the joint refinement without each one",
        )
    else:
        rep.text("Leave-one-out was not run (fewer than 3 orientations, or switched off).")
    if result.check is not None:
        c = result.check
        rep.text(
            f"Check scan ({c.label}, not used by the solution): sphere of free radius through "
            f"{c.n_points} points mapped with the new calibration; centre "
            f"{c.centre_error_m * 1e6:.1f} um from the calibrated ball centre, radius "
            f"{c.radius_m * 1e3:.4f} mm ({c.radius_error_m * 1e6:+.1f} um), RMS "
            f"{c.rms_m * 1e6:.1f} um."
        )
    if result.latency is not None:
        lat = result.latency
        suggest = result.configured_latency_s + lat.offset_s
        rep.text(
            f"Apparent sensor time offset from {lat.n_pairs} forward/backward pairs at "
            f"{lat.speed_m_s * 1e3:.1f} mm/s: {lat.offset_s * 1e3:+.3f} ms (+- "
            f"{lat.std_s * 1e3:.3f} ms). Configured latency {result.configured_latency_s * 1e3:.3f}"
            f" ms; the data suggest {suggest * 1e3:.3f} ms (set [sensor] latency_s, or run "
            "wristscan calibrate latency). Sweeping both ways cancels this offset in the "
            "solution; each forward/backward pair was re-timed by its own offset before it."
        )
        if result.uncompensated is not None:
            u = result.uncompensated
            d_t = float(np.linalg.norm(u.sensor2flange[:3, 3] - j.sensor2flange[:3, 3]))
            rep.text(
                f"Without the re-timing the joint refinement had a residual RMS of "
                f"{u.rms * 1e6:.1f} um (now {j.rms * 1e6:.1f} um) and sensor2flange "
                f"{d_t * 1e3:.4f} mm / "
                f"{math.degrees(_rotation_between(u.sensor2flange, j.sensor2flange)):.5f} deg "
                "from the final one."
            )
    if result.notes:
        rep.section("Notes")
        rep.text("\n".join(f"- {n}" for n in result.notes), preformatted=True)
    if have_matplotlib():
        _figures(rep, result)
    else:
        rep.text("Figures need matplotlib: pip install 'wristscan[plot]'.")
    rep.section("Settings")
    rep.table(
        ["setting", "value"],
        [
            [k, f"{v:g}" if isinstance(v, float) else str(v)]
            for k, v in dataclasses.asdict(s).items()
        ],
    )
    return rep


def _figures(rep: Report, result: SensorCalibrationResult) -> None:
    from wristscan.daemon.io.report import axis_equal_3d, blank_figure, new_figure

    s = result.settings
    j, t = result.joint, result.two_step
    solver = [w.for_solver() for w in result.sweeps]
    R = s.ball_radius_m

    def residuals(res: handeye.HandEyeResult) -> FloatArray:
        r = handeye.sphere_residuals(
            [w.subset(m) for w, m in zip(solver, res.inliers, strict=True)],
            res.sensor2flange,
            res.ball_centre_base,
            res.ball_radius_m,
        )
        return np.concatenate(r)

    rt, rj = residuals(t) * 1e6, residuals(j) * 1e6
    lim = float(np.percentile(np.abs(np.concatenate([rt, rj])), 99.5)) or 1.0
    fig, axes = new_figure(1, 2, figsize=(9.0, 3.6), sharey=True)
    for ax, r, name in ((axes[0], rt, "two-step (paper)"), (axes[1], rj, "joint refinement")):
        ax.hist(r, bins=80, range=(-lim, lim), color="tab:blue")
        ax.set_title(f"{name}: RMS {np.sqrt(np.mean(r**2)):.1f} um")
        ax.set_xlabel("distance to the ball surface (um)")
    axes[0].set_ylabel("points")
    rep.figure(fig, "Residuals of all inlier points, two-step beside joint refinement")

    labels = [w.label for w in result.sweeps]
    x = np.arange(len(labels))
    fig, ax = new_figure(figsize=(9.0, 3.8))
    ax.bar(x - 0.2, t.per_sweep_rms * 1e6, 0.4, label="two-step")
    ax.bar(x + 0.2, j.per_sweep_rms * 1e6, 0.4, label="joint")
    ax.set_xticks(x, labels, rotation=70, ha="right", fontsize=7)
    ax.set_ylabel("RMS residual (um)")
    ax.legend()
    rep.figure(fig, "Residual RMS per sweep")

    fig, ax = new_figure(figsize=(6.5, 6.0), subplot_kw={"projection": "3d"})
    c = j.ball_centre_base
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 24), np.linspace(0, np.pi, 12))
    ax.plot_wireframe(
        c[0] + R * np.cos(u) * np.sin(v),
        c[1] + R * np.sin(u) * np.sin(v),
        c[2] + R * np.cos(v),
        color="0.6",
        linewidth=0.5,
    )
    pts = [c]
    for group_sweeps, colour, name in (
        ([w for w in result.sweeps if w.stage == "fov"], "tab:gray", "field of view"),
        ([w for w in result.sweeps if w.stage == "tilt"], "tab:blue", "orientations"),
        (list(result.check_sweeps), "tab:red", "check scan"),
    ):
        if not group_sweeps:
            continue
        S = np.array(
            [w.sweep.flange2base[w.sweep.n_poses // 2] @ j.sensor2flange for w in group_sweeps]
        )
        o, z = S[:, :3, 3], S[:, :3, 2]
        length = float(np.median(np.linalg.norm(o - c, axis=1)))
        ax.quiver(
            o[:, 0],
            o[:, 1],
            o[:, 2],
            z[:, 0],
            z[:, 1],
            z[:, 2],
            length=length,
            color=colour,
            label=name,
            linewidth=1.0,
            arrow_length_ratio=0.08,
        )
        pts.extend(o)
    axis_equal_3d(ax, np.array(pts))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.legend(loc="upper left", fontsize=8)
    rep.figure(fig, "Pose set: sensor origins and Z axes (mid-sweep) around the ball, base frame")

    if result.check is not None:
        ck = result.check
        fig = blank_figure(figsize=(9.5, 4.0))
        ax3 = fig.add_subplot(1, 2, 1, projection="3d")
        p = ck.points_base
        sc = ax3.scatter(p[:, 0], p[:, 1], p[:, 2], c=ck.residuals_m * 1e6, s=2, cmap="coolwarm")
        fig.colorbar(sc, ax=ax3, shrink=0.7, label="residual (um)")
        axis_equal_3d(ax3, p)
        ax3.set_title("check scan in base (new calibration)", fontsize=9)
        ax2 = fig.add_subplot(1, 2, 2)
        ax2.hist(ck.residuals_m * 1e6, bins=60, color="tab:red")
        ax2.set_xlabel("distance to the fitted sphere (um)")
        ax2.set_title(
            f"centre error {ck.centre_error_m * 1e6:.1f} um, radius "
            f"{ck.radius_error_m * 1e6:+.1f} um",
            fontsize=9,
        )
        rep.figure(fig, "Check scan: sphere fit of a sweep at an orientation not used")


# --------------------------------------------------------------------------------------------
# The whole thing on a configuration


def run(
    cfg: Config,
    settings: Settings,
    *,
    nominal: FloatArray | None,
    out: str | Path,
    report: str | Path | None = None,
    manual: bool = False,
    prompt: Prompt | None = None,
    progress: Progress | None = None,
    acquisition: Acquisition | None = None,
) -> SensorCalibrationResult:
    """Open the configured devices, run the procedure, write the calibration file ``out`` and the
    report. Nothing is written unless the procedure completes.

    Raises ``MotionNotEnabled`` (automatic mode without ``[robot] motion_enabled``),
    :class:`CalibrationFailed`, :class:`CalibrationAborted`, ``DriverError`` (devices cannot be
    opened). ``acquisition``: an already built (unopened) one, for tests."""
    if not manual and not cfg.robot.motion_enabled:
        raise MotionNotEnabled(
            f"motion is not enabled in {cfg.source}: set [robot] motion_enabled = true (or use "
            "--manual and move the robot from the teach pendant)"
        )

    def say(stage: str, message: str) -> None:
        if progress is not None:
            progress(ProgressEvent(stage, 0, 0, message))

    say("connect", f"opening {cfg.robot.driver} at {cfg.robot.host} and {cfg.sensor.driver}")
    acq = acquisition or Acquisition(cfg)
    model = kinematics.get_model(cfg.robot.model)
    with acq:
        cell = RobotCell(acq, model)
        proc = SensorCalibration(
            cell,
            settings,
            nominal,
            manual=manual,
            prompt=prompt,
            progress=progress,
            configured_latency_s=float(cfg.sensor.latency_s),
        )
        result = proc.run()
    robot_id, sensor_id = identities(cfg)
    calib = calibration_of(result, robot_id, sensor_id)
    path = write_calibration(out, calib)
    say("write", f"calibration written to {path}: {calib.ur_pose_text}")
    if report is not None:
        try:
            rep = build_report(result, subtitle=f"cell {cfg.cell.name}, configuration {cfg.source}")
            say("write", f"report written to {rep.write(report)}")
        except (OSError, ValueError) as exc:  # the calibration is written: do not fail for this
            log.warning("the report could not be written: %s", exc)
            say("write", f"the report could not be written: {exc}")
    return result
