"""Sensor-to-flange calibration (the paper's "tool transformation") from ball-matching sweeps.

A tooling ball of known radius sits somewhere in the workspace, at an unknown but fixed place. The
robot moves the wrist-mounted profile sensor over it in *sweeps*: passes of many profiles, each
profile paired with the flange pose (``flange2base``) at its instant. A profile point ``(y, z)``
lies in the laser plane, so in the sensor frame it is ``(0, y, z)`` (Borangiu et al. 2009, sec. 1).
Every point of every sweep must then satisfy::

    || flange2base_j @ sensor2flange @ (0, y_j, z_j) - c_base || = R          (*)

Two solvers are offered:

* :func:`two_step` follows the paper. Step 1 (:func:`solve_orientation`, "ball matching"): with
  the robot only *translating* (constant flange orientation ``R0``), the ball is placed at >= 3
  (default 9) field-of-view (FOV) locations; at each one a sweep along the sensor X axis gives the
  ball centre ``c_s,k`` in the sensor frame (sphere fit). As ``c_base = R0 (R_sf c_s,k + t_sf) +
  t_k`` is the same for every k, ``R0 R_sf (c_s,k - c_s,j) = -(t_k - t_j)``: an orthogonal
  Procrustes problem for the rotation ``R_sf`` (Kabsch, proper rotation). Step 2
  (:func:`solve_origin`): sweeps at >= 3 different orientations give ``c_base = R_i (R_sf c_s,i +
  t_sf) + T_i``; moving the now known part ``R_i R_sf c_s,i`` into the translation turns this into
  the paper's TCP problem, Eq. (2)-(9), solved by :func:`wristscan.calib.tcp.solve_tcp` (``t_sf`` =
  tool point, ``c_base`` = world point).
* :func:`refine` solves (*) jointly for all six degrees of freedom of ``sensor2flange`` and the ball
  centre (optionally the radius) by nonlinear least squares on all inlier points of all sweeps, with
  an analytic Jacobian, covariance, per-sweep residuals and an identifiability check.

Reference frame of a sweep: the sweep's *first* pose (profile 0). The sensor-frame ball centre of a
sweep is expressed in the sensor frame at that pose.

Parameter order of every covariance returned here (``HandEyeResult.cov``, 6x6)::

    [w_x, w_y, w_z, t_x, t_y, t_z]

``w`` is a rotation-vector increment about the *sensor* axes (radians, right perturbation:
``R_sf_true = R_sf_est @ exp(w)``), ``t`` the sensor origin in the flange frame (metres).
``HandEyeResult.cov_full`` continues with the ball centre in base ``c_x, c_y, c_z`` (metres) and,
when the radius was estimated, the radius (metres).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from wristscan.calib import se3, sphere, tcp

__all__ = [
    "HandEyeResult",
    "Identifiability",
    "OrientationSolution",
    "OriginSolution",
    "PoorlyConstrained",
    "Sweep",
    "check_identifiability",
    "refine",
    "solve_orientation",
    "solve_origin",
    "sphere_residuals",
    "sweep_points_at_start",
    "two_step",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]

#: Condition number (column-equilibrated point Jacobian) above which a warning is logged. Good
#: pose sets (>= 30 deg tilts about two axes) give 5-11; 15 deg tilts about 20.
COND_SOFT = 15.0
#: Condition number above which :class:`PoorlyConstrained` is raised: tilts of ~3 deg give 100,
#: where 10 um of robot error already means millimetres of error along the weak axis.
COND_HARD = 100.0

_AXES = ("X", "Y", "Z")
#: Step 1 refuses FOV ball centres whose second principal spread is below this share of the first.
_MIN_FOV_SPREAD_RATIO = 0.1


class PoorlyConstrained(ValueError):
    """The sweeps do not pin down ``sensor2flange``; ``advice`` says which data to add."""

    def __init__(self, message: str, advice: str = "", condition: float = float("nan")) -> None:
        super().__init__(f"{message}; {advice}" if advice else message)
        self.advice = advice
        self.condition = condition


# --------------------------------------------------------------------------------------------
# Data model


@dataclass(frozen=True, eq=False)
class Sweep:
    """One ball-matching pass.

    Attributes:
        flange2base: ``(P, 4, 4)`` flange pose at each profile instant (metres).
        points_sensor: ``(N, 3)`` profile points in the sensor frame (metres); ``x`` is 0 for a
            laser-plane point ``(0, y, z)``.
        pose_index: ``(N,)`` index into ``flange2base`` of the profile each point belongs to.
    """

    flange2base: FloatArray
    points_sensor: FloatArray
    pose_index: IntArray

    def __post_init__(self) -> None:
        F = se3.check_transform(np.asarray(self.flange2base, dtype=np.float64), "flange2base")
        if F.ndim != 3:
            raise ValueError(f"flange2base: expected (P, 4, 4), got {F.shape}")
        p = np.asarray(self.points_sensor, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points_sensor: expected (N, 3), got {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ValueError("points_sensor: contains NaN or infinity")
        idx = np.asarray(self.pose_index)
        if idx.shape != (p.shape[0],) or (idx.size and not np.issubdtype(idx.dtype, np.integer)):
            raise ValueError(f"pose_index: expected ({p.shape[0]},) integers, got {idx.shape}")
        idx = idx.astype(np.intp)
        if idx.size and (idx.min() < 0 or idx.max() >= F.shape[0]):
            raise ValueError(f"pose_index: out of range for {F.shape[0]} poses")
        object.__setattr__(self, "flange2base", F)
        object.__setattr__(self, "points_sensor", p)
        object.__setattr__(self, "pose_index", idx)

    @classmethod
    def from_yz(
        cls, flange2base: ArrayLike, y: ArrayLike, z: ArrayLike, pose_index: ArrayLike
    ) -> Sweep:
        """Build from laser-plane coordinates ``y, z`` (metres, ``(N,)``)."""
        ya = np.asarray(y, dtype=np.float64)
        za = np.asarray(z, dtype=np.float64)
        pts = np.stack([np.zeros_like(ya), ya, za], axis=-1)
        return cls(np.asarray(flange2base, dtype=np.float64), pts, np.asarray(pose_index))

    @property
    def n_points(self) -> int:
        return int(self.points_sensor.shape[0])

    @property
    def n_poses(self) -> int:
        return int(self.flange2base.shape[0])

    def points_base(self, sensor2flange: ArrayLike) -> FloatArray:
        """All points mapped into the base frame through ``sensor2flange`` (4, 4): ``(N, 3)``."""
        X = np.asarray(sensor2flange, dtype=np.float64)
        pf = _rows_times(self.points_sensor, X[:3, :3].T) + X[:3, 3]
        F = self.flange2base[self.pose_index]
        return np.matmul(F[:, :3, :3], pf[:, :, None])[:, :, 0] + F[:, :3, 3]

    def subset(self, mask: ArrayLike) -> Sweep:
        """The same sweep with only the points where ``mask`` is true."""
        m = np.asarray(mask, dtype=bool)
        return Sweep(self.flange2base, self.points_sensor[m], self.pose_index[m])


@dataclass(frozen=True, eq=False)
class HandEyeResult:
    """A sensor-to-flange calibration.

    ``cov`` is ``(6, 6)`` in the order ``[w_x, w_y, w_z (rad, about sensor axes), t_x, t_y, t_z
    (m, flange frame)]``; ``cov_full`` adds the ball centre (m) and, if estimated, the radius (m).
    Residuals are signed distances of the inlier points to the ball surface (metres).
    ``advice`` is empty unless the condition number exceeded the soft threshold.
    """

    sensor2flange: FloatArray
    ball_centre_base: FloatArray
    ball_radius_m: float
    cov: FloatArray
    per_sweep_rms: FloatArray
    rms: float
    n_points: int
    condition: float
    method: str
    inliers: tuple[BoolArray, ...] = field(repr=False)
    advice: str = ""
    cov_full: FloatArray | None = field(default=None, repr=False)

    @property
    def sigma_rotation_rad(self) -> FloatArray:
        """1-sigma rotation uncertainty about the sensor X, Y, Z axes (radians)."""
        return np.sqrt(np.clip(np.diag(self.cov)[:3], 0.0, None))

    @property
    def sigma_translation_m(self) -> FloatArray:
        """1-sigma uncertainty of the sensor origin along flange X, Y, Z (metres)."""
        return np.sqrt(np.clip(np.diag(self.cov)[3:6], 0.0, None))

    def as_ur_pose(self) -> FloatArray:
        """The TCP as a UR pose ``p[x, y, z, rx, ry, rz]`` (metres, rotation vector)."""
        return se3.matrix_to_pose(self.sensor2flange)


@dataclass(frozen=True, eq=False)
class OrientationSolution:
    """Step 1: sensor-to-flange rotation from constant-orientation sweeps.

    ``residuals`` ``(K, 3)`` (m) are the Procrustes misfits of the ball centres in the
    flange-aligned frame; ``cov`` ``(3, 3)`` (rad^2) is about the sensor axes (right
    perturbation)."""

    rotation: FloatArray
    centres_sensor: FloatArray
    residuals: FloatArray
    rms: float
    cov: FloatArray
    iterations: int
    inliers: tuple[BoolArray, ...] = field(repr=False)


@dataclass(frozen=True, eq=False)
class OriginSolution:
    """Step 2: sensor origin in the flange frame (m) and the ball centre in base (m)."""

    translation: FloatArray
    ball_centre_base: FloatArray
    centres_sensor: FloatArray
    residuals: FloatArray
    cov: FloatArray
    sigma: float
    inliers: tuple[BoolArray, ...] = field(repr=False)


@dataclass(frozen=True, eq=False)
class Identifiability:
    """Conditioning of the joint problem at a solution.

    ``condition`` is the 2-norm condition number of the Jacobian after scaling every column to unit
    norm (so it does not depend on units). ``weakest`` is the parameter-space direction (same order
    as ``HandEyeResult.cov_full``) that the data constrain least; ``advice`` says what to add."""

    condition: float
    singular_values: FloatArray
    weakest: FloatArray
    advice: str


# --------------------------------------------------------------------------------------------
# Small helpers


def _skew(v: FloatArray) -> FloatArray:
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def _right_jacobian(w: FloatArray) -> FloatArray:
    """Right Jacobian of SO(3) at rotation vector ``w``: ``exp(w + e) ~ exp(w) exp(Jr(w) e)``."""
    th = float(np.linalg.norm(w))
    K = _skew(w)
    if th < 1e-6:
        return np.eye(3) - 0.5 * K + K @ K / 6.0
    return np.eye(3) - (1.0 - np.cos(th)) / th**2 * K + (th - np.sin(th)) / th**3 * (K @ K)


def _kabsch(a: FloatArray, b: FloatArray) -> FloatArray:
    """Proper rotation ``R`` minimising ``sum |R (a_k - mean a) - (b_k - mean b)|^2``."""
    ac = a - a.mean(axis=0)
    bc = b - b.mean(axis=0)
    U, _, Vt = np.linalg.svd(bc.T @ ac)
    d = np.sign(np.linalg.det(U @ Vt))
    return U @ np.diag([1.0, 1.0, d if d != 0 else 1.0]) @ Vt


def _mean_rotation(R: FloatArray) -> FloatArray:
    """Chordal L2 mean of rotations ``(n, 3, 3)``."""
    U, _, Vt = np.linalg.svd(R.sum(axis=0))
    d = np.sign(np.linalg.det(U @ Vt))
    return U @ np.diag([1.0, 1.0, d]) @ Vt


def _check_radius(ball_radius: float) -> float:
    r = float(ball_radius)
    if not np.isfinite(r) or r <= 0.0:
        raise ValueError(f"ball_radius must be a positive length in metres, got {ball_radius!r}")
    return r


def _check_sweeps(sweeps: Sequence[Sweep], what: str) -> list[Sweep]:
    out = list(sweeps)
    for k, s in enumerate(out):
        if not isinstance(s, Sweep):
            raise TypeError(f"{what}[{k}] is {type(s).__name__}, expected Sweep")
        if s.n_points < 4:
            raise ValueError(f"{what}[{k}] has {s.n_points} points; a sphere needs at least 4")
    return out


def _translation_only(sweep: Sweep, k: int, tol_rad: float) -> None:
    R = sweep.flange2base[:, :3, :3]
    dev = se3.rotation_angle(np.swapaxes(R[:1], -1, -2) @ R)
    if dev.size and float(dev.max()) > tol_rad:
        raise ValueError(
            f"sweep {k} rotates by {np.degrees(dev.max()):.3f} deg; the two-step method needs "
            "constant-orientation sweeps (use refine() for general motion)"
        )


# --------------------------------------------------------------------------------------------
# Two-step method (the paper)


def sweep_points_at_start(
    sweep: Sweep,
    sensor_rotation: ArrayLike | None = None,
    sweep_direction_sensor: ArrayLike = (1.0, 0.0, 0.0),
) -> FloatArray:
    """Points of a constant-orientation sweep in the sensor frame at the sweep's first pose (m).

    With a pure translation ``d_i = t_i - t_0`` of the flange (base frame) the sensor frame at
    profile ``i`` is the start frame shifted by ``R_sf^T R_0^T d_i``, so a point ``p`` of profile
    ``i`` is at ``p + R_sf^T R_0^T d_i`` in the start frame.

    ``sensor_rotation`` (sensor2flange rotation) unknown (``None``): the paper's ball matching
    assumption that the sweep was commanded along the sensor X axis is used, i.e. the shift is
    ``s_i * sweep_direction_sensor`` with ``s_i`` the signed travel along the sweep's principal
    direction (positive towards the last pose). :func:`solve_orientation` then iterates with the
    estimated rotation, which removes both the misalignment of the commanded axis and a wrong sign.
    """
    F = sweep.flange2base
    d = F[:, :3, 3] - F[0, :3, 3]
    if sensor_rotation is None:
        u = np.asarray(sweep_direction_sensor, dtype=np.float64)
        u = u / np.linalg.norm(u)
        _, _, Vt = np.linalg.svd(d - d.mean(axis=0), full_matrices=False)
        axis = Vt[0]
        if np.dot(d[-1], axis) < 0.0:
            axis = -axis
        shift = (d @ axis)[:, None] * u
    else:
        Rsf = np.asarray(sensor_rotation, dtype=np.float64)
        shift = d @ (F[0, :3, :3] @ Rsf)  # rows: (R_0 R_sf)^T d_i
    return sweep.points_sensor + shift[sweep.pose_index]


def _fit_centres(
    sweeps: Sequence[Sweep],
    ball_radius: float,
    sensor_rotation: FloatArray | None,
    sweep_direction_sensor: ArrayLike,
    robust: sphere.Robust,
) -> tuple[FloatArray, tuple[BoolArray, ...]]:
    """Ball centre (sensor frame at sweep start, m) and inlier mask of each sweep."""
    centres = np.empty((len(sweeps), 3))
    inl: list[BoolArray] = []
    for k, s in enumerate(sweeps):  # one fit per sweep; the fit itself is vectorised
        pts = sweep_points_at_start(s, sensor_rotation, sweep_direction_sensor)
        fit = sphere.fit_sphere(pts, radius=ball_radius, robust=robust)
        centres[k] = fit.centre
        inl.append(np.asarray(fit.inliers, dtype=bool))
    return centres, tuple(inl)


def solve_orientation(
    fov_sweeps: Sequence[Sweep],
    ball_radius: float,
    *,
    sweep_direction_sensor: ArrayLike = (1.0, 0.0, 0.0),
    orientation_tol_rad: float = 2e-3,
    robust: sphere.Robust = "tukey",
    max_iter: int = 10,
    tol_rad: float = 1e-12,
) -> OrientationSolution:
    """Step 1 (ball matching): the sensor2flange rotation from >= 3 FOV locations.

    All ``fov_sweeps`` must share one flange orientation (within ``orientation_tol_rad``) and only
    translate. Raises :class:`PoorlyConstrained` when the ball centres are (nearly) collinear in the
    sensor frame (the rotation about that line is then undetermined).
    """
    sw = _check_sweeps(fov_sweeps, "fov_sweeps")
    if len(sw) < 3:
        raise PoorlyConstrained(
            f"orientation needs the ball at >= 3 field-of-view locations, got {len(sw)}",
            "place the ball at more field-of-view locations (9 by default)",
        )
    R = _check_radius(ball_radius)
    for k, s in enumerate(sw):
        _translation_only(s, k, orientation_tol_rad)
    R_start = np.stack([s.flange2base[0, :3, :3] for s in sw])
    R0 = _mean_rotation(R_start)
    spread = se3.rotation_angle(R0.T @ R_start)
    if float(spread.max()) > orientation_tol_rad:
        raise ValueError(
            f"fov_sweeps differ in orientation by up to {np.degrees(spread.max()):.3f} deg; "
            "step 1 needs the robot only translating between field-of-view locations"
        )
    # c_base = R0 (R_sf c_k + t_sf) + t_k  =>  R_sf c_k = -R0^T t_k + const.
    b = -np.stack([s.flange2base[0, :3, 3] for s in sw]) @ R0

    Rsf: FloatArray | None = None
    centres = np.zeros((len(sw), 3))
    inl: tuple[BoolArray, ...] = ()
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - number of iterations is reported
        centres, inl = _fit_centres(sw, R, Rsf, sweep_direction_sensor, robust)
        ac = centres - centres.mean(axis=0)
        sv = np.linalg.svd(ac, compute_uv=False)
        # The rotation about the line through the centres has a lever of only sv[1].
        if sv[1] < _MIN_FOV_SPREAD_RATIO * sv[0] or sv[0] < 1e-9:
            raise PoorlyConstrained(
                "the ball centres of the field-of-view sweeps are (nearly) collinear in the sensor "
                "frame, so the rotation about that line is undetermined",
                "place the ball at more field-of-view locations, spread both along the laser line "
                "(sensor Y) and in depth (sensor Z)",
            )
        R_new = _kabsch(centres, b)
        change = float("inf") if Rsf is None else float(se3.rotation_angle(Rsf.T @ R_new))
        Rsf = R_new
        if change < tol_rad:
            break
    assert Rsf is not None
    ac = centres - centres.mean(axis=0)
    res = ac @ Rsf.T - (b - b.mean(axis=0))
    dof = max(3 * len(sw) - 6, 1)
    s2 = float(np.sum(res**2)) / dof
    # Right perturbation: R (I + [w]x) a = R a - R [a]x w; |R .| is orthogonal so J^T J = sum A^T A.
    A = _skew(ac)
    JtJ = np.einsum("kji,kjl->il", A, A)
    cov = s2 * np.linalg.pinv(JtJ)
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
    return OrientationSolution(Rsf, centres, res, rms, cov, it, inl)


def solve_origin(
    sweeps: Sequence[Sweep],
    sensor_rotation: ArrayLike,
    ball_radius: float,
    *,
    robust: sphere.Robust = "tukey",
    orientation_tol_rad: float = 2e-3,
    method: Literal["lstsq", "variance"] = "lstsq",
) -> OriginSolution:
    """Step 2: sensor origin in the flange frame and ball centre in base, given the rotation.

    Each constant-orientation sweep gives the ball centre ``c_s,i`` in the sensor frame at its start
    pose ``(R_i, T_i)``; with ``T_i' = T_i + R_i R_sf c_s,i`` the condition
    ``R_i t_sf + T_i' = c_base`` is the paper's TCP problem, solved by ``calib.tcp.solve_tcp``.
    Needs >= 3 sufficiently different orientations; otherwise raises :class:`PoorlyConstrained`.
    """
    sw = _check_sweeps(sweeps, "sweeps")
    R = _check_radius(ball_radius)
    Rsf = np.asarray(sensor_rotation, dtype=np.float64)
    for k, s in enumerate(sw):
        _translation_only(s, k, orientation_tol_rad)
    centres, inl = _fit_centres(sw, R, Rsf, (1.0, 0.0, 0.0), robust)
    return _origin_from_centres(sw, Rsf, centres, inl, method)


def _origin_from_centres(
    sw: Sequence[Sweep],
    Rsf: FloatArray,
    centres: FloatArray,
    inl: tuple[BoolArray, ...],
    method: Literal["lstsq", "variance"],
) -> OriginSolution:
    Ri = np.stack([s.flange2base[0, :3, :3] for s in sw])
    Ti = np.stack([s.flange2base[0, :3, 3] for s in sw])
    Tp = Ti + np.einsum("nij,jk,nk->ni", Ri, Rsf, centres)
    try:
        sol = tcp.solve_tcp(Ri, Tp, method=method)
    except tcp.DegeneratePoses as exc:
        raise PoorlyConstrained(
            f"the sweep orientations do not determine the sensor origin ({exc})",
            "add orientations tilted about the sensor X and Y axes (>= 45 deg between the tool Z "
            "axes, paper sec. 3)",
        ) from exc
    return OriginSolution(
        translation=np.asarray(sol.p_tool, dtype=np.float64),
        ball_centre_base=np.asarray(sol.p_world, dtype=np.float64),
        centres_sensor=centres,
        residuals=np.asarray(sol.residuals, dtype=np.float64),
        cov=np.asarray(sol.cov, dtype=np.float64),
        sigma=float(sol.sigma),
        inliers=inl,
    )


def two_step(
    fov_sweeps: Sequence[Sweep],
    tilt_sweeps: Sequence[Sweep],
    ball_radius: float,
    *,
    sweep_direction_sensor: ArrayLike = (1.0, 0.0, 0.0),
    robust: sphere.Robust = "tukey",
    orientation_tol_rad: float = 2e-3,
    check: bool = True,
    cond_soft: float = COND_SOFT,
    cond_hard: float = COND_HARD,
) -> HandEyeResult:
    """The paper's method: rotation from ``fov_sweeps`` (step 1), origin from all sweeps (step 2).

    ``fov_sweeps``: constant orientation, ball at >= 3 FOV locations. ``tilt_sweeps``: each at its
    own constant orientation; step 2 uses the FOV sweeps too. The covariance combines the
    Procrustes rotation covariance and the TCP translation covariance (their correlation is
    ignored). Residuals, inliers and the condition number are evaluated on the point model (*) at
    the solution, with the sphere-fit inliers. ``check`` raises :class:`PoorlyConstrained` above
    ``cond_hard``.
    """
    fov = _check_sweeps(fov_sweeps, "fov_sweeps")
    tilt = _check_sweeps(tilt_sweeps, "tilt_sweeps")
    R = _check_radius(ball_radius)
    ori = solve_orientation(
        fov,
        R,
        sweep_direction_sensor=sweep_direction_sensor,
        orientation_tol_rad=orientation_tol_rad,
        robust=robust,
    )
    for k, sweep in enumerate(tilt):
        _translation_only(sweep, len(fov) + k, orientation_tol_rad)
    # The FOV sweeps' centres from step 1's last pass were computed with the converged rotation.
    tc, t_inl = _fit_centres(tilt, R, ori.rotation, (1.0, 0.0, 0.0), robust)
    org = _origin_from_centres(
        [*fov, *tilt],
        ori.rotation,
        np.concatenate([ori.centres_sensor, tc]),
        (*ori.inliers, *t_inl),
        "lstsq",
    )
    X = se3.make(ori.rotation, org.translation)
    inliers = org.inliers
    stack = _Stack.build([*fov, *tilt], inliers)
    r = stack.residuals(X[:3, :3], X[:3, 3], org.ball_centre_base, R)
    cov = np.zeros((6, 6))
    cov[:3, :3] = ori.cov
    cov[3:, 3:] = org.cov
    ident = _identifiability(
        stack.jacobian(X[:3, :3], X[:3, 3], org.ball_centre_base, fit_radius=False),
        X[:3, :3],
        cond_soft,
    )
    _apply_check(ident, check, cond_soft, cond_hard)
    per, rms = stack.rms(r)
    return HandEyeResult(
        sensor2flange=X,
        ball_centre_base=org.ball_centre_base,
        ball_radius_m=R,
        cov=cov,
        per_sweep_rms=per,
        rms=rms,
        n_points=int(r.size),
        condition=ident.condition,
        method="two-step",
        inliers=inliers,
        advice=ident.advice if ident.condition > cond_soft else "",
    )


# --------------------------------------------------------------------------------------------
# Joint refinement


def _rows_times(A: FloatArray, M: FloatArray) -> FloatArray:
    """``A @ M`` for tall ``A`` (N, 3) and a 3x3 ``M``, as broadcast multiply-adds: BLAS is slow for
    such skinny products (and contends for the cores when it multi-threads)."""
    return A[:, :1] * M[0] + A[:, 1:2] * M[1] + A[:, 2:] * M[2]


@dataclass
class _Stack:
    """Points of several sweeps stacked with their flange pose, for vectorised residuals."""

    p: FloatArray  # (N, 3) sensor frame
    Rf: FloatArray  # (N, 3, 3) flange2base rotation of each point's profile
    Tf: FloatArray  # (N, 3)
    sweep: IntArray  # (N,) sweep number
    n_sweeps: int

    @classmethod
    def build(cls, sweeps: Sequence[Sweep], masks: Sequence[BoolArray] | None = None) -> _Stack:
        ps, Rs, Ts, ks = [], [], [], []
        for k, s in enumerate(sweeps):
            m = np.ones(s.n_points, bool) if masks is None else np.asarray(masks[k], bool)
            idx = s.pose_index[m]
            ps.append(s.points_sensor[m])
            Rs.append(s.flange2base[idx, :3, :3])
            Ts.append(s.flange2base[idx, :3, 3])
            ks.append(np.full(idx.shape, k, dtype=np.intp))
        return cls(
            np.concatenate(ps),
            np.concatenate(Rs),
            np.concatenate(Ts),
            np.concatenate(ks),
            len(sweeps),
        )

    def subset(self, mask: BoolArray) -> _Stack:
        return _Stack(self.p[mask], self.Rf[mask], self.Tf[mask], self.sweep[mask], self.n_sweeps)

    def to_base(self, Rsf: FloatArray, tsf: FloatArray) -> FloatArray:
        """Points in the base frame ``(N, 3)`` (m)."""
        pf = _rows_times(self.p, Rsf.T) + tsf
        return np.matmul(self.Rf, pf[:, :, None])[:, :, 0] + self.Tf

    def residuals(
        self, Rsf: FloatArray, tsf: FloatArray, c: FloatArray, radius: float
    ) -> FloatArray:
        w = self.to_base(Rsf, tsf) - c
        return np.sqrt(np.einsum("ni,ni->n", w, w)) - radius

    def normals(self, Rsf: FloatArray, tsf: FloatArray, c: FloatArray) -> FloatArray:
        """Unit vectors from the ball centre to each point, base frame ``(N, 3)``."""
        w = self.to_base(Rsf, tsf) - c
        return w / np.sqrt(np.einsum("ni,ni->n", w, w))[:, None]

    def jacobian(
        self,
        Rsf: FloatArray,
        tsf: FloatArray,
        c: FloatArray,
        fit_radius: bool,
        Jr: FloatArray | None = None,
    ) -> FloatArray:
        """d residual / d [w (sensor-axis rotation increment), t_sf, c, (radius)], ``(N, 9|10)``.

        With ``n`` the unit normal in base and ``m = R_f^T n``: d/dt = m, d/dc = -n and, for
        ``R_sf exp(w)``, d/dw = p x (R_sf^T m) (times the right Jacobian ``Jr`` away from w = 0)."""
        n = self.normals(Rsf, tsf, c)
        m_f = np.matmul(n[:, None, :], self.Rf)[:, 0, :]
        g = np.cross(self.p, _rows_times(m_f, Rsf))
        if Jr is not None:
            g = _rows_times(g, Jr)
        cols = [g, m_f, -n]
        if fit_radius:
            cols.append(-np.ones((n.shape[0], 1)))
        return np.concatenate(cols, axis=1)

    def rms(self, r: FloatArray) -> tuple[FloatArray, float]:
        cnt = np.bincount(self.sweep, minlength=self.n_sweeps).astype(np.float64)
        ss = np.bincount(self.sweep, weights=r**2, minlength=self.n_sweeps)
        with np.errstate(invalid="ignore", divide="ignore"):
            per = np.sqrt(ss / cnt)
        return per, float(np.sqrt(np.mean(r**2))) if r.size else float("nan")


def _identifiability(J: FloatArray, Rsf: FloatArray, soft: float = COND_SOFT) -> Identifiability:
    """Column-equilibrated condition number of ``J`` and advice from its weak directions.

    A direction is weak when its singular value is below ``s_max / soft`` (the smallest one always
    counts). Weak directions dominated by the rotation call for more FOV locations; those
    dominated by the sensor origin (confounded with the ball centre) call for tilts about the axes
    perpendicular to them, since a rotation about ``u`` leaves the origin along ``u`` unobserved.
    """
    norms = np.sqrt(np.einsum("ni,ni->i", J, J))
    norms[norms == 0.0] = 1.0
    Js = J / norms
    # Eigen-decomposition of the small normal matrix instead of an SVD of the tall Jacobian: the
    # condition numbers of interest (< 1e8) keep its eigenvalues well above rounding.
    lam, V = np.linalg.eigh(Js.T @ Js)
    lam, V = lam[::-1], V[:, ::-1]
    s = np.sqrt(np.clip(lam, 0.0, None))
    cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    weakest = V[:, -1] / norms
    weakest = weakest / np.linalg.norm(weakest)
    weak = [i for i in range(len(s)) if s[i] * soft < s[0]] or [len(s) - 1]
    rot_axes: list[str] = []
    trans_dirs: list[FloatArray] = []
    for i in weak:
        v = V[:, i]
        if float(np.sum(v[:3] ** 2)) >= float(np.sum(v[3:6] ** 2)):
            rot_axes.append(_AXES[int(np.argmax(np.abs(v[:3])))])
        else:
            u = Rsf.T @ v[3:6]
            trans_dirs.append(u / np.linalg.norm(u))
    parts: list[str] = []
    if trans_dirs:
        # Rank of the weak translation subspace: 1 -> one axis unobserved, >= 2 -> too few tilts.
        rank = int(np.linalg.matrix_rank(np.array(trans_dirs), tol=0.3))
        if rank >= 2:
            parts.append(
                "the sensor origin is unobserved in several directions: add orientations tilted "
                "about two different axes, e.g. the sensor X and Y axes (>= 45 deg between tool Z "
                "axes)"
            )
        else:
            i = int(np.argmax(np.abs(trans_dirs[0])))
            others = [a for j, a in enumerate(_AXES) if j != i]
            parts.append(
                f"the sensor origin along the sensor {_AXES[i]} axis is the least constrained: add "
                f"orientations tilted about the sensor {others[0]} or {others[1]} axis (>= 45 deg "
                "between tool Z axes)"
            )
    if rot_axes:
        axes = " and ".join(sorted(set(rot_axes)))
        parts.append(
            f"the rotation about the sensor {axes} axis is the least constrained: place the ball "
            "at more field-of-view locations, spread both along the laser line (sensor Y) and in "
            "depth (sensor Z)"
        )
    return Identifiability(cond, s, weakest, "; ".join(parts))


def _apply_check(ident: Identifiability, check: bool, soft: float, hard: float) -> None:
    if ident.condition > hard and check:
        raise PoorlyConstrained(
            f"sensor2flange is poorly constrained by these sweeps (condition {ident.condition:.3g} "
            f"> {hard:.3g})",
            ident.advice,
            ident.condition,
        )
    if ident.condition > soft:
        log.warning(
            "sensor2flange weakly constrained (condition %.3g > %.3g): %s",
            ident.condition,
            soft,
            ident.advice,
        )


def sphere_residuals(
    sweeps: Sequence[Sweep],
    sensor2flange: ArrayLike,
    ball_centre_base: ArrayLike,
    ball_radius: float,
) -> list[FloatArray]:
    """Signed distance (m) of every point to the ball surface, one array per sweep."""
    sw = list(sweeps)
    X = np.asarray(sensor2flange, dtype=np.float64)
    c = np.asarray(ball_centre_base, dtype=np.float64)
    return [np.linalg.norm(s.points_base(X) - c, axis=1) - float(ball_radius) for s in sw]


def check_identifiability(
    sweeps: Sequence[Sweep],
    sensor2flange: ArrayLike,
    ball_centre_base: ArrayLike,
    *,
    fit_radius: bool = False,
    masks: Sequence[BoolArray] | None = None,
    cond_soft: float = COND_SOFT,
) -> Identifiability:
    """Condition number and advice for the joint problem at a given solution (no exception).

    ``advice`` always names what would help most; it matters when ``condition > cond_soft``."""
    X = se3.check_transform(sensor2flange, "sensor2flange")
    stack = _Stack.build(_check_sweeps(sweeps, "sweeps"), masks)
    J = stack.jacobian(X[:3, :3], X[:3, 3], np.asarray(ball_centre_base, float), fit_radius)
    return _identifiability(J, X[:3, :3], cond_soft)


def _initial_fits(
    sweeps: Sequence[Sweep], X: FloatArray, radius: float | None, band_m: float
) -> tuple[list[BoolArray], FloatArray, float]:
    """Robust sphere fit of each sweep mapped to base with the initial guess: inlier masks (the
    post, table and stray points out), the median centre (m) and the median radius (m).

    A sweep whose fit fails (e.g. the post dominates it) takes the points within ``band_m`` of the
    ball predicted by the other sweeps; the refinement's residual thresholding then settles it."""
    pts = [s.points_base(X) for s in sweeps]
    masks: list[BoolArray | None] = []
    centres, radii = [], []
    for k, P in enumerate(pts):  # one robust fit per sweep; each fit is vectorised
        try:
            fit = sphere.fit_sphere(P, radius=radius, robust="tukey")
        except ValueError as exc:
            log.debug("initial sphere fit of sweep %d failed (%s); using the others", k, exc)
            masks.append(None)
            continue
        masks.append(np.asarray(fit.inliers, dtype=bool))
        centres.append(fit.centre)
        radii.append(fit.radius)
    if not centres:
        raise ValueError(
            "no sweep could be fitted with a sphere from the initial sensor2flange; pass a "
            "two_step() result or inlier masks"
        )
    c = np.median(np.array(centres), axis=0)
    r = float(np.median(radii))
    out = [
        m if m is not None else np.abs(np.linalg.norm(P - c, axis=1) - r) <= band_m
        for m, P in zip(masks, pts, strict=True)
    ]
    return out, c, r


def refine(
    sweeps: Sequence[Sweep],
    initial: HandEyeResult | ArrayLike,
    ball_radius: float | None,
    *,
    fit_radius: bool = False,
    masks: Sequence[BoolArray] | None = None,
    outlier_sigma: float = 4.0,
    min_threshold_m: float = 50e-6,
    max_rounds: int = 6,
    init_band_m: float = 2e-3,
    loss: str = "linear",
    robot_sigma_m: float = 0.0,
    check: bool = True,
    cond_soft: float = COND_SOFT,
    cond_hard: float = COND_HARD,
) -> HandEyeResult:
    """Joint least squares of sensor2flange (6 DOF) and the ball centre on all sweeps' points.

    Minimises ``sum_j (|| flange2base_j @ sensor2flange @ p_j - c || - R)^2`` over the inliers
    (scipy ``least_squares``, analytic Jacobian, rotation as a local rotation-vector increment about
    the sensor axes). Sweeps may have any motion (no constant-orientation assumption).

    Args:
        sweeps: all sweeps (FOV and tilted).
        initial: a :class:`HandEyeResult` (its ball centre and inliers are reused) or a ``(4, 4)``
            sensor2flange guess; then each sweep is mapped to base with it and robustly fitted
            (``calib.sphere.fit_sphere``) for its inlier mask, and the ball centre (and radius)
            start from the median of the fits.
        ball_radius: known radius (m). ``None`` estimates it (implies ``fit_radius``).
        fit_radius: estimate the radius, starting from ``ball_radius``.
        masks: initial inlier masks per sweep (default: ``initial.inliers`` or robust fits).
        outlier_sigma: after each round, points with ``|r| > max(outlier_sigma * sigma_robust,
            min_threshold_m)`` are excluded (``sigma_robust`` = 1.4826 MAD); repeated until the
            mask is stable or ``max_rounds``.
        init_band_m: distance (m) from the ball within which points of a sweep whose initial
            sphere fit failed are taken for the first round.
        loss: scipy robust loss (``"linear"``, ``"soft_l1"``, ``"huber"``, ``"cauchy"``); its
            scale is the robust sigma. The reported covariance always uses the plain
            Gauss-Newton form.
        robot_sigma_m: per-axis standard deviation (m) of a per-sweep error of the reported flange
            position (robot repeatability). It is propagated into ``cov`` (sandwich term), because
            it is shared by all points of a sweep and is not averaged away like sensor noise.
        check: raise :class:`PoorlyConstrained` when the condition number exceeds ``cond_hard``.

    Returns a :class:`HandEyeResult` with ``method="joint"``; ``cov = s^2 (J^T J)^-1`` (+ robot
    term) marginalised to the 6 sensor2flange parameters.
    """
    sw = _check_sweeps(sweeps, "sweeps")
    if not sw:
        raise ValueError("refine needs at least one sweep")
    if ball_radius is None:
        fit_radius = True
    if isinstance(initial, HandEyeResult):
        X0 = np.asarray(initial.sensor2flange, dtype=np.float64)
        c0 = np.asarray(initial.ball_centre_base, dtype=np.float64)
        r0 = float(initial.ball_radius_m) if ball_radius is None else _check_radius(ball_radius)
        if masks is None and len(initial.inliers) == len(sw):
            masks = initial.inliers
    else:
        X0 = se3.check_transform(np.asarray(initial, dtype=np.float64), "initial")
        c0 = None
        r0 = float("nan") if ball_radius is None else _check_radius(ball_radius)
    if masks is None or c0 is None:
        fit_masks, fit_c, fit_r = _initial_fits(
            sw, X0, None if ball_radius is None else r0, init_band_m
        )
        masks = fit_masks if masks is None else masks
        c0 = fit_c if c0 is None else c0
        r0 = fit_r if not np.isfinite(r0) else r0
    cur = [np.asarray(m, dtype=bool).copy() for m in masks]
    if len(cur) != len(sw):
        raise ValueError(f"masks: {len(cur)} arrays for {len(sw)} sweeps")
    for k, s in enumerate(sw):
        if cur[k].shape != (s.n_points,):
            raise ValueError(f"masks[{k}] has shape {cur[k].shape}, expected ({s.n_points},)")
    full = _Stack.build(sw)
    R_base = X0[:3, :3].copy()
    t = X0[:3, 3].copy()
    c = np.asarray(c0, dtype=np.float64).copy()
    radius = r0
    n_par = 10 if fit_radius else 9

    def unpack(x: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, float]:
        Rsf = R_base @ se3.rotvec_to_matrix(x[:3])
        return Rsf, x[3:6], x[6:9], (float(x[9]) if fit_radius else radius)

    mask_all = np.concatenate(cur)
    for _ in range(max_rounds):
        stack = full.subset(mask_all)
        if stack.p.shape[0] <= n_par:
            raise ValueError("too few inlier points for the joint refinement")
        # Each round re-linearises about the current rotation (w = 0 at the start).
        x0 = np.concatenate([np.zeros(3), t, c, [radius] if fit_radius else []])

        def fun(x: FloatArray, st: _Stack = stack) -> FloatArray:
            Rsf, tt, cc, rr = unpack(x)
            return st.residuals(Rsf, tt, cc, rr)

        def jac(x: FloatArray, st: _Stack = stack) -> FloatArray:
            Rsf, tt, cc, _ = unpack(x)
            return st.jacobian(Rsf, tt, cc, fit_radius, _right_jacobian(x[:3]))

        if loss == "linear":
            # MINPACK's QR on the tall Jacobian is several times faster than trf's SVD.
            sol = least_squares(fun, x0, jac=jac, method="lm", x_scale="jac",
                                xtol=1e-14, ftol=1e-14, gtol=1e-14)  # fmt: skip
        else:
            r_start = fun(x0)
            f_scale = max(1.4826 * float(np.median(np.abs(r_start - np.median(r_start)))), 1e-9)
            sol = least_squares(fun, x0, jac=jac, method="trf", loss=loss, f_scale=f_scale,
                                x_scale="jac", xtol=1e-14, ftol=1e-14, gtol=1e-14)  # fmt: skip
        R_base, t, c, radius = unpack(sol.x)
        # New inlier mask on all points from the robust scale of the current inliers.
        r_all = full.residuals(R_base, t, c, radius)
        r_in = r_all[mask_all]
        sig = 1.4826 * float(np.median(np.abs(r_in - np.median(r_in))))
        new_mask = np.abs(r_all) <= max(outlier_sigma * sig, min_threshold_m)
        if np.array_equal(new_mask, mask_all):
            break
        mask_all = new_mask

    stack = full.subset(mask_all)
    r = stack.residuals(R_base, t, c, radius)
    J = stack.jacobian(R_base, t, c, fit_radius)
    N = r.size
    s2 = float(np.sum(r**2)) / max(N - n_par, 1)
    H_inv = np.asarray(np.linalg.pinv(J.T @ J), dtype=np.float64)
    cov_full = s2 * H_inv
    if robot_sigma_m > 0.0:
        # A flange-position error e_k of sweep k shifts every residual of the sweep by n_j . e_k,
        # hence the parameters by -H^-1 G_k e_k with G_k = sum_j J_j^T n_j^T.
        n = stack.normals(R_base, t, c)
        G = np.stack(
            [
                np.stack(
                    [np.bincount(stack.sweep, J[:, a] * n[:, i], len(sw)) for i in range(3)], -1
                )
                for a in range(n_par)
            ],
            axis=1,
        )  # (sweeps, n_par, 3)
        B = np.einsum("kpi,kqi->pq", G, G)
        cov_full = cov_full + robot_sigma_m**2 * (H_inv @ B @ H_inv)
    ident = _identifiability(J, R_base, cond_soft)
    _apply_check(ident, check, cond_soft, cond_hard)
    per, rms = stack.rms(r)
    splits = np.cumsum([s.n_points for s in sw])[:-1]
    inliers = tuple(np.split(mask_all, splits))
    return HandEyeResult(
        sensor2flange=se3.make(R_base, t),
        ball_centre_base=np.asarray(c, dtype=np.float64),
        ball_radius_m=float(radius),
        cov=cov_full[:6, :6].copy(),
        per_sweep_rms=per,
        rms=rms,
        n_points=int(N),
        condition=ident.condition,
        method="joint",
        inliers=inliers,
        advice=ident.advice if ident.condition > cond_soft else "",
        cov_full=cov_full,
    )
