"""Whether the robot can make the moves of the sensor calibration: inverse kinematics near a
seed in the arm configuration of the start pose, away from the wrist singularity, with joint
continuity along the short linear moves and the TCP inside the workspace box.

The automatic mode asks it before every move (:class:`Reachability`); :mod:`.plan` takes its
answers as a callback, so the plan stays pure geometry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import kinematics, se3

__all__ = ["Reachability", "SweepReach"]

FloatArray = NDArray[np.float64]

_MAX_JOINT_STEP_RAD = 0.6
"""Largest joint change allowed along a short linear move (a larger one means a branch flip or a
singularity on the way)."""
_MIN_WRIST_SIN = math.sin(math.radians(5.0))
_MAX_ARM_CHANGE_RAD = math.radians(75.0)


@dataclass(frozen=True)
class SweepReach:
    """Joint solutions of the approach, sweep start and sweep end of one location, and of a pose
    to pass through on the way to the approach (None: straight there)."""

    approach: FloatArray
    start: FloatArray
    end: FloatArray
    via: FloatArray | None = None


class Reachability:
    """Reachability of flange poses for the plan: IK near a seed, in the arm configuration of the
    start pose (base, shoulder and elbow within ``_MAX_ARM_CHANGE_RAD`` of ``reference_q``: no
    swinging the arm over), away from the wrist singularity, joint continuity along short linear
    moves, TCP inside the workspace box (also along joint moves)."""

    def __init__(
        self,
        model: kinematics.DHParams,
        tcp2flange: FloatArray,
        workspace: tuple[FloatArray, FloatArray] | None,
        reference_q: FloatArray | None = None,
    ) -> None:
        self.model = model
        self.tcp2flange = tcp2flange
        self.workspace = workspace
        self.reference_q = None if reference_q is None else np.asarray(reference_q, float)

    def _arm_ok(self, q: FloatArray) -> bool:
        if self.reference_q is None:
            return True
        d = kinematics.wrap_angle(q[:3] - self.reference_q[:3])
        return float(np.max(np.abs(d))) <= _MAX_ARM_CHANGE_RAD

    def ik(self, flange2base: FloatArray, seed: FloatArray) -> FloatArray | None:
        """Joints reaching ``flange2base`` near ``seed``, or None when out of reach."""
        try:
            q = kinematics.inverse_nearest(self.model, flange2base, seed)
            if not self._arm_ok(q) and self.reference_q is not None:
                q = kinematics.inverse_nearest(self.model, flange2base, self.reference_q)
        except kinematics.Unreachable:
            return None
        if not self._arm_ok(q):
            return None
        if abs(math.sin(float(q[4]))) < _MIN_WRIST_SIN:
            return None
        if self.workspace is not None:
            p = (flange2base @ self.tcp2flange)[:3, 3]
            lo, hi = self.workspace
            if np.any(p < lo) or np.any(p > hi):
                return None
        return np.asarray(q, dtype=np.float64)

    def linear(
        self, a: FloatArray, b: FloatArray, qa: FloatArray, steps: int = 4
    ) -> FloatArray | None:
        """Joints at ``b`` reached by a linear move from ``a`` (joints ``qa``), or None when the
        path leaves the reach, the workspace or the joint branch."""
        q = qa
        for s in np.linspace(0.0, 1.0, steps + 1)[1:]:
            nxt = self.ik(se3.interpolate(a, b, s), q)
            if nxt is None or float(np.max(np.abs(nxt - q))) > _MAX_JOINT_STEP_RAD:
                return None
            q = nxt
        return q

    def joint_path(self, q0: FloatArray, q1: FloatArray, samples: int = 16) -> bool:
        """Whether the TCP stays inside the workspace box along the joint move ``q0 -> q1`` (as
        the driver checks it: joints interpolated linearly)."""
        if self.workspace is None:
            return True
        t = np.linspace(0.0, 1.0, samples + 1)[1:, None]
        F = kinematics.forward(self.model, q0[None, :] + t * (q1 - q0)[None, :])
        p = (F @ self.tcp2flange)[:, :3, 3]
        lo, hi = self.workspace
        return not bool(np.any((p < lo) | (p > hi)))

    def sweep(
        self,
        start: FloatArray,
        end: FloatArray,
        clearance: FloatArray,
        seed: FloatArray,
        via: FloatArray | None = None,
    ) -> SweepReach | None:
        """Approach (``start @ clearance``, joint move from ``seed``), start, end. When the
        joint move would leave the workspace box, through the flange pose ``via`` (a hub, e.g.
        above the ball), with the approach solved near it."""
        approach = start @ clearance
        qa = self.ik(approach, seed)
        qv = None
        if qa is None or not self.joint_path(seed, qa):
            qv = None if via is None else self.ik(via, seed)
            if qv is None or not self.joint_path(seed, qv):
                return None
            qa = self.ik(approach, qv)
            if qa is None or not self.joint_path(qv, qa):
                return None
        qs = self.linear(approach, start, qa)
        if qs is None:
            return None
        qe = self.linear(start, end, qs)
        if qe is None:
            return None
        return SweepReach(qa, qs, qe, qv)
