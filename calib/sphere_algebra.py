"""Algebra shared by every stage of the robust sphere and circle fits
(:mod:`wristscan.calib.sphere`), in normalised coordinates: the Riemann fit (a weighted
hyperplane on the paraboloid lift), geometric residuals, M-estimator weights and influence
functions, the robust scale, one Gauss-Newton step and the Levenberg-Marquardt refinement.

Per-point passes over large clouds run in row blocks (see :func:`_blocks`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

__all__ = [
    "REJECT_U",
    "SCALE_FLOOR_U",
    "Robust",
    "Sphere",
    "distances",
    "dot",
    "gauss_newton_step",
    "lm",
    "psi_dpsi",
    "residuals",
    "riemann",
    "robust_scale",
    "weights",
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
Sphere = tuple[FloatArray, float]  # centre, radius
Robust = Literal["tukey", "huber"] | None
_TUKEY_C = 4.685  # 95 % Gaussian efficiency
_HUBER_K = 1.345  # 95 % Gaussian efficiency
REJECT_U = _TUKEY_C  # |r|/scale beyond which a point is an outlier (both weight functions)
_MAD_TO_SIGMA = 1.482602218505602  # 1 / Phi^-1(3/4)
_MAX_RADIUS_U = 1e6  # radius beyond which a fit is a plane (normalised units)
SCALE_FLOOR_U = 1e-9  # robust scale floor (normalised units), for noise-free data
_BLOCK = 8192  # rows per block of the per-point passes


def _blocks(n: int) -> Iterator[slice]:
    """Row blocks for the per-point passes over large clouds: the temporaries of a block stay in
    cache and are reused, where whole-cloud temporaries cost a page fault every few kilobytes."""
    return (slice(i, min(i + _BLOCK, n)) for i in range(0, n, _BLOCK))


def riemann(U: FloatArray, w: FloatArray | None) -> Sphere | None:
    """Weighted hyperplane fit on the paraboloid lift (v, |v|^2). None if no finite sphere fits.

    The points are centred on their weighted mean and scaled by their RMS distance from it, so that
    the lift is well conditioned and its weighted mean is exactly (0, ..., 0, 1)."""
    n, d = U.shape
    w = np.ones(n) if w is None else w
    if np.count_nonzero(w) < d + 1:
        return None
    wsum = float(w.sum())
    mean = (w @ U) / wsum
    s2 = 0.0
    for b in _blocks(n):
        V = U[b] - mean
        s2 += float(np.einsum("n,ni,ni->", w[b], V, V))
    s = math.sqrt(s2 / wsum)
    if not s > 0.0:
        return None
    scatter = np.zeros((d + 1, d + 1))
    for b in _blocks(n):
        Zc = np.empty((b.stop - b.start, d + 1))
        np.multiply(U[b] - mean, 1.0 / s, out=Zc[:, :d])
        np.einsum("ni,ni->n", Zc[:, :d], Zc[:, :d], out=Zc[:, d])
        Zc[:, d] -= 1.0
        scatter += (Zc * w[b, None]).T @ Zc
    evals, evecs = np.linalg.eigh(scatter)
    # A second (near-)zero eigenvalue means two hyperplanes fit: coplanar points, no unique sphere.
    if not evals[1] > 1e-12 * max(evals[-1], 1e-300):
        return None
    normal = evecs[:, 0]  # the hyperplane a |v|^2 + b.v - a = 0 through the mean (0, ..., 0, 1)
    b_, a = normal[:d], float(normal[d])
    if abs(a) < 1e-300:
        return None
    centre_v = -b_ / (2.0 * a)
    rho = math.sqrt(float(centre_v @ centre_v) + 1.0)
    if not rho < _MAX_RADIUS_U:
        return None
    return mean + s * centre_v, s * rho


def distances(U: FloatArray, c: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Offsets from the centre and their lengths."""
    D = U - c
    return D, np.sqrt(np.einsum("ij,ij->i", D, D))


def dot(a: FloatArray, b: FloatArray) -> float:
    # Not BLAS: threaded dot products of long vectors stall badly on a busy machine.
    return float(np.einsum("i,i->", a, b))


def residuals(U: FloatArray, c: FloatArray, rho: float) -> FloatArray:
    """Signed geometric distances |u - c| - rho."""
    out = np.empty(len(U))
    for b in _blocks(len(U)):
        out[b] = distances(U[b], c)[1]
    out -= rho
    return out


def psi_dpsi(u: FloatArray, robust: Robust) -> tuple[FloatArray, FloatArray]:
    """Influence function psi(u) and its derivative, zero beyond the rejection cut."""
    inside = np.abs(u) <= REJECT_U
    if robust is None:
        return u.copy(), np.ones_like(u)
    if robust == "tukey":
        t = (u / _TUKEY_C) ** 2
        psi = np.where(inside, u * (1.0 - t) ** 2, 0.0)
        dpsi = np.where(inside, (1.0 - t) * (1.0 - 5.0 * t), 0.0)
        return psi, dpsi
    psi = np.where(inside, np.clip(u, -_HUBER_K, _HUBER_K), 0.0)
    dpsi = np.where(inside & (np.abs(u) <= _HUBER_K), 1.0, 0.0)
    return psi, dpsi


def weights(u: FloatArray, robust: Robust) -> FloatArray:
    """IRLS weights psi(u)/u of scaled residuals u, zero beyond the rejection cut (in place on one
    temporary: these run over every point at every iteration)."""
    if robust == "tukey":
        w = np.multiply(u, 1.0 / _TUKEY_C)
        np.square(w, out=w)
        np.subtract(1.0, w, out=w)
        np.maximum(w, 0.0, out=w)  # |u| >= c: weight zero
        return np.square(w, out=w)
    if robust == "huber":
        w = np.abs(u)
        far = w > REJECT_U
        np.maximum(w, _HUBER_K, out=w)
        np.divide(_HUBER_K, w, out=w)
        w[far] = 0.0
        return w
    return np.ones_like(u)


def robust_scale(r: FloatArray, mask: BoolArray) -> float:
    """MAD scale (about zero: residuals of a fit) of the current inliers, floored."""
    sel = np.abs(r[mask]) if mask.any() else np.abs(r)
    return max(_MAD_TO_SIGMA * float(np.median(sel)), SCALE_FLOOR_U)


def lm(
    U: FloatArray, w: FloatArray, c0: FloatArray, rho0: float, rho_fixed: float | None
) -> tuple[FloatArray, float]:
    """Weighted geometric least squares by Levenberg-Marquardt; radius held when ``rho_fixed``."""
    keep = w > 0.0
    X = U[keep]
    sw = np.sqrt(w[keep])
    d = X.shape[1]
    n_par = d if rho_fixed is not None else d + 1
    if len(X) < n_par:
        raise ValueError(f"only {len(X)} inliers left, {n_par} parameters to fit")

    def fun(x: FloatArray) -> FloatArray:
        rho = float(x[d]) if rho_fixed is None else rho_fixed
        return sw * (distances(X, x[:d])[1] - rho)

    def jac(x: FloatArray) -> FloatArray:
        D, dist = distances(X, x[:d])
        J = np.empty((len(X), n_par))
        np.multiply(D, (-sw / np.maximum(dist, 1e-300))[:, None], out=J[:, :d])
        if rho_fixed is None:
            J[:, d] = -sw
        return J

    x0 = c0 if rho_fixed is not None else np.append(c0, rho0)
    sol = least_squares(fun, x0, jac=jac, method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12)
    x = sol.x
    return x[:d].copy(), (float(x[d]) if rho_fixed is None else rho_fixed)


def gauss_newton_step(
    U: FloatArray, w: FloatArray, c: FloatArray, rho: float, rho_fixed: float | None
) -> tuple[FloatArray, float]:
    """One weighted Gauss-Newton step on the geometric residuals (normal equations)."""
    d = U.shape[1]
    n_par = d if rho_fixed is not None else d + 1
    A = np.zeros((n_par, n_par))
    g = np.zeros(n_par)
    for b in _blocks(len(U)):
        D, dist = distances(U[b], c)
        J = np.empty((len(dist), n_par))
        np.multiply(D, (-1.0 / np.maximum(dist, 1e-300))[:, None], out=J[:, :d])
        if rho_fixed is None:
            J[:, d] = -1.0
        Jw = J * w[b, None]  # points of weight zero add nothing
        A += Jw.T @ J
        g += Jw.T @ (dist - rho)
    try:
        delta = -np.linalg.solve(A, g)
    except np.linalg.LinAlgError as exc:
        raise ValueError("points are degenerate: the geometric fit is not determined") from exc
    return c + delta[:d], (rho + float(delta[d]) if rho_fixed is None else rho_fixed)
