"""Rigid corrections of overlapping clouds, measured point to plane: which points of one cloud
overlap another (nearest point close enough, normals agreeing), how well an overlap constrains a
rigid correction (the information matrix of its pairs, and the directions it leaves free), and
one linearised least-squares step of several clouds at once (multi-view point-to-plane).

The building blocks of :func:`wristscan.calib.merge.merge_passes`; metres throughout. Free
directions matter: a cylinder leaves a rotation about its axis free, a groove a slide along it,
and noise alone would drive a correction along them, so such directions are left as they were.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from wristscan.calib import se3

__all__ = [
    "MIN_OVERLAP_POINTS",
    "Constraint",
    "OrientedCloud",
    "constraint",
    "joint_step",
    "overlap",
    "restrict",
    "rms_against",
    "strong_directions",
    "transform_points",
    "union",
]

FloatArray = NDArray[np.float64]

MIN_OVERLAP_POINTS = 200
"""Fewest pairs an overlap needs to measure a correction."""
_JOINT_NEIGHBOURS = 12
"""Neighbours searched per point for one from another pass (voxelised passes: a few each)."""


def transform_points(T: FloatArray, p: FloatArray) -> FloatArray:
    """Points ``p`` (N, 3) moved by the rigid transform ``T`` (4, 4)."""
    return np.asarray(p @ T[:3, :3].T + T[:3, 3])


@dataclass
class OrientedCloud:
    """Points (N, 3) and their unit normals (N, 3)."""

    xyz: FloatArray
    normals: FloatArray


def overlap(
    src: OrientedCloud, tgt: OrientedCloud, tree: cKDTree, max_d: float, cos_agree: float
) -> tuple[NDArray[np.bool_], NDArray[np.intp]]:
    """Which ``src`` points overlap ``tgt`` (``tree`` of its points): the nearest target point
    within ``max_d`` and the normals' cosine above ``cos_agree``; and that nearest point."""
    d, j = tree.query(src.xyz, k=1, distance_upper_bound=max_d)
    ok = np.isfinite(d)
    jj = np.where(ok, j, 0)
    ok &= np.einsum("ij,ij->i", src.normals, tgt.normals[jj]) > cos_agree
    return ok, jj


@dataclass(frozen=True)
class Constraint:
    """How well an overlap constrains a rigid correction: the information matrix of the
    point-to-plane pairs (rotations scaled by ``scale_m`` about ``pivot``)."""

    H: FloatArray
    rms_m: float
    pivot: FloatArray
    scale_m: float
    n_pairs: int


def constraint(
    src: FloatArray, tgt: OrientedCloud, tree: cKDTree, max_d: float
) -> Constraint | None:
    """The constraint of the pairs of ``src`` points with their nearest ``tgt`` point within
    ``max_d``; None with fewer than :data:`MIN_OVERLAP_POINTS` pairs."""
    d, j = tree.query(src, k=1, distance_upper_bound=max_d)
    ok = np.isfinite(d)
    if ok.sum() < MIN_OVERLAP_POINTS:
        return None
    p = src[ok]
    n = tgt.normals[j[ok]]
    r = np.einsum("ij,ij->i", n, p - tgt.xyz[j[ok]])
    pivot = p.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((p - pivot) ** 2, axis=1))))
    J = np.concatenate([np.cross(p - pivot, n) / scale, n], axis=1)
    return Constraint(J.T @ J, float(np.sqrt(np.mean(r * r))), pivot, scale, int(ok.sum()))


def _twist(T: FloatArray, pivot: FloatArray, scale: float) -> FloatArray:
    """``[w * scale, v]``: rotation vector (scaled to metres at ``scale``) and displacement of
    ``pivot`` of a small rigid motion ``T``."""
    w = se3.matrix_to_rotvec(T[:3, :3])
    v = T[:3, :3] @ pivot + T[:3, 3] - pivot
    return np.concatenate([w * scale, v])


def _from_twist(x: FloatArray, pivot: FloatArray, scale: float) -> FloatArray:
    R = se3.rotvec_to_matrix(x[:3] / scale)
    return np.asarray(se3.make(R, pivot + x[3:] - R @ pivot))


def strong_directions(
    c: Constraint, weak_ratio: float, weak_sigma_m: float
) -> tuple[FloatArray, float]:
    """Eigenvectors (6, k) of the directions the overlap constrains (stiffness at least
    ``weak_ratio`` of the stiffest and 1-sigma at most ``weak_sigma_m``), and the largest
    1-sigma among them (m)."""
    ev, V = np.linalg.eigh(c.H)
    ev = np.maximum(ev, 1e-300)
    sigma = c.rms_m / np.sqrt(ev)
    strong = (ev >= weak_ratio * ev[-1]) & (sigma <= weak_sigma_m)
    return V[:, strong], float(sigma[strong].max()) if strong.any() else math.inf


def restrict(
    step: FloatArray, c: Constraint, weak_ratio: float, weak_sigma_m: float
) -> tuple[FloatArray, int, float]:
    """``step`` without its components along directions the overlap does not constrain (a
    rotation about the axis of a cylinder, a slide along a groove): those are left as the
    calibration put them. Returns (step, free directions, 1-sigma of the kept ones)."""
    E, sig = strong_directions(c, weak_ratio, weak_sigma_m)
    x = _twist(step, c.pivot, c.scale_m)
    return _from_twist(E @ (E.T @ x), c.pivot, c.scale_m), 6 - E.shape[1], sig


def rms_against(src: FloatArray, tgt: OrientedCloud, tree: cKDTree, max_d: float) -> float:
    """Point-to-plane RMS (m) of ``src`` against its nearest ``tgt`` points within ``max_d``
    (infinite when none is that near)."""
    d, j = tree.query(src, k=1, distance_upper_bound=max_d)
    ok = np.isfinite(d)
    if not ok.any():
        return math.inf
    r = np.einsum("ij,ij->i", tgt.normals[j[ok]], src[ok] - tgt.xyz[j[ok]])
    return float(np.sqrt(np.mean(r * r)))


def union(
    ds: Sequence[OrientedCloud], T: Sequence[FloatArray], idx: Sequence[int]
) -> OrientedCloud:
    """The clouds ``ds[j]`` for ``j`` in ``idx``, each moved by ``T[j]``, as one cloud."""
    return OrientedCloud(
        np.concatenate([transform_points(T[j], ds[j].xyz) for j in idx]),
        np.concatenate([ds[j].normals @ T[j][:3, :3].T for j in idx]),
    )


def joint_step(
    ds: Sequence[OrientedCloud],
    T: list[FloatArray],
    max_d: float,
    cos_agree: float,
    joint_ratio: float,
    weak_sigma_m: float,
) -> float:
    """One linearised least-squares step of all passes at once (multi-view point-to-plane):
    every point is paired with the nearest point of another pass (within ``max_d``, normals
    agreeing), the residuals are Tukey-weighted, and the 6n x 6n normal equations are solved in
    the subspace the pairs constrain (eigen-directions stiff and certain enough). The gauge (a
    motion of all passes together) is in the null space, so the minimum-norm step keeps the
    consensus as the reference. Updates ``T`` in place; returns the largest displacement (m)."""
    n = len(ds)
    X = np.concatenate([transform_points(T[i], ds[i].xyz) for i in range(n)])
    M = np.concatenate([ds[i].normals @ T[i][:3, :3].T for i in range(n)])
    owner = np.concatenate([np.full(ds[i].xyz.shape[0], i) for i in range(n)])
    if X.shape[0] < 2 * MIN_OVERLAP_POINTS:
        return 0.0
    k = min(_JOINT_NEIGHBOURS, X.shape[0])
    dist, nb = cKDTree(X).query(X, k=k, distance_upper_bound=max_d)
    ok = np.isfinite(dist)
    nb = np.where(ok, nb, 0)
    ok &= owner[nb] != owner[:, None]
    ok &= np.einsum("ij,ikj->ik", M, M[nb]) > cos_agree
    has = ok.any(axis=1)
    src = np.flatnonzero(has)
    tgt = nb[src, ok[src].argmax(axis=1)]  # nearest neighbour from another pass
    if src.size < MIN_OVERLAP_POINTS:
        return 0.0
    c = X.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((X - c) ** 2, axis=1))))
    m = M[tgt]
    r = np.einsum("ij,ij->i", m, X[src] - X[tgt])
    mad = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    u = r / max(4.685 * mad, 1e-9)
    w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
    A = np.concatenate([np.cross(X[src] - c, m) / scale, m], axis=1)
    B = -np.concatenate([np.cross(X[tgt] - c, m) / scale, m], axis=1)
    H = np.zeros((6 * n, 6 * n))
    g = np.zeros(6 * n)
    key = owner[src] * n + owner[tgt]
    order = np.argsort(key, kind="stable")
    bounds = np.flatnonzero(np.diff(key[order])) + 1
    for grp in np.split(order, bounds):
        i, j = divmod(int(key[grp[0]]), n)
        a, b, wr, ww = A[grp], B[grp], w[grp] * r[grp], w[grp][:, None]
        si, sj = slice(6 * i, 6 * i + 6), slice(6 * j, 6 * j + 6)
        H[si, si] += (a * ww).T @ a
        H[sj, sj] += (b * ww).T @ b
        H[si, sj] += (a * ww).T @ b
        H[sj, si] += (b * ww).T @ a
        g[si] += a.T @ wr
        g[sj] += b.T @ wr
    sigma_r = float(np.sqrt(np.sum(w * r * r) / max(float(w.sum()), 1e-12)))
    # Each pass's block scaled to unit mean stiffness, so that "weak" means weak for that pass
    # (a pass that sees little is not drowned by the stiffness of the others).
    stiff = np.array([np.trace(H[6 * i : 6 * i + 6, 6 * i : 6 * i + 6]) / 6.0 for i in range(n)])
    scl = np.repeat(np.where(stiff > 0, 1.0 / np.sqrt(np.maximum(stiff, 1e-300)), 0.0), 6)
    ev, V = np.linalg.eigh(H * scl[:, None] * scl[None, :])
    if float(ev[-1]) <= 0.0:
        return 0.0
    ev_safe = np.maximum(ev, 1e-300)
    sigma = sigma_r * np.linalg.norm(V * scl[:, None], axis=0) / np.sqrt(ev_safe)
    keep = (ev > joint_ratio * float(ev[-1])) & (sigma <= weak_sigma_m)
    Vs = V[:, keep]
    x = -scl * (Vs @ ((Vs.T @ (scl * g)) / ev[keep]))
    biggest = 0.0
    for i in range(n):
        xi = x[6 * i : 6 * i + 6]
        biggest = max(biggest, float(np.linalg.norm(xi[:3])) + float(np.linalg.norm(xi[3:])))
        T[i] = _from_twist(xi, c, scale) @ T[i]
    return biggest
