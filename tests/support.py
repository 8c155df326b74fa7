"""What the tests and the benchmarks share: reference data and checks against the simulator's
truth, in one place (benchmarks put this folder on ``sys.path``; pytest does for the tests)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import kinematics as kin
from wristscan.drivers.records import Profile

# KinematicsInfo of a real UR10e as printed in Universal_Robots_ROS2_Driver
# ur_calibration/doc/algorithm.rst (complete calibrated DH values, not deltas).
REAL_UR10E = kin.from_kinematics_info(
    theta=[-2.4147806894359e-07, 1.60233952386695, -1.68607190752171, 0.0837331147700119,
           -1.01260355871158e-07, 3.91986209186124e-08],
    a=[2.12234865571206e-05, 0.0193171326277006, -0.569251663611088, -4.61409023720934e-05,
       -6.39280053471802e-05, 0.0],
    d=[0.180539811714259, 439.140974079901, -446.027059806332, 7.0603368964236,
       0.119811341150314, 0.115670917257426],
    alpha=[1.57014608044242, 0.0013941666682559, 0.00693818880325995, 1.56998468543761,
           -1.57038520649543, 0.0],
    name="real UR10e",
)  # fmt: skip


def same_profile(a: Profile, b: Profile) -> bool:
    """Two profiles carry the same data (NaN where the other has NaN)."""

    def eq(x: Any, y: Any) -> bool:
        if x is None or y is None:
            return x is None and y is None
        return bool(np.array_equal(x, y, equal_nan=x.dtype.kind == "f"))

    return (
        (a.sensor_id, a.frame_counter, a.sensor_time_ns, a.encoder)
        == (b.sensor_id, b.frame_counter, b.sensor_time_ns, b.encoder)
        and eq(a.y, b.y)
        and eq(a.z, b.z)
        and eq(a.valid, b.valid)
        and eq(a.intensity, b.intensity)
    )


def surface(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """A smooth patch (m) with no symmetry: anisotropic paraboloid, cubic term, off-centre bump
    (registration has one right answer on it)."""
    bump = 0.005 * np.exp(-((x - 0.01) ** 2 + (y + 0.015) ** 2) / (2 * 0.01**2))
    return 3.0 * x**2 + 1.0 * y**2 + 2.0 * x**3 + bump


def sample_surface(
    rng: np.random.Generator, x_range: tuple[float, float], step: float
) -> NDArray[np.float64]:
    """Points of :func:`surface` on a jittered grid over ``x_range`` x (-0.04, 0.04) m."""
    gx, gy = np.meshgrid(np.arange(*x_range, step), np.arange(-0.04, 0.04, step))
    x = gx.ravel() + rng.uniform(-step / 3, step / 3, gx.size)
    y = gy.ravel() + rng.uniform(-step / 3, step / 3, gx.size)
    return np.column_stack([x, y, surface(x, y)])


def depth_errors(
    sweep: Any,
    scene: Any,
    sensor2flange: NDArray[np.float64],
    table_angle_rad: float | None,
    n_profiles: int = 30,
) -> NDArray[np.float64]:
    """Measured minus true depth (m) of about ``n_profiles`` profiles of a recorded ``sweep``
    (:class:`~wristscan.daemon.procedure.acquisition.Sweep`): each ray-cast in the simulator's
    true ``scene`` from the robot pose it was paired with. A timing or pose fault shows here
    before any registration can hide it. NaN where the true ray misses."""
    errors = []
    for k in range(0, sweep.n_profiles, max(1, sweep.n_profiles // n_profiles)):
        m = (sweep.profile_index == k) & sweep.valid
        y = sweep.y[m]
        origins = np.column_stack([np.zeros_like(y), y, np.zeros_like(y)])
        dirs = np.tile([0.0, 0.0, 1.0], (y.size, 1))
        t, _ = scene.raycast_bundles(
            (sweep.flange2base[k] @ sensor2flange)[None], origins, dirs, table_angle_rad
        )
        errors.append(sweep.z[m] - t[0])
    return np.concatenate(errors)
