"""Data of the sensor-to-flange calibration (:mod:`wristscan.calib.handeye`): the ball-matching
sweeps, the results of the solvers, and the error raised when the sweeps do not pin the
solution down. Covariance orders are those of the :mod:`~wristscan.calib.handeye` module doc.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import se3

if TYPE_CHECKING:
    from wristscan.calib.handeye_uncertainty import Jackknife, VarianceComponents

__all__ = [
    "CovarianceSigmas",
    "HandEyeResult",
    "Identifiability",
    "OrientationSolution",
    "OriginSolution",
    "PoorlyConstrained",
    "Sweep",
    "check_radius",
    "check_sweeps",
    "rows_times",
    "translation_only",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]


class PoorlyConstrained(ValueError):
    """The sweeps do not pin down ``sensor2flange``; ``advice`` says which data to add."""

    def __init__(self, message: str, advice: str = "", condition: float = float("nan")) -> None:
        super().__init__(f"{message}; {advice}" if advice else message)
        self.advice = advice
        self.condition = condition


# --------------------------------------------------------------------------------------------
# Data model


@dataclass(frozen=True, eq=False)
class Sweep:
    """One ball-matching pass.

    Attributes:
        flange2base: ``(P, 4, 4)`` flange pose at each profile instant (metres).
        points_sensor: ``(N, 3)`` profile points in the sensor frame (metres); ``x`` is 0 for a
            laser-plane point ``(0, y, z)``.
        pose_index: ``(N,)`` index into ``flange2base`` of the profile each point belongs to.
    """

    flange2base: FloatArray
    points_sensor: FloatArray
    pose_index: IntArray

    def __post_init__(self) -> None:
        F = se3.check_transform(np.asarray(self.flange2base, dtype=np.float64), "flange2base")
        if F.ndim != 3:
            raise ValueError(f"flange2base: expected (P, 4, 4), got {F.shape}")
        p = np.asarray(self.points_sensor, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points_sensor: expected (N, 3), got {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ValueError("points_sensor: contains NaN or infinity")
        idx = np.asarray(self.pose_index)
        if idx.shape != (p.shape[0],) or (idx.size and not np.issubdtype(idx.dtype, np.integer)):
            raise ValueError(f"pose_index: expected ({p.shape[0]},) integers, got {idx.shape}")
        idx = idx.astype(np.intp)
        if idx.size and (idx.min() < 0 or idx.max() >= F.shape[0]):
            raise ValueError(f"pose_index: out of range for {F.shape[0]} poses")
        object.__setattr__(self, "flange2base", F)
        object.__setattr__(self, "points_sensor", p)
        object.__setattr__(self, "pose_index", idx)

    @classmethod
    def from_yz(
        cls, flange2base: ArrayLike, y: ArrayLike, z: ArrayLike, pose_index: ArrayLike
    ) -> Sweep:
        """Build from laser-plane coordinates ``y, z`` (metres, ``(N,)``)."""
        ya = np.asarray(y, dtype=np.float64)
        za = np.asarray(z, dtype=np.float64)
        pts = np.stack([np.zeros_like(ya), ya, za], axis=-1)
        return cls(np.asarray(flange2base, dtype=np.float64), pts, np.asarray(pose_index))

    @property
    def n_points(self) -> int:
        return int(self.points_sensor.shape[0])

    @property
    def n_poses(self) -> int:
        return int(self.flange2base.shape[0])

    def points_base(self, sensor2flange: ArrayLike) -> FloatArray:
        """All points mapped into the base frame through ``sensor2flange`` (4, 4): ``(N, 3)``."""
        X = np.asarray(sensor2flange, dtype=np.float64)
        pf = rows_times(self.points_sensor, X[:3, :3].T) + X[:3, 3]
        F = self.flange2base[self.pose_index]
        return np.matmul(F[:, :3, :3], pf[:, :, None])[:, :, 0] + F[:, :3, 3]

    def subset(self, mask: ArrayLike) -> Sweep:
        """The same sweep with only the points where ``mask`` is true."""
        m = np.asarray(mask, dtype=bool)
        return Sweep(self.flange2base, self.points_sensor[m], self.pose_index[m])


class CovarianceSigmas:
    """The 1-sigma uncertainties of a ``cov`` in :class:`HandEyeResult`'s order (rotation
    increments about the sensor axes, rad, then the sensor origin, m)."""

    cov: FloatArray

    @property
    def sigma_rotation_rad(self) -> FloatArray:
        """1-sigma rotation uncertainty about the sensor X, Y, Z axes (radians)."""
        return np.sqrt(np.clip(np.diag(self.cov)[:3], 0.0, None))

    @property
    def sigma_translation_m(self) -> FloatArray:
        """1-sigma uncertainty of the sensor origin along flange X, Y, Z (metres)."""
        return np.sqrt(np.clip(np.diag(self.cov)[3:6], 0.0, None))


@dataclass(frozen=True, eq=False)
class HandEyeResult(CovarianceSigmas):
    """A sensor-to-flange calibration.

    ``cov`` is ``(6, 6)`` in the order ``[w_x, w_y, w_z (rad, about sensor axes), t_x, t_y, t_z
    (m, flange frame)]``; ``cov_full`` adds the ball centre (m) and, if estimated, the radius (m).
    Residuals are signed distances of the inlier points to the ball surface (metres).
    ``advice`` is empty unless the condition number exceeded the soft threshold.

    The joint solution's ``cov`` models the robot's pose error as well as the sensor noise
    (:mod:`~wristscan.calib.handeye_uncertainty`): ``components`` holds the variance components
    estimated from the residuals, ``jackknife`` the leave-one-pose-cluster-out cross-check (when
    asked for) and ``point_sigma_m`` / ``point_sigma_rms_m`` the predicted 1-sigma error (3-D,
    metres) of a measured point due to the calibration, maximum and RMS over the working volume
    ``working_volume_m`` (laser-plane ``y`` and ``z`` ranges, metres).
    """

    sensor2flange: FloatArray
    ball_centre_base: FloatArray
    ball_radius_m: float
    cov: FloatArray
    per_sweep_rms: FloatArray
    rms: float
    n_points: int
    condition: float
    method: str
    inliers: tuple[BoolArray, ...] = field(repr=False)
    advice: str = ""
    cov_full: FloatArray | None = field(default=None, repr=False)
    components: VarianceComponents | None = field(default=None, repr=False)
    jackknife: Jackknife | None = field(default=None, repr=False)
    point_sigma_m: float = float("nan")
    point_sigma_rms_m: float = float("nan")
    working_volume_m: tuple[tuple[float, float], tuple[float, float]] | None = None

    def as_ur_pose(self) -> FloatArray:
        """The TCP as a UR pose ``p[x, y, z, rx, ry, rz]`` (metres, rotation vector)."""
        return se3.matrix_to_pose(self.sensor2flange)


@dataclass(frozen=True, eq=False)
class OrientationSolution:
    """Step 1: sensor-to-flange rotation from constant-orientation sweeps.

    ``residuals`` ``(K, 3)`` (m) are the Procrustes misfits of the ball centres in the
    flange-aligned frame; ``cov`` ``(3, 3)`` (rad^2) is about the sensor axes (right
    perturbation)."""

    rotation: FloatArray
    centres_sensor: FloatArray
    residuals: FloatArray
    rms: float
    cov: FloatArray
    iterations: int
    inliers: tuple[BoolArray, ...] = field(repr=False)


@dataclass(frozen=True, eq=False)
class OriginSolution:
    """Step 2: sensor origin in the flange frame (m) and the ball centre in base (m)."""

    translation: FloatArray
    ball_centre_base: FloatArray
    centres_sensor: FloatArray
    residuals: FloatArray
    cov: FloatArray
    sigma: float
    inliers: tuple[BoolArray, ...] = field(repr=False)


@dataclass(frozen=True, eq=False)
class Identifiability:
    """Conditioning of the joint problem at a solution.

    ``condition`` is the 2-norm condition number of the Jacobian after scaling every column to unit
    norm (so it does not depend on units). ``weakest`` is the parameter-space direction (same order
    as ``HandEyeResult.cov_full``) that the data constrain least; ``advice`` says what to add."""

    condition: float
    singular_values: FloatArray
    weakest: FloatArray
    advice: str


# --------------------------------------------------------------------------------------------
# Checks and helpers shared by the solvers


def rows_times(A: FloatArray, M: FloatArray) -> FloatArray:
    """``A @ M`` for tall ``A`` (N, 3) and a 3x3 ``M``, as broadcast multiply-adds: BLAS is slow for
    such skinny products (and contends for the cores when it multi-threads)."""
    return A[:, :1] * M[0] + A[:, 1:2] * M[1] + A[:, 2:] * M[2]


def check_radius(ball_radius: float) -> float:
    """``ball_radius`` as a positive length (m); ValueError otherwise."""
    r = float(ball_radius)
    if not np.isfinite(r) or r <= 0.0:
        raise ValueError(f"ball_radius must be a positive length in metres, got {ball_radius!r}")
    return r


def check_sweeps(sweeps: Sequence[Sweep], what: str) -> list[Sweep]:
    """The sweeps as a list, each a :class:`Sweep` with enough points for a sphere."""
    out = list(sweeps)
    for k, s in enumerate(out):
        if not isinstance(s, Sweep):
            raise TypeError(f"{what}[{k}] is {type(s).__name__}, expected Sweep")
        if s.n_points < 4:
            raise ValueError(f"{what}[{k}] has {s.n_points} points; a sphere needs at least 4")
    return out


def translation_only(sweep: Sweep, k: int, tol_rad: float) -> None:
    """Refuse sweep ``k`` when its flange turns by more than ``tol_rad``."""
    R = sweep.flange2base[:, :3, :3]
    dev = se3.rotation_angle(np.swapaxes(R[:1], -1, -2) @ R)
    if dev.size and float(dev.max()) > tol_rad:
        raise ValueError(
            f"sweep {k} rotates by {np.degrees(dev.max()):.3f} deg; the two-step method needs "
            "constant-orientation sweeps (use refine() for general motion)"
        )
