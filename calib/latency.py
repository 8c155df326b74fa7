"""Sensor latency from sweeps over a fixed feature (tooling ball or edge) in opposite directions.

Model
-----
A profile is paired with the robot pose at the instant the synchroniser believes the exposure
happened. If that instant is late by ``dt`` (the true latency exceeds the configured one by
``dt``), every reconstructed point is displaced by the sensor's motion during ``dt``. For a sweep
``i`` in which the measured point of the feature moves with velocity ``v_i`` (metres per second,
base frame; for a translational sweep this is the TCP velocity), the feature's apparent position
is

    p_i = p* + v_i * dt + noise,

with ``p*`` the true position. Sweeps in opposite directions and at several speeds separate
``dt`` from ``p*``: forward and backward sweeps at speed ``v`` see the feature ``2 v dt`` apart
along the motion. :func:`estimate_latency` solves the linear least-squares problem for
``(p*, dt)`` over all sweeps; ``latency_s`` is the correction to *add* to the configured latency
(negative when the configured latency is too large). Positions may be 3-D (sphere centres) or
1-D (edge positions along the motion); rotation during a sweep enters through ``v_i`` of the
measured point.

Whatever constant lies between the exposure and the time the synchroniser assigns (the sensor's
exposure-to-timestamp delay, differences between the smallest transport delays of the sensor and
the robot streams, the controller's own sampling delay) is one ``dt``: that is what pairing needs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["LatencyEstimate", "estimate_latency", "latency_from_shifts"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class LatencyEstimate:
    """Result of :func:`estimate_latency` (SI units)."""

    latency_s: float
    """Time offset to add to the configured latency (s)."""
    std_s: float
    """Its standard deviation from the fit residuals (s); NaN without redundancy."""
    feature_position: FloatArray
    """Estimated true feature position ``(k,)`` (m)."""
    residuals: FloatArray
    """Per-sweep residuals ``(n, k)`` (m)."""
    rms_m: float
    """RMS of the residuals (m)."""
    n_sweeps: int


def _as_2d(a: ArrayLike, name: str) -> FloatArray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise ValueError(f"{name}: expected (n,) or (n, k), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or infinity")
    return arr


def estimate_latency(
    positions: ArrayLike, velocities: ArrayLike, weights: ArrayLike | None = None
) -> LatencyEstimate:
    """Least-squares time offset from apparent feature positions of several sweeps.

    ``positions`` ``(n, k)`` (or ``(n,)``): the feature position each sweep measured (m), with
    the configured latency applied. ``velocities`` (same shape): velocity of the measured point
    during that sweep (m/s). ``weights`` ``(n,)``: optional per-sweep weights (e.g. inverse
    variance of the fitted position). Raises ``ValueError`` when the sweeps cannot separate the
    offset from the position (all velocities equal: sweep both ways).
    """
    P = _as_2d(positions, "positions")
    V = _as_2d(velocities, "velocities")
    if P.shape != V.shape:
        raise ValueError(f"positions {P.shape} and velocities {V.shape} differ")
    n, k = P.shape
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (n,) or np.any(w < 0) or not np.all(np.isfinite(w)):
        raise ValueError("weights: expected (n,) finite non-negative values")
    # Eliminating p* (weighted mean) leaves a one-parameter fit of the centred velocities.
    wsum = float(w.sum())
    if wsum <= 0:
        raise ValueError("weights: all zero")
    Pm = (w @ P) / wsum
    Vm = (w @ V) / wsum
    Vc = V - Vm
    Pc = P - Pm
    svv = float(np.sum(w[:, None] * Vc * Vc))
    speed_scale = float(np.sqrt(np.sum(w[:, None] * V * V) / wsum))
    if svv <= 1e-12 * max(speed_scale**2, 1e-30) * wsum:
        raise ValueError(
            "sweeps do not separate latency from position: sweep the feature in opposite "
            "directions (and at several speeds)"
        )
    dt = float(np.sum(w[:, None] * Vc * Pc)) / svv
    p_star = Pm - Vm * dt
    resid = P - p_star - V * dt
    dof = n * k - k - 1
    if dof > 0:
        sigma2 = float(np.sum(w[:, None] * resid * resid)) / dof
        std = float(np.sqrt(sigma2 / svv))
    else:
        std = float("nan")
    return LatencyEstimate(
        latency_s=dt,
        std_s=std,
        feature_position=p_star,
        residuals=resid,
        rms_m=float(np.sqrt(np.mean(resid**2))),
        n_sweeps=n,
    )


def latency_from_shifts(shifts_m: ArrayLike, speeds_mps: ArrayLike) -> LatencyEstimate:
    """Time offset from forward-minus-backward apparent positions along the motion.

    ``shifts_m`` ``(n,)``: position seen sweeping in the +direction minus the position seen
    sweeping back, at speed ``speeds_mps`` ``(n,)`` (> 0). Model: ``shift = 2 v dt``. The
    returned ``feature_position`` is empty (the pair difference removes it).
    """
    s = np.asarray(shifts_m, dtype=np.float64).ravel()
    v = np.asarray(speeds_mps, dtype=np.float64).ravel()
    if s.shape != v.shape or s.shape[0] == 0:
        raise ValueError("shifts_m and speeds_mps: equal non-empty lengths needed")
    if np.any(v <= 0) or not np.all(np.isfinite(s)) or not np.all(np.isfinite(v)):
        raise ValueError("speeds_mps must be > 0 and every value finite")
    a = 2.0 * v
    dt = float(a @ s / (a @ a))
    resid = s - a * dt
    n = s.shape[0]
    std = float(np.sqrt(resid @ resid / (n - 1) / (a @ a))) if n > 1 else float("nan")
    return LatencyEstimate(
        latency_s=dt,
        std_s=std,
        feature_position=np.zeros(0),
        residuals=resid[:, None],
        rms_m=float(np.sqrt(np.mean(resid**2))),
        n_sweeps=n,
    )
