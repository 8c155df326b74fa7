"""The ``rtde_control`` script of ur_rtde, emulated natively by the simulated controller.

Emulated ``rtde_control`` script (ur_rtde 1.6, ``scripts/rtde_control.script``)
------------------------------------------------------------------------------
Every cycle, like the script's main loop: ``output_int_register_0`` = 1 (ready) while
``input_int_register_0`` is 0; a new command runs once, and on completion the register becomes 2
(done) until the client writes 0 again. Real-time commands (speedj 9, speedl 10, ...) run every
cycle and leave the register at 1. Asynchronous moves (``input_int_register_1`` = 1) report in
``output_int_register_2`` with the script's layout (bits 24-30 operation id, 16-22 write count,
bit 15 running, bits 0-14 progress). The register offset 24 of ``FLAG_UPPER_RANGE_REGISTERS`` is
read from the uploaded script. Supported: movej 1, movej_ik 2, movel 3, movel_fk 4, speedj 9,
speedl 10, speed_stop 15, servo_stop 16, set_payload 17, set_tcp 29, get_inverse_kin 30/46,
protective_stop 31, stopl 33, stopj 34, within-safety-limits 36/37, pose_trans 39,
get_tcp_offset 40, get_forward_kin 43/44, is_steady 47, get_actual_tool_flange_pose 58,
ik-has-solution 60/61, stop script 255; watchdog, payload, teach and force-mode settings are
accepted and ignored. Any other command is a script error: the program stops, so the client's
call fails instead of pretending to succeed.

:class:`RtdeControlHost` is the layer of the controller's state (:class:`~.engine.Controller`)
that does it, over the programs (:class:`~.program.ProgramHost`) and the arm
(:class:`~.arm.Arm`).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import kinematics, se3
from wristscan.drivers.sim.truth import TruthRing
from wristscan.drivers.sim.ur.arm import Job, Watch
from wristscan.drivers.sim.ur.config import ControllerConfig
from wristscan.drivers.sim.ur.motion import Motion, MotionFault, SpeedJMotion, SpeedLMotion
from wristscan.drivers.sim.ur.program import ProgramHost, int32

__all__ = ["IGNORED_COMMANDS", "REALTIME_COMMANDS", "RtdeControlHost"]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

# Commands the script processes every cycle without a done handshake.
REALTIME_COMMANDS = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
# Accepted without effect on the simulated arm (settings with no physical model here; 66-71 are
# placeholders in the script itself).
IGNORED_COMMANDS = frozenset({7, 8, 18, 19, 20, 21, 35, 59, 62, 63, 64, 66, 67, 68, 69, 70, 71, 99})
_MOVE_COMMANDS = frozenset({1, 2, 3, 4})
"""movej, movej_ik, movel, movel_fk: inputs target (doubles 0-5), speed (6), acceleration (7)."""
_QUERY_COMMANDS = frozenset({30, 36, 37, 39, 40, 43, 44, 46, 47, 58, 60, 61})
"""Kinematics and state queries: their answer goes to the output registers."""


class RtdeControlHost(ProgramHost):
    """The command-register state machine of the ``rtde_control`` script, over the programs."""

    def __init__(self, config: ControllerConfig, ring: TruthRing | None) -> None:
        super().__init__(config, ring)
        self.executing = False
        self.busy: Callable[[], bool] | None = None
        self.reg_off_int = 0
        self.reg_off_float = 0
        self.async_wr_count = 0
        self.async_op_id = 0
        self.async_watch: Watch | None = None
        self.stop_watch: Watch | None = None

    def _start_rtde_control(self, text: str) -> None:
        # ur_rtde injects the offset right after the placeholder comment, so the number may
        # start the next line: "reg_offset_int = # int register offset\n24    global ...".
        mi = re.search(r"reg_offset_int\s*=\s*(?:#[^\n]*\n)?\s*(\d+)", text)
        mf = re.search(r"reg_offset_float\s*=\s*(?:#[^\n]*\n)?\s*(\d+)", text)
        self.reg_off_int = int(mi.group(1)) if mi else 0
        self.reg_off_float = int(mf.group(1)) if mf else 0
        self.async_wr_count = 0
        self.async_op_id = 0
        self.executing = False
        self.busy = None
        self._write_async(-1)
        self._write_int(0, 1)
        log.info("rtde_control program started (register offset %d)", self.reg_off_int)

    def _clear_rtde_control(self) -> None:
        self.executing = False
        self.busy = None
        self.async_watch = self.stop_watch = None

    # ------------------------------------------------------------------ registers

    def _in_int(self, i: int) -> int:
        return int(self.inputs.get(f"input_int_register_{self.reg_off_int + i}", 0))

    def _in_double(self, i: int) -> float:
        return float(self.inputs.get(f"input_double_register_{self.reg_off_float + i}", 0.0))

    def _in_doubles(self, first: int, n: int = 6) -> FloatArray:
        return np.array([self._in_double(first + i) for i in range(n)])

    def _write_int(self, i: int, value: int) -> None:
        self.out_int[self.reg_off_int + i] = int32(value)

    def _write_doubles(self, first: int, values: ArrayLike) -> None:
        for i, v in enumerate(np.asarray(values, dtype=np.float64).tolist()):
            self.out_double[self.reg_off_float + first + i] = float(v)

    def _write_async(self, value: int) -> None:
        """``write_async_progress_register`` of the control script."""
        self.async_wr_count += 1
        if self.async_wr_count > 127:
            self.async_wr_count = 0
        if value == 0:
            self.async_op_id += 1
            if self.async_op_id > 127:
                self.async_op_id = 0
        reg = self.async_wr_count * 65536 + self.async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self._write_int(2, reg)

    # ------------------------------------------------------------------ the script's main loop

    def _rtde_control_step(self) -> None:
        """One turn of the script's main loop: run the command in ``input_int_register_0``."""
        if self.busy is not None:
            if not (self.busy() and self._caught_up()):
                return
            self.busy = None
            self._write_int(0, 2)
            return
        cmd = self._in_int(0)
        if cmd in REALTIME_COMMANDS:
            self._process(cmd)
            if self.program_kind == "rtde_control":
                self._write_int(0, 1)
            return
        if cmd == 0:
            self.executing = False
            self._write_int(0, 1)
            return
        if self.executing:
            return
        self.executing = True
        self._process(cmd)
        if self.program_kind == "rtde_control" and self.busy is None:
            self._write_int(0, 2)

    # ------------------------------------------------------------------ commands

    def _stop_async_move(self) -> None:
        w = self.async_watch
        if w is not None and w.active:
            w.active = False
            self._write_async(-1)
        self.async_watch = None

    def _cmd_move(self, kind: str, plan: Callable[[FloatArray], Motion], accel: float) -> None:
        is_async = self._in_int(1) == 1
        self._stop_async_move()
        job = Job(kind, plan)
        if is_async:
            self._write_async(0)
            self.async_watch = self._watch(lambda: job.finished, lambda: self._write_async(-1))
        self._schedule(job, accel)
        if job.error is not None:
            return
        if not is_async:
            self.busy = lambda: job.finished

    def _cmd_speed(self, kind: str, target: FloatArray, accel: float) -> None:
        m = self.motion
        if kind == "speedj" and isinstance(m, SpeedJMotion) and not m.stopping:
            m.update(target, accel)
            return
        if kind == "speedl" and isinstance(m, SpeedLMotion) and not m.stopping:
            m.update(target, accel)
            return
        if self.queue is not None and self.queue.kind == kind:
            self.queue.params = (target, accel)
            return
        job = Job(kind, lambda q0: self._plan_speed(job, q0))
        job.params = (target, accel)
        self._schedule(job, accel)

    def _plan_speed(self, job: Job, q0: FloatArray) -> Motion:
        target, accel = job.params
        if job.kind == "speedj":
            return SpeedJMotion(q0, target, accel, self.cfg.max_joint_speed_rad_s)
        return SpeedLMotion(
            self.model, self.tcp2flange.copy(), q0, target, accel, self.cfg.max_joint_speed_rad_s
        )

    def _cmd_stop(self, decel: float, is_async: bool) -> None:
        stop_move = True
        w = self.stop_watch
        if w is not None and w.active:
            w.active = False
            stop_move = False
            self._write_async(-1)
        self.stop_watch = None
        if stop_move:
            self._stop_async_move()
        if decel <= 0:
            decel = self.cfg.program_stop_decel_rad_s2
        self._stop_motion(decel, decel)
        m = self.motion

        def stopped() -> bool:
            return self.motion is None or self.motion is not m

        if is_async:
            self._write_async(0)
            self.stop_watch = self._watch(stopped, lambda: self._write_async(-1))
        else:
            self.busy = stopped

    def _cmd_speed_stop(self, decel: float) -> None:
        m = self.motion
        if isinstance(m, SpeedJMotion | SpeedLMotion):
            m.request_stop(decel if decel > 0 else 10.0)
            if m.finished:
                self.motion = None
                self._finish_job()
            else:
                self.busy = lambda: self.motion is not m
        if self.queue is not None and self.queue.kind in ("speedj", "speedl"):
            self.queue.finished = True
            self.queue = None

    def _process(self, cmd: int) -> None:
        try:
            self._process_unchecked(cmd)
        except (MotionFault, kinematics.Unreachable, ValueError, np.linalg.LinAlgError) as e:
            self._script_error(f"command {cmd}: {e}")

    def _process_unchecked(self, cmd: int) -> None:
        if cmd in _MOVE_COMMANDS:
            self._cmd_move_to(cmd)
        elif cmd in _QUERY_COMMANDS:
            self._cmd_query(cmd)
        elif cmd == 9:
            self._cmd_speed("speedj", self._in_doubles(0), self._in_double(6))
        elif cmd == 10:
            self._cmd_speed("speedl", self._in_doubles(0), self._in_double(6))
        elif cmd in (15, 16):
            self._cmd_speed_stop(self._in_double(0))
        elif cmd in (17, 65):
            self.payload = (self._in_double(0), tuple(self._in_doubles(1, 3)))
        elif cmd == 29:
            self._set_tcp(self._in_doubles(0))
        elif cmd == 31:
            self.enter_protective_stop("requested by the program (protective_stop())")
        elif cmd in (33, 34):
            self._cmd_stop(self._in_double(0), self._in_int(1) == 1)
        elif cmd == 255:
            log.info("rtde_control: stop script received")
            self._end_program("stop script command")
        elif cmd in IGNORED_COMMANDS or cmd == 6:
            log.debug("rtde_control: command %d accepted without effect", cmd)
        else:
            self._script_error(f"command {cmd} is not simulated")

    def _cmd_move_to(self, cmd: int) -> None:
        """movej 1 (joints), movej_ik 2 (TCP pose), movel 3 (TCP pose), movel_fk 4 (joints)."""
        speed, accel = self._in_double(6), self._in_double(7)
        if cmd == 1:
            q = self._in_doubles(0)
            self._cmd_move("movej", self._plan_movej(q, speed, accel), accel)
        elif cmd == 2:
            q = self._ik_tcp(se3.pose_to_matrix(self._in_doubles(0)), self.q)
            self._cmd_move("movej", self._plan_movej(q, speed, accel), accel)
        else:
            if cmd == 3:
                T = se3.pose_to_matrix(self._in_doubles(0))
            else:
                T = self._tcp_pose_matrix(self._in_doubles(0))
            self._cmd_move("movel", self._plan_movel(T, speed, accel), accel)

    def _cmd_query(self, cmd: int) -> None:
        """Kinematics and state queries, answered in the output registers."""
        if cmd in (30, 46):
            T = se3.pose_to_matrix(self._in_doubles(0))
            seed = self._in_doubles(6) if cmd == 30 else self.q
            self._write_doubles(0, self._ik_tcp(T, seed))
        elif cmd in (36, 60, 61):
            T = se3.pose_to_matrix(self._in_doubles(0))
            ok = kinematics.inverse(self.model, T @ se3.invert(self.tcp2flange)).shape[0] > 0
            self._write_int(1, int(ok))
        elif cmd == 37:
            q = self._in_doubles(0)
            self._write_int(1, int(bool(np.all(np.abs(q) <= kinematics.JOINT_LIMIT_RAD))))
        elif cmd == 39:
            T = se3.pose_to_matrix(self._in_doubles(0)) @ se3.pose_to_matrix(self._in_doubles(6))
            self._write_doubles(0, se3.matrix_to_pose(T))
        elif cmd == 40:
            self._write_doubles(0, se3.matrix_to_pose(self.tcp2flange))
        elif cmd == 43:
            self._write_doubles(0, se3.matrix_to_pose(self._tcp_pose_matrix(self.q)))
        elif cmd == 44:
            T = kinematics.forward(self.model, self._in_doubles(0)) @ se3.pose_to_matrix(
                self._in_doubles(6)
            )
            self._write_doubles(0, se3.matrix_to_pose(T))
        elif cmd == 47:
            steady = not self._moving() and float(np.max(np.abs(self.qd))) < 1e-6
            self._write_int(1, int(steady))
        elif cmd == 58:
            self._write_doubles(0, se3.matrix_to_pose(kinematics.forward(self.model, self.q)))
