"""Robust sphere and circle fits for the tooling ball (Borangiu et al. 2009, section 2).

One n-dimensional implementation serves both shapes: :func:`fit_sphere` (3D point clouds from the
ball-matching sweep) and :func:`fit_circle` (one profile's arc, points ``(y, z)`` in the laser
plane) are thin wrappers around it.

Pipeline of the robust fit (all lengths in metres on the interface):

1. **Hypotheses.** Real scans of a tooling ball also hold its post, the table around it and stray
   reflections, so the start must come from the ball alone. Minimal samples (``d + 1`` points, or
   ``d`` points plus a known radius) are drawn a batch at a time, half of them uniformly and half
   among the neighbours of a random point (the ball may be a small share of the scan), solved in
   one batched linear solve and scored in one broadcast with a truncated quadratic (MSAC) cost on a
   random subset of the points; the best of a batch is refitted on its consensus (LO-RANSAC). The
   inlier band is three times a noise scale estimated from the thickness of nearest-neighbour
   patches, so no noise level has to be configured. Where the ball departs from a sphere by more
   than that (noise-free data, a sheared sweep), the band is widened until the best sphere's
   consensus is complete and fixes the sphere. The number of draws adapts to the best inlier
   fraction seen (99.9 % confidence of one clean sample). Draws come from a seeded
   ``np.random.Generator``: results are reproducible.
2. **Riemann fit + IRLS.** The consensus points are centred, scaled and lifted onto the paraboloid
   ``(u, |u|^2)``; a sphere is a hyperplane there, found as the smallest eigenvector of the weighted
   scatter matrix (weighted total least squares). Weights are then re-derived from the geometric
   residuals (Tukey bisquare or Huber, scale by the MAD of the current inliers) and the hyperplane
   refitted until the sphere settles.
3. **Geometric refinement.** Re-weighting continues on the geometric distances ``|p - c| - r``
   with one Gauss-Newton step per round, then Levenberg-Marquardt
   (``scipy.optimize.least_squares``) converges the weighted geometric fit of the inliers. A known
   radius is held fixed here, so that only the centre is fitted.

On clouds larger than 20 000 points stage 2 and the first rounds of stage 3 run on a random part of
them; the last rounds and the refinement use every point.

``robust=None`` skips 1 and the weights: a plain Riemann start and geometric least squares on all
points. :func:`kasa_fit` and :func:`geometric_fit` expose the plain algebraic and plain geometric
fits for comparison.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Literal, TypeVar, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

__all__ = [
    "BallFit",
    "CircleFit",
    "Robust",
    "SphereFit",
    "fit_circle",
    "fit_sphere",
    "geometric_fit",
    "kasa_fit",
    "sphere_centre_from_circle",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
_Sphere = tuple[FloatArray, float]  # centre, radius
Robust = Literal["tukey", "huber"] | None

_TUKEY_C = 4.685  # 95 % Gaussian efficiency
_HUBER_K = 1.345  # 95 % Gaussian efficiency
_REJECT_U = _TUKEY_C  # |r|/scale beyond which a point is an outlier (both weight functions)
_MAD_TO_SIGMA = 1.482602218505602  # 1 / Phi^-1(3/4)
_BAND_SIGMAS = 3.0  # hypothesis inlier band, in estimated noise sigmas
_CONFIDENCE = 0.999  # probability of drawing at least one all-inlier minimal sample
_BATCH = 256  # hypotheses drawn per broadcast
_SCORE_POINTS = 2000  # points used to score hypotheses
_POOL_POINTS = 1000  # points minimal samples are drawn from
_PREVIEW_POINTS = 200  # points of the first, quick scoring of a batch
_PREVIEW_KEEP = 16  # hypotheses per batch that get the full scoring
_NOISE_POINTS = 1000  # neighbourhoods used for the noise estimate
_MAX_RADIUS_U = 1e6  # radius beyond which a fit is a plane (normalised units)
_SCALE_FLOOR_U = 1e-9  # robust scale floor (normalised units), for noise-free data
_LADDER_STEP = 4.0  # factor by which the hypothesis band widens while the consensus is incomplete
_LADDER_GROWTH = 1.05  # consensus complete: widening the band by _LADDER_STEP adds < 5 % points
_LADDER_MIN_SAMPLES = 4  # ... and it holds at least this many minimal samples' worth of points
_LADDER_MAX = 0.1  # widest band, relative to the sphere's radius (or the largest one allowed)
_IRLS_ITER = 30
_PART_POINTS = 20000  # points the first IRLS stages work on, at most
_BLOCK = 8192  # rows per block of the per-point passes


@dataclass(frozen=True, eq=False)
class BallFit:
    """Result of an n-sphere fit. Lengths in metres; arrays are read-only."""

    centre: FloatArray
    """(d,) centre."""
    radius: float
    """Radius (the imposed one when the radius was known)."""
    rms: float
    """RMS geometric residual over the inliers."""
    inliers: BoolArray
    """(N,) True for the points that belong to the fitted surface."""
    cov_centre: FloatArray
    """(d, d) covariance of the centre (m^2), from the geometric Jacobian: s^2 (J^T J)^-1 with s^2
    corrected for the M-estimator weights; marginal over the radius when it was fitted. NaN when the
    inliers leave no degrees of freedom."""
    n_inliers: int
    residuals: FloatArray
    """(N,) signed geometric residuals |p - c| - r of all points (positive outside)."""
    scale: float
    """Noise scale of the inliers: robust (MAD) scale, or the residual RMS when robust=None."""


@dataclass(frozen=True, eq=False)
class SphereFit(BallFit):
    """Sphere fit: ``centre`` (3,), ``cov_centre`` (3, 3)."""


@dataclass(frozen=True, eq=False)
class CircleFit(BallFit):
    """Circle fit: ``centre`` (2,), ``cov_centre`` (2, 2)."""


# --------------------------------------------------------------------------------------------
# public API


def fit_sphere(
    points: ArrayLike,
    radius: float | None = None,
    robust: Robust = "tukey",
    *,
    radius_range: tuple[float, float] | None = None,
    rng: np.random.Generator | int | None = None,
    threshold: float | None = None,
    max_hypotheses: int = 4096,
) -> SphereFit:
    """Fit a sphere to ``points`` (N, 3) in metres, robust to the post, table and stray points.

    ``radius``: known ball radius (m); only the centre is then fitted. ``radius_range`` (m):
    plausible radii when the radius is unknown; a fit that ends outside it raises. Without it the
    hypotheses stop at half the diagonal of the points' bounding box, which keeps large planes such
    as the table from passing for a sphere.
    ``robust``: "tukey" (default), "huber" or None (plain least squares on all points).
    ``rng``: generator or seed for the hypothesis draws (None: seed 0, so results repeat).
    ``threshold``: inlier band (m) of the hypothesis stage (default: 3x the estimated noise, widened
    while the best sphere's consensus is incomplete, as on noise-free scans of a ball that is not
    quite a sphere); the robust scale is kept below twice this band, so that a poor start cannot
    spread to the table. ``max_hypotheses``: minimal samples drawn at most per search (a quarter
    of it in each repeat at a wider band).
    Raises ValueError on bad shapes, non-finite values, fewer than 4 points or coplanar points.
    Without ``radius`` or ``radius_range`` a scan in which the table far outweighs the ball may be
    fitted by a large sphere through the table: give one of them for cluttered scans.
    """
    return cast(
        SphereFit,
        _fit_ball(
            _as_points(points, 3), radius, robust, radius_range, rng, threshold, max_hypotheses
        ),
    )


def fit_circle(
    points: ArrayLike,
    radius: float | None = None,
    robust: Robust = "tukey",
    *,
    radius_range: tuple[float, float] | None = None,
    rng: np.random.Generator | int | None = None,
    threshold: float | None = None,
    max_hypotheses: int = 4096,
) -> CircleFit:
    """Fit a circle to ``points`` (N, 2) in metres, e.g. one profile's ``(y, z)`` arc of the ball.

    Same arguments and behaviour as :func:`fit_sphere`, in the plane (needs at least 3 points). For
    a profile of a ball of known radius R, the circle radius is unknown: pass
    ``radius_range=(0, 1.01 * R)`` (a little slack for noise near the equator) and recover the
    sphere centre with :func:`sphere_centre_from_circle`.
    """
    return cast(
        CircleFit,
        _fit_ball(
            _as_points(points, 2), radius, robust, radius_range, rng, threshold, max_hypotheses
        ),
    )


def kasa_fit(points: ArrayLike) -> BallFit:
    """Plain algebraic (Kasa) least squares: minimise sum (|p|^2 - 2 c.p + |c|^2 - r^2)^2.

    ``points`` (N, d) in metres, d >= 2. Biased towards small radii on short arcs; here for
    comparison. Returns a SphereFit for d = 3, a CircleFit for d = 2 (all points inliers).
    """
    P = _as_points(points, None)
    origin, scale = _normaliser(P)
    U = (P - origin) / scale
    A = np.column_stack([2.0 * U, np.ones(len(U))])
    sol, *_ = np.linalg.lstsq(A, np.einsum("ij,ij->i", U, U), rcond=None)
    c = sol[:-1]
    rho2 = float(sol[-1] + c @ c)
    if not rho2 > 0.0 or not np.all(np.isfinite(sol)):
        raise ValueError("points are degenerate: the algebraic fit has no real radius")
    return _finish(P, origin, scale, c, math.sqrt(rho2), np.ones(len(P), bool), None, None, 0)


def geometric_fit(
    points: ArrayLike, init: BallFit | ArrayLike, radius: float | None = None
) -> BallFit:
    """Plain geometric least squares (Levenberg-Marquardt on |p - c| - r, no weights, all points).

    ``points`` (N, d) in metres; ``init`` a previous fit or an array ``(c_1..c_d, r)`` (m) to start
    from; ``radius`` (m) fixes the radius (then ``init`` may be just the centre).
    """
    P = _as_points(points, None)
    d = P.shape[1]
    if isinstance(init, BallFit):
        x0 = np.append(init.centre, init.radius)
    else:
        x0 = np.asarray(init, dtype=np.float64).reshape(-1)
    if x0.shape not in ((d + 1,), (d,)) or (x0.shape == (d,) and radius is None):
        raise ValueError(
            f"init must be (centre ({d},), radius) as shape ({d + 1},), got {x0.shape}"
        )
    if not np.all(np.isfinite(x0)):
        raise ValueError("init holds non-finite values")
    r_fixed = _check_radius(radius)
    origin, scale = _normaliser(P)
    U = (P - origin) / scale
    c0 = (x0[:d] - origin) / scale
    rho0 = (r_fixed if r_fixed is not None else float(x0[d])) / scale
    R_u = None if r_fixed is None else r_fixed / scale
    c, rho = _lm(U, np.ones(len(U)), c0, rho0, R_u)
    n_fixed = 0 if R_u is None else 1
    return _finish(P, origin, scale, c, rho, np.ones(len(P), bool), None, None, n_fixed)


def sphere_centre_from_circle(
    circle_centre_yz: ArrayLike,
    circle_radius: float,
    sphere_radius: float,
    side: int = +1,
    tol: float | None = None,
) -> FloatArray:
    """Sphere centre (3,) in the sensor frame from a circle fitted in the laser plane (x = 0).

    The laser plane cuts the ball of radius R in a circle of radius r centred at (y, z); the ball's
    centre is ``(side * sqrt(R^2 - r^2), y, z)``. ``side`` (+1 or -1) says on which side of the
    plane the centre lies (a single profile cannot tell). All lengths in metres. ``r`` may exceed R
    by ``tol`` (default 0.1 % of R), which is clipped to a centre in the plane; more raises
    ValueError.
    """
    yz = np.asarray(circle_centre_yz, dtype=np.float64)
    if yz.shape != (2,) or not np.all(np.isfinite(yz)):
        raise ValueError(f"circle_centre_yz must be 2 finite numbers (y, z), got {yz!r}")
    r = float(circle_radius)
    R = float(sphere_radius)
    if not (math.isfinite(R) and R > 0.0):
        raise ValueError(f"sphere_radius must be a positive finite length (m), got {R}")
    if not (math.isfinite(r) and r >= 0.0):
        raise ValueError(f"circle_radius must be a non-negative finite length (m), got {r}")
    if side not in (1, -1):
        raise ValueError(f"side must be +1 or -1, got {side!r}")
    tol_m = 1e-3 * R if tol is None else float(tol)
    excess = r - R
    if excess > tol_m:
        raise ValueError(
            f"circle radius {r:.6g} m exceeds the sphere radius {R:.6g} m by {excess:.3g} m "
            f"(tolerance {tol_m:.3g} m): this arc does not lie on that ball"
        )
    x = side * math.sqrt(max(R * R - r * r, 0.0))
    return np.array([x, yz[0], yz[1]])


# --------------------------------------------------------------------------------------------
# input checks


def _as_points(points: ArrayLike, dim: int | None) -> FloatArray:
    a = np.asarray(points)
    shape_txt = f"(N, {dim})" if dim is not None else "(N, d) with d >= 2"
    if a.dtype == object or np.iscomplexobj(a) or not np.issubdtype(a.dtype, np.number):
        raise ValueError(f"points must be a real numeric array of shape {shape_txt}")
    if a.ndim != 2 or (dim is not None and a.shape[1] != dim) or a.shape[1] < 2:
        raise ValueError(f"points must have shape {shape_txt}, got {a.shape}")
    d = a.shape[1]
    if a.shape[0] < d + 1:
        what = {2: "circle", 3: "sphere"}.get(d, f"{d}-sphere")
        raise ValueError(f"need at least {d + 1} points to fit a {what}, got {a.shape[0]}")
    P = a.astype(np.float64)  # integer input: cast before any scaling
    bad = ~np.isfinite(P)
    if bad.any():
        raise ValueError(f"points hold {int(bad.any(axis=1).sum())} rows with NaN or inf values")
    return P


def _check_radius(radius: float | None) -> float | None:
    if radius is None:
        return None
    r = float(radius)
    if not (math.isfinite(r) and r > 0.0):
        raise ValueError(f"radius must be a positive finite length (m), got {radius!r}")
    return r


def _normaliser(P: FloatArray) -> tuple[FloatArray, float]:
    """Robust origin and scale (m) that bring the points to O(1) coordinates."""
    origin = np.median(P, axis=0)
    dist = np.linalg.norm(P - origin, axis=1)
    scale = float(np.median(dist))
    if not scale > 0.0:
        scale = float(dist.max())
    if not scale > 0.0:
        raise ValueError("all points coincide: no sphere is determined")
    return origin, scale


def _as_generator(rng: np.random.Generator | int | None) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    return np.random.default_rng(0 if rng is None else rng)


# --------------------------------------------------------------------------------------------
# algebra shared by every stage (normalised coordinates)


def _blocks(n: int) -> Iterator[slice]:
    """Row blocks for the per-point passes over large clouds: the temporaries of a block stay in
    cache and are reused, where whole-cloud temporaries cost a page fault every few kilobytes."""
    return (slice(i, min(i + _BLOCK, n)) for i in range(0, n, _BLOCK))


def _riemann(U: FloatArray, w: FloatArray | None) -> _Sphere | None:
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


def _distances(U: FloatArray, c: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Offsets from the centre and their lengths."""
    D = U - c
    return D, np.sqrt(np.einsum("ij,ij->i", D, D))


def _dot(a: FloatArray, b: FloatArray) -> float:
    # Not BLAS: threaded dot products of long vectors stall badly on a busy machine.
    return float(np.einsum("i,i->", a, b))


def _residuals(U: FloatArray, c: FloatArray, rho: float) -> FloatArray:
    """Signed geometric distances |u - c| - rho."""
    out = np.empty(len(U))
    for b in _blocks(len(U)):
        out[b] = _distances(U[b], c)[1]
    out -= rho
    return out


def _psi_dpsi(u: FloatArray, robust: Robust) -> tuple[FloatArray, FloatArray]:
    """Influence function psi(u) and its derivative, zero beyond the rejection cut."""
    inside = np.abs(u) <= _REJECT_U
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


def _weights(u: FloatArray, robust: Robust) -> FloatArray:
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
        far = w > _REJECT_U
        np.maximum(w, _HUBER_K, out=w)
        np.divide(_HUBER_K, w, out=w)
        w[far] = 0.0
        return w
    return np.ones_like(u)


def _robust_scale(r: FloatArray, mask: BoolArray) -> float:
    """MAD scale (about zero: residuals of a fit) of the current inliers, floored."""
    sel = np.abs(r[mask]) if mask.any() else np.abs(r)
    return max(_MAD_TO_SIGMA * float(np.median(sel)), _SCALE_FLOOR_U)


def _lm(
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
        return sw * (_distances(X, x[:d])[1] - rho)

    def jac(x: FloatArray) -> FloatArray:
        D, dist = _distances(X, x[:d])
        J = np.empty((len(X), n_par))
        np.multiply(D, (-sw / np.maximum(dist, 1e-300))[:, None], out=J[:, :d])
        if rho_fixed is None:
            J[:, d] = -sw
        return J

    x0 = c0 if rho_fixed is not None else np.append(c0, rho0)
    sol = least_squares(fun, x0, jac=jac, method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12)
    x = sol.x
    return x[:d].copy(), (float(x[d]) if rho_fixed is None else rho_fixed)


def _gauss_newton_step(
    U: FloatArray, w: FloatArray, c: FloatArray, rho: float, rho_fixed: float | None
) -> tuple[FloatArray, float]:
    """One weighted Gauss-Newton step on the geometric residuals (normal equations)."""
    d = U.shape[1]
    n_par = d if rho_fixed is not None else d + 1
    A = np.zeros((n_par, n_par))
    g = np.zeros(n_par)
    for b in _blocks(len(U)):
        D, dist = _distances(U[b], c)
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


# --------------------------------------------------------------------------------------------
# hypothesis stage


def _noise_sigma(U: FloatArray, gen: np.random.Generator) -> float:
    """Noise scale from the thickness of local neighbourhoods (model-free, robust by the median)."""
    n, d = U.shape
    # Thin dense clouds first: neighbourhoods must be wider than the noise, or their thickness
    # underestimates it. Surfaces (d - 1 dimensional) thin out faster in 3D than curves in 2D.
    T = U[gen.choice(n, size=min(n, 500 if d == 2 else 3000), replace=False)]
    k = min(4 * d + 4, len(T))
    q = gen.choice(len(T), size=min(len(T), _NOISE_POINTS), replace=False)
    _, nn = cKDTree(T).query(T[q], k=k)
    X = T[nn]
    X = X - X.mean(axis=1, keepdims=True)
    lam = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", X, X))[:, 0]
    return float(np.median(np.sqrt(np.maximum(lam, 0.0) / max(k - d, 1))))


def _solve_batched(A: FloatArray, b: FloatArray) -> tuple[FloatArray, BoolArray]:
    """Solve many small systems at once; flag the ill-conditioned ones instead of failing."""
    with np.errstate(all="ignore"):
        cond = np.linalg.cond(A)
    ok: BoolArray = np.isfinite(cond) & (cond < 1e10)
    A = np.where(ok[:, None, None], A, np.eye(A.shape[-1]))
    x = np.asarray(np.linalg.solve(A, b[..., None])[..., 0], dtype=np.float64)
    return x, ok


def _minimal_spheres(S: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Spheres through d + 1 points each: S (H, d+1, d) -> centres (H, d), radii (H,), NaN if
    none."""
    H, m, d = S.shape
    A = np.concatenate([2.0 * S, np.ones((H, m, 1))], axis=2)
    sol, ok = _solve_batched(A, np.einsum("hmi,hmi->hm", S, S))
    c = sol[:, :d]
    rho2 = sol[:, d] + np.einsum("hi,hi->h", c, c)
    rho = np.sqrt(np.where(ok & (rho2 > 0.0), rho2, np.nan))
    return c, rho


def _minimal_spheres_known_radius(S: FloatArray, rho: float) -> tuple[FloatArray, FloatArray]:
    """Spheres of radius ``rho`` through d points each: two centres per sample, either side of the
    points' affine hull. S (H, d, d) -> centres (2H, d), radii (2H,) (NaN: none)."""
    A = S[:, 1:, :] - S[:, :1, :]  # (H, d-1, d) edge vectors
    G = A @ A.transpose(0, 2, 1)
    lam, ok = _solve_batched(G, 0.5 * np.einsum("hii->hi", G))
    foot = S[:, 0, :] + np.einsum("hk,hki->hi", lam, A)  # circumcentre within the hull
    normal = np.linalg.svd(A, full_matrices=True)[2][:, -1, :]  # unit normal to the hull
    h2 = rho * rho - np.einsum("hi,hi->h", foot - S[:, 0, :], foot - S[:, 0, :])
    h = np.sqrt(np.where(ok & (h2 >= 0.0), h2, np.nan))
    centres = np.concatenate([foot + h[:, None] * normal, foot - h[:, None] * normal])
    return centres, np.where(np.isfinite(np.concatenate([h, h])), rho, np.nan)


def _msac(
    X: FloatArray, centres: FloatArray, radii: FloatArray, band: float
) -> tuple[FloatArray, FloatArray]:
    """Truncated quadratic cost and inlier count of every hypothesis on the points X, at once."""
    d2 = (
        np.einsum("si,si->s", X, X)[None, :]
        - 2.0 * centres @ X.T
        + np.einsum("hi,hi->h", centres, centres)[:, None]
    )
    r = np.abs(np.sqrt(np.maximum(d2, 0.0)) - radii[:, None])
    cost = np.minimum(r * r, band * band).sum(axis=1)
    count = (r < band).sum(axis=1)
    return cost, count


def _draw_samples(pool: FloatArray, m: int, local: float, gen: np.random.Generator) -> FloatArray:
    """A batch of minimal samples (_BATCH, m, d): half drawn from the whole pool, half as a random
    point and m - 1 random neighbours within ``local`` of it, so that a ball that holds only a small
    share of a cluttered scan is still sampled cleanly often enough (NAPSAC-style)."""
    n_pool = len(pool)
    n_glob = _BATCH // 2
    glob = pool[gen.integers(0, n_pool, size=(n_glob, m))]
    first = gen.integers(0, n_pool, size=_BATCH - n_glob)
    sq = np.einsum("pi,pi->p", pool, pool)
    far = sq[first][:, None] + sq[None, :] - 2.0 * (pool[first] @ pool.T) > local * local
    # Random keys, excluded points pushed to infinity: the m - 1 smallest are a random draw among
    # the neighbours.
    keys = np.where(far, np.inf, gen.random(far.shape))
    keys[np.arange(len(first)), first] = np.inf
    nb = np.argpartition(keys, m - 2, axis=1)[:, : m - 1]
    idx = np.concatenate([first[:, None], nb], axis=1)
    # Too few neighbours: repeat the first point, a degenerate sample that the conditioning check
    # downstream discards.
    void = ~np.isfinite(np.take_along_axis(keys, nb, axis=1)).all(axis=1)
    idx[void] = first[void, None]
    return np.concatenate([glob, pool[idx]])


def _search(
    sub: FloatArray,
    band: float,
    seeds: list[_Sphere],
    rho_known: float | None,
    rho_bounds: tuple[float, float],
    locals_: list[float],
    gen: np.random.Generator,
    max_hypotheses: int,
) -> tuple[_Sphere | None, int]:
    """Best sphere (MSAC cost at ``band``) among the ``seeds`` and minimal-sample hypotheses drawn
    until the adaptive count is reached (None if none is admissible), and the number drawn."""
    d = sub.shape[1]
    lo, hi = rho_bounds
    best_cost, best_c, best_rho, best_frac = math.inf, np.zeros(d), math.nan, 0.0
    m = d + 1 if rho_known is None else d

    def refine(c: FloatArray, rho: float, cost: float) -> tuple[FloatArray, float, float, int]:
        # Local optimisation (LO-RANSAC): a minimal sample of noisy points is a rough sphere;
        # refitting its consensus often scores much better and stops the search sooner.
        near = np.abs(_residuals(sub, c, rho)) < band
        refit = _riemann(sub, near.astype(np.float64))
        if refit is not None:
            c_lo, rho_lo = refit[0], (refit[1] if rho_known is None else rho_known)
            if lo <= rho_lo <= hi or rho_known is not None:
                cost_lo, count_lo = _msac(sub, c_lo[None, :], np.array([rho_lo]), band)
                if cost_lo[0] < cost:
                    return c_lo, rho_lo, float(cost_lo[0]), int(count_lo[0])
        return c, rho, cost, 0

    for c_s, rho_s in seeds:
        cost, count = _msac(sub, c_s[None, :], np.array([rho_s]), band)
        if cost[0] < best_cost:
            best_c, best_rho, best_cost, n_lo = refine(c_s, rho_s, float(cost[0]))
            best_frac = max(float(count[0]), n_lo) / len(sub)

    drawn, needed = 0, max_hypotheses
    while drawn < min(needed, max_hypotheses):
        local = locals_[(drawn // _BATCH) % len(locals_)]
        S = _draw_samples(sub[:_POOL_POINTS], m, local, gen)
        drawn += _BATCH
        if rho_known is None:
            centres, radii = _minimal_spheres(S)
            radii = np.where((radii >= lo) & (radii <= hi), radii, np.nan)
        else:
            centres, radii = _minimal_spheres_known_radius(S, rho_known)
        ok = np.isfinite(radii) & np.all(np.isfinite(centres), axis=1)
        if not ok.any():
            continue
        centres, radii = centres[ok], radii[ok]
        # Preemptive scoring: a first look on a few points, then only the best on all of them.
        quick, _ = _msac(sub[:_PREVIEW_POINTS], centres, radii, band)
        top = np.argsort(quick)[:_PREVIEW_KEEP]
        cost, count = _msac(sub, centres[top], radii[top], band)
        i = int(np.argmin(cost))
        if cost[i] < best_cost:
            best_c, best_rho, best_cost, n_lo = refine(
                centres[top[i]], float(radii[top[i]]), float(cost[i])
            )
            count = np.append(count, n_lo)
        best_frac = max(best_frac, float(count.max()) / len(sub))
        if best_frac > 0.0:
            p_clean = best_frac**m
            needed = (
                drawn
                if p_clean >= 1.0
                else math.ceil(math.log(1.0 - _CONFIDENCE) / math.log1p(-p_clean))
            )
    if not math.isfinite(best_cost):
        return None, drawn
    return (best_c, best_rho), drawn


def _supported(X: FloatArray, c: FloatArray) -> bool:
    """Whether the points X on a sphere about c fix all its parameters (centre and radius), each
    with the support of more than one point: the largest leverage of the geometric fit is below
    one half. Noise-free profiles make consensus sets that fail this: one profile's arc lies
    exactly on every sphere through its circle, and a single point off its plane picks one of
    them; such a set is exact at any band, but says nothing about the band the ball needs."""
    D, dist = _distances(X, c)
    J = np.column_stack([D / np.maximum(dist, 1e-300)[:, None], np.ones(len(X))])
    Q, sv, _ = np.linalg.svd(J, full_matrices=False)
    if not sv[-1] > 1e-8 * sv[0]:
        return False  # coplanar points: no sphere at all
    return float(np.einsum("ij,ij->i", Q, Q).max()) < 0.5


def _hypothesise(
    U: FloatArray,
    rho_known: float | None,
    rho_range: tuple[float, float] | None,
    band: float | None,
    gen: np.random.Generator,
    max_hypotheses: int,
) -> tuple[BoolArray, float | None]:
    """Consensus set (N,) of the best sphere hypothesis (all points if none is admissible) and the
    inlier band used (None when the stage was skipped).

    Without a given ``band`` the search starts at a band from the estimated noise. That estimate
    sees only noise: on noise-free data it collapses (exact planes such as a simulated table hold
    most neighbourhoods) while the ball may still depart from a sphere by far more (a sheared
    sweep). A band below that misfit leaves every hypothesis with little more than its own sample,
    and the choice is arbitrary (often a circle of table points). So the band is widened, and the
    search repeated, until the best sphere's consensus is complete: four times the band adds
    almost no points (the noise, or the misfit, lies within it)."""
    n, d = U.shape
    everything = np.ones(n, bool)
    if n < 2 * (4 * d + 4):
        # Too few points for the neighbourhood noise estimate and a meaningful consensus.
        return everything, None
    fixed_band = band is not None
    if band is None:
        band = _BAND_SIGMAS * _noise_sigma(U, gen)
    band = max(band, _SCALE_FLOOR_U)
    sub = U[gen.choice(n, size=min(n, _SCORE_POINTS), replace=False)]
    # Neighbourhood radii for local sampling, cycled batch by batch: about the sphere's radius.
    if rho_range is None:
        # No prior: a sphere wider than the scan is more likely a plane (the table) than the ball,
        # and the ball may be small: try several scales.
        lo, hi = 0.0, 0.5 * float(np.linalg.norm(U.max(axis=0) - U.min(axis=0)))
        locals_ = [hi / 2.0, hi / 4.0, hi / 8.0, hi / 16.0]
    else:
        lo, hi = rho_range
        locals_ = [hi, max(lo, hi / 2.0)]
    if rho_known is not None:
        locals_ = [rho_known]

    # The plain fit of all points competes too: it wins on clean data, whatever its radius (unless
    # a radius range was given).
    plain: list[_Sphere] = []
    whole = _riemann(sub, None)
    if whole is not None:
        rho_w = whole[1] if rho_known is None else rho_known
        if rho_range is None or lo <= rho_w <= hi:
            plain.append((whole[0], rho_w))

    m = d + 1 if rho_known is None else d
    # Widest band tried: a fraction of the sphere's size, beyond which the ball no longer stands
    # out from the clutter around it.
    band_max = _LADDER_MAX * (rho_known if rho_known is not None else hi)
    first: tuple[_Sphere | None, float] | None = None
    drawn = 0
    seeds, budget = plain, max_hypotheses
    while True:
        best, k = _search(sub, band, seeds, rho_known, (lo, hi), locals_, gen, budget)
        drawn += k
        if first is None:
            first = (best, band)
        if fixed_band or best is None:
            break
        r = np.abs(_residuals(sub, *best))
        near = r < band
        n_in = int(np.count_nonzero(near))
        n_wide = int(np.count_nonzero(r < _LADDER_STEP * band))
        # Judged only on enough points that fix the sphere between them (see _supported).
        n_need = _LADDER_MIN_SAMPLES * m
        judged = n_in >= n_need and _supported(sub[near], best[0])
        if judged and n_wide <= _LADDER_GROWTH * n_in:
            break
        if _LADDER_STEP * band > band_max:
            # No band makes a complete consensus: keep the noise-based one.
            best, band = first
            break
        log.debug("consensus %d/%d incomplete at band %.3g: widening", n_in, n_wide, band)
        # Nothing to judge: skip to the band that gives this sphere enough points more.
        k_more = min(n_in + n_need, len(r)) - 1
        enough = 0.0 if judged else float(np.partition(r, k_more)[k_more])
        band = max(_LADDER_STEP * band, min(enough, band_max))
        # Carried over, the best sphere so far is refitted at the wider band (LO step): fewer
        # fresh draws are needed there.
        seeds, budget = [*plain, best], max(_BATCH, max_hypotheses // 4)
    if best is None:
        log.debug("no admissible sphere hypothesis; starting from all points")
        return everything, band
    consensus: BoolArray = np.abs(_residuals(U, *best)) < band
    if consensus.sum() < d + 2:
        log.debug("hypothesis consensus too small (%d); starting from all points", consensus.sum())
        return everything, band
    log.debug(
        "best of %d hypotheses: %d/%d points within %.3g (normalised)",
        drawn,
        int(consensus.sum()),
        n,
        band,
    )
    return consensus, band


# --------------------------------------------------------------------------------------------
# robust fit


def _irls(
    U: FloatArray,
    c: FloatArray,
    rho: float,
    mask: BoolArray,
    robust: Robust,
    solve: Callable[[FloatArray, FloatArray, FloatArray, float], _Sphere],
    s_max: float,
    tol: float,
) -> tuple[FloatArray, float, BoolArray, float, FloatArray]:
    """Alternate robust weights (from geometric residuals) and a weighted solve until stable.

    ``s_max`` bounds the robust scale: from a poor start the MAD grows with every clutter point it
    takes in, and the fit would run off to the table."""
    for _ in range(_IRLS_ITER):
        r = _residuals(U, c, rho)
        s = min(_robust_scale(r, mask), s_max)
        new_mask = np.abs(r) <= _REJECT_U * s
        w = _weights(r / s, robust) * new_mask
        c_new, rho_new = solve(U, w, c, rho)
        step = max(float(np.max(np.abs(c_new - c))), abs(rho_new - rho))
        c, rho, mask = c_new, rho_new, new_mask
        # Stop once the steps are far below the statistical error of the centre (~ s / sqrt(n));
        # points flipping at the rejection cut carry almost no weight, so the step alone judges.
        if step < max(tol * s / math.sqrt(max(int(mask.sum()), 1)), 1e-13):
            break
    r = _residuals(U, c, rho)
    s = min(_robust_scale(r, mask), s_max)
    mask = np.abs(r) <= _REJECT_U * s
    return c, rho, mask, s, _weights(r / s, robust) * mask


def _fit_ball(
    P: FloatArray,
    radius: float | None,
    robust: Robust,
    radius_range: tuple[float, float] | None,
    rng: np.random.Generator | int | None,
    threshold: float | None,
    max_hypotheses: int,
) -> BallFit:
    n, d = P.shape
    if robust not in ("tukey", "huber", None):
        raise ValueError(f"robust must be 'tukey', 'huber' or None, got {robust!r}")
    r_known = _check_radius(radius)
    if radius_range is not None:
        if r_known is not None:
            raise ValueError("give either radius or radius_range, not both")
        lo, hi = (float(v) for v in radius_range)
        if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo < hi):
            raise ValueError(
                f"radius_range must be (min, max) with 0 <= min < max, got {radius_range}"
            )
    if threshold is not None and not (math.isfinite(threshold) and threshold > 0.0):
        raise ValueError(f"threshold must be a positive length (m), got {threshold!r}")
    if max_hypotheses < 1:
        raise ValueError(f"max_hypotheses must be >= 1, got {max_hypotheses}")

    origin, scale = _normaliser(P)
    U = (P - origin) / scale
    R_u = None if r_known is None else r_known / scale
    n_fixed = 0 if R_u is None else 1

    if robust is None:
        got = _riemann(U, None)
        if got is None:
            raise _degenerate(d)
        c, rho = got
        c, rho = _lm(U, np.ones(n), c, R_u if R_u is not None else rho, R_u)
        return _finish(P, origin, scale, c, rho, np.ones(n, bool), None, None, n_fixed)

    rho_range = None if radius_range is None else (radius_range[0] / scale, radius_range[1] / scale)
    band = None if threshold is None else threshold / scale
    gen = _as_generator(rng)
    mask, band = _hypothesise(U, R_u, rho_range, band, gen, max_hypotheses)
    s_max = math.inf if band is None else 2.0 * band
    # The algebraic stage only has to find the ball's points, and the first re-weightings only have
    # to come close: on a large cloud a random part of it does both as well and much cheaper.
    part = gen.choice(n, size=_PART_POINTS, replace=False) if n > _PART_POINTS else None
    U_a = U if part is None else U[part]

    def riemann_step(X: FloatArray, w: FloatArray, c: FloatArray, rho: float) -> _Sphere:
        got = _riemann(X, w)
        if got is None:
            raise _degenerate(d)
        return got

    def gn_step(X: FloatArray, w: FloatArray, c: FloatArray, rho: float) -> _Sphere:
        return _gauss_newton_step(X, w, c, rho, R_u)

    mask_a = mask if part is None else mask[part]
    c, rho = riemann_step(U_a, mask_a.astype(np.float64), np.zeros(d), 0.0)
    # Tolerances are in standard errors of the centre: loose while only the inliers are sought.
    c, rho, mask_a, s, _ = _irls(U_a, c, rho, mask_a, robust, riemann_step, s_max, 0.1)
    if R_u is not None:
        rho = R_u  # the algebraic stage fits the radius even when it is known; later ones hold it
    if part is None:
        mask = mask_a
    else:
        c, rho, mask_a, s, _ = _irls(U_a, c, rho, mask_a, robust, gn_step, s_max, 0.1)
        mask = np.abs(_residuals(U, c, rho)) <= _REJECT_U * s
    # The remaining re-weighting error after a 0.05 SE step is ~0.01 SE (the iteration contracts
    # ~5x per round); Levenberg-Marquardt then converges the fit for these weights.
    c, rho, mask, s, w = _irls(U, c, rho, mask, robust, gn_step, s_max, 0.05)
    c, rho = _lm(U, w, c, rho, R_u)
    if radius_range is not None and not (radius_range[0] <= rho * scale <= radius_range[1]):
        raise ValueError(
            f"no sphere with a radius in radius_range {radius_range} m fits these points: the fit "
            f"ended at radius {rho * scale:.6g} m (too few points on the ball among the clutter?)"
        )
    return _finish(P, origin, scale, c, rho, mask, robust, s * scale, n_fixed)


def _degenerate(d: int) -> ValueError:
    return ValueError(
        "points are degenerate (coplanar or collinear): no unique "
        + ("sphere; fit a circle and use sphere_centre_from_circle" if d == 3 else "circle")
    )


def _finish(
    P: FloatArray,
    origin: FloatArray,
    scale: float,
    c_u: FloatArray,
    rho_u: float,
    mask: BoolArray,
    robust: Robust,
    s: float | None,
    n_fixed: int,
) -> BallFit:
    """Back to metres; residuals, RMS and the centre covariance from the geometric Jacobian."""
    d = P.shape[1]
    centre = origin + scale * c_u
    radius = scale * rho_u
    D, dist = _distances(P, centre)
    res = dist - radius
    n_in = int(mask.sum())
    r_in = res[mask]
    rms = math.sqrt(float(np.mean(r_in * r_in))) if n_in else math.nan
    n_par = d + 1 - n_fixed
    J = -D[mask] / np.maximum(dist[mask], 1e-300)[:, None]
    if n_fixed == 0:
        J = np.column_stack([J, -np.ones(n_in)])
    dof = n_in - n_par
    cov_full = np.full((n_par, n_par), np.nan)
    if dof > 0:
        if s is None or robust is None:
            s_m = rms
            s2 = _dot(r_in, r_in) / dof
        else:
            # Huber (1981, 7.6) covariance of an M-estimate: scale^2 K^2 mean(psi^2)/mean(psi')^2,
            # which reduces to the least-squares s^2 when psi(u) = u.
            s_m = s
            psi, dpsi = _psi_dpsi(r_in / s, robust)
            m1 = float(dpsi.mean())
            if m1 > 0.1:
                k = 1.0 + n_par / n_in * float(dpsi.var()) / (m1 * m1)
                s2 = s * s * k * k * _dot(psi, psi) / dof / (m1 * m1)
            else:
                s2 = _dot(r_in, r_in) / dof
        try:
            cov_full = s2 * np.linalg.inv(J.T @ J)
        except np.linalg.LinAlgError:
            log.debug("singular Jacobian: centre covariance unknown")
    else:
        s_m = rms if s is None else s
    cls = {3: SphereFit, 2: CircleFit}.get(d, BallFit)
    out = cls(
        centre=_frozen(centre),
        radius=float(radius),
        rms=rms,
        inliers=_frozen(mask.copy()),
        cov_centre=_frozen(np.ascontiguousarray(cov_full[:d, :d])),
        n_inliers=n_in,
        residuals=_frozen(res),
        scale=float(s_m),
    )
    return out


_A = TypeVar("_A", bound=np.ndarray)


def _frozen(a: _A) -> _A:
    a.flags.writeable = False
    return a
