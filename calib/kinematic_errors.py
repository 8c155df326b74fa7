"""A robot as wrong as a real one: the arm's true kinematics, what its controller believes, and
the flange poses that follow, for a batch of joint positions.

A real arm differs from the nominal DH table of its model (:data:`wristscan.calib.dh.UR_MODELS`)
by small per-joint deviations of ``theta``, ``a``, ``d`` and ``alpha`` (machining, assembly,
joint zero offsets). The simulated controller (``[sim.controller] kinematic_errors``) and the
benchmarks use the same model, defined here:

* :func:`true_model` - the nominal table plus seeded normal deviations of the given standard
  deviations (:class:`KinematicErrorSizes`; :data:`REALISTIC` by default);
* :func:`factory_model` - the model a controller reports as its factory calibration
  (KinematicsInfo) and computes its poses with: ``"exact"`` (the true model), ``"partial"`` (the
  true model with ``residual`` of every deviation left, as a real factory calibration leaves some)
  or ``"none"`` (the nominal table);
* :class:`RobotErrorModel` - both, plus encoder noise on the reported joints and the
  repeatability of each pose, applied to commanded joint positions of stop-and-go poses
  (:meth:`RobotErrorModel.observe`) without running a controller.

All lengths in metres, angles in radians; poses are ``flange2base`` 4x4 transforms.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib.dh import DHParams, get_model
from wristscan.calib.kinematics import forward, jacobian

__all__ = [
    "DEFAULT_RESIDUAL",
    "FACTORY_CALIBRATIONS",
    "NO_ERRORS",
    "REALISTIC",
    "FactoryCalibration",
    "KinematicErrorSizes",
    "Observation",
    "RobotErrorModel",
    "factory_model",
    "model_dict",
    "model_from_dict",
    "pose_errors",
    "true_model",
]

FloatArray = NDArray[np.float64]
FactoryCalibration = Literal["exact", "partial", "none"]
FACTORY_CALIBRATIONS: tuple[str, ...] = ("exact", "partial", "none")
DEFAULT_RESIDUAL = 0.15
"""Fraction of each deviation a ``"partial"`` factory calibration leaves (10-20 % is typical)."""


@dataclass(frozen=True)
class KinematicErrorSizes:
    """Standard deviations of the per-joint deviations of the true arm from its nominal table."""

    theta_rad: float = math.radians(0.01)
    """Joint zero offsets."""
    a_m: float = 0.1e-3
    """Link lengths."""
    d_m: float = 0.1e-3
    """Link offsets."""
    alpha_rad: float = math.radians(0.01)
    """Link twists."""

    def __post_init__(self) -> None:
        for name in ("theta_rad", "a_m", "d_m", "alpha_rad"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"KinematicErrorSizes.{name} must be finite and >= 0, got {v}")

    @property
    def zero(self) -> bool:
        return self.theta_rad == self.a_m == self.d_m == self.alpha_rad == 0.0


REALISTIC = KinematicErrorSizes()
"""Deviations of a real arm's size: 0.1 mm and 0.01 deg (1 sigma) per parameter, which put the
flange of a UR5e 0.1-0.5 mm (typically 0.3 mm) from where the nominal table puts it."""
NO_ERRORS = KinematicErrorSizes(0.0, 0.0, 0.0, 0.0)


def true_model(
    nominal: str | DHParams, sizes: KinematicErrorSizes = REALISTIC, seed: int = 0
) -> DHParams:
    """The arm's true kinematics: ``nominal`` plus normal deviations of ``sizes`` drawn from
    ``seed`` (theta, a, d, alpha of joints 1-6, in that order). Zero sizes give ``nominal``."""
    base = get_model(nominal)
    if sizes.zero:
        return base
    rng = np.random.default_rng(seed)
    sd = np.array([sizes.theta_rad, sizes.a_m, sizes.d_m, sizes.alpha_rad])[:, None]
    dev = rng.normal(0.0, 1.0, (4, 6)) * sd
    d, a, alpha, theta = base.arrays()
    return DHParams(
        name=f"{base.name} true (seed {seed})",
        d=_six(d + dev[2]),
        a=_six(a + dev[1]),
        alpha=_six(alpha + dev[3]),
        theta_offset=_six(theta + dev[0]),
    )


def factory_model(
    nominal: str | DHParams,
    true: DHParams,
    calibration: str,
    residual: float = DEFAULT_RESIDUAL,
) -> DHParams:
    """What a controller reports and computes with: ``"exact"`` the ``true`` model, ``"none"``
    the ``nominal`` table, ``"partial"`` the true model with ``residual`` (0..1) of each
    deviation from the nominal table left."""
    base = get_model(nominal)
    if calibration == "exact":
        return true
    if calibration == "none":
        return base
    if calibration != "partial":
        raise ValueError(
            f"factory calibration must be one of {', '.join(FACTORY_CALIBRATIONS)}, "
            f"got {calibration!r}"
        )
    if not 0.0 <= residual <= 1.0:
        raise ValueError(f"residual must be in [0, 1], got {residual}")
    n, t = base.arrays(), true.arrays()
    d, a, alpha, theta = (_six(ti - residual * (ti - ni)) for ni, ti in zip(n, t, strict=True))
    return DHParams(
        name=f"{base.name} factory calibration", d=d, a=a, alpha=alpha, theta_offset=theta
    )


def _six(values: FloatArray) -> tuple[float, ...]:
    return tuple(float(v) for v in values)


def model_dict(model: DHParams) -> dict[str, object]:
    """A model as plain data (name and four lists of 6 floats), e.g. for JSON."""
    return {
        "name": model.name,
        "theta": list(model.theta_offset),
        "a": list(model.a),
        "d": list(model.d),
        "alpha": list(model.alpha),
    }


def model_from_dict(data: dict[str, object]) -> DHParams:
    """The inverse of :func:`model_dict`."""
    return DHParams(
        name=str(data.get("name", "model")),
        d=data["d"],  # type: ignore[arg-type]
        a=data["a"],  # type: ignore[arg-type]
        alpha=data["alpha"],  # type: ignore[arg-type]
        theta_offset=data["theta"],  # type: ignore[arg-type]
    )


def pose_errors(A: ArrayLike, B: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Position distance (m) and rotation angle (rad) between poses ``A`` and ``B`` (..., 4, 4)."""
    a = np.asarray(A, dtype=np.float64)
    b = np.asarray(B, dtype=np.float64)
    dist = np.linalg.norm(a[..., :3, 3] - b[..., :3, 3], axis=-1)
    rel = np.swapaxes(a[..., :3, :3], -1, -2) @ b[..., :3, :3]
    cos = np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return np.asarray(dist, dtype=np.float64), np.asarray(np.arccos(cos), dtype=np.float64)


class Observation(NamedTuple):
    """Stop-and-go poses as a controller reports them and as they are."""

    q_reported: FloatArray
    """(N, 6) joints the controller reports (with encoder noise)."""
    q_true: FloatArray
    """(N, 6) joints the arm really has (the commanded ones moved by the repeatability)."""
    flange_reported: FloatArray
    """(N, 4, 4) ``flange2base`` the controller reports: its factory model at ``q_reported``."""
    flange_true: FloatArray
    """(N, 4, 4) where the flange really is: the true model at ``q_true``."""


@dataclass(frozen=True)
class RobotErrorModel:
    """A simulated arm's errors, as the simulated controller applies them (SI units).

    ``repeatability_m`` is the RMS length of a per-pose offset of the flange position (each axis
    ``repeatability_m / sqrt(3)``), independent from pose to pose (stop-and-go: every pose is
    approached anew); ``joint_noise_rad`` the standard deviation of the encoder noise on each
    reported joint.
    """

    nominal: str | DHParams = "UR5e"
    sizes: KinematicErrorSizes = REALISTIC
    seed: int = 0
    factory: str = "partial"
    residual: float = DEFAULT_RESIDUAL
    joint_noise_rad: float = 0.0
    repeatability_m: float = 0.0

    def __post_init__(self) -> None:
        get_model(self.nominal)
        factory_model(self.nominal, get_model(self.nominal), self.factory, self.residual)
        if self.joint_noise_rad < 0 or self.repeatability_m < 0:
            raise ValueError("joint_noise_rad and repeatability_m must be >= 0")

    @property
    def nominal_model(self) -> DHParams:
        return get_model(self.nominal)

    @property
    def true_model(self) -> DHParams:
        return true_model(self.nominal, self.sizes, self.seed)

    @property
    def reported_model(self) -> DHParams:
        """The factory calibration the controller reports and computes its poses with."""
        return factory_model(self.nominal, self.true_model, self.factory, self.residual)

    def observe(
        self,
        q: ArrayLike,
        rng: np.random.Generator | int | None = None,
        groups: ArrayLike | None = None,
    ) -> Observation:
        """Commanded joints ``q`` (N, 6) -> what the controller reports and where the flange
        really is; ``rng`` draws the encoder noise and the repeatability. Each row is a pose
        approached anew (stop-and-go), unless ``groups`` (N,) says otherwise: rows with the same
        label share one repeatability offset of the flange position (the samples of one sweep,
        which the arm follows without stopping)."""
        g = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        qc = np.atleast_2d(np.asarray(q, dtype=np.float64))
        true = self.true_model
        q_true = qc.copy()
        if self.repeatability_m > 0:
            if groups is None:
                label = np.arange(qc.shape[0])
            else:
                label = np.unique(np.asarray(groups), return_inverse=True)[1].reshape(-1)
            draws = g.normal(0.0, self.repeatability_m / math.sqrt(3.0), (label.max() + 1, 3))
            offset = draws[label]
            Jp = jacobian(true, qc)[:, :3, :]
            A = Jp @ np.swapaxes(Jp, -1, -2) + 1e-9 * np.eye(3)
            q_true += (np.swapaxes(Jp, -1, -2) @ np.linalg.solve(A, offset[..., None]))[..., 0]
        q_rep = qc + g.normal(0.0, self.joint_noise_rad, qc.shape) if self.joint_noise_rad else qc
        return Observation(
            q_reported=q_rep,
            q_true=q_true,
            flange_reported=forward(self.reported_model, q_rep),
            flange_true=forward(true, q_true),
        )

    def flange_error(self, q: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Position (m) and angle (rad) by which the reported model misses the true flange at
        joints ``q`` (N, 6), without noise or repeatability."""
        qa = np.asarray(q, dtype=np.float64)
        return pose_errors(forward(self.reported_model, qa), forward(self.true_model, qa))
