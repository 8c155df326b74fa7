"""Point-to-plane ICP between two scans of the same surface (metres, rigid motion only).

Used to measure (and optionally correct) the small misalignment left between passes after Eq. (1)
(the paper's section 4: up to ~0.5 mm between overlapping passes, removed by ICP).

Each iteration pairs every moved source point with its nearest target point (k-d tree), drops
pairs farther than ``max_distance`` and keeps the ``trim_fraction`` closest of the rest (robust to
partial overlap), then solves the linearised point-to-plane problem
``min sum (n_i . (R p_i + t - q_i))^2`` for a small rotation and translation (6x6 normal
equations) and composes the step onto the estimate.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from wristscan.calib import se3
from wristscan.calib.se3 import FloatArray

__all__ = ["IcpResult", "estimate_normals", "icp_point_to_plane", "point_to_plane_rms"]

log = logging.getLogger(__name__)

_NORMAL_BLOCK = 65536
"""Points per block in :func:`estimate_normals` (bounds the (block, k, 3) temporary)."""
_MIN_PAIRS = 6
_MIN_EIG_RATIO = 1e-5
"""Smallest / largest eigenvalue of the scaled normal matrix below which the geometry is taken as
not constraining all six degrees of freedom (a plane, a sphere, or a nearly flat patch, where a
solution would slide along the weak direction by noise / discretisation)."""


@dataclass(frozen=True)
class IcpResult:
    """Outcome of :func:`icp_point_to_plane` (metres, degrees where named)."""

    source2target: FloatArray
    """(4, 4) estimated transform mapping source coordinates into the target frame."""
    rmse_before: float
    """Point-to-plane RMS (m) of the kept pairs at ``init``."""
    rmse_after: float
    """Point-to-plane RMS (m) of the kept pairs at the result."""
    n_pairs: int
    """Pairs kept at the result."""
    iterations: int
    """Correspondence rounds performed."""
    converged: bool
    correction_translation_m: float
    """Translation of ``source2target @ inv(init)``: how far ICP moved from ``init`` (m)."""
    correction_rotation_deg: float
    """Rotation angle of ``source2target @ inv(init)`` (degrees)."""


def _points(a: ArrayLike, name: str, min_n: int = 1) -> FloatArray:
    p = np.asarray(a, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (N, 3), got {p.shape}")
    if p.shape[0] < min_n:
        raise ValueError(f"{name}: need at least {min_n} points, got {p.shape[0]}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name}: contains NaN or infinity")
    return p


def estimate_normals(
    points: ArrayLike, k: int = 12, viewpoint: ArrayLike | None = None
) -> FloatArray:
    """Unit surface normals (N, 3) of ``points`` (N, 3) by PCA of each point's ``k`` nearest
    neighbours (itself included): the eigenvector of the smallest covariance eigenvalue.

    The sign is arbitrary (point-to-plane ICP does not care) unless ``viewpoint`` (3,) is given:
    then every normal points towards it (e.g. the sensor position).
    """
    if k < 3:
        raise ValueError(f"k must be >= 3 neighbours, got {k}")
    p = _points(points, "points", min_n=k)
    tree = cKDTree(p)
    normals = np.empty_like(p)
    for a in range(0, p.shape[0], _NORMAL_BLOCK):
        b = min(a + _NORMAL_BLOCK, p.shape[0])
        _, nb = tree.query(p[a:b], k=k)
        q = p[nb]  # (m, k, 3)
        q -= q.mean(axis=1, keepdims=True)
        cov = np.einsum("mki,mkj->mij", q, q)
        _, vec = np.linalg.eigh(cov)  # ascending eigenvalues
        normals[a:b] = vec[:, :, 0]
    if viewpoint is not None:
        v = np.asarray(viewpoint, dtype=np.float64)
        if v.shape != (3,):
            raise ValueError(f"viewpoint: expected (3,), got {v.shape}")
        flip = np.einsum("ni,ni->n", normals, v - p) < 0
        normals[flip] *= -1.0
    return normals


def _pairs(
    tree: cKDTree, moved: FloatArray, max_distance: float, trim_fraction: float
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """(source rows, target rows) of the kept nearest-neighbour pairs, as index arrays."""
    dist, j = tree.query(moved, k=1, distance_upper_bound=max_distance)
    ok = np.flatnonzero(np.isfinite(dist))
    if trim_fraction < 1.0 and ok.size > _MIN_PAIRS:
        keep = max(_MIN_PAIRS, math.ceil(trim_fraction * ok.size))
        if keep < ok.size:
            # Sorted so that equal pair sets compare equal (see the repeat test in the ICP loop).
            ok = np.sort(ok[np.argpartition(dist[ok], keep - 1)[:keep]])
    return ok, np.asarray(j[ok], dtype=np.intp)


def point_to_plane_rms(
    source: ArrayLike,
    target: ArrayLike,
    target_normals: ArrayLike,
    max_distance: float = math.inf,
) -> float:
    """RMS (m) of ``n . (s - q)`` over source points whose nearest target point ``q`` lies within
    ``max_distance`` (m). Raises ``ValueError`` if no pair qualifies."""
    s = _points(source, "source")
    t = _points(target, "target")
    n = _normals(target_normals, t.shape[0])
    si, ti = _pairs(cKDTree(t), s, max_distance, 1.0)
    if si.size == 0:
        raise ValueError(f"no source point within max_distance={max_distance} m of the target")
    r = np.einsum("ni,ni->n", n[ti], s[si] - t[ti])
    return float(np.sqrt(np.mean(r * r)))


def _normals(a: ArrayLike, m: int) -> FloatArray:
    n = np.asarray(a, dtype=np.float64)
    if n.shape != (m, 3):
        raise ValueError(f"target_normals: expected shape ({m}, 3), got {n.shape}")
    norm = np.linalg.norm(n, axis=1)
    if not np.all(np.isfinite(norm)) or np.any(np.abs(norm - 1.0) > 1e-3):
        raise ValueError("target_normals must be finite unit vectors")
    return n


def _check_constrained(arm: FloatArray, n: FloatArray, scale: float) -> None:
    """Refuse geometry that leaves a rigid motion free. Arms are taken from the target points:
    with the source points the discrete pairing hides e.g. a sphere's free rotations."""
    J = np.concatenate([np.cross(arm, n) / scale, n], axis=1)
    ev = np.linalg.eigvalsh(J.T @ J)
    if ev[0] < _MIN_EIG_RATIO * ev[-1]:
        raise ValueError(
            "the overlap does not constrain all 6 degrees of freedom (plane, sphere, cylinder "
            f"or a nearly flat patch; eigenvalue ratio {ev[0] / ev[-1]:.1e}): ICP is ill-posed "
            "on this geometry"
        )


def icp_point_to_plane(
    source: ArrayLike,
    target: ArrayLike,
    target_normals: ArrayLike | None = None,
    init: ArrayLike | None = None,
    max_iter: int = 50,
    max_distance: float = math.inf,
    trim_fraction: float = 0.9,
    tol: float = 1e-7,
    normal_k: int = 12,
) -> IcpResult:
    """Align ``source`` (N, 3) onto ``target`` (M, 3) (metres); returns the estimated
    ``source2target`` and fit statistics.

    ``target_normals`` (M, 3) unit vectors, estimated with :func:`estimate_normals` (``normal_k``
    neighbours) when omitted. ``init`` (4, 4) is the starting ``source2target`` (identity when
    omitted). Pairs farther than ``max_distance`` (m) are rejected, then only the
    ``trim_fraction`` (0 < f <= 1) closest pairs are used. Iteration stops when a step moves no
    source point by more than ``tol`` (m) or when the kept pair set repeats an earlier one (a
    fixed point or a limit cycle of the trimmed pairs), else after ``max_iter`` steps
    (``converged=False``).

    Raises ``ValueError`` on bad shapes or parameters, when fewer than 6 pairs remain, or when
    the overlap does not constrain all six degrees of freedom (checked on the first pairing,
    e.g. a plane or a nearly flat patch). Symmetric shapes (sphere, cylinder) are caught only
    with exact normals: errors of estimated normals break the symmetry and hide the free
    rotation, so the overlap must hold asymmetric features.
    """
    src = _points(source, "source", min_n=_MIN_PAIRS)
    tgt = _points(target, "target", min_n=max(_MIN_PAIRS, normal_k))
    if not 0.0 < trim_fraction <= 1.0:
        raise ValueError(f"trim_fraction must be in (0, 1], got {trim_fraction}")
    if not max_distance > 0.0:
        raise ValueError(f"max_distance must be > 0 m, got {max_distance}")
    if max_iter < 1:
        raise ValueError(f"max_iter must be >= 1, got {max_iter}")
    normals = (
        estimate_normals(tgt, normal_k)
        if target_normals is None
        else _normals(target_normals, tgt.shape[0])
    )
    T0 = se3.identity() if init is None else se3.check_transform(init, "init")
    if T0.shape != (4, 4):
        raise ValueError(f"init: expected (4, 4), got {T0.shape}")

    tree = cKDTree(tgt)
    pairing = _Pairing(tree, tgt, normals, max_distance, trim_fraction)
    T, rmse_before, converged, it = _iterate(src, pairing, T0, max_iter, tol)

    R, t = T[:3, :3], T[:3, 3]
    moved = src @ R.T + t
    si, ti = _pairs(tree, moved, max_distance, trim_fraction)
    if si.size < _MIN_PAIRS:
        raise ValueError(f"ICP diverged: only {si.size} pairs left at the result")
    r = np.einsum("ni,ni->n", normals[ti], moved[si] - tgt[ti])
    rmse_after = float(np.sqrt(np.mean(r * r)))
    corr = T @ se3.invert(T0)
    log.debug(
        "icp: %d iterations, converged=%s, rmse %.3g -> %.3g m, %d pairs",
        it,
        converged,
        rmse_before,
        rmse_after,
        si.size,
    )
    return IcpResult(
        source2target=T,
        rmse_before=rmse_before,
        rmse_after=rmse_after,
        n_pairs=int(si.size),
        iterations=it,
        converged=converged,
        correction_translation_m=float(np.linalg.norm(corr[:3, 3])),
        correction_rotation_deg=float(np.degrees(se3.rotation_angle(corr[:3, :3]))),
    )


@dataclass(frozen=True)
class _Pairing:
    """The target side of the ICP: its points, normals and k-d tree, and the pairing limits."""

    tree: cKDTree
    points: FloatArray
    normals: FloatArray
    max_distance: float
    trim_fraction: float


def _iterate(
    src: FloatArray, tg: _Pairing, T0: FloatArray, max_iter: int, tol: float
) -> tuple[FloatArray, float, bool, int]:
    """The ICP loop from ``T0``: returns the estimate, the RMS of the first pairing, whether it
    converged and the number of correspondence rounds."""
    # Rotations are linearised about the source centroid with a length scale so that the six
    # unknowns have comparable size (better conditioned normal equations).
    centroid = src.mean(axis=0)
    local = src - centroid
    radii = np.linalg.norm(local, axis=1)
    scale = float(np.sqrt(np.mean(radii**2)))
    reach = float(radii.max())
    if scale <= 0.0:
        raise ValueError("source points coincide")

    T = T0.copy()
    rmse_before = math.nan
    converged = False
    it = 0
    seen: dict[int, int] = {}  # hash of a kept pair set -> iteration it was seen at
    for it in range(1, max_iter + 1):
        R, t = T[:3, :3], T[:3, 3]
        moved = src @ R.T + t
        si, ti = _pairs(tg.tree, moved, tg.max_distance, tg.trim_fraction)
        if si.size < _MIN_PAIRS:
            raise ValueError(
                f"only {si.size} source points within max_distance={tg.max_distance} m of the "
                "target; improve init or raise max_distance"
            )
        # With noise, trimming can flip a few pairs back and forth: once a pair set repeats,
        # the estimate only cycles among poses that differ by less than the noise.
        key = hash((si.tobytes(), ti.tobytes()))
        if key in seen:
            converged = True
            break
        seen[key] = it
        n = tg.normals[ti]
        c = R @ centroid + t  # moved centroid: rotation pivot
        r = np.einsum("ni,ni->n", n, moved[si] - tg.points[ti])
        if it == 1:
            rmse_before = float(np.sqrt(np.mean(r * r)))
            _check_constrained(tg.points[ti] - c, n, scale)
        step, moved_by = _step(moved[si] - c, n, r, c, scale, reach)
        T = step @ T
        if moved_by < tol:
            converged = True
            break
    return T, rmse_before, converged, it


def _step(
    arm: FloatArray, n: FloatArray, r: FloatArray, c: FloatArray, scale: float, reach: float
) -> tuple[FloatArray, float]:
    """The linearised point-to-plane step about the pivot ``c`` (arms ``arm`` from it, normals
    ``n``, residuals ``r``), and an upper bound of how far it moves any source point (m)."""
    # r_i + (arm_i x n_i) . w + n_i . v = 0, with w scaled by `scale` for conditioning.
    J = np.concatenate([np.cross(arm, n) / scale, n], axis=1)
    H = J.T @ J
    g = J.T @ r
    x = -np.linalg.solve(H, g)
    w = x[:3] / scale
    v = x[3:]
    dR = se3.rotvec_to_matrix(w)
    # Step about the moved centroid: p -> dR (p - c) + c + v.
    step = se3.make(dR, c + v - dR @ c)
    return step, float(np.linalg.norm(v)) + float(np.linalg.norm(w)) * reach
