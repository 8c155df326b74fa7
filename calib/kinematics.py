"""Forward and inverse kinematics of Universal Robots arms (standard Denavit-Hartenberg).

Conventions
-----------
* Standard DH, one transform per joint ``i``: ``Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)`` with
  ``theta_i = q_i + theta_offset_i``. Joint ``i`` rotates about the z axis of frame ``i - 1``.
* Lengths in metres, angles in radians. ``forward`` returns ``flange2base``: it maps flange (tool0)
  coordinates into the robot base frame, exactly as the controller's ``actual_TCP_pose`` does with a
  zero TCP offset.
* Nominal parameters: Universal_Robots_ROS2_Description ``config/<model>/default_kinematics.yaml``
  and UR's article "DH parameters for calculations of kinematics" (table in PROTOCOLS.md). At
  ``q = 0`` the flange sits at ``(a2 + a3, -(d4 + d6), d1 - d5)``.

Per-robot calibration
---------------------
Every UR arm leaves the factory with its own DH corrections. The robot's ``calibration.conf``
holds *deltas* (``delta_theta, delta_a, delta_d, delta_alpha``) that the controller adds to the
nominal table; the primary interface's KinematicsInfo sub-package (ROBOT_STATE type 5) reports the
*sums* (nominal + delta, with theta carrying only the delta because nominal offsets are zero).
Use :func:`with_deltas` for the former and :func:`from_kinematics_info` for the latter
(both, with the nominal tables, in :mod:`wristscan.calib.dh` and importable from here). The raw
values can look odd (``d2``/``d3`` of hundreds of metres that cancel, theta offsets of ~1.6 rad on
joints 2-4, see Universal_Robots_ROS2_Driver ``ur_calibration/doc/algorithm.rst``); this module
evaluates them as they are; in float64 that costs ~1e-13 m of rounding at the flange.

Inverse kinematics
------------------
The closed form solution needs the ideal UR geometry (``alpha = [pi/2, 0, 0, pi/2, -pi/2, 0]``,
``a1 = a4 = a5 = a6 = 0``, ``d2 = d3 = 0``; theta offsets are allowed). For a calibrated model the
closed form runs on the ideal model that best fits its flange poses; each branch is re-solved on
targets corrected by the model discrepancy and then refined by a Levenberg-Marquardt fit of the
6-D pose error (scipy ``least_squares``). Either way every returned ``q`` maps back through
:func:`forward` to within :data:`IK_TOL_POS_M` / :data:`IK_TOL_ROT_RAD` of the target. Wrist
singularity (``sin q5 = 0``): joints 2, 3, 4 and 6 are parallel and a one-parameter family of
solutions exists; the one with the requested q6 is returned, never NaN.
"""

from __future__ import annotations

import functools
import logging
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from wristscan.calib import kinematics_small, se3
from wristscan.calib.dh import (
    UR_ALPHA,
    UR_MODELS,
    DHParams,
    from_kinematics_info,
    get_model,
    six_floats,
    with_deltas,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

logger = logging.getLogger(__name__)

__all__ = [
    "IK_TOL_POS_M",
    "IK_TOL_ROT_RAD",
    "JOINT_LIMIT_RAD",
    "UR_ALPHA",
    "UR_MODELS",
    "DHParams",
    "Unreachable",
    "forward",
    "forward_between",
    "from_kinematics_info",
    "get_model",
    "inverse",
    "inverse_nearest",
    "jacobian",
    "with_deltas",
    "wrap_angle",
]


IK_TOL_POS_M = 1e-9
"""Largest flange position error (m) of a solution returned by :func:`inverse`."""
IK_TOL_ROT_RAD = 1e-9
"""Largest flange rotation error (rad) of a solution returned by :func:`inverse`."""
JOINT_LIMIT_RAD = 2.0 * math.pi
"""UR joints turn +-2 pi (+-360 degrees)."""

# Analytic solutions better than this skip the numerical polish.
_POLISH_TOL = 1e-13
# Slack for acos/asin arguments that leave [-1, 1] by rounding only (at the workspace boundary).
_DOMAIN_SLACK = 1e-10
# Seeds for calibrated models: branch margin (rad, see _analytic); discrepancy corrections.
_SEED_MARGIN = 0.02
_SEED_ITERATIONS = 6
# A seed still this far off (m or rad) after the corrections is a branch the arm does not have
# for this pose; refining it would only burn iterations.
_SEED_GIVE_UP = 0.05
# |sin(theta5)| below this: wrist singular, joints 4 and 6 are coaxial and theta6 is free.
_WRIST_SINGULAR = 1e-12
# Two solutions closer than this (rad, every joint, modulo 2 pi) are the same solution.
_SAME_SOLUTION_RAD = 1e-7
_TWO_PI = 2.0 * math.pi


class Unreachable(ValueError):
    """No joint configuration puts the flange at the requested pose."""


def wrap_angle(angle_rad: ArrayLike) -> FloatArray:
    """Wrap angles (rad) into ``(-pi, pi]``."""
    x = np.asarray(angle_rad, dtype=np.float64)
    return np.asarray(np.pi - np.mod(np.pi - x, _TWO_PI), dtype=np.float64)


def _joint_array(q: ArrayLike, name: str = "q") -> FloatArray:
    qa = np.asarray(q, dtype=np.float64)
    if qa.ndim < 1 or qa.shape[-1] != 6:
        raise ValueError(f"{name}: expected joint angles of shape (..., 6) in rad, got {qa.shape}")
    return qa


def _chain(
    model: DHParams, q: FloatArray, keep_axes: bool
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, list[tuple[FloatArray, FloatArray]]]:
    """Accumulate the DH chain column-wise: x, y, z axes and origin t, each ``(..., 3)``.

    Right-multiplying by an elementary rotation only mixes two columns, so each joint costs a few
    vector operations over the whole batch instead of a stacked 4x4 matrix product.
    When ``keep_axes``, also returns (z, t) of frame i-1 for each joint i (for the Jacobian).
    """
    d, a, alpha, off = model.arrays()
    theta = q + off
    c = np.cos(theta)[..., None]
    s = np.sin(theta)[..., None]
    lead = q.shape[:-1]
    x: FloatArray = np.broadcast_to(np.array([1.0, 0.0, 0.0]), (*lead, 3))
    y: FloatArray = np.broadcast_to(np.array([0.0, 1.0, 0.0]), (*lead, 3))
    z: FloatArray = np.broadcast_to(np.array([0.0, 0.0, 1.0]), (*lead, 3))
    t: FloatArray = np.zeros((*lead, 3))
    axes: list[tuple[FloatArray, FloatArray]] = []
    for i in range(6):
        if keep_axes:
            axes.append((z, t))
        ci, si = c[..., i, :], s[..., i, :]
        x_new = ci * x + si * y
        y = ci * y - si * x
        x = x_new
        t = t + d[i] * z + a[i] * x
        ca, sa = math.cos(alpha[i]), math.sin(alpha[i])
        if sa != 0.0:
            y, z = ca * y + sa * z, ca * z - sa * y
    return x, y, z, t, axes


def forward(model: str | DHParams, q: ArrayLike) -> FloatArray:
    """Forward kinematics: joint angles ``q`` ``(..., 6)`` (rad) to ``flange2base`` ``(..., 4, 4)``.

    Vectorised over any leading batch shape. NaN joint rows give NaN transforms (no error), so
    batches with gaps stay aligned. Small batches (the pairer's, per tick) are computed pose by
    pose compiled, or as products of the DH matrices without numba
    (:mod:`wristscan.calib.kinematics_small`), large ones column by column: all agree to
    rounding (~1e-16).
    """
    m = get_model(model)
    qa = _joint_array(q)
    if qa.size <= 6 * kinematics_small.MATMUL_MAX:
        return kinematics_small.forward_small(m, qa)
    x, y, z, t, _ = _chain(m, qa, keep_axes=False)
    out = np.empty((*qa.shape[:-1], 4, 4))
    out[..., :3, 0] = x
    out[..., :3, 1] = y
    out[..., :3, 2] = z
    out[..., :3, 3] = t
    out[..., 3, :] = (0.0, 0.0, 0.0, 1.0)
    return out


def forward_between(
    model: str | DHParams, samples: FloatArray, rows: IntArray, frac: FloatArray
) -> FloatArray:
    """:func:`forward` at the joints interpolated between samples: ``q = samples[rows, :6] +
    (samples[rows + 1, :6] - samples[rows, :6]) * frac[:, None]`` (``samples`` (n, >= 6) rad,
    ``rows`` (M,), ``frac`` (M,)); ``(M, 4, 4)``. One compiled call for the pairer's batches
    (the same bits as interpolating, then :func:`forward`)."""
    m = get_model(model)
    out = kinematics_small.between_small(m, samples, rows, frac)
    if out is not None:
        return out
    q0 = samples[rows, :6]
    return forward(m, q0 + (samples[rows + 1, :6] - q0) * frac[:, None])


def jacobian(model: str | DHParams, q: ArrayLike) -> FloatArray:
    """Geometric Jacobian in the base frame, ``(..., 6, 6)``: rows ``[v (m/s); omega (rad/s)]``.

    ``[v; omega] = J @ dq/dt`` where ``v`` is the velocity of the flange origin and ``omega`` the
    angular velocity, both in base coordinates. Vectorised like :func:`forward`.
    """
    m = get_model(model)
    qa = _joint_array(q)
    _, _, _, p_end, axes = _chain(m, qa, keep_axes=True)
    J = np.empty((*qa.shape[:-1], 6, 6))
    for i, (zi, ti) in enumerate(axes):
        J[..., :3, i] = np.cross(zi, p_end - ti)
        J[..., 3:, i] = zi
    return J


# ---------------------------------------------------------------------------------------------
# Inverse kinematics


def _is_ideal(model: DHParams, tol: float = 1e-12) -> bool:
    """True when the closed-form solution applies exactly (theta offsets may be anything)."""
    d, a, alpha, _ = model.arrays()
    return bool(
        np.all(np.abs(alpha - np.array(UR_ALPHA)) <= tol)
        and np.all(np.abs(a[[0, 3, 4, 5]]) <= tol)
        and np.all(np.abs(d[[1, 2]]) <= tol)
    )


def _ideal(params: FloatArray, name: str) -> DHParams:
    """Ideal-geometry model from ``[d1, a2, a3, d4, d5, d6, offset1..6]``."""
    d1, a2, a3, d4, d5, d6 = (float(v) for v in params[:6])
    return DHParams(
        name=name,
        d=(d1, 0.0, 0.0, d4, d5, d6),
        a=(0.0, a2, a3, 0.0, 0.0, 0.0),
        alpha=UR_ALPHA,
        theta_offset=six_floats(params[6:], "theta_offset"),
    )


@functools.lru_cache(maxsize=64)
def _ideal_approximation(model: DHParams) -> DHParams:
    """The ideal UR-geometry model whose flange poses best match ``model`` (seeds the IK).

    Fitted on flange poses rather than derived from the parameters, because calibrated parameters
    can differ from the nominal ones by metres while describing nearly the same arm.
    """
    if _is_ideal(model):
        return model
    rng = np.random.default_rng(20090101)
    q_fit = rng.uniform(-np.pi, np.pi, size=(48, 6))
    target = forward(model, q_fit)[..., :3, :]

    def residual(p: FloatArray) -> FloatArray:
        # Rotation entries enter unscaled: 1 rad of error weighs like 1 m at the flange.
        return np.asarray((forward(_ideal(p, "fit"), q_fit)[..., :3, :] - target).ravel())

    d, a, _, off = model.arrays()
    starts = [np.concatenate([[d[0], a[1], a[2], d[1] + d[2] + d[3], d[4], d[5]], off])]
    for nominal in UR_MODELS.values():
        nd, na, _, _ = nominal.arrays()
        starts.append(np.concatenate([[nd[0], na[1], na[2], nd[3], nd[4], nd[5]], np.zeros(6)]))
    best = min(starts, key=lambda p: float(np.sum(residual(p) ** 2)))
    from scipy.optimize import least_squares  # here: 0.4 s at every process start otherwise

    fit = least_squares(residual, best, method="lm", xtol=1e-12, ftol=1e-12)
    rms = float(np.sqrt(np.mean(fit.fun**2)))
    if rms > 0.05:
        logger.warning(
            "model %s is far from a UR geometry (ideal fit rms %.3g); inverse kinematics may miss "
            "solutions",
            model.name,
            rms,
        )
    else:
        logger.debug("ideal UR approximation of %s: rms %.3g", model.name, rms)
    return _ideal(np.asarray(fit.x, dtype=np.float64), f"{model.name}~ideal")


def _dh_transforms(theta: FloatArray, d: float, a: float, alpha: float) -> FloatArray:
    """One joint's DH transforms for a batch of angles ``theta`` ``(n,)``: ``(n, 4, 4)``."""
    c, s = np.cos(theta), np.sin(theta)
    ca, sa = math.cos(alpha), math.sin(alpha)
    T = np.zeros((theta.shape[0], 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2], T[:, 0, 3] = c, -s * ca, s * sa, a * c
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2], T[:, 1, 3] = s, c * ca, -c * sa, a * s
    T[:, 2, 1], T[:, 2, 2], T[:, 2, 3] = sa, ca, d
    T[:, 3, 3] = 1.0
    return T


def _analytic(
    model: DHParams,
    T: FloatArray,
    free_theta6: float,
    seeding: bool = False,
    branch_margin: float = 0.0,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Closed-form IK of an ideal UR model: joint angles ``(8, 6)`` and a validity mask ``(8,)``.

    ``T`` is one target ``(4, 4)`` or one per branch ``(8, 4, 4)``.

    Branch index = 4*shoulder + 2*wrist + elbow (two choices each). Works on DH angles theta;
    offsets are removed at the end. Arguments of asin/acos that overshoot by rounding only are
    clipped; the caller checks every candidate with forward() anyway.

    ``seeding``: the model only approximates the real arm, so nothing is rejected (out-of-range
    arguments are clipped). ``branch_margin`` (rad) keeps the two elbow branches (and the two
    shoulder branches) apart, so that near a stretched or folded elbow each refines to its own
    solution instead of both collapsing onto one.
    """
    d, a, alpha, off = model.arrays()
    d1, a2, a3, d4, d6 = d[0], a[1], a[2], d[3], d[5]
    R, p = T[..., :3, :3], T[..., :3, 3]
    X, Y, Z = R[..., :, 0], R[..., :, 1], R[..., :, 2]
    slack = math.inf if seeding else _DOMAIN_SLACK
    shoulder = np.repeat([1.0, -1.0], 4)
    wrist = np.tile(np.repeat([1.0, -1.0], 2), 2)
    elbow = np.tile([1.0, -1.0], 4)

    # Shoulder: the wrist centre p5 lies at distance d4 from the arm plane, along z1.
    p5 = p - d6 * Z
    r = np.hypot(p5[..., 0], p5[..., 1])
    phi = np.arctan2(p5[..., 1], p5[..., 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(r > 0.0, d4 / r, 0.0 if d4 == 0.0 else math.copysign(math.inf, d4))
    ok = np.broadcast_to(np.abs(ratio) <= 1.0 + slack, (8,))
    beta = np.arcsin(np.clip(ratio, -1.0, 1.0))
    if branch_margin > 0.0:
        # Same for the two shoulder branches, which merge when the wrist centre is at distance
        # |d4| from axis 1.
        beta = np.clip(beta, branch_margin - math.pi / 2, math.pi / 2 - branch_margin)
    th1 = np.where(shoulder > 0.0, phi + beta, phi + math.pi - beta)

    s1, c1 = np.sin(th1), np.cos(th1)
    # z1 = (s1, -c1, 0): the common axis of joints 2, 3, 4. In flange coordinates it reads
    # (s5 c6, -s5 s6, c5), which gives theta5 and theta6 without dividing by s5.
    xz = X[..., 0] * s1 - X[..., 1] * c1
    yz = Y[..., 0] * s1 - Y[..., 1] * c1
    zz = Z[..., 0] * s1 - Z[..., 1] * c1
    s5 = wrist * np.hypot(xz, yz)
    th5 = np.arctan2(s5, zz)
    singular = np.abs(s5) < _WRIST_SINGULAR
    th6 = np.where(singular, free_theta6, np.arctan2(-yz * wrist, xz * wrist))

    # Frame 4 seen from frame 1: planar 3R chain of joints 2, 3, 4.
    T01 = _dh_transforms(th1, d1, 0.0, alpha[0])
    T46 = _dh_transforms(th5, d[4], 0.0, alpha[4]) @ _dh_transforms(th6, d6, 0.0, alpha[5])
    T14 = se3.invert(T01) @ T @ se3.invert(T46)
    px, py = T14[:, 0, 3], T14[:, 1, 3]
    th234 = np.arctan2(T14[:, 1, 0], T14[:, 0, 0])
    c3 = (px * px + py * py - a2 * a2 - a3 * a3) / (2.0 * a2 * a3)
    ok = ok & (np.abs(c3) <= 1.0 + slack)
    th3 = np.arccos(np.clip(c3, -1.0, 1.0))
    if branch_margin > 0.0:
        th3 = np.clip(th3, branch_margin, math.pi - branch_margin)
    th3 = elbow * th3
    th2 = np.arctan2(py, px) - np.arctan2(a3 * np.sin(th3), a2 + a3 * np.cos(th3))
    th4 = th234 - th2 - th3
    theta = np.stack([th1, th2, th3, th4, th5, th6], axis=-1)
    return wrap_angle(theta - off), ok


def _seeds(model: DHParams, ideal: DHParams, T: FloatArray, free_theta6: float) -> FloatArray:
    """Eight starting points for refining the IK of a calibrated ``model``, one per branch.

    The ideal model misses the real arm by millimetres, enough to put a branch on the wrong side
    of an elbow or wrist singularity. Each branch is therefore re-solved a few times on a target
    corrected by that branch's own model discrepancy D = ideal(q)^-1 model(q) (flange side):
    solving ideal(q) = T D^-1 converges towards model(q) = T within the branch.
    """
    q, _ = _analytic(ideal, T, free_theta6, seeding=True, branch_margin=_SEED_MARGIN)
    best = q
    best_err = np.full(8, np.inf)
    for i in range(_SEED_ITERATIONS + 1):
        F = forward(model, q)
        pos, rot = _pose_errors(model, q, T, F)
        err = pos + rot  # 1 rad weighs like 1 m
        better = err < best_err
        best = np.where(better[:, None], q, best)
        best_err = np.where(better, err, best_err)
        if i == _SEED_ITERATIONS:
            break
        # Near a wrist singularity this iteration can diverge; the best iterate is kept.
        corrected = T @ se3.invert(F) @ forward(ideal, q)
        q, _ = _analytic(ideal, corrected, free_theta6, seeding=True)
    return best


def _pose_errors(
    model: DHParams, q: FloatArray, T: FloatArray, F: FloatArray | None = None
) -> tuple[FloatArray, FloatArray]:
    """Position (m) and rotation (rad) errors of ``forward(q)`` (or ``F``) against target ``T``."""
    if F is None:
        F = forward(model, q)
    pos = np.linalg.norm(F[:, :3, 3] - T[:3, 3], axis=-1)
    rot = se3.rotation_angle(F[:, :3, :3] @ T[:3, :3].T)
    return pos, rot


def _inv_left_jacobian_so3(phi: FloatArray) -> FloatArray:
    """Inverse left Jacobian of SO(3) at rotation vector ``phi``: maps a small left (spatial)
    rotation increment to the increment of ``phi``."""
    th = float(np.linalg.norm(phi))
    P = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    if th < 1e-6:
        coef = 1.0 / 12.0 + th * th / 720.0
    else:
        coef = 1.0 / (th * th) - (1.0 + math.cos(th)) / (2.0 * th * math.sin(th))
    return np.asarray(np.eye(3) - 0.5 * P + coef * (P @ P), dtype=np.float64)


def _refine(model: DHParams, T: FloatArray, q0: FloatArray) -> FloatArray:
    """Levenberg-Marquardt on the 6-D pose error from seed ``q0``; returns the final ``q``."""
    p_t, R_t = T[:3, 3], T[:3, :3]

    def pose_error(q: FloatArray) -> tuple[FloatArray, FloatArray]:
        F = forward(model, q)
        phi = Rotation.from_matrix(F[:3, :3] @ R_t.T).as_rotvec()
        return np.concatenate([F[:3, 3] - p_t, phi]), phi

    def fun(q: FloatArray) -> FloatArray:
        return pose_error(q)[0]

    def jac(q: FloatArray) -> FloatArray:
        J = jacobian(model, q)
        _, phi = pose_error(q)
        J[3:, :] = _inv_left_jacobian_so3(phi) @ J[3:, :]
        return J

    from scipy.optimize import least_squares  # as in _ideal_approximation

    # Seeds are close (or belong to a branch that does not exist): cap the work on hopeless ones.
    res = least_squares(
        fun, q0, jac=jac, method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-15, max_nfev=60
    )
    return np.asarray(res.x, dtype=np.float64)


def _unique(q: FloatArray) -> FloatArray:
    """Drop solutions equal (modulo 2 pi, every joint) to an earlier one; keeps order."""
    keep: list[int] = []
    for i in range(q.shape[0]):
        if not any(np.all(np.abs(wrap_angle(q[i] - q[j])) < _SAME_SOLUTION_RAD) for j in keep):
            keep.append(i)
    return q[keep]


def _target(flange2base: ArrayLike) -> FloatArray:
    T = se3.check_transform(flange2base, "flange2base")
    if T.shape != (4, 4):
        raise ValueError(f"flange2base: expected one (4, 4) transform, got shape {T.shape}")
    # Project onto SO(3): a target that is orthonormal only to 1e-7 could not be matched to 1e-9.
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T = T.copy()
    T[:3, :3] = U @ Vt
    return T


def _solve_refined(model: DHParams, T: FloatArray, seeds: FloatArray) -> FloatArray:
    """Refine each seed ``(k, 6)`` where needed; rows that do not reach the target become NaN."""
    pos, rot = _pose_errors(model, seeds, T)
    out = np.full_like(seeds, np.nan)
    for i, q in enumerate(seeds):
        if pos[i] <= _POLISH_TOL and rot[i] <= _POLISH_TOL:
            out[i] = q
        elif pos[i] < _SEED_GIVE_UP and rot[i] < _SEED_GIVE_UP:
            out[i] = _refine(model, T, q)
    out = wrap_angle(out)
    done = np.all(np.isfinite(out), axis=-1)
    pos, rot = _pose_errors(model, np.where(done[:, None], out, 0.0), T)
    good = done & (pos <= IK_TOL_POS_M) & (rot <= IK_TOL_ROT_RAD)
    out[~good] = np.nan
    return out


def _inverse(
    m: DHParams, T: FloatArray, wrist_q6: float, extra_seeds: FloatArray | None = None
) -> FloatArray:
    ideal = _ideal_approximation(m)
    free_theta6 = wrist_q6 + ideal.theta_offset[5]
    if ideal is m:
        candidates, ok = _analytic(m, T, free_theta6)
        sols = _solve_refined(m, T, candidates[ok])
    else:
        sols = _solve_refined(m, T, _seeds(m, ideal, T, free_theta6))
    if extra_seeds is not None and extra_seeds.shape[0] > 0:
        sols = np.concatenate([_solve_refined(m, T, extra_seeds), sols])
    return _unique(sols[np.all(np.isfinite(sols), axis=-1)])


def inverse(model: str | DHParams, flange2base: ArrayLike, *, wrist_q6: float = 0.0) -> FloatArray:
    """All joint solutions ``(k, 6)`` (rad, wrapped to ``(-pi, pi]``) for one flange pose.

    ``k <= 8`` (shoulder left/right x wrist up/down x elbow up/down); ``k == 0`` when the pose is
    out of reach. Each returned row maps back through :func:`forward` to within
    :data:`IK_TOL_POS_M` and :data:`IK_TOL_ROT_RAD`. At a wrist singularity (joints 4 and 6
    coaxial) any q6 works; ``wrist_q6`` (rad) is the one used.

    For a calibrated model (see the module notes) the list is complete away from singularities.
    Close to one (within a few hundredths of a radian of ``sin q5 = 0``; elbow stretched or
    folded; wrist centre at distance ``|d4|`` from axis 1) its solutions come in close pairs that
    the branch seeds may not all find. Every returned row is still exact, and
    :func:`inverse_nearest` also starts from its seed, so tracking a path through such a region
    works.
    """
    m = get_model(model)
    T = _target(flange2base)
    return _inverse(m, T, float(wrist_q6))


def _nearest_equivalent(q: FloatArray, seed: FloatArray) -> FloatArray:
    """Per joint, the 2-pi equivalent of ``q`` (..., 6) nearest to ``seed`` within +-2 pi."""
    shifts = np.array([-_TWO_PI, 0.0, _TWO_PI])
    cand = wrap_angle(q)[..., None] + shifts  # (..., 6, 3) spans (-3 pi, 3 pi]
    dist = np.abs(cand - seed[..., None])
    dist = np.where(np.abs(cand) <= JOINT_LIMIT_RAD, dist, np.inf)
    pick = np.argmin(dist, axis=-1)
    return np.take_along_axis(cand, pick[..., None], axis=-1)[..., 0]


def inverse_nearest(model: str | DHParams, flange2base: ArrayLike, seed: ArrayLike) -> FloatArray:
    """The IK solution ``(6,)`` (rad) nearest to ``seed`` (Euclidean in joint space).

    Each joint is returned as the 2-pi equivalent closest to the seed within the UR joint range
    +-2 pi, so a seed of 6.0 rad yields about 6.0 rather than -0.28. At a wrist singularity q6 is
    taken from the seed. Raises :class:`Unreachable` when no solution exists.
    """
    m = get_model(model)
    s = _joint_array(seed, "seed")
    if s.shape != (6,):
        raise ValueError(f"seed: expected shape (6,), got {s.shape}")
    if not np.all(np.isfinite(s)):
        raise ValueError("seed: contains NaN or infinity")
    T = _target(flange2base)
    # A calibrated model is also refined from the seed itself: when the seed is close (tracking a
    # path), that finds the solution the arm is on even where the branch seeds are poor.
    extra = None if _ideal_approximation(m) is m else s[None, :]
    sols = _inverse(m, T, float(wrap_angle(s[5])), extra)
    if sols.shape[0] == 0:
        raise Unreachable(
            f"{m.name}: flange pose at {np.round(T[:3, 3], 4).tolist()} m is out of reach"
        )
    near = _nearest_equivalent(sols, s)
    return np.asarray(near[np.argmin(np.sum((near - s) ** 2, axis=-1))], dtype=np.float64)
