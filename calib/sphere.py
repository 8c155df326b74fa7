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

import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import sphere_check
from wristscan.calib.sphere_algebra import (
    REJECT_U,
    Robust,
    Sphere,
    distances,
    dot,
    gauss_newton_step,
    lm,
    psi_dpsi,
    residuals,
    riemann,
    robust_scale,
    weights,
)
from wristscan.calib.sphere_check import ImplausibleFit
from wristscan.calib.sphere_search import hypothesise

__all__ = [
    "BallFit",
    "CircleFit",
    "ImplausibleFit",
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

_IRLS_ITER = 30
_PART_POINTS = 20000  # points the first IRLS stages work on, at most


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
    plausible: bool = True
    """False when the fit does not look like the ball (:mod:`~wristscan.calib.sphere_check`)."""
    why: str = ""
    """Why the fit is implausible (empty when plausible)."""
    noise_m: float = math.nan
    """The noise (m) the RMS was judged against: the given one, else the estimated one."""


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
    noise_m: float | None = None,
    expected_radius: tuple[float, float] | None = None,
    min_fraction: float | None = None,
    strict: bool = False,
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

    Plausibility (:mod:`~wristscan.calib.sphere_check`): the result's ``plausible`` is False, and
    ``why`` says why, when its RMS is far above ``noise_m`` (the sensor's noise sigma, m; default
    the noise estimated from the points), its radius outside ``expected_radius`` (m) or its
    inliers few (or fewer than ``min_fraction`` of the points). ``strict`` raises
    :class:`~wristscan.calib.sphere_check.ImplausibleFit` (a ValueError) instead.
    """
    P = _as_points(points, 3)
    fit = _fit_ball(P, radius, robust, radius_range, rng, threshold, max_hypotheses)
    judged = _judged(fit, P, radius is not None, noise_m, expected_radius, min_fraction, strict)
    return cast(SphereFit, judged)


def fit_circle(
    points: ArrayLike,
    radius: float | None = None,
    robust: Robust = "tukey",
    *,
    radius_range: tuple[float, float] | None = None,
    rng: np.random.Generator | int | None = None,
    threshold: float | None = None,
    max_hypotheses: int = 4096,
    noise_m: float | None = None,
    expected_radius: tuple[float, float] | None = None,
    min_fraction: float | None = None,
    strict: bool = False,
) -> CircleFit:
    """Fit a circle to ``points`` (N, 2) in metres, e.g. one profile's ``(y, z)`` arc of the ball.

    Same arguments and behaviour as :func:`fit_sphere`, in the plane (needs at least 3 points). For
    a profile of a ball of known radius R, the circle radius is unknown: pass
    ``radius_range=(0, 1.01 * R)`` (a little slack for noise near the equator) and recover the
    sphere centre with :func:`sphere_centre_from_circle`. A circle through the corners of a box
    beside a short arc of the ball comes back with ``plausible`` False (see :func:`fit_sphere`).
    """
    P = _as_points(points, 2)
    fit = _fit_ball(P, radius, robust, radius_range, rng, threshold, max_hypotheses)
    judged = _judged(fit, P, radius is not None, noise_m, expected_radius, min_fraction, strict)
    return cast(CircleFit, judged)


def _judged(
    fit: BallFit,
    P: FloatArray,
    radius_known: bool,
    noise_m: float | None,
    expected_radius: tuple[float, float] | None,
    min_fraction: float | None,
    strict: bool,
) -> BallFit:
    """``fit`` with its plausibility (:func:`~wristscan.calib.sphere_check.judge`)."""
    if noise_m is not None and not (math.isfinite(noise_m) and noise_m > 0.0):
        raise ValueError(f"noise_m must be a positive length (m), got {noise_m!r}")
    noise = sphere_check.estimated_noise(P) if noise_m is None else float(noise_m)
    d = P.shape[1]
    why = sphere_check.judge(
        rms=fit.rms,
        radius=fit.radius,
        n_inliers=fit.n_inliers,
        n_points=P.shape[0],
        n_parameters=d + (0 if radius_known else 1),
        noise_m=noise,
        expected_radius=expected_radius,
        min_fraction=min_fraction,
    )
    if why and strict:
        raise sphere_check.ImplausibleFit(why)
    return dataclasses.replace(fit, plausible=not why, why=why, noise_m=noise)


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
    c, rho = lm(U, np.ones(len(U)), c0, rho0, R_u)
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
# --------------------------------------------------------------------------------------------
# robust fit


def _irls(
    U: FloatArray,
    c: FloatArray,
    rho: float,
    mask: BoolArray,
    robust: Robust,
    solve: Callable[[FloatArray, FloatArray, FloatArray, float], Sphere],
    s_max: float,
    tol: float,
) -> tuple[FloatArray, float, BoolArray, float, FloatArray]:
    """Alternate robust weights (from geometric residuals) and a weighted solve until stable.

    ``s_max`` bounds the robust scale: from a poor start the MAD grows with every clutter point it
    takes in, and the fit would run off to the table."""
    for _ in range(_IRLS_ITER):
        r = residuals(U, c, rho)
        s = min(robust_scale(r, mask), s_max)
        new_mask = np.abs(r) <= REJECT_U * s
        w = weights(r / s, robust) * new_mask
        c_new, rho_new = solve(U, w, c, rho)
        step = max(float(np.max(np.abs(c_new - c))), abs(rho_new - rho))
        c, rho, mask = c_new, rho_new, new_mask
        # Stop once the steps are far below the statistical error of the centre (~ s / sqrt(n));
        # points flipping at the rejection cut carry almost no weight, so the step alone judges.
        if step < max(tol * s / math.sqrt(max(int(mask.sum()), 1)), 1e-13):
            break
    r = residuals(U, c, rho)
    s = min(robust_scale(r, mask), s_max)
    mask = np.abs(r) <= REJECT_U * s
    return c, rho, mask, s, weights(r / s, robust) * mask


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
        got = riemann(U, None)
        if got is None:
            raise _degenerate(d)
        c, rho = got
        c, rho = lm(U, np.ones(n), c, R_u if R_u is not None else rho, R_u)
        return _finish(P, origin, scale, c, rho, np.ones(n, bool), None, None, n_fixed)

    rho_range = None if radius_range is None else (radius_range[0] / scale, radius_range[1] / scale)
    band = None if threshold is None else threshold / scale
    gen = _as_generator(rng)
    mask, band = hypothesise(U, R_u, rho_range, band, gen, max_hypotheses)
    s_max = math.inf if band is None else 2.0 * band
    # The algebraic stage only has to find the ball's points, and the first re-weightings only have
    # to come close: on a large cloud a random part of it does both as well and much cheaper.
    part = gen.choice(n, size=_PART_POINTS, replace=False) if n > _PART_POINTS else None
    U_a = U if part is None else U[part]

    def riemann_step(X: FloatArray, w: FloatArray, c: FloatArray, rho: float) -> Sphere:
        got = riemann(X, w)
        if got is None:
            raise _degenerate(d)
        return got

    def gn_step(X: FloatArray, w: FloatArray, c: FloatArray, rho: float) -> Sphere:
        return gauss_newton_step(X, w, c, rho, R_u)

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
        mask = np.abs(residuals(U, c, rho)) <= REJECT_U * s
    # The remaining re-weighting error after a 0.05 SE step is ~0.01 SE (the iteration contracts
    # ~5x per round); Levenberg-Marquardt then converges the fit for these weights.
    c, rho, mask, s, w = _irls(U, c, rho, mask, robust, gn_step, s_max, 0.05)
    c, rho = lm(U, w, c, rho, R_u)
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
    D, dist = distances(P, centre)
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
            s2 = dot(r_in, r_in) / dof
        else:
            # Huber (1981, 7.6) covariance of an M-estimate: scale^2 K^2 mean(psi^2)/mean(psi')^2,
            # which reduces to the least-squares s^2 when psi(u) = u.
            s_m = s
            psi, dpsi = psi_dpsi(r_in / s, robust)
            m1 = float(dpsi.mean())
            if m1 > 0.1:
                k = 1.0 + n_par / n_in * float(dpsi.var()) / (m1 * m1)
                s2 = s * s * k * k * dot(psi, psi) / dof / (m1 * m1)
            else:
                s2 = dot(r_in, r_in) / dof
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
