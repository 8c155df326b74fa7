"""Stop-and-go calibration data made by the simulator, with its ground truth.

What a user of a peer project has on disk: the robot stopped at ``K`` poses around a tooling
ball, one profile per pose, and the flange pose the controller reported. :func:`make_stopgo`
plans sensor poses looking at the ball of the simulated scene (tilted up to ``max_tilt_deg`` at
spread azimuths, the laser line cutting the ball at varied heights on one side of its centre),
reaches them by inverse kinematics of the nominal arm, moves the arm by its *true* kinematics
when a :class:`~wristscan.calib.kinematic_errors.RobotErrorModel` is given (the controller then
reports its factory model's flange pose, with encoder noise and repeatability), and takes each
profile with the simulator's laser model against the scene (ball, post, table top) at the true
sensor pose. :func:`write_dataset` writes the folder that ``wristscan calibrate import`` reads
(docs/calibration_import.md) and ``truth.json`` beside it.

Production code never imports this module (it imports the simulator).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import kinematics, se3
from wristscan.calib import pose_conventions as pc
from wristscan.calib.kinematic_errors import RobotErrorModel
from wristscan.daemon.config import SimConfig
from wristscan.drivers.sim.laser import LaserModel
from wristscan.drivers.sim.scene import demo_scene

__all__ = ["EXAMPLE", "StopGoSet", "make_example", "make_stopgo", "truth_of", "write_dataset"]

FloatArray = NDArray[np.float64]

_Q_SEED = np.radians([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])


@dataclass(frozen=True, eq=False)
class StopGoSet:
    """A stop-and-go data set and its truth (SI units)."""

    names: tuple[str, ...]
    flange2base: FloatArray
    """(K, 4, 4) as the controller reports them."""
    flange2base_true: FloatArray
    """(K, 4, 4) where the flange really was."""
    profiles: tuple[FloatArray, ...]
    """(N, 3) per pose: ``y, z`` (m, NaN where invalid) and ``valid`` (0 or 1) of every point."""
    sensor2flange: FloatArray
    ball_centre_base: FloatArray
    ball_radius_m: float
    side: int
    noise_m: float

    def points(self, k: int) -> FloatArray:
        """The valid ``(y, z)`` points of pose ``k`` (m)."""
        p = self.profiles[k]
        return p[p[:, 2] > 0, :2]


def _sensor_poses(
    rng: np.random.Generator,
    centre: FloatArray,
    radius: float,
    n: int,
    fov: tuple[float, float, float],
    side: int,
    max_tilt_deg: float,
) -> FloatArray:
    """``n`` sensor2base poses looking at the ball: tilts spread over ``[0, max_tilt]`` and the
    azimuths, random yaw, the ball at varied places of the laser plane and heights of the cut."""
    half_width, z_lo, z_hi = fov
    y_span = max(half_width - radius - 2e-3, 0.0)
    tilts = np.radians(max_tilt_deg) * np.sqrt((np.arange(n) + 0.5) / n)
    az = rng.permutation(np.linspace(0.0, 2 * math.pi, n, endpoint=False))
    out = np.empty((n, 4, 4))
    for k in range(n):
        axis = np.array([math.cos(az[k]), math.sin(az[k]), 0.0])
        Rs = (
            se3.rotvec_to_matrix(axis * tilts[k])
            @ se3.rot_x(math.pi)
            @ se3.rot_z(rng.uniform(-math.pi, math.pi))
        )
        cs = np.array(
            [
                side * radius * rng.uniform(0.15, 0.8),
                rng.uniform(-y_span, y_span),
                rng.uniform(z_lo + radius + 5e-3, z_hi - 5e-3),
            ]
        )
        out[k] = se3.make(Rs, centre - Rs @ cs)
    return out


def make_stopgo(
    sim: SimConfig | None = None,
    *,
    n_poses: int = 15,
    seed: int = 0,
    robot: RobotErrorModel | None = None,
    n_points: int | None = None,
    side: int = 1,
    max_tilt_deg: float = 45.0,
) -> StopGoSet:
    """A stop-and-go set on the simulated cell of ``sim`` (default: the default simulated cell:
    its ball, true sensor2flange, sensor and robot model). ``robot``: the arm's errors (None: the
    arm is exactly its nominal model). ``n_points``: points per profile (default the sensor's)."""
    sim = sim or SimConfig()
    s = sim.sensor
    radius = float(sim.scene.ball_radius_m)
    centre = np.asarray(sim.scene.ball_centre_m, dtype=np.float64)
    X = sim.truth.sensor2flange()
    rng = np.random.default_rng(seed)
    laser = LaserModel(
        n_points=n_points or s.n_points,
        half_width_m=s.fov_lateral_m / 2,
        z_min_m=s.depth_min_m,
        z_max_m=s.depth_max_m,
        noise_std_m=s.noise_m,
        rng=rng,
        cache_size=0,
    )
    fov = (s.fov_lateral_m / 2, s.depth_min_m, s.depth_max_m)
    S = _sensor_poses(rng, centre, radius, n_poses, fov, side, max_tilt_deg)
    model = robot.nominal if robot is not None else sim.controller.model
    q = np.array([kinematics.inverse_nearest(model, Sk @ se3.invert(X), _Q_SEED) for Sk in S])
    if robot is None:
        reported = true = kinematics.forward(model, q)
    else:
        obs = robot.observe(q, rng)
        reported, true = obs.flange_reported, obs.flange_true
    scene = demo_scene(ball_radius_m=radius, ball_centre=centre, with_part=False)
    y, z, valid = laser.profile(true @ X, scene)
    profiles = tuple(np.column_stack([y[k], z[k], valid[k]]) for k in range(n_poses))
    return StopGoSet(
        names=tuple(f"p{k + 1:02d}" for k in range(n_poses)),
        flange2base=np.asarray(reported, dtype=np.float64),
        flange2base_true=np.asarray(true, dtype=np.float64),
        profiles=profiles,
        sensor2flange=X,
        ball_centre_base=centre,
        ball_radius_m=radius,
        side=side,
        noise_m=float(s.noise_m),
    )


def truth_of(data: StopGoSet) -> dict[str, Any]:
    """The ground truth of a set as ``truth.json`` holds it (SI units)."""
    return {
        "sensor2flange_matrix_rows": data.sensor2flange.tolist(),
        "sensor2flange_ur_pose": se3.matrix_to_pose(data.sensor2flange).tolist(),
        "ball_centre_base_m": data.ball_centre_base.tolist(),
        "ball_radius_m": data.ball_radius_m,
        "side": data.side,
        "sensor_noise_m": data.noise_m,
        "flange_pose_error_m": np.linalg.norm(
            data.flange2base[:, :3, 3] - data.flange2base_true[:, :3, 3], axis=1
        ).tolist(),
    }


def write_dataset(
    folder: Path,
    data: StopGoSet,
    *,
    convention: str = "ur-rotvec",
    units: str = "mm",
    with_valid: bool = False,
    made_by: dict[str, Any] | None = None,
) -> Path:
    """Write ``data`` as a dataset folder (``poses.csv``, ``profiles/<pose>.csv``) in
    ``convention`` and ``units`` ("mm" or "m"), plus ``truth.json``. Without ``with_valid`` the
    profiles hold only the valid points; with it every point and a ``valid`` column.
    ``made_by`` (how the set was made) goes into ``truth.json``."""
    scale = {"mm": 1e3, "m": 1.0}[units]
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "profiles").mkdir(exist_ok=True)
    rows = pc.from_matrix(convention, data.flange2base)
    rows[:, :3] *= scale
    lines = [",".join(("pose", *pc.columns(convention)))]
    lines += [
        ",".join((n, *(f"{v:.10g}" for v in r))) for n, r in zip(data.names, rows, strict=True)
    ]
    (folder / "poses.csv").write_text("\n".join(lines) + "\n")
    d = {"mm": 5, "m": 8}[units]  # 10 nm either way
    for name, prof in zip(data.names, data.profiles, strict=True):
        if with_valid:
            out = ["y,z,valid"] + [
                f"{y * scale:.{d}f},{z * scale:.{d}f},1" if v else f"{y * scale:.{d}f},,0"
                for y, z, v in prof
            ]
        else:
            out = ["y,z"] + [f"{y * scale:.{d}f},{z * scale:.{d}f}" for y, z, v in prof if v]
        (folder / "profiles" / f"{name}.csv").write_text("\n".join(out) + "\n")
    truth = truth_of(data) | ({"made_by": made_by} if made_by else {})
    (folder / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    return folder


EXAMPLE: dict[str, Any] = {
    "n_poses": 15,
    "seed": 1,
    "n_points": 400,
    "robot": {"nominal": "UR5e", "seed": 1, "factory": "partial", "repeatability_m": 30e-6},
    "convention": "fanuc-xyzwpr",
    "units": "mm",
}
"""How the example data set of docs/calibration_import.md and tests/data/import_example/ is
made: the default simulated cell, a UR5e as wrong as a real one (realistic DH deviations, a
partial factory calibration, 30 um repeatability), 15 poses, 400 points per profile."""


def make_example(folder: Path) -> Path:
    """Write the example data set (:data:`EXAMPLE`) into ``folder``."""
    e = EXAMPLE
    robot = RobotErrorModel(**e["robot"])
    data = make_stopgo(n_poses=e["n_poses"], seed=e["seed"], robot=robot, n_points=e["n_points"])
    return write_dataset(
        folder, data, convention=e["convention"], units=e["units"], with_valid=True, made_by=e
    )
