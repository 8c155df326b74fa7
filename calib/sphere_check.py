"""Whether a sphere or circle fit (:mod:`wristscan.calib.sphere`) is plausible as the tooling ball.

A robust fit always returns *some* sphere. On a profile where the ball shows only a short arc among
the planes of a box or a table, the best-supported circle may run through the box's corners: a
wrong centre by millimetres, its "inliers" spread over a tenth of a millimetre. Such a fit is
flagged here instead of returned silently, on three signs:

* **RMS far above the noise**: the RMS residual of the inliers above :data:`RMS_FACTOR` times the
  sensor noise (the configured one, else the noise estimated from the thickness of
  nearest-neighbour patches of the points themselves, not below :data:`NOISE_FLOOR_M`);
* **radius outside the expected range** (when one is given);
* **few inliers**: fewer than :data:`MIN_INLIERS_PER_PARAMETER` per fitted parameter, or, when a
  minimum share is given, fewer than that share of the points.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from wristscan.calib.sphere_search import noise_sigma

__all__ = [
    "MIN_INLIERS_PER_PARAMETER",
    "NOISE_FLOOR_M",
    "RMS_FACTOR",
    "ImplausibleFit",
    "estimated_noise",
    "judge",
]

FloatArray = NDArray[np.float64]

#: A fit whose inlier RMS exceeds this many noise sigmas is implausible. Gaussian noise gives an
#: RMS within a few percent of sigma on hundreds of points; a misfit of the ball's shape
#: (a sweep whose timing slipped) a few sigmas; a circle through a box's corners 6-12.
RMS_FACTOR = 5.0
#: Smallest noise (m) the estimated noise is taken as: noise-free simulated points would otherwise
#: make any shape misfit "far above the noise".
NOISE_FLOOR_M = 5e-6
#: Fewer inliers than this per fitted parameter (centre coordinates, radius) is implausible.
MIN_INLIERS_PER_PARAMETER = 5


class ImplausibleFit(ValueError):
    """A sphere or circle fit that does not look like the ball; ``why`` says why."""

    def __init__(self, why: str) -> None:
        super().__init__(f"implausible fit: {why}")
        self.why = why


def estimated_noise(points: FloatArray) -> float:
    """Noise sigma (m) of ``points`` ``(N, d)`` from the thickness of nearest-neighbour patches
    (a seeded sample of them), at least :data:`NOISE_FLOOR_M`; the floor for too few points."""
    n, d = points.shape
    if n < 2 * (4 * d + 4):
        return NOISE_FLOOR_M
    origin = np.median(points, axis=0)
    scale = float(np.median(np.linalg.norm(points - origin, axis=1))) or 1.0
    U = (points - origin) / scale
    return max(noise_sigma(U, np.random.default_rng(0)) * scale, NOISE_FLOOR_M)


def judge(
    *,
    rms: float,
    radius: float,
    n_inliers: int,
    n_points: int,
    n_parameters: int,
    noise_m: float,
    expected_radius: tuple[float, float] | None = None,
    min_fraction: float | None = None,
) -> str:
    """Why the fit is implausible (empty when it is plausible); see the module doc."""
    reasons = []
    if math.isfinite(rms) and rms > RMS_FACTOR * noise_m:
        reasons.append(
            f"the RMS residual {rms * 1e6:.1f} um is {rms / noise_m:.0f} times the noise "
            f"{noise_m * 1e6:.1f} um (a shape among clutter, not the ball?)"
        )
    if expected_radius is not None and not expected_radius[0] <= radius <= expected_radius[1]:
        lo, hi = expected_radius
        reasons.append(
            f"the radius {radius * 1e3:.3f} mm is outside the expected "
            f"{lo * 1e3:.3f}-{hi * 1e3:.3f} mm"
        )
    need = MIN_INLIERS_PER_PARAMETER * n_parameters
    if n_inliers < need:
        reasons.append(f"only {n_inliers} points lie on it (fewer than {need})")
    elif min_fraction is not None and n_inliers < min_fraction * n_points:
        reasons.append(
            f"only {n_inliers} of {n_points} points ({100.0 * n_inliers / max(n_points, 1):.0f} "
            f"%) lie on it, fewer than {100.0 * min_fraction:.0f} %"
        )
    return "; ".join(reasons)
