"""The closed-form start of the stop-and-go calibration (:mod:`wristscan.calib.perpose`, which
explains the model) and the fit of the poses' ball centres alone.

For pose ``k`` with flange pose ``(R_k, T_k)``, circle ``(y_k, z_k, r_k)`` in the laser plane and
``h_k = sqrt(R^2 - r_k^2)``, the ball centre ``c_base = R_k (R_sf c_k + t_sf) + T_k`` with
``c_k = (s h_k, y_k, z_k)`` is linear in the columns ``a, b, d`` of ``R_sf``, ``t_sf`` and
``c_base`` (:func:`closed_form`); :func:`centre_fit` is its nonlinear least squares over the poses
(optionally with the radius free), :func:`calibrate_from_circles` both for circle centres alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from wristscan.calib import se3
from wristscan.calib.handeye_model import PoorlyConstrained

__all__ = [
    "CIRCLE_RADIUS_SLACK",
    "MIN_POSES",
    "CentreFit",
    "ClosedForm",
    "PerPoseDataError",
    "calibrate_from_circles",
    "centre_fit",
    "check_poses",
    "check_radius",
    "closed_form",
    "heights",
]

FloatArray = NDArray[np.float64]

MIN_POSES = 6
"""Fewest poses accepted: (2) has 15 unknowns and 3 equations per pose; 5 poses leave no check."""
CIRCLE_RADIUS_SLACK = 0.01
"""A profile's circle may exceed the ball radius by this share (noise near the equator)."""
_DEGENERATE_COND = 1e5
"""Condition number of the equilibrated system (2) without ``a`` above which the poses do not
determine the solution at all (no tilt between orientations, or the ball at one place in the
laser plane)."""


class PerPoseDataError(ValueError):
    """Per-pose data that cannot be used; ``pose`` is the 0-based pose it concerns (or None)."""

    def __init__(self, message: str, pose: int | None = None) -> None:
        super().__init__(message)
        self.pose = pose


@dataclass(frozen=True, eq=False)
class ClosedForm:
    """The closed-form start for one side: sensor2flange, the ball centre in base (m) and the
    RMS of (1) over the poses (m). ``handedness`` is ``a . (b x d)`` of the linear solution
    for side +1 (about +1 or -1 when the heights ``h_k`` vary enough to tell the side)."""

    side: int
    sensor2flange: FloatArray
    ball_centre_base: FloatArray
    centre_rms_m: float
    handedness: float


def check_radius(ball_radius: float) -> float:
    R = float(ball_radius)
    if not (math.isfinite(R) and R > 0.0):
        raise ValueError(f"ball_radius must be a positive length in metres, got {ball_radius!r}")
    return R


def heights(circles: FloatArray, R: float) -> FloatArray:
    """``h_k = sqrt(R^2 - r_k^2)``, 0 where the circle is the equator (within the slack)."""
    r = circles[:, 2]
    big = np.flatnonzero(r > (1 + CIRCLE_RADIUS_SLACK) * R)
    if big.size:
        k = int(big[0])
        raise PerPoseDataError(
            f"circle radius {r[k] * 1e3:.3f} mm exceeds the ball radius {R * 1e3:.3f} mm", k
        )
    return np.sqrt(np.clip(R * R - r * r, 0.0, None))


def check_poses(flange2base: ArrayLike, n: int | None = None) -> FloatArray:
    F = se3.check_transform(np.asarray(flange2base, dtype=np.float64), "flange2base")
    if F.ndim != 3:
        raise ValueError(f"flange2base: expected (K, 4, 4), got {F.shape}")
    if n is not None and F.shape[0] != n:
        raise ValueError(f"{F.shape[0]} flange poses for {n} profiles")
    if F.shape[0] < MIN_POSES:
        raise PerPoseDataError(
            f"{F.shape[0]} poses; the calibration needs >= {MIN_POSES} (12 or more recommended)"
        )
    return F


def _equilibrated_cond(A: FloatArray) -> float:
    n = np.linalg.norm(A, axis=0)
    s = np.linalg.svd(A / np.where(n > 0, n, 1.0), compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


def _nearest_rotation_bd(b: FloatArray, d: FloatArray) -> FloatArray:
    """The proper rotation whose Y and Z columns are nearest to ``b`` and ``d``."""
    M = np.outer(b, [0.0, 1.0, 0.0]) + np.outer(d, [0.0, 0.0, 1.0])
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt))) or 1.0])
    return np.asarray(U @ D @ Vt, dtype=np.float64)


def _origin_and_ball(
    F: FloatArray, Rsf: FloatArray, c_sensor: FloatArray
) -> tuple[FloatArray, FloatArray, float]:
    """(2) with the rotation known: ``R_k t - c = -T_k - R_k R_sf c_k``, linear in ``t, c``."""
    K = F.shape[0]
    Rk, Tk = F[:, :3, :3], F[:, :3, 3]
    A = np.concatenate([Rk, -np.broadcast_to(np.eye(3), (K, 3, 3))], axis=2).reshape(3 * K, 6)
    rhs = (-Tk - np.einsum("kij,jl,kl->ki", Rk, Rsf, c_sensor)).reshape(-1)
    x, *_ = np.linalg.lstsq(A, rhs, rcond=None)
    res = (A @ x - rhs).reshape(K, 3)
    return x[:3], x[3:], float(np.sqrt(np.mean(np.sum(res**2, axis=1))))


def closed_form(
    flange2base: ArrayLike, circles: ArrayLike, ball_radius: float
) -> tuple[ClosedForm, ClosedForm]:
    """The closed-form starts for side +1 and side -1 from the flange poses ``(K, 4, 4)`` and the
    circles ``(K, 3)``: ``y, z`` centre and radius in the laser plane (m). Needs no initial
    guess and no constant-orientation group. Raises :class:`PoorlyConstrained` when the poses
    do not determine the solution."""
    C = np.asarray(circles, dtype=np.float64)
    if C.ndim != 2 or C.shape[1] != 3 or not np.all(np.isfinite(C)):
        raise ValueError(f"circles: expected (K, 3) finite numbers (y, z, r), got {C.shape}")
    F = check_poses(flange2base, C.shape[0])
    R = check_radius(ball_radius)
    h = heights(C, R)
    K = F.shape[0]
    Rk = F[:, :3, :3]
    eye = np.broadcast_to(np.eye(3), (K, 3, 3))
    blocks = [h[:, None, None] * Rk, C[:, 0, None, None] * Rk, C[:, 1, None, None] * Rk, Rk, -eye]
    A = np.concatenate(blocks, axis=2).reshape(3 * K, 15)
    cond = _equilibrated_cond(A[:, 3:])
    if cond > _DEGENERATE_COND:
        raise PoorlyConstrained(
            f"the poses do not determine sensor2flange (condition {cond:.3g} of the linear "
            "problem)",
            "tilt the flange between poses about two different axes (>= 30 deg) and place the "
            "ball at different points of the laser line",
            cond,
        )
    rhs = -F[:, :3, 3].reshape(-1)
    n = np.linalg.norm(A, axis=0)
    x, *_ = np.linalg.lstsq(A / n, rhs, rcond=1e-10)
    x = x / n
    a, b, d = x[0:3], x[3:6], x[6:9]
    Rsf = _nearest_rotation_bd(b, d)
    handedness = float(a @ Rsf[:, 0])
    out = []
    for side in (1, -1):
        c_sensor = np.column_stack([side * h, C[:, 0], C[:, 1]])
        t, c, rms = _origin_and_ball(F, Rsf, c_sensor)
        out.append(ClosedForm(side, se3.make(Rsf, t), c, rms, handedness))
    return out[0], out[1]


@dataclass(frozen=True, eq=False)
class CentreFit:
    """:func:`centre_fit`'s solution: sensor2flange, the ball centre and radius (m) and the RMS
    of the weighted centre misfits (m)."""

    sensor2flange: FloatArray
    ball_centre_base: FloatArray
    radius: float
    rms_m: float


def centre_fit(
    flange2base: FloatArray,
    circles: FloatArray,
    sides: FloatArray,
    start: ClosedForm,
    ball_radius: float,
    fit_radius: bool = False,
) -> CentreFit:
    """Least squares of the ball centre condition over the poses from ``start``; ``sides`` (K,)
    the side of each pose. The misfit is taken in the sensor axes, its X part weighted by
    ``h_k / r_k`` (the height follows from the radius: ``dh = (r / h) dr``). ``fit_radius``
    frees the radius (bounded below by the largest circle)."""
    F, C, R = flange2base, circles, ball_radius
    Rk, Tk = F[:, :3, :3], F[:, :3, 3]
    R0 = start.sensor2flange[:3, :3]
    r2 = C[:, 2] ** 2

    def fun(x: FloatArray) -> FloatArray:
        rad = float(x[9]) if fit_radius else R
        h = np.sqrt(np.clip(rad * rad - r2, 0.0, None))
        c_sensor = np.column_stack([sides * h, C[:, 0], C[:, 1]])
        Rsf = R0 @ se3.rotvec_to_matrix(x[:3])
        pred = np.einsum("kij,kj->ki", Rk, c_sensor @ Rsf.T + x[3:6]) + Tk
        r_sensor = np.einsum("kji,kj->ki", Rk, pred - x[6:9]) @ Rsf  # misfit in sensor axes
        r_sensor[:, 0] *= np.clip(h / np.maximum(C[:, 2], 1e-9), 0.0, 1.0)
        return np.asarray(r_sensor.reshape(-1), dtype=np.float64)

    x0 = np.concatenate(
        [np.zeros(3), start.sensor2flange[:3, 3], start.ball_centre_base, [R] if fit_radius else []]
    )
    if fit_radius:
        lo = np.full(10, -np.inf)
        hi = np.full(10, np.inf)
        lo[9], hi[9] = float(np.sqrt(r2.max())) * 1.0001, 10.0 * R
        x0[9] = min(max(x0[9], lo[9] * 1.001), hi[9] * 0.999)
        sol = least_squares(fun, x0, bounds=(lo, hi), method="trf", xtol=1e-12, ftol=1e-12)
    else:
        sol = least_squares(fun, x0, method="lm", xtol=1e-14, ftol=1e-14)
    X = se3.make(R0 @ se3.rotvec_to_matrix(sol.x[:3]), sol.x[3:6])
    rms = float(np.sqrt(np.mean(np.sum(sol.fun.reshape(-1, 3) ** 2, axis=1))))
    rad = float(sol.x[9]) if fit_radius else R
    return CentreFit(X, np.asarray(sol.x[6:9], dtype=np.float64), rad, rms)


def calibrate_from_circles(
    flange2base: ArrayLike,
    circles: ArrayLike,
    ball_radius: float,
    *,
    side: Literal[1, -1] = 1,
) -> tuple[FloatArray, FloatArray, float]:
    """sensor2flange, the ball centre (m) and the RMS of the centre misfits (m) from circle
    centres and radii ``(K, 3)`` (``y, z, r`` in the laser plane, m) for a known ``side``: the
    closed form, then :func:`centre_fit`."""
    C = np.asarray(circles, dtype=np.float64)
    F = check_poses(flange2base, C.shape[0] if C.ndim == 2 else None)
    R = check_radius(ball_radius)
    start = closed_form(F, C, R)[0 if side == 1 else 1]
    fit = centre_fit(F, C, np.full(C.shape[0], float(side)), start, R)
    return fit.sensor2flange, fit.ball_centre_base, fit.rms_m
