"""Motion generation of the simulated UR controller.

* :class:`Trapezoid` - time-optimal rest-to-rest profile along a path (accelerate, cruise,
  decelerate); :class:`Decel` - a stop from a moving state.
* :class:`JointPath` - ``movej``: straight line in joint space, path parameter in radians of the
  leading joint (UR's ``v``/``a`` of movej refer to the leading axis), all joints synchronised.
* :class:`CartesianPath` - ``movel``: straight line of the TCP with the orientation slerped; path
  parameter in metres of TCP travel (radians of rotation for a pure reorientation). Joints come
  from :func:`wristscan.calib.kinematics.inverse_nearest` at knots every 5 mm / 0.02 rad, joined by
  cubic Hermite segments whose end slopes come from the Jacobian, so the TCP stays on the line to
  well under a micrometre while the inverse kinematics runs only a few hundred times per second of
  motion. The last knot is the exact solution for the target.
* :class:`PolylinePath` - a run of blended ``movel``/``movep`` moves of a URScript program,
  approximated: the TCP passes through every waypoint on straight segments at the run's speed
  without stopping (no corner rounding, so it stays exactly on the polyline), one trapezoidal
  profile over the whole run.
* :class:`PathMotion`, :class:`SpeedJMotion`, :class:`SpeedLMotion` - what the controller steps
  every internal tick (``step(dtau)`` returns the joint positions); each can be asked to stop with a
  deceleration.
* :class:`RepeatabilityNoise` - the difference between the true and the reported robot.

Units: metres, radians, seconds. ``tcp2flange`` is the TCP offset (UR ``set_tcp``) as a 4x4
transform; poses ``*2base`` are 4x4 transforms in the robot base frame.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import kinematics, se3
from wristscan.drivers.sim.ur.fastkin import fast_kinematics, rotvec_of, tcp_jacobian

__all__ = [
    "CartesianPath",
    "Decel",
    "JointPath",
    "Motion",
    "MotionFault",
    "PathMotion",
    "PolylinePath",
    "RepeatabilityNoise",
    "SpeedJMotion",
    "SpeedLMotion",
    "Trapezoid",
]

FloatArray = NDArray[np.float64]

KNOT_SPACING_M = 0.005
"""Largest TCP travel between two inverse-kinematics knots of a linear move (m)."""
KNOT_SPACING_RAD = 0.02
"""Largest TCP rotation between two knots of a linear move (rad)."""
MAX_KNOT_JUMP_RAD = 0.35
"""A joint turning more than this between neighbouring knots means the line crosses a
singularity or the solution branch flipped: the controller protective-stops (as a real one does
when a linear move would need an infinite joint speed)."""


class MotionFault(RuntimeError):
    """The motion cannot continue (unreachable pose, singularity, joint limit)."""


class Trapezoid:
    """Rest-to-rest profile over ``length`` >= 0 with speed limit ``vmax`` and acceleration
    ``amax`` (path units per second, per second squared); triangular when ``vmax`` is not
    reached."""

    def __init__(self, length: float, vmax: float, amax: float) -> None:
        if vmax <= 0 or amax <= 0:
            raise ValueError(f"speed and acceleration must be positive, got {vmax}, {amax}")
        self.length = max(0.0, float(length))
        t_acc = vmax / amax
        if amax * t_acc * t_acc >= self.length:
            t_acc = math.sqrt(self.length / amax)
            vmax = amax * t_acc
        self.t_acc = t_acc
        self.v_peak = vmax
        self.amax = amax
        self.t_flat = (self.length - amax * t_acc * t_acc) / vmax if vmax > 0 else 0.0
        self.t_flat = max(0.0, self.t_flat)
        self.duration = 2.0 * t_acc + self.t_flat

    def at(self, tau: float) -> tuple[float, float]:
        """Path position and speed at profile time ``tau`` (s)."""
        a, ta, tf = self.amax, self.t_acc, self.t_flat
        if tau <= 0.0:
            return 0.0, 0.0
        if tau < ta:
            return 0.5 * a * tau * tau, a * tau
        if tau < ta + tf:
            return 0.5 * a * ta * ta + self.v_peak * (tau - ta), self.v_peak
        if tau < self.duration:
            r = self.duration - tau
            return self.length - 0.5 * a * r * r, a * r
        return self.length, 0.0


class Decel:
    """Stop from path position ``s0`` moving at ``v0`` >= 0, decelerating at ``decel``; never
    passes ``s_max`` (the end of the path)."""

    def __init__(self, s0: float, v0: float, decel: float, s_max: float) -> None:
        if decel <= 0:
            raise ValueError(f"deceleration must be positive, got {decel}")
        self.s0, self.v0, self.decel, self.s_max = s0, max(0.0, v0), decel, s_max
        self.duration = self.v0 / decel

    def at(self, tau: float) -> tuple[float, float]:
        t = min(max(tau, 0.0), self.duration)
        s = self.s0 + self.v0 * t - 0.5 * self.decel * t * t
        v = self.v0 - self.decel * t
        if s >= self.s_max:
            return self.s_max, 0.0
        return s, v


class JointPath:
    """``movej`` path: joints move on a straight line in joint space."""

    unit = "rad"

    def __init__(self, q_start: ArrayLike, q_end: ArrayLike) -> None:
        self.q0 = np.asarray(q_start, dtype=np.float64).copy()
        self.q1 = np.asarray(q_end, dtype=np.float64).copy()
        self.length = float(np.max(np.abs(self.q1 - self.q0)))

    def q_at(self, s: float) -> FloatArray:
        if self.length <= 0.0 or s >= self.length:
            return self.q1.copy()
        return np.asarray(self.q0 + (self.q1 - self.q0) * (s / self.length), dtype=np.float64)


class CartesianPath:
    """``movel`` path from the current joints to a TCP pose (see the module docstring)."""

    def __init__(
        self,
        model: kinematics.DHParams,
        tcp2flange: FloatArray,
        q_start: ArrayLike,
        tcp2base_end: FloatArray,
    ) -> None:
        self.model = model
        self.tcp2flange = np.asarray(tcp2flange, dtype=np.float64)
        self._flange2tcp = se3.invert(self.tcp2flange)
        q0 = np.asarray(q_start, dtype=np.float64).copy()
        self.T0 = kinematics.forward(model, q0) @ self.tcp2flange
        self.T1 = np.asarray(tcp2base_end, dtype=np.float64)
        dp = self.T1[:3, 3] - self.T0[:3, 3]
        rv = se3.matrix_to_rotvec(self.T0[:3, :3].T @ self.T1[:3, :3])
        dist, angle = float(np.linalg.norm(dp)), float(np.linalg.norm(rv))
        if dist > 1e-7:
            self.length, self.unit = dist, "m"
        else:
            self.length, self.unit = angle, "rad"
        self.n = max(1, math.ceil(dist / KNOT_SPACING_M), math.ceil(angle / KNOT_SPACING_RAD))
        # TCP twist per unit of the normalised parameter u in [0, 1]: slerp from R0 about rv
        # turns at the constant base-frame rate R0 @ rv.
        self._twist_u = np.concatenate([dp, self.T0[:3, :3] @ rv])
        # Fail before moving when the target itself is out of reach.
        if kinematics.inverse(model, self._flange(1.0)).shape[0] == 0:
            raise MotionFault(f"movel target {np.round(self.T1[:3, 3], 4).tolist()} m unreachable")
        self._q: list[FloatArray] = [q0]
        self._dq: list[FloatArray | None] = [self._slope(q0)]

    def _flange(self, u: float) -> FloatArray:
        return np.asarray(se3.interpolate(self.T0, self.T1, u) @ self._flange2tcp)

    def _slope(self, q: FloatArray) -> FloatArray | None:
        """dq/du at ``q`` from the Jacobian, or None near a singularity."""
        J, _ = fast_kinematics(self.model).tcp_jacobian(q, self.tcp2flange)
        if np.linalg.cond(J) > 1e7:
            return None
        return np.asarray(np.linalg.solve(J, self._twist_u), dtype=np.float64)

    def _ensure(self, k: int) -> None:
        while len(self._q) <= k:
            i = len(self._q)
            prev = self._q[-1]
            try:
                q = kinematics.inverse_nearest(self.model, self._flange(i / self.n), prev)
            except kinematics.Unreachable as e:
                raise MotionFault(f"movel leaves the workspace: {e}") from e
            if float(np.max(np.abs(q - prev))) > MAX_KNOT_JUMP_RAD:
                raise MotionFault("movel passes through a singularity")
            self._q.append(q)
            self._dq.append(self._slope(q))

    @property
    def q_end(self) -> FloatArray:
        self._ensure(self.n)
        return self._q[self.n].copy()

    def q_at(self, s: float) -> FloatArray:
        u = 1.0 if self.length <= 0.0 else min(max(s / self.length, 0.0), 1.0)
        k = min(int(u * self.n), self.n - 1)
        self._ensure(k + 1)
        q0, q1 = self._q[k], self._q[k + 1]
        if u >= 1.0:
            return q1.copy()
        h = 1.0 / self.n
        t = (u - k * h) / h
        chord = (q1 - q0) / h
        m0 = self._dq[k]
        m1 = self._dq[k + 1]
        m0a = chord if m0 is None else m0
        m1a = chord if m1 is None else m1
        t2, t3 = t * t, t * t * t
        return np.asarray(
            (2 * t3 - 3 * t2 + 1) * q0
            + (t3 - 2 * t2 + t) * h * m0a
            + (-2 * t3 + 3 * t2) * q1
            + (t3 - t2) * h * m1a,
            dtype=np.float64,
        )


ROTATION_LEVER_M = 0.1
"""A pure reorientation within a :class:`PolylinePath` counts as this many metres per radian of
path (so that it takes time at the run's speed)."""


class PolylinePath:
    """Linear moves through ``targets`` (TCP poses, base frame) one after the other, as one path
    (see the module docstring). Path parameter: metres of TCP travel (a pure reorientation counts
    :data:`ROTATION_LEVER_M` per radian). The linear segments are built when the motion reaches
    them, each from the joints where the previous one ended."""

    unit = "m"

    def __init__(
        self,
        model: kinematics.DHParams,
        tcp2flange: FloatArray,
        q_start: ArrayLike,
        targets: list[FloatArray],
    ) -> None:
        if not targets:
            raise ValueError("a polyline needs at least one target")
        self.model = model
        self.tcp2flange = np.asarray(tcp2flange, dtype=np.float64)
        self.q0 = np.asarray(q_start, dtype=np.float64).copy()
        T = [kinematics.forward(model, self.q0) @ self.tcp2flange]
        lengths: list[float] = []
        for Ti in targets:
            Ti = np.asarray(Ti, dtype=np.float64)
            dist = float(np.linalg.norm(Ti[:3, 3] - T[-1][:3, 3]))
            angle = float(se3.rotation_angle(T[-1][:3, :3].T @ Ti[:3, :3]))
            L = dist if dist > 1e-7 else angle * ROTATION_LEVER_M
            if L <= 1e-9:
                continue  # a repeated waypoint
            T.append(Ti)
            lengths.append(L)
        self.targets = T[1:]
        self.seg_lengths = np.asarray(lengths, dtype=np.float64)
        self.cum = np.concatenate([[0.0], np.cumsum(self.seg_lengths)])
        self.length = float(self.cum[-1])
        # Fail before moving when the last target is out of reach.
        if (
            self.targets
            and kinematics.inverse(model, self.targets[-1] @ se3.invert(self.tcp2flange)).shape[0]
            == 0
        ):
            raise MotionFault(
                f"movel target {np.round(self.targets[-1][:3, 3], 4).tolist()} m unreachable"
            )
        self._segs: list[CartesianPath] = []

    def _segment(self, i: int) -> CartesianPath:
        while len(self._segs) <= i:
            j = len(self._segs)
            q = self.q0 if j == 0 else self._segs[-1].q_end
            self._segs.append(CartesianPath(self.model, self.tcp2flange, q, self.targets[j]))
        return self._segs[i]

    @property
    def q_end(self) -> FloatArray:
        if not self.targets:
            return self.q0.copy()
        return self._segment(len(self.targets) - 1).q_end

    def q_at(self, s: float) -> FloatArray:
        if not self.targets:
            return self.q0.copy()
        if s >= self.length:
            return self.q_end
        i = int(np.searchsorted(self.cum, max(s, 0.0), side="right")) - 1
        i = min(max(i, 0), len(self.targets) - 1)
        seg = self._segment(i)
        frac = (max(s, 0.0) - float(self.cum[i])) / float(self.seg_lengths[i])
        return seg.q_at(frac * seg.length)


class Motion:
    """Something the controller steps every internal tick."""

    finished: bool = False

    def step(self, dtau: float) -> FloatArray:  # pragma: no cover - interface
        raise NotImplementedError

    def request_stop(self, decel: float) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    @property
    def stopping(self) -> bool:
        return False


class PathMotion(Motion):
    """A path followed with a trapezoidal profile; a stop decelerates along the same path."""

    def __init__(
        self, path: JointPath | CartesianPath | PolylinePath, speed: float, accel: float
    ) -> None:
        self.path = path
        self.profile: Trapezoid | Decel = Trapezoid(path.length, speed, accel)
        self.tau = 0.0
        self._stopping = False
        self.finished = self.profile.duration <= 0.0
        self.s, self.v = 0.0, 0.0

    @property
    def stopping(self) -> bool:
        return self._stopping

    def step(self, dtau: float) -> FloatArray:
        self.tau += dtau
        self.s, self.v = self.profile.at(self.tau)
        if self.tau >= self.profile.duration:
            self.finished = True
            if not self._stopping:
                self.s, self.v = self.path.length, 0.0
        return self.path.q_at(self.s)

    def request_stop(self, decel: float) -> None:
        if self.finished:
            return
        self.profile = Decel(self.s, self.v, decel, self.path.length)
        self.tau = 0.0
        self._stopping = True
        self.finished = self.profile.duration <= 0.0


def _approach(current: FloatArray, target: FloatArray, max_change: float) -> FloatArray:
    """Move a vector towards ``target`` by at most ``max_change`` (Euclidean)."""
    d = target - current
    n = float(np.linalg.norm(d))
    if n <= max_change:
        return target.copy()
    return np.asarray(current + d * (max_change / n), dtype=np.float64)


class SpeedJMotion(Motion):
    """``speedj``: joint velocities ramp towards a target at ``accel`` (rad/s^2, norm)."""

    def __init__(self, q: ArrayLike, qd_target: ArrayLike, accel: float, max_speed: float) -> None:
        self.q = np.asarray(q, dtype=np.float64).copy()
        self.qd = np.zeros(6)
        self.max_speed = max_speed
        self.update(qd_target, accel)
        self._stopping = False

    def update(self, qd_target: ArrayLike, accel: float) -> None:
        tgt = np.asarray(qd_target, dtype=np.float64)
        self.target = np.clip(tgt, -self.max_speed, self.max_speed)
        self.accel = max(float(accel), 1e-9)

    @property
    def stopping(self) -> bool:
        return self._stopping

    def step(self, dtau: float) -> FloatArray:
        self.qd = _approach(self.qd, self.target, self.accel * dtau)
        q = self.q + self.qd * dtau
        if np.any(np.abs(q) > kinematics.JOINT_LIMIT_RAD):
            raise MotionFault("speedj drives a joint past its limit")
        self.q = q
        if self._stopping and not np.any(self.qd):
            self.finished = True
        return self.q.copy()

    def request_stop(self, decel: float) -> None:
        self.target = np.zeros(6)
        self.accel = max(float(decel), 1e-9)
        self._stopping = True
        if not np.any(self.qd):
            self.finished = True


class SpeedLMotion(Motion):
    """``speedl``: the TCP twist ``[v (m/s), omega (rad/s)]`` (base frame) ramps towards a
    target at ``accel`` (m/s^2 for the linear part, rad/s^2 for the angular part, as UR uses the
    same value for both). The commanded TCP pose is integrated exactly and the joints follow it by
    one Newton step through the TCP Jacobian per tick, so the TCP does not drift off the
    commanded motion."""

    def __init__(
        self,
        model: kinematics.DHParams,
        tcp2flange: FloatArray,
        q: ArrayLike,
        xd_target: ArrayLike,
        accel: float,
        max_joint_speed: float,
    ) -> None:
        self.kin = fast_kinematics(model)
        self.tcp2flange = tcp2flange
        self.q = np.asarray(q, dtype=np.float64).copy()
        self.T_cmd = self.kin.forward(self.q) @ tcp2flange
        self.xd = np.zeros(6)
        self.max_joint_speed = max_joint_speed
        self.update(xd_target, accel)
        self._stopping = False

    def update(self, xd_target: ArrayLike, accel: float) -> None:
        self.target = np.asarray(xd_target, dtype=np.float64).copy()
        self.accel = max(float(accel), 1e-9)

    @property
    def stopping(self) -> bool:
        return self._stopping

    def step(self, dtau: float) -> FloatArray:
        dv = self.accel * dtau
        self.xd = np.concatenate(
            [
                _approach(self.xd[:3], self.target[:3], dv),
                _approach(self.xd[3:], self.target[3:], dv),
            ]
        )
        if not np.any(self.xd):
            if self._stopping:
                self.finished = True
            return self.q.copy()
        T = self.T_cmd.copy()
        T[:3, 3] += self.xd[:3] * dtau
        T[:3, :3] = se3.rotvec_to_matrix(self.xd[3:] * dtau) @ T[:3, :3]
        J, T_now = self.kin.tcp_jacobian(self.q, self.tcp2flange)
        err = np.concatenate([T[:3, 3] - T_now[:3, 3], rotvec_of(T[:3, :3] @ T_now[:3, :3].T)])
        try:
            dq = np.linalg.solve(J, err)
        except np.linalg.LinAlgError as e:
            raise MotionFault("speedl reached a singularity") from e
        if float(np.max(np.abs(dq))) > 1.5 * self.max_joint_speed * dtau:
            raise MotionFault("speedl needs a joint speed above the limit (near a singularity)")
        q = self.q + dq
        if np.any(np.abs(q) > kinematics.JOINT_LIMIT_RAD):
            raise MotionFault("speedl drives a joint past its limit")
        self.q = q
        self.T_cmd = T
        return self.q.copy()

    def request_stop(self, decel: float) -> None:
        self.target = np.zeros(6)
        self.accel = max(float(decel), 1e-9)
        self._stopping = True
        if not np.any(self.xd):
            self.finished = True


class RepeatabilityNoise:
    """How far the true robot is from the one the controller reports.

    The true TCP position differs from the reported one by a 3-D offset following an
    Ornstein-Uhlenbeck process whose "time" is joint travel (sum of ``|dq|`` over the joints, rad):
    the offset stays put while the robot stands still and decorrelates over ``corr_rad`` of
    motion, so returning to a pose lands within the repeatability but not on the same spot. Each
    axis has standard deviation ``sigma_m / sqrt(3)``, making ``sigma_m`` the RMS length of the
    offset. The offset maps to joint offsets through the damped pseudo-inverse of the TCP's
    translational Jacobian (smallest joint change producing it); ``true_q = q + offset``.
    """

    def __init__(
        self,
        model: kinematics.DHParams,
        tcp2flange: FloatArray,
        sigma_m: float,
        corr_rad: float = 0.5,
        seed: int | None = None,
    ) -> None:
        if sigma_m < 0 or corr_rad <= 0:
            raise ValueError("repeatability must be >= 0 and its correlation length > 0")
        self.model = model
        self.tcp2flange = tcp2flange
        self.sigma_axis = sigma_m / math.sqrt(3.0)
        self.corr_rad = corr_rad
        self._rng = np.random.default_rng(seed)
        self.offset_m = self._rng.normal(0.0, self.sigma_axis, 3)
        self._q_last: FloatArray | None = None
        self._dq_last: FloatArray | None = None

    def joint_offsets(self, q: ArrayLike) -> FloatArray:
        """Joint offsets ``(N, 6)`` (rad) for consecutive reported samples ``q`` ``(N, 6)``."""
        qa = np.atleast_2d(np.asarray(q, dtype=np.float64))
        n = qa.shape[0]
        if self.sigma_axis == 0.0:
            return np.zeros_like(qa)
        prev = qa[:1] if self._q_last is None else self._q_last[None]
        travel = np.sum(np.abs(np.diff(np.vstack([prev, qa]), axis=0)), axis=1)
        if self._dq_last is not None and not np.any(travel):
            self._q_last = qa[-1].copy()
            return np.broadcast_to(self._dq_last, qa.shape).copy()
        # Exact OU discretisation; sequential by nature (each offset depends on the previous).
        decay = np.exp(-travel / self.corr_rad)
        kicks = (
            self._rng.normal(0.0, 1.0, (n, 3))
            * (self.sigma_axis * np.sqrt(1.0 - decay * decay))[:, None]
        )
        x = np.empty((n, 3))
        cur = self.offset_m
        for i in range(n):
            cur = decay[i] * cur + kicks[i]
            x[i] = cur
        self.offset_m = cur
        if n <= 32:  # the controller's per-cycle batches: scalar kinematics is faster
            kin = fast_kinematics(self.model)
            Jp = np.stack([kin.tcp_jacobian(row, self.tcp2flange)[0][:3] for row in qa])
        else:
            Jp = tcp_jacobian(self.model, qa, self.tcp2flange)[:, :3, :]  # (N, 3, 6)
        lam2 = 1e-6  # damping (m^2): bounded joint offsets even at a singularity
        A = Jp @ np.swapaxes(Jp, -1, -2) + lam2 * np.eye(3)
        y = np.linalg.solve(A, x[..., None])
        dq = (np.swapaxes(Jp, -1, -2) @ y)[..., 0]
        self._q_last = qa[-1].copy()
        self._dq_last = dq[-1].copy()
        return np.asarray(dq, dtype=np.float64)
