"""Denavit-Hartenberg parameters of Universal Robots arms: the nominal table of each model and
the per-robot corrections (:mod:`wristscan.calib.kinematics` evaluates them).

* Standard DH, one transform per joint ``i``: ``Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)`` with
  ``theta_i = q_i + theta_offset_i``; lengths in metres, angles in radians.
* Nominal parameters: Universal_Robots_ROS2_Description ``config/<model>/default_kinematics.yaml``
  and UR's article "DH parameters for calculations of kinematics" (table in PROTOCOLS.md).
* Every UR arm leaves the factory with its own DH corrections: the robot's ``calibration.conf``
  holds *deltas* (:func:`with_deltas`), the primary interface's KinematicsInfo sub-package
  reports the *sums* (:func:`from_kinematics_info`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "UR_ALPHA",
    "UR_MODELS",
    "DHParams",
    "from_kinematics_info",
    "get_model",
    "six_floats",
    "with_deltas",
]

FloatArray = NDArray[np.float64]

UR_ALPHA: tuple[float, ...] = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
"""Link twists (rad) shared by every UR model."""


def six_floats(values: ArrayLike, name: str) -> tuple[float, ...]:
    """``values`` as 6 finite floats (one per joint); ValueError naming ``name`` otherwise."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.shape != (6,):
        raise ValueError(f"{name}: expected 6 values (one per joint), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or infinity")
    return tuple(float(v) for v in arr)


@dataclass(frozen=True)
class DHParams:
    """Standard DH parameters of a 6-joint arm; every field holds 6 values, joint 1 first.

    ``d`` and ``a`` in metres, ``alpha`` and ``theta_offset`` in radians (``theta = q +
    theta_offset``). Each field is checked (6 finite numbers) and stored as a tuple of floats.
    Hashable, so it can key caches.
    """

    name: str
    d: tuple[float, ...]
    a: tuple[float, ...]
    alpha: tuple[float, ...]
    theta_offset: tuple[float, ...] = (0.0,) * 6

    def __post_init__(self) -> None:
        for field in ("d", "a", "alpha", "theta_offset"):
            # Frozen dataclass: normalise in place through object.__setattr__.
            object.__setattr__(self, field, six_floats(getattr(self, field), f"DHParams.{field}"))

    def arrays(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """``(d, a, alpha, theta_offset)`` as float64 arrays of shape ``(6,)``."""
        return (
            np.array(self.d),
            np.array(self.a),
            np.array(self.alpha),
            np.array(self.theta_offset),
        )


def _ur(name: str, d1: float, a2: float, a3: float, d4: float, d5: float, d6: float) -> DHParams:
    return DHParams(
        name=name, d=(d1, 0.0, 0.0, d4, d5, d6), a=(0.0, a2, a3, 0.0, 0.0, 0.0), alpha=UR_ALPHA
    )


UR_MODELS: dict[str, DHParams] = {
    m.name: m
    for m in (
        _ur("UR3", 0.1519, -0.24365, -0.21325, 0.11235, 0.08535, 0.0819),
        _ur("UR5", 0.089159, -0.425, -0.39225, 0.10915, 0.09465, 0.0823),
        _ur("UR10", 0.1273, -0.612, -0.5723, 0.163941, 0.1157, 0.0922),
        _ur("UR3e", 0.15185, -0.24355, -0.2132, 0.13105, 0.08535, 0.0921),
        _ur("UR5e", 0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996),
        _ur("UR10e", 0.1807, -0.6127, -0.57155, 0.17415, 0.11985, 0.11655),
        _ur("UR16e", 0.1807, -0.4784, -0.36, 0.17415, 0.11985, 0.11655),
        _ur("UR20", 0.2363, -0.862, -0.7287, 0.201, 0.1593, 0.1543),
    )
}
"""Nominal DH parameters of each UR model, keyed by model name."""


def get_model(name_or_params: str | DHParams) -> DHParams:
    """Resolve a model name (case-insensitive, e.g. ``"UR5e"``) or pass a :class:`DHParams` through.

    Raises ``ValueError`` listing the known names for an unknown one.
    """
    if isinstance(name_or_params, DHParams):
        return name_or_params
    if not isinstance(name_or_params, str):
        raise TypeError(
            f"expected a UR model name or DHParams, got {type(name_or_params).__name__}"
        )
    by_lower = {k.lower(): v for k, v in UR_MODELS.items()}
    try:
        return by_lower[name_or_params.strip().lower()]
    except KeyError:
        raise ValueError(
            f"unknown robot model {name_or_params!r}; valid names: {', '.join(UR_MODELS)}"
        ) from None


def with_deltas(
    model: str | DHParams,
    delta_theta: ArrayLike,
    delta_a: ArrayLike,
    delta_d: ArrayLike,
    delta_alpha: ArrayLike,
) -> DHParams:
    """Apply per-robot calibration deltas (``calibration.conf`` ``[mounting]`` values).

    Each delta holds 6 values (joint 1 first), metres for ``a``/``d`` and radians for
    ``theta``/``alpha``; they are added to the model's parameters (``theta_offset`` carries
    ``delta_theta``).
    """
    base = get_model(model)

    def add(nominal: tuple[float, ...], delta: ArrayLike, name: str) -> tuple[float, ...]:
        return tuple(x + y for x, y in zip(nominal, six_floats(delta, name), strict=True))

    return DHParams(
        name=f"{base.name}+deltas",
        d=add(base.d, delta_d, "delta_d"),
        a=add(base.a, delta_a, "delta_a"),
        alpha=add(base.alpha, delta_alpha, "delta_alpha"),
        theta_offset=add(base.theta_offset, delta_theta, "delta_theta"),
    )


def from_kinematics_info(
    theta: ArrayLike, a: ArrayLike, d: ArrayLike, alpha: ArrayLike, name: str = "calibrated"
) -> DHParams:
    """Model from the primary interface's KinematicsInfo (``double[6]`` theta, a, d, alpha).

    Those are complete calibrated parameters (nominal plus deltas), not deltas.
    """
    return DHParams(
        name=name,
        d=six_floats(d, "d"),
        a=six_floats(a, "a"),
        alpha=six_floats(alpha, "alpha"),
        theta_offset=six_floats(theta, "theta"),
    )
