"""Edge paths: raw edge points smoothed and resampled at a resolution (Borangiu et al. 2009,
section 5: "the robot learns the trajectory with a resolution specified by the user").

Raw edge points (one per profile, in acquisition order) are parametrised by arc length,
smoothed by local quadratic regression (Gaussian kernel of ``bandwidth_m``), re-parametrised on
the smoothed curve and resampled at exactly ``resolution_m``. The local quadratic follows
curvature without the shrinkage of a moving average. Normals measured in the laser plane miss
their component along the sensor's X axis; given that axis per point, they are completed with
the condition that the surface normal is perpendicular to the edge tangent.

Base frame, metres. The edge models found in one profile are :mod:`wristscan.calib.edge`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

__all__ = ["EdgePath", "smooth_path"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class EdgePath:
    """An edge path resampled at a constant spacing (base frame, metres)."""

    points: FloatArray
    """(K, 3) points spaced ``resolution_m`` along the smoothed curve."""
    tangents: FloatArray
    """(K, 3) unit tangents in the direction of travel."""
    normals: FloatArray
    """(K, 3) unit surface normals, perpendicular to the tangents (zeros when not given)."""
    s: FloatArray
    """(K,) arc length from the first point (m)."""
    resolution_m: float
    support: FloatArray
    """(K,) raw points within half a spacing of each station."""
    residual_rms_m: float
    """RMS distance of the raw points to the smoothed curve."""
    max_gap_m: float
    """Largest arc-length gap between consecutive raw points (m): the path has no hole wider."""

    @property
    def length_m(self) -> float:
        return float(self.s[-1]) if self.s.size else 0.0


def _loess(
    s: FloatArray,
    values: FloatArray,
    stations: FloatArray,
    h: float,
    weights: FloatArray,
    degree: int = 2,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Local polynomial regression of ``values (N, m)`` over sorted ``s`` at ``stations``:
    returns values, first derivatives (K, m) and the kernel weight sums (K,)."""
    lo = np.searchsorted(s, stations - 3 * h, side="left")
    hi = np.searchsorted(s, stations + 3 * h, side="right")
    width = int(max(1, (hi - lo).max()))
    K = stations.shape[0]
    m = values.shape[1]
    out = np.full((K, m), np.nan)
    der = np.full((K, m), np.nan)
    wsum = np.zeros(K)
    chunk = max(1, 2_000_000 // width)
    for c0 in range(0, K, chunk):
        c1 = min(K, c0 + chunk)
        idx = lo[c0:c1, None] + np.arange(width)[None, :]
        inside = idx < hi[c0:c1, None]
        idx = np.minimum(idx, s.shape[0] - 1)
        d = (s[idx] - stations[c0:c1, None]) / h
        w = np.where(inside, np.exp(-0.5 * d * d), 0.0) * weights[idx]
        cols = [np.ones_like(d), d, d * d][: degree + 1]
        X = np.stack(cols, axis=-1)  # (k, W, p)
        XtW = X * w[..., None]
        A = np.einsum("kwp,kwq->kpq", XtW, X)
        B = np.einsum("kwp,kwm->kpm", XtW, values[idx])
        p = degree + 1
        ridge = 1e-9 * np.maximum(np.trace(A, axis1=1, axis2=2), 1e-300)
        A = A + ridge[:, None, None] * np.eye(p)
        coef = np.linalg.solve(A, B)  # (k, p, m)
        out[c0:c1] = coef[:, 0, :]
        der[c0:c1] = coef[:, 1, :] / h
        wsum[c0:c1] = w.sum(axis=1)
    return out, der, wsum


def _arc(points: FloatArray) -> FloatArray:
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)])


def _project_on_polyline(poly: FloatArray, s_poly: FloatArray, P: FloatArray) -> FloatArray:
    """Arc-length parameter of the nearest point of ``poly`` to each of ``P``."""
    tree = cKDTree(poly)
    _, j = tree.query(P)
    j = np.asarray(j, dtype=np.int64)
    # Refine on the two neighbouring segments.
    best_s = s_poly[j].astype(np.float64)
    best_d = np.linalg.norm(P - poly[j], axis=1)
    for k0 in (j - 1, j):
        k0 = np.clip(k0, 0, poly.shape[0] - 2)
        a, b = poly[k0], poly[k0 + 1]
        ab = b - a
        L2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
        t = np.clip(np.einsum("ij,ij->i", P - a, ab) / L2, 0.0, 1.0)
        q = a + t[:, None] * ab
        dist = np.linalg.norm(P - q, axis=1)
        better = dist < best_d
        best_d = np.where(better, dist, best_d)
        best_s = np.where(better, s_poly[k0] + t * np.sqrt(L2), best_s)
    return np.asarray(best_s)


def smooth_path(
    points: ArrayLike,
    resolution_m: float = 0.001,
    *,
    bandwidth_m: float | None = None,
    normals: ArrayLike | None = None,
    view_x: ArrayLike | None = None,
    weights: ArrayLike | None = None,
) -> EdgePath:
    """Smooth raw edge points ``(N, 3)`` given in acquisition order and resample them every
    ``resolution_m`` along the curve (see the module doc).

    ``bandwidth_m``: kernel width (default: the resolution, at least 0.5 mm). ``normals
    (N, 3)``: measured surface normals (laser-plane projections when ``view_x (N, 3)``, the
    sensor X axis per point, is given: they are completed to be perpendicular to the edge).
    ``weights (N,)``: confidence per point. Raises ValueError with fewer than 5 points or a path
    shorter than one resolution step.
    """
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {P.shape}")
    if P.shape[0] < 5:
        raise ValueError("a path needs at least 5 points")
    if not resolution_m > 0:
        raise ValueError("resolution_m must be positive")
    n = P.shape[0]
    W = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64).reshape(n)
    h = float(bandwidth_m) if bandwidth_m is not None else max(float(resolution_m), 0.0005)
    res = float(resolution_m)
    s1 = _parameter(P, W, h, res)
    order = np.argsort(s1, kind="stable")
    s1s = s1[order]
    Ps, Ws = P[order], W[order]
    u, pts, tang = _stations(s1s, Ps, Ws, h, res)
    nrm = np.zeros_like(pts)
    if normals is not None:
        N = _completed_normals(normals, view_x, s1, u, tang)
        nv, _, _ = _loess(s1s, N[order], u, h, Ws, degree=1)
        nv = nv - np.einsum("ij,ij->i", nv, tang)[:, None] * tang
        nrm = nv / np.maximum(np.linalg.norm(nv, axis=1, keepdims=True), 1e-300)
    return _with_statistics(P, pts, tang, nrm, res)


def _parameter(P: FloatArray, W: FloatArray, h: float, res: float) -> FloatArray:
    """Steps 1-3 of the smoothing: arc length of a running mean in acquisition order, a first
    smooth curve densely sampled on it, and each raw point's arc length on that curve."""
    n = P.shape[0]
    # 1. A first parameter: arc length of a running mean in acquisition order.
    k = int(min(15, max(1, n // 5)))
    kernel = np.ones(k) / k
    pad = np.pad(P, ((k // 2, k - 1 - k // 2), (0, 0)), mode="edge")
    Q = np.column_stack([np.convolve(pad[:, i], kernel, mode="valid") for i in range(3)])
    s0 = _arc(Q)
    if s0[-1] < res:
        raise ValueError(f"the path is only {s0[-1] * 1e3:.2f} mm long")
    order = np.argsort(s0, kind="stable")
    s0, P0, W0 = s0[order], P[order], W[order]
    # 2. A first smooth curve, densely sampled.
    dense_step = min(h, res) / 4
    st0 = np.arange(s0[0], s0[-1] + 1e-12, dense_step)
    C1, _, _ = _loess(s0, P0, st0, h, W0)
    ok = np.all(np.isfinite(C1), axis=1)
    C1 = C1[ok]
    s_c1 = _arc(C1)
    # 3. Parameter = arc length of the nearest point on it.
    return _project_on_polyline(C1, s_c1, P)


def _stations(
    s1s: FloatArray, Ps: FloatArray, Ws: FloatArray, h: float, res: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The final curve resampled at exactly ``res`` along its own arc length: the parameters of
    the stations, their points and unit tangents."""
    dense_step = min(h, res) / 4
    dense = np.arange(s1s[0], s1s[-1] + 1e-12, dense_step)
    Cd, _, _ = _loess(s1s, Ps, dense, h, Ws)
    s_cd = _arc(Cd)
    targets = np.arange(0.0, s_cd[-1] + 1e-12, res)
    u = np.interp(targets, s_cd, dense)
    pts, der, _ = _loess(s1s, Ps, u, h, Ws)
    tang = der / np.maximum(np.linalg.norm(der, axis=1, keepdims=True), 1e-300)
    return u, pts, tang


def _completed_normals(
    normals: ArrayLike, view_x: ArrayLike | None, s1: FloatArray, u: FloatArray, tang: FloatArray
) -> FloatArray:
    """The measured normals (N, 3) as unit vectors; with ``view_x`` completed along it to be
    perpendicular to the curve's tangent at each raw point (parameter ``s1``)."""
    n = s1.shape[0]
    N = np.asarray(normals, dtype=np.float64).reshape(n, 3)
    if view_x is not None:
        X = np.asarray(view_x, dtype=np.float64).reshape(n, 3)
        # Tangent at each raw point from the curve, then n = n_m + lam X with n . t = 0.
        t_raw = np.column_stack([np.interp(s1, u, tang[:, i]) for i in range(3)])
        xt = np.einsum("ij,ij->i", X, t_raw)
        nt = np.einsum("ij,ij->i", N, t_raw)
        lam = np.where(np.abs(xt) > 0.2, -nt / np.where(np.abs(xt) > 0.2, xt, 1.0), 0.0)
        N = N + lam[:, None] * X
    return np.asarray(N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-300))


def _with_statistics(
    P: FloatArray, pts: FloatArray, tang: FloatArray, nrm: FloatArray, res: float
) -> EdgePath:
    """The path with its statistics against the raw points ``P``."""
    n = P.shape[0]
    s_final = _arc(pts)
    s_fp = _project_on_polyline(pts, s_final, P) if pts.shape[0] >= 2 else np.zeros(n)
    near = np.column_stack([np.interp(s_fp, s_final, pts[:, i]) for i in range(3)])
    # Points past the last station (less than a spacing) project onto the end: not residuals.
    inside = s_fp < s_final[-1] - 1e-9
    resid = np.linalg.norm(P - near, axis=1)[inside]
    gaps = np.diff(np.sort(s_fp))
    support = np.histogram(s_fp, bins=np.concatenate([s_final - res / 2, [s_final[-1] + res / 2]]))[
        0
    ].astype(np.float64)
    return EdgePath(
        points=pts,
        tangents=tang,
        normals=nrm,
        s=s_final,
        resolution_m=res,
        support=support,
        residual_rms_m=float(np.sqrt(np.mean(resid**2))) if resid.size else 0.0,
        max_gap_m=float(gaps.max()) if gaps.size else 0.0,
    )
