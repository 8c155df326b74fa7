"""The simulated arm on its tick grid: motion, queued moves, the truth ring.

Time and state
--------------
The controller starts at host time ``start_time_ns`` (``time.monotonic_ns()``); cycle ``k`` happens
at ``start_time_ns + k * period`` and reports ``timestamp = k * period`` (seconds, exact multiples
of 2 ms or 8 ms). Internally the arm is simulated on a 1 ms grid (``truth_rate_hz``): each tick
steps the current motion (:mod:`.motion`) and appends the TRUE joint positions to the
:class:`~wristscan.drivers.sim.truth.TruthRing` when one is given. ``q`` (``target_q``) are
the controller's own joint positions (its encoders); the true arm differs from them by the
repeatability model :class:`~.motion.RepeatabilityNoise` (``true_q = q + offset``; zero
offset with the default ``repeatability_m = 0``), and ``actual_q`` from ``q`` by the encoder
noise (``joint_noise_rad``). The controller computes with its factory calibration
(``ControllerConfig.reported_model``): ``actual_TCP_pose`` is ``FK_reported(actual_q) @ tcp`` as
a UR pose, and its moves are planned with it; the flange really is at ``FK_true(true_q)``
(``ControllerConfig.true_model``), which differs when the arm has kinematic errors.

Velocities and accelerations are finite differences over the last tick. The motion
is computed ``motion_lookahead_s`` (4 ms) ahead of the cycle being reported, and the truth ring
written that far ahead, so that a simulated sensor finds the true pose of an exposure in the ring
when it exposes; commands therefore take effect that much later, as a controller's own planning
delays them.

Stops decelerate along the current path with the given deceleration in the path's own units
(m/s^2 for a linear move, rad/s^2 of the leading joint for a joint move); stopl/stopj also end a
speedl/speedj (the real script would leave its speed thread running until speed_stop). A new
move while the arm still moves first decelerates it with the new move's acceleration.

:class:`Arm` is the lowest layer of the controller's state (:class:`~.engine.Controller`): the
layers above it run programs (:mod:`.program`), emulate the ``rtde_control`` script
(:mod:`.rtde_control`) and publish the cycle (:mod:`.engine`).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import kinematics, se3
from wristscan.drivers.sim.truth import TruthRing
from wristscan.drivers.sim.ur.config import ControllerConfig
from wristscan.drivers.sim.ur.fastkin import fast_kinematics, rotvec_of
from wristscan.drivers.sim.ur.motion import (
    CartesianPath,
    JointPath,
    Motion,
    MotionFault,
    PathMotion,
    RepeatabilityNoise,
    SpeedLMotion,
)

__all__ = ["Arm", "Job", "Watch"]

FloatArray = NDArray[np.float64]


class Watch:
    """Run ``action`` once, in the first cycle where ``done()`` holds."""

    __slots__ = ("action", "active", "done")

    def __init__(self, done: Callable[[], bool], action: Callable[[], None]) -> None:
        self.done, self.action, self.active = done, action, True


class Job:
    """A motion to start (now, or once the arm has stopped)."""

    def __init__(self, kind: str, plan: Callable[[FloatArray], Motion]) -> None:
        self.kind = kind
        self.plan = plan
        self.finished = False
        self.error: str | None = None
        self.params: tuple[Any, ...] = ()


class Arm:
    """The arm's joints (reported and true), its motion and the moves waiting to start."""

    def __init__(self, config: ControllerConfig, ring: TruthRing | None) -> None:
        self.cfg = config
        self.model = config.reported_model
        """What the controller believes (its factory calibration): its moves and reported poses."""
        self.kin = fast_kinematics(self.model)
        self.kin_true = fast_kinematics(config.true_model)
        """How the arm really is: the true flange pose is ``kin_true.forward(q_true)``."""
        self.ring = ring
        self.period_ns = config.period_ns
        self.tick_ns = config.tick_ns
        self.tcp2flange = se3.pose_to_matrix(np.asarray(config.tcp_offset, dtype=np.float64))
        self.q = np.asarray(config.initial_q, dtype=np.float64).copy()
        self.qd = np.zeros(6)
        self.qdd = np.zeros(6)
        self.q_true = self.q.copy()
        # The physics frontier, ``lookahead_ns`` ahead of the reported (present) state above;
        # the ticks in between wait in _history as (t_ns, q, qd, qdd, q_true).
        self.lookahead_ns = config.lookahead_ns
        self._pq, self._pqd, self._pqdd = self.q.copy(), np.zeros(6), np.zeros(6)
        self._history: deque[tuple[int, FloatArray, FloatArray, FloatArray, FloatArray]] = deque()
        self._moved_until_ns = 0
        """Frontier time from which the arm stands still (the first tick with zero velocity)."""
        self.noise = RepeatabilityNoise(
            self.model,
            self.tcp2flange,
            config.repeatability_m,
            config.noise_corr_rad,
            config.noise_seed,
        )
        self.encoder_noise = (
            np.random.default_rng(None if config.noise_seed is None else config.noise_seed + 1)
            if config.joint_noise_rad > 0
            else None
        )
        self.speed_slider = config.speed_slider
        # motion
        self.motion: Motion | None = None
        self.job: Job | None = None
        self.queue: Job | None = None
        self.watches: list[Watch] = []
        # time
        self.start_ns = 0
        self.t_tick_ns = 0
        self.cycle = 0
        # The reported TCP pose is cached for the joints in _pose_key (b"": recompute).
        self._tool_z = np.zeros(3)
        self._pose_key = b""
        self._pose_cache: tuple[float, ...] = (0.0,) * 6
        self._tcp_offset_pose = tuple(se3.matrix_to_pose(self.tcp2flange).tolist())

    # ------------------------------------------------------------------ hooks of the layers above

    def enter_protective_stop(self, reason: str) -> None:
        """Protective-stop the robot (a motion fault does): :class:`~.program.ProgramHost`."""
        raise NotImplementedError

    def _script_error(self, message: str) -> None:
        """A move could not be planned: :class:`~.program.ProgramHost` stops the program."""
        raise NotImplementedError

    # ------------------------------------------------------------------ clock and physics

    def begin(self, start_ns: int) -> None:
        self.start_ns = start_ns
        self.t_tick_ns = start_ns
        self._history.clear()
        self._append_truth([start_ns], self._pq[None], np.zeros((1, 6)), np.zeros((1, 6)))

    def _advance(self, t_end_ns: int) -> None:
        times: list[int] = []
        qs: list[FloatArray] = []
        qds: list[FloatArray] = []
        qdds: list[FloatArray] = []
        dt = self.tick_ns * 1e-9
        while self.t_tick_ns + self.tick_ns <= t_end_ns:
            self.t_tick_ns += self.tick_ns
            q = self._step_motion(dt * self.speed_slider)
            qd = (q - self._pq) / dt
            self._pqdd = (qd - self._pqd) / dt
            self._pqd = qd
            self._pq = q
            if qd.any():
                self._moved_until_ns = self.t_tick_ns + self.tick_ns
            times.append(self.t_tick_ns)
            qs.append(q)
            qds.append(self._pqd)
            qdds.append(self._pqdd)
        if qs:
            self._append_truth(times, np.array(qs), np.array(qds), np.array(qdds))

    def _caught_up(self) -> bool:
        """The reported state shows the arm standing still since its last motion: completions
        are signalled only then, as a real controller signals them when the arm has stopped."""
        return self.start_ns + self.cycle * self.period_ns >= self._moved_until_ns

    def _settle(self, t_ns: int) -> None:
        """Make the last computed tick at or before ``t_ns`` the reported state."""
        h = self._history
        last = None
        while h and h[0][0] <= t_ns:
            last = h.popleft()
        if last is not None:
            _, self.q, self.qd, self.qdd, self.q_true = last

    def _append_truth(
        self, times: Sequence[int], qs: FloatArray, qds: FloatArray, qdds: FloatArray
    ) -> None:
        q_true = qs + self.noise.joint_offsets(qs) if self.cfg.repeatability_m > 0 else qs
        for i, t in enumerate(times):
            self._history.append((int(t), qs[i], qds[i], qdds[i], q_true[i]))
        if self.ring is not None:
            for t, row in zip(times, q_true, strict=True):
                self.ring.append(int(t), row)

    def _step_motion(self, dtau: float) -> FloatArray:
        if self.motion is None and self.queue is not None:
            job, self.queue = self.queue, None
            self._start_job(job)
        m = self.motion
        if m is None:
            return self._pq
        try:
            q = m.step(dtau)
        except MotionFault as e:
            # The arm halts where it is; a real controller protective-stops on such faults.
            self.motion = None
            self._finish_job()
            self.enter_protective_stop(str(e))
            return self._pq
        if m.finished:
            self.motion = None
            self._finish_job()
        return q

    def _start_job(self, job: Job) -> None:
        try:
            motion = job.plan(self._pq.copy())
        except (MotionFault, kinematics.Unreachable, ValueError) as e:
            job.error = str(e)
            job.finished = True
            self._script_error(f"{job.kind}: {e}")
            return
        self.job = job
        if motion.finished:
            self._finish_job()
        else:
            self.motion = motion

    def _finish_job(self) -> None:
        if self.job is not None:
            self.job.finished = True
            self.job = None

    def _check_watches(self) -> None:
        if not self.watches:
            return
        pending = []
        for w in self.watches:
            if not w.active:
                continue
            if w.done() and self._caught_up():
                w.active = False
                w.action()
            else:
                pending.append(w)
        self.watches = pending

    def _watch(self, done: Callable[[], bool], action: Callable[[], None]) -> Watch:
        w = Watch(done, action)
        self.watches.append(w)
        return w

    def _decel(self, motion: Motion, joint_a: float, linear_a: float) -> float:
        linear = isinstance(motion, SpeedLMotion) or (
            isinstance(motion, PathMotion) and motion.path.unit == "m"
        )
        return linear_a if linear else joint_a

    def _stop_motion(self, joint_a: float, linear_a: float, override: bool = True) -> None:
        """Decelerate the current motion and drop any queued one."""
        if self.queue is not None:
            self.queue.finished = True
            self.queue = None
        m = self.motion
        if m is not None and (override or not m.stopping):
            m.request_stop(self._decel(m, joint_a, linear_a))
            if m.finished:
                self.motion = None
                self._finish_job()

    def _schedule(self, job: Job, preempt_decel: float) -> None:
        """Start ``job`` now, or after decelerating the current motion."""
        if self.motion is not None:
            if self.queue is not None:
                self.queue.finished = True
            self.motion.request_stop(preempt_decel)
            if self.motion.finished:
                self.motion = None
                self._finish_job()
                self._start_job(job)
            else:
                self.queue = job
        else:
            self._start_job(job)

    def _moving(self) -> bool:
        return self.motion is not None or self.queue is not None

    # ------------------------------------------------------------------ kinematics and planning

    def _set_tcp(self, pose: ArrayLike) -> None:
        """``set_tcp``: the TCP in the flange frame as a UR pose."""
        p = np.asarray(pose, dtype=np.float64)
        self.tcp2flange = se3.pose_to_matrix(p)
        self._tcp_offset_pose = tuple(p.tolist())
        self._pose_key = b""

    def _tcp_pose_matrix(self, q: FloatArray) -> FloatArray:
        return self.kin.forward(q) @ self.tcp2flange

    def _true_tcp_pose_matrix(self) -> FloatArray:
        return self.kin_true.forward(self.q_true) @ self.tcp2flange

    def _actual(
        self, q_t: tuple[float, ...], pose_t: tuple[float, ...]
    ) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """``(actual_q, actual_TCP_pose)`` of the present cycle, given the noise-free joints and
        TCP pose: the encoder noise (``joint_noise_rad``) on the joints, and the pose the
        controller computes from them."""
        if self.encoder_noise is None:
            return q_t, pose_t
        q = self.q + self.encoder_noise.normal(0.0, self.cfg.joint_noise_rad, 6)
        T = self._tcp_pose_matrix(q)
        return tuple(q.tolist()), (*T[:3, 3].tolist(), *rotvec_of(T[:3, :3]))

    def _ik_tcp(self, tcp2base: FloatArray, seed: FloatArray) -> FloatArray:
        flange2base = tcp2base @ se3.invert(self.tcp2flange)
        return kinematics.inverse_nearest(self.model, flange2base, seed)

    def _plan_movej(self, target: FloatArray, v: float, a: float) -> Callable[[FloatArray], Motion]:
        if np.any(np.abs(target) > kinematics.JOINT_LIMIT_RAD):
            raise MotionFault(f"movej target {np.round(target, 4).tolist()} beyond +-2 pi")
        v = min(v, self.cfg.max_joint_speed_rad_s)
        a = min(a, self.cfg.max_joint_accel_rad_s2)
        return lambda q0: PathMotion(JointPath(q0, target), v, a)

    def _plan_movel(
        self, tcp2base: FloatArray, v: float, a: float
    ) -> Callable[[FloatArray], Motion]:
        v = min(v, self.cfg.max_tool_speed_m_s)
        tcp = self.tcp2flange.copy()
        return lambda q0: PathMotion(CartesianPath(self.model, tcp, q0, tcp2base), v, a)

    def set_joint_positions(self, q: Sequence[float]) -> bool:
        if self._moving():
            return False
        self.q = np.asarray(q, dtype=np.float64).copy()
        self.qd = np.zeros(6)
        self._pq, self._pqd, self._pqdd = self.q.copy(), np.zeros(6), np.zeros(6)
        self._history.clear()
        self._pose_key = b""
        return True
