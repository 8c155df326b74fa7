"""Synthetic ball-matching sweeps with a known ground truth, for tests and benchmarks.

The laser plane (sensor Y-Z) is ray-cast analytically: every profile samples a uniform grid of
``y`` along the laser line and casts a ray along sensor +Z (parallel-projection model of a
triangulation sensor; +Z points towards the part) through the measuring range. Each ray keeps its
nearest hit among the tooling ball, and optionally the post holding it (a cylinder hanging below
the centre along base -Z) and the table (a plane normal to base Z). Hits steeper than
``max_incidence_rad`` to the surface normal are not seen, as on a real sensor.

A sweep moves the flange in a straight line along the *commanded* sensor X axis (taken from
``sensor2flange_nominal``, the tool the robot believes in), centred on the pose that puts the ball
centre at the requested FOV location ``(0, y, z)`` of the true sensor frame, from ``-(R + margin)``
to ``+(R + margin)``. Robot error is applied to the *reported* flange poses: a per-sweep
translation offset (repeatability), optional per-profile jitter and an optional per-sweep rotation.
Sensor noise is Gaussian on ``y`` and ``z`` of every point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import se3
from wristscan.calib.handeye import Sweep

__all__ = [
    "BallScene",
    "BallSweeps",
    "SensorModel",
    "fov_grid",
    "make_ball_sweeps",
    "tilt_orientations",
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class SensorModel:
    """Laser-plane geometry in the sensor frame (metres): the sensor origin is the FOV centre."""

    y_range_m: tuple[float, float] = (-0.035, 0.035)
    z_range_m: tuple[float, float] = (-0.04, 0.04)
    y_pitch_m: float = 0.25e-3
    max_incidence_rad: float = np.deg2rad(75.0)


@dataclass(frozen=True, eq=False)
class BallScene:
    """Clutter around the ball: a post (cylinder) below it and a table plane (metres)."""

    post_radius_m: float = 4e-3
    table_below_centre_m: float = 0.03
    post: bool = True
    table: bool = True


@dataclass(frozen=True, eq=False)
class BallSweeps:
    """Generated sweeps and, per sweep, which points lie on the ball (ground truth)."""

    fov: list[Sweep]
    tilt: list[Sweep]
    fov_on_ball: list[BoolArray]
    tilt_on_ball: list[BoolArray]

    @property
    def all(self) -> list[Sweep]:
        return [*self.fov, *self.tilt]

    @property
    def all_on_ball(self) -> list[BoolArray]:
        return [*self.fov_on_ball, *self.tilt_on_ball]


def fov_grid(
    n_y: int = 3, n_z: int = 3, y_half_m: float = 0.02, z_half_m: float = 0.015
) -> FloatArray:
    """``(n_y * n_z, 2)`` ball positions ``(y, z)`` (m) on a regular grid over the FOV."""
    y = np.linspace(-y_half_m, y_half_m, n_y)
    z = np.linspace(-z_half_m, z_half_m, n_z)
    Y, Z = np.meshgrid(y, z, indexing="ij")
    return np.stack([Y.ravel(), Z.ravel()], axis=-1)


def tilt_orientations(base: ArrayLike, angle_rad: float = np.deg2rad(45.0)) -> FloatArray:
    """Six flange orientations ``(6, 3, 3)``: ``base`` tilted by +-angle about its X and Y axes and
    by angle about X and Y combined with +-90 deg about Z."""
    B = np.asarray(base, dtype=np.float64)
    a = angle_rad
    rel = [
        se3.rot_x(a),
        se3.rot_x(-a),
        se3.rot_y(a),
        se3.rot_y(-a),
        se3.rot_z(np.pi / 2) @ se3.rot_x(a),
        se3.rot_z(-np.pi / 2) @ se3.rot_y(a),
    ]
    return np.stack([B @ r for r in rel])


def _first_hits(
    origins: FloatArray,
    direction: FloatArray,
    centre: FloatArray,
    radius: float,
    scene: BallScene | None,
    max_len: float,
    cos_max: float,
) -> tuple[FloatArray, BoolArray, BoolArray]:
    """Nearest hit distance along rays (base frame). origins (P, G, 3), direction (P, 3).

    Returns s (P, G) (inf where nothing is hit), valid (P, G), on_ball (P, G)."""
    D = direction[:, None, :]
    w = origins - centre
    b = np.sum(w * D, axis=-1)
    disc = b**2 - (np.sum(w * w, axis=-1) - radius**2)
    with np.errstate(invalid="ignore"):
        s_ball = -b - np.sqrt(disc)
    hit = disc > 0.0
    nrm = (w + s_ball[..., None] * D) / radius
    hit &= -np.sum(nrm * D, axis=-1) >= cos_max
    s_ball = np.where(hit & (s_ball >= 0.0) & (s_ball <= max_len), s_ball, np.inf)
    best = s_ball.copy()
    if scene is not None and scene.post:
        a = np.array([0.0, 0.0, -1.0])
        rp = scene.post_radius_m
        wp = w - np.sum(w * a, axis=-1)[..., None] * a
        Dp = D - np.sum(D * a, axis=-1)[..., None] * a
        A = np.sum(Dp * Dp, axis=-1)
        B = 2.0 * np.sum(wp * Dp, axis=-1)
        C = np.sum(wp * wp, axis=-1) - rp**2
        dd = B**2 - 4.0 * A * C
        with np.errstate(invalid="ignore", divide="ignore"):
            s_post = (-B - np.sqrt(dd)) / (2.0 * A)
        h = np.sum((w + s_post[..., None] * D) * a, axis=-1)
        ok = (dd > 0.0) & (A > 1e-12) & (h >= np.sqrt(radius**2 - rp**2))
        ok &= h <= scene.table_below_centre_m
        with np.errstate(invalid="ignore"):
            pn = (wp + s_post[..., None] * Dp) / rp
        ok &= -np.sum(pn * D, axis=-1) >= cos_max
        s_post = np.where(ok & (s_post >= 0.0) & (s_post <= max_len), s_post, np.inf)
        best = np.minimum(best, s_post)
    if scene is not None and scene.table:
        height = centre[2] - scene.table_below_centre_m
        dz = D[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            s_tab = (height - origins[..., 2]) / dz
        ok = (-dz >= cos_max) & (s_tab >= 0.0) & (s_tab <= max_len)
        best = np.minimum(best, np.where(ok, s_tab, np.inf))
    valid = np.isfinite(best)
    on_ball = valid & (best == s_ball)
    return best, valid, on_ball


def _sweep(
    X_true: FloatArray,
    R_nom: FloatArray,
    R_flange: FloatArray,
    fov_yz: FloatArray,
    c_base: FloatArray,
    radius: float,
    sensor: SensorModel,
    scene: BallScene | None,
    step_m: float,
    margin_m: float,
    robot_noise_m: float,
    robot_jitter_m: float,
    robot_rot_noise_rad: float,
    sensor_noise_m: float,
    rng: np.random.Generator,
) -> tuple[Sweep, BoolArray]:
    Rsf, tsf = X_true[:3, :3], X_true[:3, 3]
    c_s = np.array([0.0, fov_yz[0], fov_yz[1]])
    T_mid = c_base - R_flange @ (Rsf @ c_s + tsf)
    d = R_flange @ R_nom[:, 0]  # commanded sweep direction: nominal sensor X, base frame
    half = radius + margin_m
    s = np.arange(-half, half + 0.5 * step_m, step_m)
    P = s.size
    F_true = se3.make(np.broadcast_to(R_flange, (P, 3, 3)), T_mid + s[:, None] * d)
    S = F_true @ X_true  # sensor2base per profile
    y = np.arange(
        sensor.y_range_m[0], sensor.y_range_m[1] + 0.5 * sensor.y_pitch_m, sensor.y_pitch_m
    )
    z0, z1 = sensor.z_range_m
    o_s = np.stack([np.zeros_like(y), y, np.full_like(y, z0)], axis=-1)  # (G, 3)
    origins = se3.apply(S, o_s)  # (P, G, 3)
    direction = S[:, :3, 2]
    dist, valid, on_ball = _first_hits(
        origins, direction, c_base, radius, scene, z1 - z0, float(np.cos(sensor.max_incidence_rad))
    )
    pi, gi = np.nonzero(valid)
    yy = y[gi] + rng.normal(0.0, sensor_noise_m, gi.size)
    zz = z0 + dist[pi, gi] + rng.normal(0.0, sensor_noise_m, gi.size)
    # Reported poses: true poses plus robot error.
    F_rep = F_true.copy()
    F_rep[:, :3, 3] += rng.normal(0.0, robot_noise_m, 3) + rng.normal(0.0, robot_jitter_m, (P, 3))
    if robot_rot_noise_rad > 0.0:
        F_rep[:, :3, :3] = F_rep[:, :3, :3] @ se3.rotvec_to_matrix(
            rng.normal(0.0, robot_rot_noise_rad, 3)
        )
    return Sweep.from_yz(F_rep, yy, zz, pi), on_ball[pi, gi]


def make_ball_sweeps(
    sensor2flange_true: ArrayLike,
    ball_centre: ArrayLike,
    radius: float,
    fov_grid: ArrayLike,
    orientations: ArrayLike,
    robot_noise_m: float,
    sensor_noise_m: float,
    rng: np.random.Generator,
    *,
    base_orientation: ArrayLike | None = None,
    tilt_fov: ArrayLike | None = None,
    sensor2flange_nominal: ArrayLike | None = None,
    sensor: SensorModel | None = None,
    scene: BallScene | None = None,
    sweep_step_m: float = 0.3e-3,
    sweep_margin_m: float = 1e-3,
    robot_jitter_m: float = 0.0,
    robot_rot_noise_rad: float = 0.0,
) -> BallSweeps:
    """Ball-matching sweeps over a ball of ``radius`` (m) centred at ``ball_centre`` (base, m).

    Args:
        sensor2flange_true: ``(4, 4)`` ground truth.
        fov_grid: ``(K, 2)`` ball positions ``(y, z)`` in the sensor FOV (m) for the step-1 sweeps,
            all at the flange orientation ``base_orientation`` (default: sensor Z pointing down,
            ``rot_x(pi) @ R_sf^T``), the robot only translating between them.
        orientations: ``(M, 3, 3)`` flange2base rotations of the tilted sweeps.
        tilt_fov: ``(M, 2)`` FOV position of the ball in each tilted sweep (default FOV centre).
        robot_noise_m: per-axis sigma of a per-sweep offset of the reported flange position.
        sensor_noise_m: per-axis sigma of ``y`` and ``z`` of every profile point.
        sensor2flange_nominal: the tool the robot uses to command sweeps along sensor X (default:
            the truth); its rotation error tilts the sweep direction away from the true sensor X.
        scene: clutter (post, table); ``None`` for the ball alone.
        sweep_step_m: flange travel between profiles; ``sweep_margin_m`` extra travel beyond +-R.
        robot_jitter_m: per-profile per-axis sigma of the reported flange position.
        robot_rot_noise_rad: per-sweep per-axis sigma of a rotation error of the reported flange.
    """
    X = se3.check_transform(np.asarray(sensor2flange_true, dtype=np.float64), "sensor2flange_true")
    Xn = X if sensor2flange_nominal is None else np.asarray(sensor2flange_nominal, dtype=np.float64)
    c = np.asarray(ball_centre, dtype=np.float64)
    grid = np.atleast_2d(np.asarray(fov_grid, dtype=np.float64))
    ori = np.asarray(orientations, dtype=np.float64).reshape(-1, 3, 3)
    R0 = (
        se3.rot_x(np.pi) @ X[:3, :3].T
        if base_orientation is None
        else np.asarray(base_orientation, dtype=np.float64)
    )
    tfov = (
        np.zeros((ori.shape[0], 2)) if tilt_fov is None else np.asarray(tilt_fov, dtype=np.float64)
    )
    if tfov.shape != (ori.shape[0], 2):
        raise ValueError(f"tilt_fov: expected ({ori.shape[0]}, 2), got {tfov.shape}")
    sm = SensorModel() if sensor is None else sensor

    def one(R_flange: FloatArray, yz: FloatArray) -> tuple[Sweep, BoolArray]:
        return _sweep(
            X, Xn[:3, :3], R_flange, yz, c, float(radius), sm, scene, sweep_step_m,
            sweep_margin_m, robot_noise_m, robot_jitter_m, robot_rot_noise_rad, sensor_noise_m, rng,
        )  # fmt: skip

    # A handful of sweeps; each one is vectorised over its profiles and rays.
    fov_pairs = [one(R0, yz) for yz in grid]
    tilt_pairs = [one(Rf, yz) for Rf, yz in zip(ori, tfov, strict=True)]
    fov = [p[0] for p in fov_pairs]
    fov_on = [p[1] for p in fov_pairs]
    tilt = [p[0] for p in tilt_pairs]
    tilt_on = [p[1] for p in tilt_pairs]
    return BallSweeps(fov, tilt, fov_on, tilt_on)
