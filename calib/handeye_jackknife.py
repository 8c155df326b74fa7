"""The jackknife over pose clusters of the joint hand-eye solution
(:func:`wristscan.calib.handeye.refine`): the refinement repeated without each cluster of poses,
a cross-check of the covariance that does not rest on its error model
(:mod:`~wristscan.calib.handeye_uncertainty`).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence

import numpy as np

from wristscan.calib import handeye
from wristscan.calib import handeye_uncertainty as uncertainty
from wristscan.calib.handeye_model import HandEyeResult, Sweep
from wristscan.calib.handeye_uncertainty import Jackknife

__all__ = ["jackknife", "with_jackknife"]

log = logging.getLogger(__name__)

#: A repeat whose condition number exceeds this many times the full solution's is left out of the
#: jackknife (the cluster left out was the only one constraining some direction) ...
_JACKKNIFE_COND_RATIO = 3.0
#: ... and so is one that lands farther than this from it (rad, m): another optimum, not a spread.
_JACKKNIFE_JUMP = (np.radians(5.0), 5e-3)


def jackknife(
    sweeps: Sequence[Sweep],
    result: HandEyeResult,
    *,
    fit_radius: bool = False,
    max_points: int = 1500,
) -> Jackknife | None:
    """The joint refinement repeated without each pose cluster of ``result.components`` (or of
    :func:`~wristscan.calib.handeye_uncertainty.pose_clusters`), on at most ``max_points`` inliers
    per sweep (the spread comes from the poses, not from the sensor noise), each from ``result``.
    None with fewer than 4 clusters, or when fewer than 4 repeats succeed."""
    sw = list(sweeps)
    cl = (
        uncertainty.pose_clusters(sw)
        if result.components is None
        else np.asarray(result.components.clusters)
    )
    groups = np.unique(cl)
    if groups.size < 4 or len(result.inliers) != len(sw):
        return None
    thin = []
    for s, m in zip(sw, result.inliers, strict=True):
        idx = np.flatnonzero(m)
        if idx.size > max_points:
            idx = idx[np.linspace(0, idx.size - 1, max_points).astype(np.intp)]
        pick = np.zeros(s.n_points, dtype=bool)
        pick[idx] = True
        thin.append(s.subset(pick))
    left, Xs = [], []
    for g in groups:
        sub = [thin[k] for k in range(len(thin)) if cl[k] != g]
        init = dataclasses.replace(
            result, inliers=tuple(np.ones(s.n_points, dtype=bool) for s in sub)
        )
        try:
            r = handeye.refine(
                sub, init, result.ball_radius_m, fit_radius=fit_radius, check=False,
                robot_model=False,
            )  # fmt: skip
        except ValueError as exc:
            log.debug("jackknife without pose cluster %d failed: %s", g, exc)
            continue
        d = uncertainty.local_errors(r.sensor2flange[None], result.sensor2flange)[0]
        jump = (
            np.linalg.norm(d[:3]) > _JACKKNIFE_JUMP[0] or np.linalg.norm(d[3:]) > _JACKKNIFE_JUMP[1]
        )
        if jump or r.condition > max(_JACKKNIFE_COND_RATIO * result.condition, handeye.COND_SOFT):
            # Without this cluster the rest does not pin the solution down (e.g. the only
            # field-of-view group): its repeat says nothing about the spread over poses.
            log.debug("jackknife without pose cluster %d: condition %.3g, %s", g, r.condition, d)
            continue
        left.append(int(g))
        Xs.append(r.sensor2flange)
    if len(Xs) < 4:
        return None
    E = np.array(Xs)
    cov = uncertainty.jackknife_cov(uncertainty.local_errors(E, result.sensor2flange))
    return Jackknife(tuple(left), E, cov)


def with_jackknife(
    sweeps: Sequence[Sweep], result: HandEyeResult, *, fit_radius: bool = False
) -> HandEyeResult:
    """``result`` with its :func:`jackknife` (None when there are too few pose clusters)."""
    return dataclasses.replace(result, jackknife=jackknife(sweeps, result, fit_radius=fit_radius))
