"""What every teaching procedure (:mod:`.plane`, :mod:`.measure`, :mod:`.edge`,
:mod:`.edge_model`) runs on: its errors, the acquisition it opens and the guard around its
motion, moving the sensor to a pose in the base frame, recording still profiles, and the points
of a sweep in the base frame. Kept in one place so that the procedures stop, fail and see the
surface the same way.

Safety as in the calibration procedures: no motion unless ``[robot] motion_enabled`` and
confirmed; speeds capped by the configuration; the driver refuses targets outside the workspace
box; any failure while moving stops the robot and raises :class:`TeachAborted` (the guard is the
procedure kit's :func:`~wristscan.daemon.procedure.motion.guarded_motion`).
"""

from __future__ import annotations

import time
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import se3
from wristscan.daemon.config import Config
from wristscan.daemon.procedure.errors import ProcedureAborted, ProcedureError
from wristscan.daemon.procedure.in_force import procedure_acquisition
from wristscan.daemon.procedure.motion import guarded_motion

if TYPE_CHECKING:
    from wristscan.daemon.procedure.acquisition import Acquisition, Sweep

__all__ = [
    "Mover",
    "TeachAborted",
    "TeachError",
    "guarded",
    "mean_pose",
    "points_in_base",
    "record_still",
    "teach_acquisition",
]

FloatArray = NDArray[np.float64]


class TeachError(ProcedureError):
    """A teaching procedure cannot run or failed; the message tells the operator why."""


class TeachAborted(TeachError, ProcedureAborted):
    """Stopped part way (protective stop, refused move, lost device, Ctrl-C); the robot was
    stopped and nothing was written."""


def points_in_base(
    sweep: Sweep, sensor2flange: ArrayLike, max_points: int | None = None, seed: int = 0
) -> tuple[FloatArray, NDArray[np.int64]]:
    """Valid points of ``sweep`` in the base frame ``(M, 3)`` and their profile index ``(M,)``
    (a seeded random subset of at most ``max_points``)."""
    m = sweep.valid & np.isfinite(sweep.y) & np.isfinite(sweep.z)
    prof = sweep.profile_index[m]
    y, z = sweep.y[m], sweep.z[m]
    if max_points is not None and prof.size > max_points:
        keep = np.sort(np.random.default_rng(seed).choice(prof.size, max_points, replace=False))
        prof, y, z = prof[keep], y[keep], z[keep]
    s2b = sweep.flange2base @ np.asarray(sensor2flange, dtype=np.float64)
    R = s2b[prof, :3, :3]
    pts = R[:, :, 1] * y[:, None] + R[:, :, 2] * z[:, None] + s2b[prof, :3, 3]
    return np.asarray(pts, dtype=np.float64), np.asarray(prof, dtype=np.int64)


def mean_pose(T: FloatArray) -> FloatArray:
    """Average of nearby poses ``(P, 4, 4)`` (mean translation, rotation of the mean matrix
    projected back onto SO(3))."""
    if T.shape[0] == 0:
        raise ValueError("no poses to average")
    R = T[:, :3, :3].mean(axis=0)
    U, _, Vt = np.linalg.svd(R)
    Rm = U @ Vt
    if np.linalg.det(Rm) < 0:
        U[:, -1] *= -1
        Rm = U @ Vt
    return np.asarray(se3.make(Rm, T[:, :3, 3].mean(axis=0)))


class Mover:
    """Moves the sensor to poses in the base frame through the robot's TCP; records still
    profiles. Everything goes through an open :class:`Acquisition`."""

    def __init__(self, acq: Acquisition, sensor2flange: ArrayLike, speed_m_s: float) -> None:
        self.acq = acq
        self.robot = acq.robot
        self.s2f = np.asarray(sensor2flange, dtype=np.float64)
        self.f2s = se3.invert(self.s2f)
        r = acq.cfg.robot
        self.speed = min(float(speed_m_s), float(r.max_speed_m_s))
        self.accel = float(r.max_accel_m_s2)
        self.tcp2flange = se3.pose_to_matrix(np.asarray(self.robot.tcp_offset(), dtype=float))

    def tcp_pose(self, sensor2base: ArrayLike) -> FloatArray:
        """UR pose of the TCP that puts the sensor at ``sensor2base``."""
        return np.asarray(se3.matrix_to_pose(np.asarray(sensor2base) @ self.f2s @ self.tcp2flange))

    def move_sensor(self, sensor2base: ArrayLike, speed_m_s: float | None = None) -> None:
        speed = self.speed if speed_m_s is None else min(float(speed_m_s), self.speed)
        self.robot.move_l(self.tcp_pose(sensor2base), speed, self.accel)


def teach_acquisition(
    cfg: Config, acquisition: Acquisition | None = None
) -> AbstractContextManager[Acquisition]:
    """:func:`~wristscan.daemon.procedure.in_force.procedure_acquisition` for the teaching
    procedures: a device that does not answer in time is tried again (a controller busy
    starting up); a device failure becomes a :class:`TeachError`."""
    return procedure_acquisition(cfg, acquisition, attempts=3, open_error=TeachError)


def record_still(acq: Acquisition, dwell_s: float, settle_s: float = 0.05) -> Sweep:
    """Profiles recorded for ``dwell_s`` while the robot stands still (after ``settle_s``)."""
    time.sleep(settle_s)
    with acq.record() as rec:
        time.sleep(dwell_s)
    sweep = rec.result()
    if sweep.n_profiles == 0:
        raise TeachError(
            "no profile was paired with a robot pose while standing still (wristscan run -v "
            "shows the synchroniser's counters)"
        )
    return sweep


def guarded(acq: Acquisition, what: str) -> AbstractContextManager[None]:
    """The procedures' guard for teaching: stop the robot when anything goes wrong inside the
    block; driver errors, Ctrl-C and a failed fit (ValueError) while moving become
    :class:`TeachAborted` (the table is not used here)."""
    return guarded_motion(
        acq,
        what,
        error=TeachAborted,
        also=(ValueError,),
        consequence="the robot was stopped",
        table=False,
    )
