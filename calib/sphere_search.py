"""The hypothesis stage of the robust sphere and circle fits (:mod:`wristscan.calib.sphere`,
step 1 of its module doc): minimal samples drawn a batch at a time (half uniformly, half among
the neighbours of a random point), solved in one batched linear solve, scored with a truncated
quadratic (MSAC) cost, the best refitted on its consensus (LO-RANSAC); the inlier band from the
noise estimated on nearest-neighbour patches, widened while the best sphere's consensus is
incomplete. Normalised coordinates; draws from a seeded generator, so results repeat.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from wristscan.calib.sphere_algebra import SCALE_FLOOR_U, Sphere, distances, residuals, riemann

__all__ = ["hypothesise", "noise_sigma"]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

_BAND_SIGMAS = 3.0  # hypothesis inlier band, in estimated noise sigmas
_CONFIDENCE = 0.999  # probability of drawing at least one all-inlier minimal sample
_BATCH = 256  # hypotheses drawn per broadcast
_SCORE_POINTS = 2000  # points used to score hypotheses
_POOL_POINTS = 1000  # points minimal samples are drawn from
_PREVIEW_POINTS = 200  # points of the first, quick scoring of a batch
_PREVIEW_KEEP = 16  # hypotheses per batch that get the full scoring
_NOISE_POINTS = 1000  # neighbourhoods used for the noise estimate
_LADDER_STEP = 4.0  # factor by which the hypothesis band widens while the consensus is incomplete
_LADDER_GROWTH = 1.05  # consensus complete: widening the band by _LADDER_STEP adds < 5 % points
_LADDER_MIN_SAMPLES = 4  # ... and it holds at least this many minimal samples' worth of points
_LADDER_MAX = 0.1  # widest band, relative to the sphere's radius (or the largest one allowed)


def noise_sigma(U: FloatArray, gen: np.random.Generator) -> float:
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
    seeds: list[Sphere],
    rho_known: float | None,
    rho_bounds: tuple[float, float],
    locals_: list[float],
    gen: np.random.Generator,
    max_hypotheses: int,
) -> tuple[Sphere | None, int]:
    """Best sphere (MSAC cost at ``band``) among the ``seeds`` and minimal-sample hypotheses drawn
    until the adaptive count is reached (None if none is admissible), and the number drawn."""
    d = sub.shape[1]
    lo, hi = rho_bounds
    best_cost, best_c, best_rho, best_frac = math.inf, np.zeros(d), math.nan, 0.0
    m = d + 1 if rho_known is None else d

    def refine(c: FloatArray, rho: float, cost: float) -> tuple[FloatArray, float, float, int]:
        # Local optimisation (LO-RANSAC): a minimal sample of noisy points is a rough sphere;
        # refitting its consensus often scores much better and stops the search sooner.
        near = np.abs(residuals(sub, c, rho)) < band
        refit = riemann(sub, near.astype(np.float64))
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
    D, dist = distances(X, c)
    J = np.column_stack([D / np.maximum(dist, 1e-300)[:, None], np.ones(len(X))])
    Q, sv, _ = np.linalg.svd(J, full_matrices=False)
    if not sv[-1] > 1e-8 * sv[0]:
        return False  # coplanar points: no sphere at all
    return float(np.einsum("ij,ij->i", Q, Q).max()) < 0.5


def hypothesise(
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
        band = _BAND_SIGMAS * noise_sigma(U, gen)
    band = max(band, SCALE_FLOOR_U)
    sub = U[gen.choice(n, size=min(n, _SCORE_POINTS), replace=False)]
    lo, hi, locals_ = _local_scales(U, rho_known, rho_range)
    plain = _plain_seeds(sub, rho_known, rho_range, (lo, hi))
    best, band, drawn = _ladder(
        sub, band, fixed_band, plain, rho_known, (lo, hi), locals_, gen, max_hypotheses
    )
    if best is None:
        log.debug("no admissible sphere hypothesis; starting from all points")
        return everything, band
    consensus: BoolArray = np.abs(residuals(U, *best)) < band
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


def _local_scales(
    U: FloatArray, rho_known: float | None, rho_range: tuple[float, float] | None
) -> tuple[float, float, list[float]]:
    """Radius bounds of the hypotheses and the neighbourhood radii for local sampling, cycled
    batch by batch: about the sphere's radius."""
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
    return lo, hi, locals_


def _plain_seeds(
    sub: FloatArray,
    rho_known: float | None,
    rho_range: tuple[float, float] | None,
    bounds: tuple[float, float],
) -> list[Sphere]:
    """The plain fit of all points, which competes too: it wins on clean data, whatever its
    radius (unless a radius range was given)."""
    lo, hi = bounds
    plain: list[Sphere] = []
    whole = riemann(sub, None)
    if whole is not None:
        rho_w = whole[1] if rho_known is None else rho_known
        if rho_range is None or lo <= rho_w <= hi:
            plain.append((whole[0], rho_w))
    return plain


def _ladder(
    sub: FloatArray,
    band: float,
    fixed_band: bool,
    plain: list[Sphere],
    rho_known: float | None,
    bounds: tuple[float, float],
    locals_: list[float],
    gen: np.random.Generator,
    max_hypotheses: int,
) -> tuple[Sphere | None, float, int]:
    """Search at ``band``, widened (unless ``fixed_band``) until the best sphere's consensus is
    complete (see :func:`hypothesise`): the best sphere, the band and the hypotheses drawn."""
    d = sub.shape[1]
    _, hi = bounds
    m = d + 1 if rho_known is None else d
    # Widest band tried: a fraction of the sphere's size, beyond which the ball no longer stands
    # out from the clutter around it.
    band_max = _LADDER_MAX * (rho_known if rho_known is not None else hi)
    first: tuple[Sphere | None, float] | None = None
    drawn = 0
    seeds, budget = plain, max_hypotheses
    while True:
        best, k = _search(sub, band, seeds, rho_known, bounds, locals_, gen, budget)
        drawn += k
        if first is None:
            first = (best, band)
        if fixed_band or best is None:
            break
        r = np.abs(residuals(sub, *best))
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
    return best, band, drawn
