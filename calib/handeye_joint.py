"""The joint refinement of :func:`wristscan.calib.handeye.refine`, step by step: where it
starts (robust sphere fits of each sweep mapped with the initial guess, unless a previous result
gives the ball and the inliers), rounds of least squares on the inliers of all sweeps with a new
inlier mask after each, and the covariance of the result (Gauss-Newton, plus the robot's
repeatability shared by all points of a sweep).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from wristscan.calib import handeye_uncertainty as uncertainty
from wristscan.calib import se3, sphere
from wristscan.calib.handeye_model import (
    HandEyeResult,
    Identifiability,
    Sweep,
    check_radius,
    rows_times,
)
from wristscan.calib.handeye_points import PointStack, identifiability, right_jacobian

__all__ = ["initial_fits", "joint_result", "rounds", "start"]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


def initial_fits(
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


def start(
    sw: Sequence[Sweep],
    initial: HandEyeResult | ArrayLike,
    ball_radius: float | None,
    masks: Sequence[BoolArray] | None,
    init_band_m: float,
) -> tuple[FloatArray, FloatArray, float, list[BoolArray]]:
    """Where :func:`refine` starts: sensor2flange, ball centre (m), radius (m, NaN when unknown
    and not fitted) and the inlier mask of each sweep (checked against the sweeps)."""
    if isinstance(initial, HandEyeResult):
        X0 = np.asarray(initial.sensor2flange, dtype=np.float64)
        c0 = np.asarray(initial.ball_centre_base, dtype=np.float64)
        r0 = float(initial.ball_radius_m) if ball_radius is None else check_radius(ball_radius)
        if masks is None and len(initial.inliers) == len(sw):
            masks = initial.inliers
    else:
        X0 = se3.check_transform(np.asarray(initial, dtype=np.float64), "initial")
        c0 = None
        r0 = float("nan") if ball_radius is None else check_radius(ball_radius)
    if masks is None or c0 is None:
        fit_masks, fit_c, fit_r = initial_fits(
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
    return X0, np.asarray(c0, dtype=np.float64).copy(), r0, cur


def rounds(
    full: PointStack,
    X0: FloatArray,
    c: FloatArray,
    radius: float,
    mask_all: BoolArray,
    fit_radius: bool,
    loss: str,
    outliers: tuple[float, float, int],
) -> tuple[FloatArray, FloatArray, FloatArray, float, BoolArray]:
    """Rounds of least squares on the inliers, each followed by a new inlier mask on all points
    from the robust scale of the current inliers, until the mask is stable or after
    ``max_rounds``; ``outliers`` = (outlier_sigma, min_threshold_m, max_rounds). Returns the
    rotation, the sensor origin, the ball centre, the radius and the inlier mask."""
    outlier_sigma, min_threshold_m, max_rounds = outliers
    R_base = X0[:3, :3].copy()
    t = X0[:3, 3].copy()
    n_par = 10 if fit_radius else 9
    for _ in range(max_rounds):
        stack = full.subset(mask_all)
        if stack.p.shape[0] <= n_par:
            raise ValueError("too few inlier points for the joint refinement")
        R_base, t, c, radius = _solve_round(stack, R_base, t, c, radius, fit_radius, loss)
        # New inlier mask on all points from the robust scale of the current inliers, about each
        # sweep's own offset: the robot's error shifts a whole sweep, which is no outlier.
        dev = _about_sweep_offsets(full, R_base, t, c, radius, mask_all)
        d_in = dev[mask_all]
        sig = 1.4826 * float(np.median(np.abs(d_in - np.median(d_in))))
        new_mask = np.abs(dev) <= max(outlier_sigma * sig, min_threshold_m)
        if np.array_equal(new_mask, mask_all):
            break
        mask_all = new_mask
    return R_base, t, c, radius, mask_all


def _about_sweep_offsets(
    full: PointStack,
    R_base: FloatArray,
    t: FloatArray,
    c: FloatArray,
    radius: float,
    mask: BoolArray,
) -> FloatArray:
    """Residuals of all points less their sweep's best offset ``n . d_k`` (least squares on the
    inliers ``mask``): what is left once each sweep's flange error is allowed for."""
    w_c = full.to_base(R_base, t) - c
    dist = np.sqrt(np.einsum("ni,ni->n", w_c, w_c))
    r, n = dist - radius, w_c / dist[:, None]
    K = full.n_sweeps
    w = mask.astype(np.float64)
    M = np.empty((K, 3, 3))
    b = np.empty((K, 3))
    for i in range(3):
        b[:, i] = np.bincount(full.sweep, w * n[:, i] * r, K)
        for j in range(i, 3):
            M[:, i, j] = M[:, j, i] = np.bincount(full.sweep, w * n[:, i] * n[:, j], K)
    d = np.einsum("kij,kj->ki", np.linalg.pinv(M, rcond=1e-6, hermitian=True), b)
    return np.asarray(r - np.einsum("ni,ni->n", n, d[full.sweep]), dtype=np.float64)


def _solve_round(
    stack: PointStack,
    R_base: FloatArray,
    t: FloatArray,
    c: FloatArray,
    radius: float,
    fit_radius: bool,
    loss: str,
) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """One least-squares solve on the points of ``stack``, linearised about ``R_base`` (w = 0 at
    the start): the rotation, the sensor origin, the ball centre and the radius."""

    def unpack(x: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, float]:
        Rsf = R_base @ se3.rotvec_to_matrix(x[:3])
        return Rsf, x[3:6], x[6:9], (float(x[9]) if fit_radius else radius)

    x0 = np.concatenate([np.zeros(3), t, c, [radius] if fit_radius else []])

    def fun(x: FloatArray) -> FloatArray:
        Rsf, tt, cc, rr = unpack(x)
        return stack.residuals(Rsf, tt, cc, rr)

    def jac(x: FloatArray) -> FloatArray:
        Rsf, tt, cc, _ = unpack(x)
        return stack.jacobian(Rsf, tt, cc, fit_radius, right_jacobian(x[:3]))

    if loss == "linear":
        # MINPACK's QR on the tall Jacobian is several times faster than trf's SVD.
        sol = least_squares(fun, x0, jac=jac, method="lm", x_scale="jac",
                            xtol=1e-14, ftol=1e-14, gtol=1e-14)  # fmt: skip
    else:
        r_start = fun(x0)
        f_scale = max(1.4826 * float(np.median(np.abs(r_start - np.median(r_start)))), 1e-9)
        sol = least_squares(fun, x0, jac=jac, method="trf", loss=loss, f_scale=f_scale,
                            x_scale="jac", xtol=1e-14, ftol=1e-14, gtol=1e-14)  # fmt: skip
    return unpack(sol.x)


def joint_result(
    sw: Sequence[Sweep],
    stack: PointStack,
    mask_all: BoolArray,
    solution: tuple[FloatArray, FloatArray, FloatArray, float],
    fit_radius: bool,
    robot_sigma_m: float,
    cond_soft: float,
    *,
    robot_model: bool = False,
    clusters: ArrayLike | None = None,
    working_volume: tuple[tuple[float, float], tuple[float, float]] | None = None,
) -> tuple[HandEyeResult, Identifiability]:
    """The joint result on the inliers ``stack``: its covariance, residuals, and the
    identifiability of the problem (its advice in the result above ``cond_soft``).

    ``robot_model``: the covariance of :mod:`~wristscan.calib.handeye_uncertainty` (sensor noise,
    per-sweep and per-pose-cluster robot error estimated from the residuals, the per-sweep part
    at least ``robot_sigma_m``); otherwise ``s^2 (J^T J)^-1`` plus ``robot_sigma_m`` per sweep
    (see :func:`~wristscan.calib.handeye.refine`)."""
    R_base, t, c, radius = solution
    r = stack.residuals(R_base, t, c, radius)
    J = stack.jacobian(R_base, t, c, fit_radius)
    n = stack.normals(R_base, t, c)
    cl = (
        uncertainty.pose_clusters(sw)
        if clusters is None
        else np.asarray(clusters, dtype=np.intp).copy()
    )
    if cl.shape != (len(sw),):
        raise ValueError(f"clusters: expected ({len(sw)},) cluster numbers, got {cl.shape}")
    cl = np.unique(cl, return_inverse=True)[1].astype(np.intp)
    p_f = rows_times(stack.p, R_base.T) + t
    m_f = np.matmul(n[:, None, :], stack.Rf)[:, 0, :]
    rot = uncertainty.rotation_rows(p_f, m_f)
    design = uncertainty.design(J, r, n, stack.sweep, cl, rot)
    if robot_model:
        vc = uncertainty.components(design, r, cl, robot_sigma_m)
    else:
        N, n_par = r.size, J.shape[1]
        s = float(np.sqrt(np.sum(r**2) / max(N - n_par, 1)))
        vc = uncertainty.VarianceComponents(s, robot_sigma_m, float("nan"), 0.0, cl)
    cov_full = uncertainty.covariance(design, vc)
    ident = identifiability(J, R_base, cond_soft)
    per, rms = stack.rms(r)
    splits = np.cumsum([s.n_points for s in sw])[:-1]
    inliers = tuple(np.split(mask_all, splits))
    if working_volume is None:
        lo, hi = stack.p.min(axis=0), stack.p.max(axis=0)
        working_volume = ((float(lo[1]), float(hi[1])), (float(lo[2]), float(hi[2])))
    X = se3.make(R_base, t)
    p_rms, p_max = uncertainty.point_error(cov_full[:6, :6], X, *working_volume)
    result = HandEyeResult(
        sensor2flange=X,
        ball_centre_base=np.asarray(c, dtype=np.float64),
        ball_radius_m=float(radius),
        cov=cov_full[:6, :6].copy(),
        per_sweep_rms=per,
        rms=rms,
        n_points=int(r.size),
        condition=ident.condition,
        method="joint",
        inliers=inliers,
        advice=ident.advice if ident.condition > cond_soft else "",
        cov_full=cov_full,
        components=vc,
        point_sigma_m=p_max,
        point_sigma_rms_m=p_rms,
        working_volume_m=working_volume,
    )
    return result, ident
