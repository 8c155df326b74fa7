"""Tool centre point (TCP) from n >= 3 flange poses that hold one physical point fixed.

Borangiu et al. 2009, Eq. (2)-(9). The point ``p`` (tool/flange frame, metres) is touched, or its
sphere centre measured, from several flange poses ``flange2base = (R_i, T_i)``; every pose must map
it onto the same world point ``p_world``:

    R_i p + T_i = p_world            for i = 1..n                      (Eq. 6)

Noise model used for every covariance here: the orientations ``R_i`` are exact and each position
``T_i`` carries independent isotropic Gaussian noise of standard deviation ``sigma`` (metres) per
axis, which is also what the paper's Monte Carlo study assumes (section 3). Under that model:

* ``solve_tcp_three`` -- Eq. (7): ``M p = b`` with ``M = R1 - (R2 + R3)/2`` and
  ``b = -(T1 - (T2 + T3)/2)``.  The noise on ``b`` is ``e1 - (e2 + e3)/2``, whose covariance is
  ``(1 + 1/4 + 1/4) sigma^2 I``, hence ``cov(p) = 1.5 sigma^2 M^-1 M^-T``.  Eq. (7) keeps only one
  of the two independent differences of three poses, so it is never better than least squares on the
  same poses, and much worse for small tilts (its error grows like 1/alpha^2 instead of 1/alpha).
* ``solve_tcp(method="lstsq")`` -- unknowns ``x = [p; p_world]`` and the 3n equations
  ``[R_i, -I] x = -T_i``.  Each equation carries exactly the noise of one ``T_i`` (independent,
  variance ``sigma^2``), so ordinary least squares is the best linear unbiased estimator and
  ``cov(x) = sigma^2 (A^T A)^-1``; ``cov(p)`` is its upper-left 3x3 block.  (Stacking pairwise
  differences ``(R_i - R_j) p = -(T_i - T_j)`` instead gives the same estimate when all pairs are
  used, but its equations share noise, so ``sigma^2 (A^T A)^-1`` would not be its covariance.)
* ``solve_tcp(method="variance")`` -- Eq. (8)-(9): minimise the summed variances of the world points
  ``w_i = R_i p + T_i``.  Centring turns it into the linear least-squares problem
  ``min_p || C p + d ||^2`` with ``C`` the stacked ``R_i - mean(R)`` and ``d`` the stacked
  ``T_i - mean(T)``; it eliminates ``p_world`` (its optimum is the mean world point) and so has the
  same minimiser as "lstsq".  ``(C^T C)^-1`` is the Schur complement form of the same block of
  ``(A^T A)^-1``, so both methods report the same covariance.

``sigma`` is estimated from the residuals ``r_i = w_i - p_world`` as ``sqrt(|r|^2 / k)`` where
``k = E|r|^2 / sigma^2``: ``3n - 6`` for least squares (3n equations, 6 unknowns), and for Eq. (7)
the squared Frobenius norm of the linear map from position noise to residuals (computed exactly).

Degenerate pose sets are refused: if all orientations differ only by rotations about one common
axis, the TCP component along that axis cannot be observed (``R_i v`` is the same for every pose, so
``p + t v`` fits equally well).  The spread is measured by the *effective tilt*
``2 asin(sqrt(lambda_min(I - Rbar^T Rbar)))`` with ``Rbar`` the mean rotation matrix; for two poses
it is exactly the rotation angle between them about the worst axis.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

__all__ = [
    "DEFAULT_MIN_TILT_DEG",
    "WARN_TILT_DEG",
    "DegeneratePoses",
    "TcpSolution",
    "covariance_lstsq",
    "covariance_three",
    "design_matrix",
    "effective_tilt_deg",
    "eq7_system",
    "solve_tcp",
    "solve_tcp_batch",
    "solve_tcp_three",
    "solve_tcp_three_batch",
]

log = logging.getLogger(__name__)

DEFAULT_MIN_TILT_DEG = 5.0
"""Pose sets whose effective tilt is below this (degrees) raise ``DegeneratePoses``: at 5 degrees
0.1 mm of position noise already becomes about 1 mm of TCP error."""

WARN_TILT_DEG = 30.0
"""Below this effective tilt (degrees) a warning is logged; the paper finds accuracy collapsing when
the Z axes of three poses are less than 45 degrees apart (effective tilt about 30 degrees)."""

_ROT_TOL = 1e-6
_AXIS_NAMES = ("x", "y", "z")


class DegeneratePoses(ValueError):
    """The orientations do not constrain the TCP; the message says which pose to add."""


@dataclass(frozen=True, eq=False)
class TcpSolution:
    """A TCP estimate; every length in metres.

    ``cond`` is the 2-norm condition number of the matrix actually solved: ``M`` (3x3) for Eq. (7),
    the 3n x 6 design ``A`` for "lstsq", the centred 3n x 3 ``C`` for "variance".
    """

    p_tool: FloatArray
    """(3,) the point in the flange (tool) frame."""
    p_world: FloatArray
    """(3,) the same point in the world (robot base) frame: mean of the world points."""
    residuals: FloatArray
    """(n, 3) world-point deviations ``R_i p_tool + T_i - p_world``."""
    sigma: float
    """Estimated position noise per axis (metres), from the residuals (see module docstring)."""
    cov: FloatArray
    """(3, 3) covariance of ``p_tool`` (m^2) for position noise ``sigma`` (or the given one)."""
    cond: float
    method: str
    """"three", "lstsq" or "variance"."""
    tilt_deg: float
    """Effective tilt of the pose set (degrees); see the module docstring."""

    @property
    def std(self) -> FloatArray:
        """(3,) standard deviation of ``p_tool`` per tool axis (metres)."""
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))


# --------------------------------------------------------------------------------------------
# validation and degeneracy


def _check_rotations(R: ArrayLike, n: int | None = None) -> FloatArray:
    Ra = np.asarray(R, dtype=np.float64)
    if Ra.ndim == 3 and Ra.shape[1:] == (4, 4):
        raise ValueError(
            f"R must be rotations of shape (n, 3, 3), got transforms {Ra.shape}; "
            "pass flange2base[:, :3, :3] and flange2base[:, :3, 3]"
        )
    if Ra.ndim != 3 or Ra.shape[1:] != (3, 3):
        raise ValueError(f"R must have shape (n, 3, 3) (flange2base rotations), got {Ra.shape}")
    if n is not None and Ra.shape[0] != n:
        raise ValueError(f"R must hold exactly {n} rotations, got {Ra.shape[0]}")
    if Ra.shape[0] < 3:
        raise ValueError(f"the TCP needs at least 3 poses, got {Ra.shape[0]}")
    if not np.all(np.isfinite(Ra)):
        raise ValueError("R contains NaN or infinity")
    err = float(np.abs(np.swapaxes(Ra, -1, -2) @ Ra - np.eye(3)).max())
    if err > _ROT_TOL:
        raise ValueError(f"R is not a set of rotation matrices (orthonormality error {err:.2e})")
    if np.any(np.linalg.det(Ra) < 0):
        raise ValueError("R contains a reflection (det < 0), not a rotation")
    return Ra


def _check_translations(T: ArrayLike, n: int, batched: bool) -> FloatArray:
    Ta = np.asarray(T, dtype=np.float64)
    want = "(..., n, 3)" if batched else "(n, 3)"
    if Ta.ndim < 2 or (not batched and Ta.ndim != 2) or Ta.shape[-1] != 3:
        raise ValueError(
            f"T must have shape {want} (flange2base translations, metres), got {Ta.shape}"
        )
    if Ta.shape[-2] != n:
        raise ValueError(f"T holds {Ta.shape[-2]} translations but R holds {n} rotations")
    if not np.all(np.isfinite(Ta)):
        raise ValueError("T contains NaN or infinity")
    return Ta


def _spread(R: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Eigen-decomposition of ``I - Rbar^T Rbar`` = mean of ``(R_i - Rbar)^T (R_i - Rbar)``.

    Eigenvalues in [0, 1], ascending; an eigenvector ``v`` with eigenvalue 0 is a tool-frame
    direction that every pose maps to the same world direction (the unobservable TCP component).
    """
    Rbar = R.mean(axis=0)
    lam, V = np.linalg.eigh(np.eye(3) - Rbar.T @ Rbar)
    return np.clip(lam, 0.0, 1.0), V


def _tilt_deg(lam: float) -> float:
    return float(np.degrees(2.0 * np.arcsin(np.sqrt(lam))))


def effective_tilt_deg(R: ArrayLike) -> float:
    """Effective tilt (degrees) of rotations ``(n, 3, 3)``: the rotation between the poses about
    the worst-observed axis; 0 when all orientations share a rotation axis."""
    Ra = np.asarray(R, dtype=np.float64)
    if Ra.ndim != 3 or Ra.shape[1:] != (3, 3) or Ra.shape[0] < 1:
        raise ValueError(f"R must have shape (n, 3, 3), got {Ra.shape}")
    lam, _ = _spread(Ra)
    return _tilt_deg(float(lam[0]))


def _axis_text(w: FloatArray) -> str:
    k = int(np.argmax(np.abs(w)))
    if abs(w[k]) > np.cos(np.radians(15.0)):
        return _AXIS_NAMES[k]
    w = np.round(w * np.sign(w[k]), 2) + 0.0  # an axis has no sign; + 0.0 turns -0.0 into 0.0
    return "[" + ", ".join(f"{c:.2f}" for c in w) + "]"


def _check_spread(R: FloatArray, min_tilt_deg: float, warn: bool = True) -> float:
    """Raise ``DegeneratePoses`` with advice when the poses do not constrain the TCP; return the
    effective tilt in degrees (and log a warning when it is small)."""
    lam, V = _spread(R)
    tilt = _tilt_deg(float(lam[0]))
    if tilt < min_tilt_deg:
        if _tilt_deg(float(lam[1])) < min_tilt_deg:
            raise DegeneratePoses(
                f"all orientations are nearly identical (effective tilt {tilt:.2f} deg < "
                f"{min_tilt_deg:g} deg), so the TCP is unobservable; add poses tilted by >= 45 "
                "degrees about two different axes (e.g. x and y)"
            )
        # The world direction every pose maps v onto is the shared rotation axis.
        w = R[0] @ V[:, 0]
        # Advise the world axis most perpendicular to it (x before y before z on ties).
        other = _AXIS_NAMES[int(np.argmin(np.abs(w) + 1e-9 * np.arange(3)))]
        verb = "rotated" if other == "z" else "tilted"
        raise DegeneratePoses(
            f"all orientations rotate about nearly the same axis ({_axis_text(w)}; effective tilt "
            f"{tilt:.2f} deg < {min_tilt_deg:g} deg), so the TCP component along it is "
            f"unobservable; add a pose {verb} about {other} by >= 45 degrees"
        )
    if warn and tilt < WARN_TILT_DEG:
        log.warning(
            "pose set has a small effective tilt (%.1f deg < %.0f deg): expect a poor TCP; "
            "spread the Z axes by >= 45 degrees",
            tilt,
            WARN_TILT_DEG,
        )
    return tilt


# --------------------------------------------------------------------------------------------
# the linear systems (shared with the Monte Carlo study, so it exercises this very code)


def eq7_system(R: ArrayLike, T: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Eq. (7): ``M = R1 - (R2 + R3)/2`` (3, 3) and ``b = -(T1 - (T2 + T3)/2)`` (..., 3).

    ``R`` is (3, 3, 3); ``T`` is (..., 3, 3) (metres), batched over leading dimensions.
    """
    Ra = np.asarray(R, dtype=np.float64)
    Ta = np.asarray(T, dtype=np.float64)
    M = Ra[0] - 0.5 * (Ra[1] + Ra[2])
    b = -(Ta[..., 0, :] - 0.5 * (Ta[..., 1, :] + Ta[..., 2, :]))
    return M, b


def design_matrix(R: ArrayLike) -> FloatArray:
    """The (3n, 6) matrix ``A`` of ``[R_i, -I] [p; p_world] = -T_i`` for rotations (n, 3, 3)."""
    Ra = np.asarray(R, dtype=np.float64)
    n = Ra.shape[0]
    A = np.empty((n, 3, 6))
    A[:, :, :3] = Ra
    A[:, :, 3:] = -np.eye(3)
    return A.reshape(3 * n, 6)


def covariance_three(R: ArrayLike, sigma_m: float) -> FloatArray:
    """Covariance (3, 3) (m^2) of the Eq. (7) TCP: ``1.5 sigma^2 M^-1 M^-T``."""
    M, _ = eq7_system(R, np.zeros((3, 3)))
    Minv = np.linalg.inv(M)
    return np.asarray(1.5 * sigma_m**2 * (Minv @ Minv.T), dtype=np.float64)


def covariance_lstsq(R: ArrayLike, sigma_m: float) -> FloatArray:
    """Covariance (3, 3) (m^2) of the least-squares TCP: ``sigma^2 [(A^T A)^-1]_{0:3, 0:3}``."""
    A = design_matrix(R)
    return np.asarray(sigma_m**2 * np.linalg.inv(A.T @ A)[:3, :3], dtype=np.float64)


def solve_tcp_three_batch(
    R: ArrayLike, T: ArrayLike, *, min_tilt_deg: float = DEFAULT_MIN_TILT_DEG
) -> FloatArray:
    """Eq. (7) for one orientation set ``R`` (3, 3, 3) and many translation sets ``T`` (..., 3, 3).

    Returns ``p_tool`` (..., 3) in metres; all sets are solved in one batched ``np.linalg.solve``.
    """
    Ra = _check_rotations(R, n=3)
    Ta = _check_translations(T, 3, batched=True)
    _check_spread(Ra, min_tilt_deg, warn=False)  # batches are simulations: small tilts on purpose
    M, b = eq7_system(Ra, Ta)
    return np.asarray(np.linalg.solve(M, b[..., None])[..., 0], dtype=np.float64)


def solve_tcp_batch(
    R: ArrayLike, T: ArrayLike, *, min_tilt_deg: float = DEFAULT_MIN_TILT_DEG
) -> tuple[FloatArray, FloatArray]:
    """Least squares on ``[R_i, -I] [p; p_world] = -T_i`` for one orientation set ``R`` (n, 3, 3)
    and many translation sets ``T`` (..., n, 3).  Returns ``(p_tool, p_world)``, each (..., 3),
    metres; the pseudo-inverse of ``A`` is formed once and applied to every set."""
    Ra = _check_rotations(R)
    n = Ra.shape[0]
    Ta = _check_translations(T, n, batched=True)
    _check_spread(Ra, min_tilt_deg, warn=False)
    pinv = np.linalg.pinv(design_matrix(Ra))
    x = -Ta.reshape((*Ta.shape[:-2], 3 * n)) @ pinv.T
    return x[..., :3], x[..., 3:]


# --------------------------------------------------------------------------------------------
# single solutions with diagnostics


def _frozen(a: ArrayLike) -> FloatArray:
    a = np.array(a, dtype=np.float64)
    a.setflags(write=False)
    return a


def _finish(
    R: FloatArray,
    T: FloatArray,
    p_tool: ArrayLike,
    dof: float,
    cov_unit: ArrayLike,
    noise_sigma_m: float | None,
    cond: float,
    method: str,
    tilt: float,
) -> TcpSolution:
    p_tool = np.asarray(p_tool, dtype=np.float64)
    world = np.einsum("nij,j->ni", R, p_tool) + T
    p_world = world.mean(axis=0)
    residuals = world - p_world
    sigma = float(np.sqrt(np.sum(residuals**2) / dof))
    s = sigma if noise_sigma_m is None else float(noise_sigma_m)
    return TcpSolution(
        p_tool=_frozen(p_tool),
        p_world=_frozen(p_world),
        residuals=_frozen(residuals),
        sigma=sigma,
        cov=_frozen(s**2 * np.asarray(cov_unit, dtype=np.float64)),
        cond=cond,
        method=method,
        tilt_deg=tilt,
    )


def _check_noise(noise_sigma_m: float | None) -> None:
    if noise_sigma_m is not None and not (np.isfinite(noise_sigma_m) and noise_sigma_m >= 0):
        raise ValueError(f"noise_sigma_m must be a finite number >= 0, got {noise_sigma_m}")


def solve_tcp_three(
    R: ArrayLike,
    T: ArrayLike,
    *,
    noise_sigma_m: float | None = None,
    min_tilt_deg: float = DEFAULT_MIN_TILT_DEG,
) -> TcpSolution:
    """The paper's three-pose TCP, Eq. (7), exactly.

    ``R`` (3, 3, 3) and ``T`` (3, 3) are the flange2base rotations and translations (metres).
    ``cov = 1.5 s^2 M^-1 M^-T`` with ``s = noise_sigma_m`` if given, else the estimated ``sigma``.
    Raises ``DegeneratePoses`` when the orientations share a rotation axis (``M`` singular).
    """
    _check_noise(noise_sigma_m)
    Ra = _check_rotations(R, n=3)
    Ta = _check_translations(T, 3, batched=False)
    tilt = _check_spread(Ra, min_tilt_deg)
    M, b = eq7_system(Ra, Ta)
    p_tool = np.linalg.solve(M, b)
    # E|r|^2 = sigma^2 |P|_F^2, P the map from position noise (9,) to residuals (9,): the
    # residuals of Eq. (7) are not least-squares residuals, so 3n - 6 would be wrong here.
    E = np.eye(9).reshape(9, 3, 3)
    _, bE = eq7_system(Ra, E)
    dE = np.linalg.solve(M, bE[..., None])[..., 0]
    wE = np.einsum("nij,kj->kni", Ra, dE) + E
    k = float(np.sum((wE - wE.mean(axis=1, keepdims=True)) ** 2))
    Minv = np.linalg.inv(M)
    return _finish(
        Ra,
        Ta,
        p_tool,
        k,
        1.5 * Minv @ Minv.T,
        noise_sigma_m,
        float(np.linalg.cond(M)),
        "three",
        tilt,
    )


def solve_tcp(
    R: ArrayLike,
    T: ArrayLike,
    method: str = "lstsq",
    *,
    noise_sigma_m: float | None = None,
    min_tilt_deg: float = DEFAULT_MIN_TILT_DEG,
) -> TcpSolution:
    """TCP from n >= 3 poses: ``R`` (n, 3, 3), ``T`` (n, 3) flange2base (metres).

    ``method="lstsq"`` solves the 3n x 6 system for ``[p_tool; p_world]``; ``"variance"``
    minimises Eq. (8)-(9) by centring.  Both give the same estimate and the covariance
    ``s^2 [(A^T A)^-1]_{p block}`` (= ``s^2 (C^T C)^-1``), ``s = noise_sigma_m`` if given, else the
    estimated ``sigma = sqrt(|r|^2 / (3n - 6))``.  Raises ``DegeneratePoses`` with advice.
    """
    if method not in ("lstsq", "variance"):
        raise ValueError(f"method must be 'lstsq' or 'variance', got {method!r}")
    _check_noise(noise_sigma_m)
    Ra = _check_rotations(R)
    n = Ra.shape[0]
    Ta = _check_translations(T, n, batched=False)
    tilt = _check_spread(Ra, min_tilt_deg)
    if method == "lstsq":
        A = design_matrix(Ra)
        x, *_ = np.linalg.lstsq(A, -Ta.reshape(3 * n), rcond=None)
        p_tool = x[:3]
        cov_unit = np.linalg.inv(A.T @ A)[:3, :3]
        cond = float(np.linalg.cond(A))
    else:
        # Eq. (9) sums squared deviations from the mean world point; the mean of R_i p + T_i is
        # Rbar p + Tbar, so the deviations are (R_i - Rbar) p + (T_i - Tbar): linear in p.
        C = (Ra - Ra.mean(axis=0)).reshape(3 * n, 3)
        d = (Ta - Ta.mean(axis=0)).reshape(3 * n)
        p_tool, *_ = np.linalg.lstsq(C, -d, rcond=None)
        cov_unit = np.linalg.inv(C.T @ C)
        cond = float(np.linalg.cond(C))
    return _finish(Ra, Ta, p_tool, 3 * n - 6, cov_unit, noise_sigma_m, cond, method, tilt)
