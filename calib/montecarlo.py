"""Monte Carlo study of the TCP estimators (Borangiu et al. 2009, section 3, Fig. 4).

Setup of the paper: a TCP at (60, 10, 200) mm in the flange frame; three flange poses -- vertical
and looking down, the same rotated by ``alpha`` about the world X axis, and rotated by ``alpha``
about the world Y axis; the orientations are exact and every position axis gets independent
Gaussian noise (sigma = 0.1 mm in the paper); 200 trials per ``alpha``; the standard deviation of
the TCP error per tool axis is reported.

Besides Eq. (7) on those three poses ("three"), the study can run least squares on a balanced set
of ``n`` poses ("lstsq-n<N>"), the paper's recommendation: ``n`` poses tilted by ``alpha`` from the
down-looking pose about horizontal world axes at azimuths ``360 k / n`` degrees (k = 0..n-1), so the
tool Z axes are spread evenly on a cone of half-angle ``alpha`` around the vertical, without spin
about the tool axis.  (Unlike the three-pose set it has no vertical pose: the angle between two Z
axes of the cone reaches ``2 alpha``.)

Every trial is solved by the library code of ``tcp`` (batched), not by a copy of the formulas.
Each row draws from its own random stream, seeded by ``(seed, alpha, method)``, so a row does not
depend on which other rows were requested.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import se3, tcp

FloatArray = NDArray[np.float64]

__all__ = [
    "PAPER_SIGMA_M",
    "PAPER_TCP_M",
    "PAPER_TRIALS",
    "StudyRow",
    "analytic_cov",
    "cone_poses",
    "monte_carlo_errors",
    "paper_poses",
    "study",
]

PAPER_TCP_M = (0.060, 0.010, 0.200)
"""The TCP of the paper's simulation (flange frame, metres)."""
PAPER_SIGMA_M = 1e-4
"""Position noise of the paper's simulation: 0.1 mm per axis."""
PAPER_TRIALS = 200

_P_WORLD_M = (0.45, -0.10, 0.15)
"""Where the fixed point sits in the world; the estimators are translation invariant, so any."""

_DOWN = np.diag([1.0, -1.0, -1.0])
"""Flange looking straight down: tool Z = -world Z (a rotation of pi about world X)."""

_STUDY_MIN_TILT_DEG = 1e-3
"""The study wants small tilts (that is its point); only refuse sets that are exactly degenerate."""

_CHUNK_VALUES = 1 << 21
"""Noise values drawn and solved per batch (16 MiB of float64)."""

Method = Literal["three", "lstsq"]


@dataclass(frozen=True)
class StudyRow:
    """One row of the study; deviations in millimetres (as the paper plots them)."""

    alpha_deg: float
    method: str
    """"three" (Eq. 7 on the paper's poses) or "lstsq-n<N>" (least squares on the cone set)."""
    std_mm: tuple[float, float, float]
    """Monte Carlo standard deviation (ddof=1) of the TCP error per tool axis x, y, z."""
    trials: int
    analytic_std_mm: tuple[float, float, float]
    """Square roots of the diagonal of the predicted covariance."""

    def as_dict(self) -> dict[str, object]:
        d = asdict(self)
        d["std_mm"] = list(self.std_mm)
        d["analytic_std_mm"] = list(self.analytic_std_mm)
        return d


def paper_poses(alpha_rad: float) -> FloatArray:
    """The paper's three orientations (3, 3, 3): down-looking, then rotated by ``alpha_rad`` about
    world X, then about world Y."""
    return np.stack([_DOWN, se3.rot_x(alpha_rad) @ _DOWN, se3.rot_y(alpha_rad) @ _DOWN])


def cone_poses(alpha_rad: float, n: int) -> FloatArray:
    """``n`` orientations (n, 3, 3) with tool Z axes evenly spread on a cone of half-angle
    ``alpha_rad`` around the downward vertical (tilts about horizontal axes at azimuth 2 pi k / n).
    """
    if n < 3:
        raise ValueError(f"the cone pose set needs n >= 3 poses, got {n}")
    phi = 2.0 * np.pi * np.arange(n) / n
    axes = np.stack([np.cos(phi), np.sin(phi), np.zeros(n)], axis=-1)
    return se3.rotvec_to_matrix(axes * alpha_rad) @ _DOWN


def analytic_cov(R: ArrayLike, sigma_m: float, method: Method) -> FloatArray:
    """Predicted TCP covariance (3, 3) (m^2): ``1.5 sigma^2 M^-1 M^-T`` for Eq. (7) ("three"),
    ``sigma^2 [(A^T A)^-1]_{p block}`` for least squares ("lstsq")."""
    if method == "three":
        return tcp.covariance_three(R, sigma_m)
    if method == "lstsq":
        return tcp.covariance_lstsq(R, sigma_m)
    raise ValueError(f"method must be 'three' or 'lstsq', got {method!r}")


def monte_carlo_errors(
    R: ArrayLike,
    sigma_m: float,
    trials: int,
    rng: np.random.Generator,
    method: Method,
    p_tool_m: ArrayLike = PAPER_TCP_M,
) -> FloatArray:
    """TCP errors (trials, 3) in metres (estimate minus truth, tool frame) for exact orientations
    ``R`` (n, 3, 3) and Gaussian position noise ``sigma_m`` per axis; all trials in one batch."""
    if method not in ("three", "lstsq"):
        raise ValueError(f"method must be 'three' or 'lstsq', got {method!r}")
    Ra = np.asarray(R, dtype=np.float64)
    p_tool = np.asarray(p_tool_m, dtype=np.float64)
    T_true = np.asarray(_P_WORLD_M) - Ra @ p_tool  # every pose maps p_tool onto _P_WORLD_M
    out = np.empty((trials, 3))
    # Batches of at most ~_CHUNK_VALUES noise values bound the memory for huge runs.
    step = max(1, _CHUNK_VALUES // T_true.size)
    for start in range(0, trials, step):
        stop = min(trials, start + step)
        T = T_true + rng.normal(scale=sigma_m, size=(stop - start, *T_true.shape))
        if method == "three":
            est = tcp.solve_tcp_three_batch(Ra, T, min_tilt_deg=_STUDY_MIN_TILT_DEG)
        else:
            est, _ = tcp.solve_tcp_batch(Ra, T, min_tilt_deg=_STUDY_MIN_TILT_DEG)
        out[start:stop] = est - p_tool
    return out


def _row(alpha_deg: float, n: int | None, trials: int, sigma_m: float, seed: int) -> StudyRow:
    """One row: Eq. (7) on the paper's poses (``n`` None) or least squares on the cone set."""
    a = float(np.radians(alpha_deg))
    R = paper_poses(a) if n is None else cone_poses(a, n)
    method: Method = "three" if n is None else "lstsq"
    # Row-specific stream: stable whatever other alphas or methods are requested.
    rng = np.random.default_rng([seed, round(alpha_deg * 1e6), 0 if n is None else n])
    err = monte_carlo_errors(R, sigma_m, trials, rng, method)
    std = np.std(err, axis=0, ddof=1) * 1e3
    ana = np.sqrt(np.diag(analytic_cov(R, sigma_m, method))) * 1e3
    return StudyRow(
        alpha_deg=float(alpha_deg),
        method="three" if n is None else f"lstsq-n{n}",
        std_mm=(float(std[0]), float(std[1]), float(std[2])),
        trials=trials,
        analytic_std_mm=(float(ana[0]), float(ana[1]), float(ana[2])),
    )


def study(
    alphas_deg: ArrayLike,
    trials: int,
    sigma_m: float,
    n_poses: int | Sequence[int] | None = None,
    seed: int = 0,
) -> list[StudyRow]:
    """The paper's section-3 study for each ``alpha`` (degrees, in (0, 180)).

    Per alpha: a "three" row (Eq. 7 on the paper's poses) and, for each ``n`` in ``n_poses``, an
    "lstsq-n<N>" row (least squares on the cone set of ``n`` poses).  ``sigma_m``: position noise
    per axis (metres).  Raises ``ValueError`` for bad arguments, ``tcp.DegeneratePoses`` for a pose
    set that does not constrain the TCP.
    """
    alphas = np.atleast_1d(np.asarray(alphas_deg, dtype=np.float64))
    if alphas.ndim != 1 or alphas.size == 0:
        raise ValueError("alphas_deg must be a non-empty 1-D sequence of angles in degrees")
    if not np.all(np.isfinite(alphas)) or np.any((alphas <= 0) | (alphas >= 180)):
        raise ValueError(f"every alpha must be in (0, 180) degrees, got {alphas.tolist()}")
    if isinstance(trials, bool) or int(trials) != trials or trials < 2:
        raise ValueError(f"trials must be an integer >= 2, got {trials}")
    if not (np.isfinite(sigma_m) and sigma_m > 0):
        raise ValueError(f"sigma_m must be a positive number of metres, got {sigma_m}")
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    ns = [] if n_poses is None else [n_poses] if isinstance(n_poses, int) else list(n_poses)
    for n in ns:
        if int(n) != n or n < 3:
            raise ValueError(f"n_poses must be integers >= 3, got {n}")
    # A handful of angles and pose sets; the trials inside each row are vectorised.
    return [
        _row(float(alpha), n, int(trials), float(sigma_m), seed)
        for alpha in alphas
        for n in [None, *(int(k) for k in ns)]
    ]
