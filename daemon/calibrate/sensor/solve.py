"""The sensor calibration's solution on recorded sweeps (pure functions): the paper's two-step
solution and the joint refinement (:func:`solve`, :func:`quick_refine`), the sensor origin from
the ball centres while the orientations are still being visited (:func:`origin_estimate`), the
sensor time offset seen in passes run both ways and its removal (:class:`ApparentLatency`,
:func:`compensate_timing`), and the places whose passes disagree with the solution
(:func:`inconsistent_locations`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import handeye, sphere
from wristscan.calib.dh import DHParams, get_model
from wristscan.daemon.calibrate.sensor.errors import CalibrationFailed
from wristscan.daemon.calibrate.sensor.sweeps import MIN_BALL_POINTS, RecordedSweep

__all__ = [
    "ApparentLatency",
    "apparent_latency",
    "can_drop",
    "centre_at_start",
    "compensate_timing",
    "inconsistent_locations",
    "inlier_masks",
    "kinematic_prior_for",
    "location_offsets",
    "observed_robot_sigma",
    "origin_estimate",
    "quick_refine",
    "retime",
    "solve",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


def solve(
    sweeps: Sequence[RecordedSweep],
    ball_radius_m: float,
    robot_sigma_m: float = 0.0,
    kinematic_prior: handeye.KinematicPrior | None = None,
) -> tuple[handeye.HandEyeResult, handeye.HandEyeResult]:
    """The paper's two-step solution and the joint refinement started from it, on the same
    sweeps. ``sweeps`` must list the FOV sweeps first, then the tilted ones (the order of
    ``per_sweep_rms`` and ``inliers``). ``kinematic_prior`` (the arm's model and the prior sigma
    of its DH parameters, :mod:`wristscan.calib.handeye_kinematic`) adds the arm's systematic
    kinematic error to the joint solution's covariance. Raises :class:`CalibrationFailed` with
    advice."""
    fov = [s.for_solver() for s in sweeps if s.stage == "fov"]
    tilt = [s.for_solver() for s in sweeps if s.stage == "tilt"]
    if [s.stage for s in sweeps] != ["fov"] * len(fov) + ["tilt"] * len(tilt):
        raise ValueError("solve: list the FOV sweeps first, then the tilted ones")
    try:
        two = handeye.two_step(fov, tilt, ball_radius_m)
        joint = handeye.refine(
            [*fov, *tilt], two, ball_radius_m, robot_sigma_m=robot_sigma_m,
            kinematic_prior=kinematic_prior,
        )  # fmt: skip
    except handeye.PoorlyConstrained as exc:
        raise CalibrationFailed(f"the sweeps do not determine sensor2flange: {exc}") from None
    except ValueError as exc:
        raise CalibrationFailed(f"the calibration could not be solved: {exc}") from None
    return two, joint


def kinematic_prior_for(
    model: DHParams | None, nominal: str | DHParams | None, seed: FloatArray | None = None
) -> handeye.KinematicPrior | None:
    """The default prior of the arm's kinematic error for a robot whose flange poses come from
    ``model`` (``Robot.kinematic_model()``; None: the configured ``nominal`` one): a model that
    differs from the ``nominal`` table is a factory calibration (15 % of a real arm's DH
    deviations left, :func:`~wristscan.calib.handeye_kinematic.prior_sigma` ``"partial"``), the
    nominal table has all of them (``"none"``). None when neither is known. ``seed``: the arm's
    joints in its working configuration (the inverse kinematics' branch), default the usual one.
    """
    if model is None and nominal is None:
        return None
    table = None if nominal is None else get_model(nominal)
    used = model if model is not None else table
    assert used is not None
    factory = table is not None and not np.allclose(used.arrays(), table.arrays(), 0.0, 1e-12)
    prior = handeye.KinematicPrior.for_factory(used, "partial" if factory else "none")
    return prior if seed is None else dataclasses.replace(prior, seed=np.asarray(seed, float))


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


def centre_at_start(rs: RecordedSweep, rotation: FloatArray, radius: float) -> FloatArray:
    """Ball centre (m) in the sensor frame at the first pose of ``rs.for_solver()``."""
    sw = rs.for_solver()
    pts = handeye.sweep_points_at_start(sw, rotation)
    try:
        return np.asarray(sphere.fit_sphere(pts, radius=radius, robust="tukey").centre)
    except ValueError:
        return np.full(3, np.nan)


def origin_estimate(
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


# --------------------------------------------------------------------------------------------
# Timing: the sensor time offset seen in passes run both ways


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
            if pts.shape[0] < MIN_BALL_POINTS:
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


# --------------------------------------------------------------------------------------------
# Consistency: the places against the solution


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
        if pts.shape[0] < MIN_BALL_POINTS:
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


def can_drop(sweeps: Sequence[RecordedSweep], drop: set[int]) -> bool:
    """Whether enough remains without the locations ``drop`` (3 FOV places, 2 orientations)."""
    rest = [w for w in sweeps if w.location not in drop]
    fov = {w.location for w in rest if w.stage == "fov"}
    tilt = {w.group for w in rest if w.stage == "tilt"}
    return len(fov) >= 3 and len(tilt) >= 2
