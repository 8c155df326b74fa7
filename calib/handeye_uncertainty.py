"""Honest uncertainty of the joint hand-eye solution (:func:`wristscan.calib.handeye.refine`).

A robot does not stand where it says: its reported flange pose errs by a few hundredths to a few
tenths of a millimetre, partly at random (repeatability) and mostly systematically (joint offsets
and link lengths that differ from the DH table). Either way the error is *common to all points of
one sweep* (or of one profile, when the data come one profile per pose), so the points are not
independent and the plain Gauss-Newton covariance ``s^2 (J^T J)^-1`` of thousands of points is
far too optimistic. The model used here has three variance components::

    r_j = n_j . (u_g(j) + v_k(j)) + e_j         u_g ~ N(0, sp^2 I3),  v_k ~ N(0, ss^2 I3),
                                                  e_j ~ N(0, s^2)

``e`` the sensor noise of each point, ``v_k`` a flange-position error of sweep ``k`` (the robot's
repeatability: independent per sweep) and ``u_g`` an error shared by all sweeps of one *pose
cluster* ``g`` (sweeps at the same flange orientation and nearby positions: what a systematic
kinematic error looks like over a calibration's poses). ``n_j`` is the ball's normal at the point.
A flange rotation error moves the points of a sweep (a few centimetres across, tens of
centimetres from the flange) almost rigidly, so it is covered by the same translation term.

The three variances are estimated from the residuals by the method of moments (:func:`components`):
the residual sum of squares, the share of it that per-sweep offsets explain and the share that
per-cluster offsets explain have expectations linear in ``(s^2, ss^2, sp^2)``, exactly computed
for the fitted model (the parameters absorb part of every offset). The per-sweep part is floored
at the data sheet's repeatability. The covariance is then the sandwich
``H^-1 J^T Cov(r) J H^-1`` of the least-squares estimator (:func:`covariance`).

Cross-checks: :func:`wristscan.calib.handeye.jackknife` repeats the refinement without each pose
cluster (:class:`Jackknife`, :func:`jackknife_cov`); :func:`point_error` gives the predicted error
of a measured point in the sensor's working volume caused by the calibration's uncertainty.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import nnls

from wristscan.calib import se3

if TYPE_CHECKING:
    from wristscan.calib.handeye_model import Sweep

__all__ = [
    "Jackknife",
    "VarianceComponents",
    "components",
    "covariance",
    "design",
    "jackknife_cov",
    "local_errors",
    "point_error",
    "pose_clusters",
    "rotation_rows",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]

#: Sweeps whose flange orientations differ by less than this share a pose cluster (rad) ...
CLUSTER_ANGLE_RAD = float(np.radians(2.0))
#: ... when their flange positions are also within this distance (m).
CLUSTER_DISTANCE_M = 0.1


@dataclass(frozen=True, eq=False)
class VarianceComponents:
    """What the residuals say about the errors (metres, 1 sigma per axis).

    ``noise_sigma_m``: sensor noise of a point; ``sweep_sigma_m``: per-sweep flange error used
    (the larger of the data sheet's and the estimate); ``sweep_sigma_estimated_m``: the estimate
    (NaN when no cluster holds two sweeps, then the clusters' term holds all the robot error);
    ``pose_sigma_m``: error shared by a pose cluster; ``clusters``: the cluster of each sweep."""

    noise_sigma_m: float
    sweep_sigma_m: float
    sweep_sigma_estimated_m: float
    pose_sigma_m: float
    clusters: IntArray = field(repr=False)

    @property
    def robot_sigma_m(self) -> float:
        """Per-axis sigma of the whole flange error of one sweep (m)."""
        return float(np.hypot(self.sweep_sigma_m, self.pose_sigma_m))


def pose_clusters(
    sweeps: Sequence[Sweep],
    angle_rad: float = CLUSTER_ANGLE_RAD,
    distance_m: float = CLUSTER_DISTANCE_M,
) -> IntArray:
    """Cluster number of each sweep: sweeps whose first flange poses are within ``angle_rad``
    and ``distance_m`` of a cluster's first sweep join it (greedy, in order)."""
    heads: list[FloatArray] = []
    out = np.empty(len(sweeps), dtype=np.intp)
    for k, s in enumerate(sweeps):
        F = s.flange2base[0]
        for g, H in enumerate(heads):
            ang = float(se3.rotation_angle(H[:3, :3].T @ F[:3, :3]))
            if ang < angle_rad and float(np.linalg.norm(H[:3, 3] - F[:3, 3])) < distance_m:
                out[k] = g
                break
        else:
            out[k] = len(heads)
            heads.append(F)
    return out


def _sums(idx: IntArray, n_groups: int, A: FloatArray, X: FloatArray) -> FloatArray:
    """Per group, ``sum_j a_j x_j^T`` for the rows of ``A`` and ``X``: ``(groups, q, m)``."""
    out = np.empty((n_groups, A.shape[1], X.shape[1]))
    for i in range(A.shape[1]):
        for a in range(X.shape[1]):
            out[:, i, a] = np.bincount(idx, A[:, i] * X[:, a], n_groups)
    return out


@dataclass(frozen=True, eq=False)
class _Design:
    """The small matrices of the moment equations and of the sandwich covariance: ``Z_s`` maps
    the sweeps' flange errors to the points' residuals (rows ``n_j``), ``Z_c`` the clusters'
    (rows ``a_j``: ``n_j`` and the rotation term)."""

    H_inv: FloatArray  # (p, p)
    Gs: FloatArray  # (3K, p) = Z_s^T J
    Gc: FloatArray  # (qC, p) = Z_c^T J
    Ms: FloatArray  # (K, 3, 3) = blocks of Z_s^T Z_s
    Mc: FloatArray  # (C, q, q) = blocks of Z_c^T Z_c
    member: FloatArray  # (qC, 3K) = Z_c^T Z_s
    bs: FloatArray  # (K, 3) = Z_s^T r
    bc: FloatArray  # (C, q) = Z_c^T r


def design(
    J: FloatArray,
    r: FloatArray,
    n: FloatArray,
    sweep: IntArray,
    clusters: IntArray,
    rot: FloatArray | None = None,
) -> _Design:
    """The per-sweep and per-cluster sums behind :func:`components` and :func:`covariance`.

    ``rot`` ``(N, 3)``: the residuals' response to a flange rotation error, scaled by the lever
    (see :func:`rotation_rows`); None models the clusters' error as a translation alone."""
    H_inv = np.asarray(np.linalg.pinv(J.T @ J), dtype=np.float64)
    K, C = len(clusters), int(clusters.max()) + 1 if len(clusters) else 0
    cl = clusters[sweep]
    a = n if rot is None else np.hstack([n, rot])
    q = a.shape[1]
    Ms = _sums(sweep, K, n, n)
    per_sweep = _sums(sweep, K, a, n)  # (K, q, 3)
    member = np.zeros((q * C, 3 * K))
    for k, g in enumerate(clusters):
        member[q * g : q * g + q, 3 * k : 3 * k + 3] = per_sweep[k]
    return _Design(
        H_inv,
        _sums(sweep, K, n, J).reshape(3 * K, -1),
        _sums(cl, C, a, J).reshape(q * C, -1),
        Ms,
        _sums(cl, C, a, a),
        member,
        _sums(sweep, K, n, r[:, None])[..., 0],
        _sums(cl, C, a, r[:, None])[..., 0],
    )


def rotation_rows(
    points_flange: FloatArray, normals_flange: FloatArray, lever_m: float | None = None
) -> FloatArray:
    """``(N, 3)``: the change of each residual per flange rotation error ``u / lever`` (rad):
    ``(p_f x m) / lever`` for points ``p_f`` and normals ``m`` in the flange frame. The lever
    (default the RMS distance of the points from the flange) makes a rotation error of the
    cluster's sigma over the lever as likely as a translation of the cluster's sigma."""
    L = float(np.sqrt(np.mean(np.sum(points_flange**2, axis=1)))) if lever_m is None else lever_m
    return np.asarray(np.cross(points_flange, normals_flange) / max(L, 1e-9), dtype=np.float64)


def _blockdiag(M: FloatArray) -> FloatArray:
    m, q = M.shape[0], M.shape[1]
    out = np.zeros((q * m, q * m))
    for i in range(m):
        out[q * i : q * i + q, q * i : q * i + q] = M[i]
    return out


def _pinv(M: FloatArray) -> FloatArray:
    return np.asarray(np.linalg.pinv(M, hermitian=True), dtype=np.float64)


def _moments(d: _Design, n_points: int) -> FloatArray:
    """Expectations of ``[r.r, T_sweep, T_cluster]`` per unit of ``[s^2, ss^2, sp^2]`` (3, 3).

    ``T = b^T W b`` with ``b = Z^T r`` the per-group sums of ``a_j r_j`` and ``W`` the blocks'
    pseudo-inverses of ``Z^T Z``: the residual sum of squares the groups' offsets explain."""
    Hi = d.H_inv
    Bs, Bc = _blockdiag(d.Ms), _blockdiag(d.Mc)
    Ws, Wc = _blockdiag(_pinv(d.Ms)), _blockdiag(_pinv(d.Mc))
    # Z_a^T P Z_b = Z_a^T Z_b - G_a H^-1 G_b^T for the point, sweep and cluster offsets.
    ss = Bs - d.Gs @ Hi @ d.Gs.T
    cc = Bc - d.Gc @ Hi @ d.Gc.T
    cs = d.member - d.Gc @ Hi @ d.Gs.T
    p = Hi.shape[0]
    row0 = [n_points - p, float(np.trace(ss)), float(np.trace(cc))]
    row_s = [
        float(np.trace(Ws @ ss)),
        float(np.trace(Ws @ ss @ ss)),
        float(np.trace(Ws @ cs.T @ cs)),
    ]
    row_c = [
        float(np.trace(Wc @ cc)),
        float(np.trace(Wc @ cs @ cs.T)),
        float(np.trace(Wc @ cc @ cc)),
    ]
    return np.array([row0, row_s, row_c])


def components(
    d: _Design, r: FloatArray, clusters: IntArray, sweep_sigma_floor_m: float = 0.0
) -> VarianceComponents:
    """The variance components from the residuals ``r`` of the inliers (see the module doc) and
    their :func:`design`; ``clusters`` the pose cluster of each sweep, ``sweep_sigma_floor_m``
    the data sheet's per-axis repeatability."""
    K, C = len(clusters), d.Mc.shape[0]
    T = np.array(
        [
            float(r @ r),
            float(np.einsum("ki,kij,kj->", d.bs, _pinv(d.Ms), d.bs)),
            float(np.einsum("ki,kij,kj->", d.bc, _pinv(d.Mc), d.bc)),
        ]
    )
    A = _moments(d, r.size)
    floor2 = sweep_sigma_floor_m**2
    ss_est = float("nan")
    ss2 = floor2
    if C < K:  # some cluster holds several sweeps: their scatter is the repeatability
        x, _ = nnls(A, T)
        ss_est = float(np.sqrt(x[1]))
        if x[1] >= floor2:
            s2, ss2, sp2 = (float(v) for v in x)
            return VarianceComponents(
                float(np.sqrt(s2)), ss_est, ss_est, float(np.sqrt(sp2)), clusters.copy()
            )
    # The data sheet's repeatability holds (or, one sweep per cluster, the sweep term cannot be
    # told from the clusters'): the rest of the robot error goes to the clusters.
    rows = [0, 2] if C == K else [0, 1, 2]
    y, _ = nnls(A[rows][:, [0, 2]], T[rows] - A[rows, 1] * ss2)
    return VarianceComponents(
        float(np.sqrt(y[0])), float(np.sqrt(ss2)), ss_est, float(np.sqrt(y[1])), clusters.copy()
    )


def covariance(d: _Design, vc: VarianceComponents) -> FloatArray:
    """The sandwich covariance of the parameters under the variance components ``vc``."""
    Hi = d.H_inv
    B = vc.sweep_sigma_m**2 * (d.Gs.T @ d.Gs) + vc.pose_sigma_m**2 * (d.Gc.T @ d.Gc)
    return np.asarray(vc.noise_sigma_m**2 * Hi + Hi @ B @ Hi, dtype=np.float64)


def point_error(
    cov6: ArrayLike,
    sensor2flange: ArrayLike,
    y_range_m: tuple[float, float],
    z_range_m: tuple[float, float],
    n_grid: int = 5,
) -> tuple[float, float]:
    """Predicted 1-sigma error (m, 3-D: square root of the trace) of a measured point caused by
    the calibration's uncertainty ``cov6`` (order of ``HandEyeResult.cov``), over a grid of the
    sensor's working volume (laser plane ``y`` x ``z``): ``(RMS over the grid, maximum)``.

    A point ``p`` of the sensor frame lands at ``R exp(w) p + t`` in the flange frame, so its
    error is ``-R [p]x w + dt``."""
    C = np.asarray(cov6, dtype=np.float64)
    R = np.asarray(sensor2flange, dtype=np.float64)[:3, :3]
    y = np.linspace(y_range_m[0], y_range_m[1], n_grid)
    z = np.linspace(z_range_m[0], z_range_m[1], n_grid)
    Y, Z = np.meshgrid(y, z, indexing="ij")
    sig = []
    for p in np.stack([np.zeros(Y.size), Y.ravel(), Z.ravel()], axis=-1):
        px = np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])
        A = np.hstack([-R @ px, np.eye(3)])
        sig.append(float(np.sqrt(max(np.trace(A @ C @ A.T), 0.0))))
    s = np.array(sig)
    return float(np.sqrt(np.mean(s**2))), float(s.max())


def local_errors(estimates: FloatArray, reference: ArrayLike) -> FloatArray:
    """Estimates ``(n, 4, 4)`` as 6-vectors about ``reference`` in the order of
    ``HandEyeResult.cov``: the rotation vector of ``R_ref^T R`` (sensor axes), ``t - t_ref``."""
    X = np.asarray(reference, dtype=np.float64)
    E = np.asarray(estimates, dtype=np.float64)
    w = se3.matrix_to_rotvec(np.swapaxes(X[:3, :3], -1, -2) @ E[:, :3, :3])
    return np.concatenate([w.reshape(-1, 3), E[:, :3, 3] - X[:3, 3]], axis=1)


@dataclass(frozen=True, eq=False)
class Jackknife:
    """The solution repeated without each pose cluster: the estimates ``(n, 4, 4)``, the
    clusters left out and the jackknife covariance (order of ``HandEyeResult.cov``)."""

    left_out: tuple[int, ...]
    sensor2flange: FloatArray
    cov: FloatArray

    @property
    def sigma(self) -> FloatArray:
        """Jackknife 1-sigma of ``[w_x, w_y, w_z (rad), t_x, t_y, t_z (m)]``."""
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))


def jackknife_cov(deltas: FloatArray) -> FloatArray:
    """``(n - 1) / n sum (d_i - mean)(d_i - mean)^T`` of the leave-one-out estimates ``deltas``."""
    n = deltas.shape[0]
    D = deltas - deltas.mean(axis=0)
    return np.asarray((n - 1) / n * (D.T @ D), dtype=np.float64)
