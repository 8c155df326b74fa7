"""The arm's systematic kinematic error in the uncertainty of the joint hand-eye solution.

A controller computes its flange poses with a kinematic model (the nominal DH table, or its factory
calibration) that differs from the arm by a few hundredths of a millimetre and of a degree per
parameter. That error is a smooth function of the joints; over one calibration's poses part of it
moves every sweep alike (a wrong last link length entirely so, along the tool axis) and is then
indistinguishable from a change of sensor2flange: the residuals cannot show it, so no estimate
from them (:mod:`~wristscan.calib.handeye_uncertainty`) covers it. It enters the covariance as a
*prior*: the 1-sigma of each DH parameter left after the arm's calibration (:func:`prior_sigma`),
propagated through the solver::

    e_k = -G_k dDH                  error of sweep k's reported flange (twist [w, v], flange
                                    frame) when the arm is the model + dDH,
                                    G_k = d log(F_k^-1 F_k(DH + dDH)) / d dDH at the sweep's joints
    dr_j = z_j . e_k(j)             z_j = [p_f x m_f, m_f] (point and ball normal, flange frame)
    dX = -H^-1 J^T dr = A dDH       A = H^-1 sum_k (sum_{j in k} J_j^T z_j) G_k
    Sigma_sys = A Sigma_DH A^T      added to the joint solution's covariance

``Sigma_sys`` is correlated across all poses (one arm, one error), unlike the random effects per
sweep and per pose cluster. The part of a DH error that varies from pose to pose also shows in the
residuals and is estimated there as well; counting it twice is small next to the invisible common
part (docs/calibration.md, "Benchmark: honest uncertainty with a realistic robot").

The joints of each sweep are taken at its middle pose: given (``KinematicPrior.joints``) or found
by the arm model's inverse kinematics nearest to ``KinematicPrior.seed`` (the arm's usual
configuration; the branch matters, since ``G`` depends on it).

Parameter order of a DH vector here: ``theta_1..6, a_1..6, d_1..6, alpha_1..6`` (rad, m, m, rad).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import handeye_uncertainty as uncertainty
from wristscan.calib import kinematics, se3
from wristscan.calib.dh import DHParams, get_model
from wristscan.calib.handeye_model import HandEyeResult, Sweep
from wristscan.calib.handeye_points import PointStack
from wristscan.calib.kinematic_errors import (
    DEFAULT_RESIDUAL,
    FACTORY_CALIBRATIONS,
    REALISTIC,
    KinematicErrorSizes,
)

__all__ = [
    "Q_USUAL",
    "KinematicPrior",
    "common_part",
    "flange_sensitivity",
    "prior_sigma",
    "sensitivity",
    "sweep_joints",
    "systematic_cov",
    "with_kinematic_prior",
]

FloatArray = NDArray[np.float64]

#: A UR arm's usual configuration (elbow up, wrist down): the IK branch taken by default.
Q_USUAL = np.array([0.0, -1.9, 1.9, -1.57, -1.57, 0.0])

#: Central-difference steps of the DH parameters (rad for theta/alpha, m for a/d).
_STEP = (1e-6, 1e-6, 1e-6, 1e-6)


def prior_sigma(
    factory: str,
    residual: float = DEFAULT_RESIDUAL,
    sizes: KinematicErrorSizes = REALISTIC,
) -> FloatArray:
    """The default prior, ``(4, 6)`` 1-sigma of theta, a, d, alpha per joint, for the model the
    controller computes with: ``"none"`` (the nominal table) the full size of a real arm's
    deviations (:data:`~wristscan.calib.kinematic_errors.REALISTIC`: 0.1 mm, 0.01 deg);
    ``"partial"`` (a factory calibration) ``residual`` of them (15 %: a factory calibration
    removes 80-90 %); ``"exact"`` none (the simulator's exact model; a real arm has no such)."""
    if factory not in FACTORY_CALIBRATIONS:
        raise ValueError(
            f"factory calibration must be one of {', '.join(FACTORY_CALIBRATIONS)}, got {factory!r}"
        )
    share = {"none": 1.0, "partial": residual, "exact": 0.0}[factory]
    per = np.array([sizes.theta_rad, sizes.a_m, sizes.d_m, sizes.alpha_rad]) * share
    return np.repeat(per[:, None], 6, axis=1)


@dataclass(frozen=True, eq=False)
class KinematicPrior:
    """What is known of the arm's kinematic error: the ``model`` its flange poses were computed
    with, the 1-sigma ``sigma`` ``(4, 6)`` of its DH parameters (theta, a, d, alpha per joint;
    :func:`prior_sigma`), optionally the ``joints`` ``(K, 6)`` at each sweep's middle pose (else
    inverse kinematics nearest to ``seed``)."""

    model: DHParams
    sigma: FloatArray = field(repr=False)
    joints: FloatArray | None = field(default=None, repr=False)
    seed: FloatArray = field(default_factory=lambda: Q_USUAL.copy(), repr=False)

    def __post_init__(self) -> None:
        s = np.asarray(self.sigma, dtype=np.float64)
        if s.shape != (4, 6) or not np.all(np.isfinite(s)) or np.any(s < 0):
            raise ValueError(f"sigma: expected (4, 6) finite values >= 0, got shape {s.shape}")
        object.__setattr__(self, "sigma", s)
        object.__setattr__(self, "model", get_model(self.model))

    @classmethod
    def for_factory(
        cls, model: str | DHParams, factory: str, residual: float = DEFAULT_RESIDUAL
    ) -> KinematicPrior:
        """The default prior for a controller computing with ``model`` (``factory``: see
        :func:`prior_sigma`)."""
        return cls(get_model(model), prior_sigma(factory, residual))

    @property
    def cov(self) -> FloatArray:
        """Diagonal ``(24, 24)`` covariance of the DH vector (order of the module doc)."""
        return np.diag(self.sigma.reshape(-1) ** 2)


def _perturbed(model: DHParams, i: int, h: float) -> DHParams:
    theta, a, d, alpha = (list(v) for v in (model.theta_offset, model.a, model.d, model.alpha))
    [theta, a, d, alpha][i // 6][i % 6] += h
    return DHParams(
        model.name, d=tuple(d), a=tuple(a), alpha=tuple(alpha), theta_offset=tuple(theta)
    )


def _twist(F0_inv: FloatArray, F: FloatArray) -> FloatArray:
    """First-order twist ``[w, v]`` (flange frame) of ``F0^-1 F`` (..., 6)."""
    D = F0_inv @ F
    R = D[..., :3, :3]
    w = 0.5 * np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        axis=-1,
    )
    return np.concatenate([w, D[..., :3, 3]], axis=-1)


def flange_sensitivity(model: str | DHParams, q: ArrayLike) -> FloatArray:
    """``(n, 6, 24)``: the flange error twist ``[w, v]`` (flange frame, rad and m) per DH
    parameter (order of the module doc) at joints ``q`` ``(n, 6)``, by central differences."""
    m = get_model(model)
    qa = np.atleast_2d(np.asarray(q, dtype=np.float64))
    F0_inv = se3.invert(kinematics.forward(m, qa))
    out = np.empty((qa.shape[0], 6, 24))
    for i in range(24):
        h = _STEP[i // 6]
        Fp = kinematics.forward(_perturbed(m, i, h), qa)
        Fm = kinematics.forward(_perturbed(m, i, -h), qa)
        out[:, :, i] = (_twist(F0_inv, Fp) - _twist(F0_inv, Fm)) / (2.0 * h)
    return out


def sweep_joints(prior: KinematicPrior, sweeps: Sequence[Sweep]) -> FloatArray:
    """``(K, 6)`` joints at each sweep's middle pose: ``prior.joints`` or inverse kinematics of
    ``prior.model`` nearest to ``prior.seed`` (each sweep seeded by the previous one's)."""
    if prior.joints is not None:
        q = np.asarray(prior.joints, dtype=np.float64)
        if q.shape != (len(sweeps), 6):
            raise ValueError(f"joints: expected ({len(sweeps)}, 6), got {q.shape}")
        return q
    out = np.empty((len(sweeps), 6))
    for k, s in enumerate(sweeps):  # one IK per sweep (a handful), the rest is vectorised
        out[k] = kinematics.inverse_nearest(prior.model, s.flange2base[s.n_poses // 2], prior.seed)
    return out


def sensitivity(
    stack: PointStack,
    result: HandEyeResult,
    G: FloatArray,
) -> FloatArray:
    """``A = dX / dDH`` ``(p, 24)``: the change of the joint solution's parameters (order of
    ``result.cov_full``) per deviation of the arm's DH parameters from the model its flange poses
    were computed with, through the normal equations at ``result`` on the
    inlier points ``stack``, for the sweeps' flange sensitivities ``G`` ``(K, 6, 24)``."""
    X = result.sensor2flange
    R, t, c = X[:3, :3], X[:3, 3], np.asarray(result.ball_centre_base, dtype=np.float64)
    n_par = 9 if result.cov_full is None else result.cov_full.shape[0]
    J = stack.jacobian(R, t, c, fit_radius=n_par == 10)
    n = stack.normals(R, t, c)
    p_f = stack.p @ R.T + t
    m_f = np.matmul(n[:, None, :], stack.Rf)[:, 0, :]
    z = np.hstack([uncertainty.rotation_rows(p_f, m_f, lever_m=1.0), m_f])  # (N, 6)
    K = G.shape[0]
    Q = np.empty((K, J.shape[1], 6))  # per sweep sum_j J_j^T z_j
    for i in range(J.shape[1]):
        for a in range(6):
            Q[:, i, a] = np.bincount(stack.sweep, J[:, i] * z[:, a], K)
    H_inv = np.linalg.pinv(J.T @ J)
    return np.asarray(H_inv @ np.einsum("kia,kab->ib", Q, G), dtype=np.float64)


def systematic_cov(A: FloatArray, prior: KinematicPrior) -> FloatArray:
    """``A Sigma_DH A^T``: the solution's covariance due to the arm's kinematic error."""
    return np.asarray(A @ prior.cov @ A.T, dtype=np.float64)


def common_part(G: FloatArray, clusters: ArrayLike | None = None) -> FloatArray:
    """``G`` ``(K, 6, 24)`` replaced by its mean over the pose ``clusters`` of the sweeps (each
    cluster once; all sweeps when None): the flange error every pose shares, which the residuals
    cannot show. The rest varies from cluster to cluster and is what the residuals' per-cluster
    component (:func:`~wristscan.calib.handeye_uncertainty.components`) estimates."""
    if clusters is None:
        mean = G.mean(axis=0)
    else:
        cl = np.unique(np.asarray(clusters), return_inverse=True)[1].reshape(-1)
        per = np.stack([G[cl == g].mean(axis=0) for g in range(int(cl.max()) + 1)])
        mean = per.mean(axis=0)
    return np.asarray(np.broadcast_to(mean, G.shape).copy(), dtype=np.float64)


def with_kinematic_prior(
    result: HandEyeResult,
    sweeps: Sequence[Sweep],
    stack: PointStack,
    prior: KinematicPrior,
    *,
    common_only: bool = True,
) -> HandEyeResult:
    """``result`` with the arm's kinematic error (:func:`systematic_cov`) added to ``cov`` and
    ``cov_full`` and the predicted point error recomputed; ``stack`` the inlier points of
    ``sweeps`` (as the solution used them). ``common_only`` propagates only the error all poses
    share (:func:`common_part`) when ``result`` carries the residuals' estimate of the rest (a
    per-cluster component, ``result.components.pose_sigma_m > 0``); otherwise the whole."""
    G = flange_sensitivity(prior.model, sweep_joints(prior, sweeps))
    vc = result.components
    if common_only and vc is not None and vc.pose_sigma_m > 0:
        G = common_part(G, vc.clusters)
    A = sensitivity(stack, result, G)
    cov_full = systematic_cov(A, prior)
    if result.cov_full is not None and result.cov_full.shape == cov_full.shape:
        cov_full += result.cov_full
    else:
        cov_full[:6, :6] += result.cov
    p_rms, p_max = result.point_sigma_rms_m, result.point_sigma_m
    if result.working_volume_m is not None:
        p_rms, p_max = uncertainty.point_error(
            cov_full[:6, :6], result.sensor2flange, *result.working_volume_m
        )
    return dataclasses.replace(
        result,
        cov=cov_full[:6, :6].copy(),
        cov_full=cov_full,
        point_sigma_m=p_max,
        point_sigma_rms_m=p_rms,
    )
