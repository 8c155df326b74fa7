"""Robust plane (and 2D line) fits, and the frame of a taught plane (Borangiu et al. 2009,
section 5: "learning a reference frame for a tilted plane").

One implementation serves planes in 3D and lines in 2D (a hyperplane of ``R^d``):

1. **Start.** Least median of squares over minimal samples (``d`` points), scored on at most
   2 000 points: a wrong start from a second surface or stray points is very unlikely while the
   surface holds more than half of the points. ``init`` (a normal and a point) skips it.
2. **IRLS.** Weighted total least squares (the smallest eigenvector of the weighted scatter
   matrix), Tukey bisquare or Huber weights on the orthogonal residuals, scale from the MAD of the
   current inliers, until the normal settles.
3. **Covariance.** ``s^2 (J^T W J)^-1`` of the parameters ``(tilts about the in-plane axes,
   offset along the normal)`` with ``s^2`` the weighted residual variance.

Flatness: ``rms`` (orthogonal residual RMS of the inliers) and ``peak_to_valley`` describe the
points; noise makes them grow with the noise level and, for the peak-to-valley, with the number
of points. A bump or a warp larger than the noise is rejected by the robust fit as outliers, so
:attr:`PlaneFit.form_error` looks at every point: the peak-to-valley of the median residual in
``form_bin_m`` cells of the plane, which removes the sensor noise and stray points and leaves the
shape of the surface (warp, steps, bumps): the figure to compare with a flatness tolerance.

Units: metres and radians. Pure NumPy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "HyperplaneFit",
    "PlaneFit",
    "Robust",
    "fit_hyperplane",
    "fit_plane",
    "plane_frame",
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
Robust = Literal["tukey", "huber"] | None

_TUKEY_C = 4.685
_HUBER_K = 1.345
_MAD_TO_SIGMA = 1.482602218505602
_LMEDS_SAMPLES = 200
_SCORE_POINTS = 2000
_IRLS_ITER = 50
_SCALE_FLOOR_REL = 1e-9  # robust scale floor relative to the extent of the points (exact data)


@dataclass(frozen=True, eq=False)
class HyperplaneFit:
    """A hyperplane ``normal . x = offset`` of ``R^d`` (``d`` = 2: a line, 3: a plane)."""

    normal: FloatArray
    """(d,) unit normal."""
    point: FloatArray
    """(d,) weighted centroid of the inliers (on the hyperplane)."""
    offset: float
    """``normal . point`` (m)."""
    rms: float
    """RMS orthogonal residual of the inliers (m)."""
    scale: float
    """Robust noise scale (MAD of the inliers' residuals; the RMS when ``robust`` is None)."""
    inliers: BoolArray
    """(N,) points that belong to the hyperplane."""
    residuals: FloatArray
    """(N,) signed orthogonal distances of all points (positive on the normal's side)."""
    basis: FloatArray
    """(d, d-1) orthonormal in-plane axes used for :attr:`cov`."""
    cov: FloatArray
    """(d, d) covariance of ``(tilt about each in-plane axis (rad), offset (m))``; the tilt
    ``k`` turns the normal towards ``basis[:, k]``. NaN without degrees of freedom."""

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))

    @property
    def peak_to_valley(self) -> float:
        """Spread (max - min) of the inliers' residuals (m): noise included."""
        r = self.residuals[self.inliers]
        return float(r.max() - r.min()) if r.size else math.nan

    @property
    def sigma_normal_rad(self) -> float:
        """1-sigma tilt of the normal (rad): square root of the largest tilt variance."""
        t = self.cov[:-1, :-1]
        return float(math.sqrt(max(float(np.linalg.eigvalsh(t).max()), 0.0)))

    @property
    def sigma_offset_m(self) -> float:
        """1-sigma offset along the normal at :attr:`point` (m)."""
        return float(math.sqrt(max(float(self.cov[-1, -1]), 0.0)))

    def distance(self, points: ArrayLike) -> FloatArray:
        """Signed distances of ``points (..., d)`` (m)."""
        return np.asarray(np.asarray(points, dtype=np.float64) @ self.normal - self.offset)

    def project(self, points: ArrayLike) -> FloatArray:
        """Orthogonal projection of ``points (..., d)`` onto the hyperplane."""
        p = np.asarray(points, dtype=np.float64)
        return np.asarray(p - self.distance(p)[..., None] * self.normal)

    def intersect_line(self, origin: ArrayLike, direction: ArrayLike) -> FloatArray:
        """Where the line ``origin + t direction`` meets the hyperplane; ValueError when it runs
        parallel to it."""
        o = np.asarray(origin, dtype=np.float64)
        d = np.asarray(direction, dtype=np.float64)
        den = float(d @ self.normal)
        if abs(den) < 1e-9 * float(np.linalg.norm(d)):
            raise ValueError("the line runs parallel to the plane")
        return np.asarray(o - (float(o @ self.normal) - self.offset) / den * d)


@dataclass(frozen=True, eq=False)
class PlaneFit(HyperplaneFit):
    """A plane in 3D; adds the form error."""

    form_error: float = math.nan
    """Peak-to-valley (m) of the median residual of every point (inliers or not) in cells of
    ``form_bin_m`` of the plane (cells with at least 5 points): the surface's departure from
    flatness without the noise, and without stray points unless they fill a cell."""
    form_bin_m: float = math.nan
    extent_m: tuple[float, float] = (math.nan, math.nan)
    """Extent of the inliers along the two in-plane axes of :attr:`basis` (m)."""


def _as_points(points: ArrayLike, dim: int) -> FloatArray:
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != dim:
        raise ValueError(f"points must be (N, {dim}), got {P.shape}")
    if not np.all(np.isfinite(P)):
        raise ValueError("points must be finite")
    if P.shape[0] < dim:
        raise ValueError(f"need at least {dim} points, got {P.shape[0]}")
    return P


def _null_basis(n: FloatArray) -> FloatArray:
    """(d, d-1) orthonormal basis of the complement of unit ``n``."""
    d = n.shape[0]
    # Householder-free: QR of [n, I] gives n's complement in the remaining columns.
    q, _ = np.linalg.qr(np.column_stack([n, np.eye(d)]))
    B = q[:, 1:d]
    return np.asarray(B, dtype=np.float64)


def _weighted_hyperplane(P: FloatArray, w: FloatArray) -> tuple[FloatArray, FloatArray]:
    sw = float(w.sum())
    c = (w @ P) / sw
    X = P - c
    S = (X * w[:, None]).T @ X
    _, vecs = np.linalg.eigh(S)
    return np.asarray(vecs[:, 0]), np.asarray(c)


def _weights(u: FloatArray, robust: Robust) -> FloatArray:
    a = np.abs(u)
    if robust == "tukey":
        return np.where(a < _TUKEY_C, (1.0 - (a / _TUKEY_C) ** 2) ** 2, 0.0)
    if robust == "huber":
        return np.where(a <= _HUBER_K, 1.0, _HUBER_K / np.maximum(a, 1e-300))
    return np.ones_like(u)


def _lmeds_start(P: FloatArray, rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    n, d = P.shape
    score = P if n <= _SCORE_POINTS else P[rng.choice(n, _SCORE_POINTS, replace=False)]
    idx = rng.integers(0, n, size=(_LMEDS_SAMPLES, d))
    S = P[idx]  # (K, d, d)
    base = S[:, 0]
    E = S[:, 1:] - base[:, None, :]  # (K, d-1, d)
    if d == 2:
        e = E[:, 0]
        normals = np.column_stack([-e[:, 1], e[:, 0]])
    else:
        normals = np.cross(E[:, 0], E[:, 1])
    norm = np.linalg.norm(normals, axis=1)
    # Nearly collinear samples (three points of one laser line) leave the normal free to turn
    # about the line: keep samples that span an area (a length for d = 2).
    ext = float(np.ptp(P, axis=0).max())
    ok = norm > 1e-3 * ext ** (d - 1)
    if not np.any(ok):
        raise ValueError("the points are degenerate (coincident or collinear)")
    normals = normals[ok] / norm[ok, None]
    base = base[ok]
    res = np.abs((score[None, :, :] - base[:, None, :]) @ normals[:, :, None])[..., 0]
    best = int(np.argmin(np.median(res, axis=1)))
    return normals[best], base[best]


def fit_hyperplane(
    points: ArrayLike,
    robust: Robust = "tukey",
    *,
    init: tuple[ArrayLike, ArrayLike] | None = None,
    weights: ArrayLike | None = None,
    seed: int = 0,
    max_iter: int = _IRLS_ITER,
    tol: float = 1e-10,
    min_scale: float = 0.0,
) -> HyperplaneFit:
    """Robust hyperplane through ``points (N, d)`` (d = 2 or 3; see the module doc).

    ``init``: a start ``(normal, point)`` instead of the least-median-of-squares search.
    ``weights``: prior per-point weights (``(N,)``, >= 0) multiplying the robust ones.
    ``min_scale`` (m) floors the robust scale: with few points the MAD can shrink onto a
    handful of them. IRLS stops after ``max_iter`` rounds or when the normal moves less than
    ``tol`` (rad) and the scale by less than 1 %. Raises ValueError for fewer than ``d`` usable
    points or degenerate ones.
    """
    P0 = np.asarray(points, dtype=np.float64)
    d = P0.shape[1] if P0.ndim == 2 else 0
    if d not in (2, 3):
        raise ValueError(f"points must be (N, 2) or (N, 3), got {P0.shape}")
    P = _as_points(P0, d)
    n_pts = P.shape[0]
    prior = np.ones(n_pts) if weights is None else np.asarray(weights, dtype=np.float64)
    if prior.shape != (n_pts,) or np.any(prior < 0) or not np.all(np.isfinite(prior)):
        raise ValueError("weights must be (N,) finite and >= 0")
    extent = float(np.ptp(P, axis=0).max()) if n_pts > 1 else 0.0
    if extent <= 0.0:
        raise ValueError("the points are all the same")
    floor = max(_SCALE_FLOOR_REL * extent, float(min_scale))
    rng = np.random.default_rng(seed)
    if init is not None:
        normal = np.asarray(init[0], dtype=np.float64).reshape(d)
        normal = normal / np.linalg.norm(normal)
        anchor = np.asarray(init[1], dtype=np.float64).reshape(d)
    elif robust is None:
        normal, anchor = _weighted_hyperplane(P, prior)
    else:
        normal, anchor = _lmeds_start(P, rng)
    if robust is None:
        w = prior.copy()
        normal, centre = _weighted_hyperplane(P, w)
    else:
        r = (P - anchor) @ normal
        normal, centre, scale, w = _irls(P, normal, r, prior, robust, floor, max_iter, tol)
    # Orientation convention: the normal's largest component positive (callers re-orient).
    if normal[int(np.argmax(np.abs(normal)))] < 0:
        normal = -normal
    offset = float(normal @ centre)
    r = P @ normal - offset
    if robust is None:
        inliers = prior > 0
        scale_out = float(np.sqrt(np.mean(r[inliers] ** 2)))
    else:
        inliers = (np.abs(r) < _TUKEY_C * scale) & (prior > 0)
        scale_out = scale
    rms = float(np.sqrt(np.mean(r[inliers] ** 2))) if np.any(inliers) else math.nan
    B = _null_basis(normal)
    cov = _covariance(P - centre, B, np.where(inliers, w, 0.0), r)
    return HyperplaneFit(
        normal=_ro(normal),
        point=_ro(np.asarray(centre)),
        offset=offset,
        rms=rms,
        scale=float(scale_out),
        inliers=_ro(inliers),
        residuals=_ro(r),
        basis=_ro(B),
        cov=_ro(np.asarray(cov)),
    )


def _irls(
    P: FloatArray,
    normal: FloatArray,
    r: FloatArray,
    prior: FloatArray,
    robust: Robust,
    floor: float,
    max_iter: int,
    tol: float,
) -> tuple[FloatArray, FloatArray, float, FloatArray]:
    """Iteratively re-weighted total least squares from the start ``normal`` (residuals ``r``):
    returns the normal, the weighted centre, the robust scale and the final weights."""
    d = P.shape[1]
    scale = max(_MAD_TO_SIGMA * float(np.median(np.abs(r))), floor)
    for _ in range(max_iter):
        w = _weights(r / scale, robust) * prior
        if float(w.sum()) <= 0 or np.count_nonzero(w) < d:
            raise ValueError("too few points support a hyperplane")
        new_normal, centre = _weighted_hyperplane(P, w)
        if float(new_normal @ normal) < 0:
            new_normal = -new_normal
        change = float(np.linalg.norm(new_normal - normal))
        normal = new_normal
        r = (P - centre) @ normal
        inl = np.abs(r) < _TUKEY_C * scale
        med = float(np.median(np.abs(r[inl]))) if np.any(inl) else 0.0
        new_scale = max(_MAD_TO_SIGMA * med, floor)
        done = change < tol and abs(new_scale - scale) <= 1e-2 * scale
        scale = new_scale
        if done:
            break
    return normal, centre, scale, _weights(r / scale, robust) * prior


def _covariance(X: FloatArray, B: FloatArray, W: FloatArray, r: FloatArray) -> FloatArray:
    """Covariance (d, d) of the tilts along the basis ``B`` and the offset, from the weighted
    residuals ``r`` of the points ``X`` (relative to the centre); NaN without degrees of
    freedom or when ill-conditioned."""
    d = X.shape[1]
    J = np.column_stack([X @ B, -np.ones(X.shape[0])])  # d r / d (tilts, offset)
    JTJ = (J * W[:, None]).T @ J
    dof = float(W.sum()) - d
    if dof > 0 and np.linalg.cond(JTJ) < 1e14:
        s2 = float(W @ (r * r)) / dof
        return np.asarray(s2 * np.linalg.inv(JTJ))
    return np.full((d, d), math.nan)


_A = TypeVar("_A", bound=NDArray[Any])


def _ro(a: _A) -> _A:
    out = a.copy()
    out.setflags(write=False)
    return out


def _form_error(uv: FloatArray, r: FloatArray, bin_m: float) -> float:
    """Peak-to-valley of the per-cell median residuals (cells of ``bin_m``, >= 5 points)."""
    if uv.shape[0] < 5 or not bin_m > 0:
        return math.nan
    keys = np.floor((uv - uv.min(axis=0)) / bin_m).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    order = np.lexsort((r, inv))  # by cell, then by residual
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    full = counts >= 5
    if not np.any(full):
        return math.nan
    lo = order[starts[full] + (counts[full] - 1) // 2]
    hi = order[starts[full] + counts[full] // 2]
    medians = 0.5 * (r[lo] + r[hi])
    return float(medians.max() - medians.min())


def fit_plane(
    points: ArrayLike,
    robust: Robust = "tukey",
    *,
    form_bin_m: float = 0.002,
    init: tuple[ArrayLike, ArrayLike] | None = None,
    weights: ArrayLike | None = None,
    seed: int = 0,
) -> PlaneFit:
    """Robust plane through ``points (N, 3)`` (m) with flatness statistics (module doc)."""
    P = _as_points(points, 3)
    h = fit_hyperplane(P, robust, init=init, weights=weights, seed=seed)
    m = h.inliers
    uv_all = (P - h.point) @ h.basis
    uv = uv_all[m]
    ext = np.ptp(uv, axis=0) if uv.shape[0] else np.full(2, math.nan)
    return PlaneFit(
        normal=h.normal,
        point=h.point,
        offset=h.offset,
        rms=h.rms,
        scale=h.scale,
        inliers=h.inliers,
        residuals=h.residuals,
        basis=h.basis,
        cov=h.cov,
        form_error=_form_error(uv_all, h.residuals, form_bin_m),
        form_bin_m=float(form_bin_m),
        extent_m=(float(ext[0]), float(ext[1])),
    )


def plane_frame(
    normal: ArrayLike,
    origin: ArrayLike,
    x_towards: ArrayLike,
    z_side: ArrayLike,
) -> FloatArray:
    """``frame2base`` (4, 4) of a plane: origin at ``origin`` (a point on the plane), Z along the
    unit ``normal`` flipped to the side of the point ``z_side`` (where the robot measured from),
    X towards ``x_towards`` projected onto the plane, Y = Z x X.

    Raises ValueError when ``x_towards`` lies on the normal through the origin or ``z_side`` on
    the plane."""
    n = np.asarray(normal, dtype=np.float64).reshape(3)
    n = n / np.linalg.norm(n)
    o = np.asarray(origin, dtype=np.float64).reshape(3)
    side = float((np.asarray(z_side, dtype=np.float64).reshape(3) - o) @ n)
    if side == 0.0:
        raise ValueError("z_side lies on the plane: the side of Z is undefined")
    z = n if side > 0 else -n
    v = np.asarray(x_towards, dtype=np.float64).reshape(3) - o
    x = v - (v @ z) * z
    nx = float(np.linalg.norm(x))
    if nx < 1e-9:
        raise ValueError("x_towards lies on the plane's normal through the origin")
    x = x / nx
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, o
    return T
