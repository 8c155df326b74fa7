"""Programs, safety and the robot's I/O of the simulated controller.

The layer of the controller's state (:class:`~.engine.Controller`) above the arm
(:class:`~.arm.Arm`): robot and safety modes, the program the script port or the dashboard
started, the dashboard's hooks (:class:`~.dashboard.DashboardTarget`), RTDE inputs and the
output registers, and the statements of a minimal URScript program (:mod:`.script`). The
``rtde_control`` script that ur_rtde uploads is emulated one layer up (:mod:`.rtde_control`).

A protective stop (fault request, command 31, or a linear move / speedl hitting a singularity or
the workspace boundary) decelerates the arm (``protective_stop_decel_*``), sets ``safety_mode`` 3
and bit 2 of ``safety_status_bits``, and stops the program; the dashboard's ``unlock protective
stop`` clears it after ``pstop_unlock_delay_s``.
"""

from __future__ import annotations

import logging
import re
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import kinematics, se3
from wristscan.drivers.sim.truth import TruthRing
from wristscan.drivers.sim.ur.arm import Arm, Job
from wristscan.drivers.sim.ur.config import ControllerConfig
from wristscan.drivers.sim.ur.motion import Motion, MotionFault, PathMotion, PolylinePath
from wristscan.drivers.sim.ur.script import ScriptOp, parse_script

__all__ = [
    "ROBOT_MODE_IDLE",
    "ROBOT_MODE_POWER_OFF",
    "ROBOT_MODE_RUNNING",
    "RUNTIME_PAUSED",
    "RUNTIME_PLAYING",
    "RUNTIME_STOPPED",
    "SAFETY_NORMAL",
    "SAFETY_PROTECTIVE_STOP",
    "ProgramHost",
    "int32",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

ROBOT_MODE_POWER_OFF, ROBOT_MODE_IDLE, ROBOT_MODE_RUNNING = 3, 5, 7
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP = 1, 3
RUNTIME_STOPPED, RUNTIME_PLAYING, RUNTIME_PAUSED = 1, 2, 4

_U32 = 0xFFFFFFFF


def int32(value: int) -> int:
    """``value`` as a signed 32-bit register value (wrapping)."""
    value &= _U32
    return value - (1 << 32) if value >= 1 << 31 else value


class ProgramHost(Arm):
    """Modes, the running program and the robot's I/O, over the arm."""

    def __init__(self, config: ControllerConfig, ring: TruthRing | None) -> None:
        super().__init__(config, ring)
        v = config.version
        self.version: tuple[int, int, int, int] = (int(v[0]), int(v[1]), int(v[2]), int(v[3]))
        self.serial_number = config.serial_number
        self.model_name = kinematics.get_model(config.model).name  # the nominal model's name
        self.robot_mode = ROBOT_MODE_RUNNING if config.powered_on else ROBOT_MODE_POWER_OFF
        self.safety_mode = SAFETY_NORMAL
        self.pstop_ns = 0
        self.runtime_state = RUNTIME_STOPPED
        self.program_name = ""
        self.program_kind: str | None = None
        self.program_text = ""
        self.loaded_program: str | None = None
        self.payload = (config.payload_kg, (0.0, 0.0, 0.0))
        self.digital_out = 0
        # a minimal URScript program
        self.custom_end_cycle = -1
        self.script_ops: list[ScriptOp] = []
        self.script_running = False
        self.script_sleep_until = 0
        # registers
        self.inputs: dict[str, Any] = {}
        self.input_owner: dict[str, object] = {}
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48

    # ------------------------------------------------------------------ hooks of rtde_control

    def _start_rtde_control(self, text: str) -> None:
        """Set up the emulated ``rtde_control`` script: :class:`~.rtde_control.RtdeControlHost`."""
        raise NotImplementedError

    def _rtde_control_step(self) -> None:
        """One cycle of the ``rtde_control`` script: :class:`~.rtde_control.RtdeControlHost`."""
        raise NotImplementedError

    def _clear_rtde_control(self) -> None:
        """Forget the commands in progress (the program ended): :mod:`.rtde_control`."""
        raise NotImplementedError

    # ------------------------------------------------------------------ safety and program

    def enter_protective_stop(self, reason: str) -> None:
        if self.safety_mode == SAFETY_PROTECTIVE_STOP:
            return
        log.warning("protective stop: %s", reason)
        self.safety_mode = SAFETY_PROTECTIVE_STOP
        self.pstop_ns = time.monotonic_ns()
        self._stop_motion(
            self.cfg.protective_stop_decel_rad_s2, self.cfg.protective_stop_decel_m_s2
        )
        self._end_program("protective stop")

    def clear_protective_stop(self) -> None:
        if self.safety_mode == SAFETY_PROTECTIVE_STOP:
            log.info("protective stop cleared")
        self.safety_mode = SAFETY_NORMAL

    def unlock_protective_stop(self) -> bool:
        if self.safety_mode != SAFETY_PROTECTIVE_STOP:
            return True
        if time.monotonic_ns() - self.pstop_ns < self.cfg.pstop_unlock_delay_s * 1e9:
            return False
        self.clear_protective_stop()
        return True

    def _script_error(self, message: str) -> None:
        log.error("script error, program stopped: %s", message)
        self._end_program("script error")

    def _end_program(self, reason: str) -> None:
        if self.runtime_state == RUNTIME_STOPPED and self.program_kind is None:
            return
        log.info("program %s stopped (%s)", self.program_name or "<unnamed>", reason)
        self.runtime_state = RUNTIME_STOPPED
        self.program_kind = None
        self._clear_rtde_control()
        for w in self.watches:
            w.active = False
        self.watches = []
        self.script_ops = []
        self.script_running = False
        self._stop_motion(
            self.cfg.program_stop_decel_rad_s2, self.cfg.program_stop_decel_m_s2, override=False
        )

    def start_program(self, text: str) -> None:
        first = text.lstrip().splitlines()[0] if text.strip() else ""
        m = re.match(r"\s*(?:def|sec)\s+(\w+)\s*\(", first)
        name = m.group(1) if m else "<unnamed>"
        self.program_text = text
        if self.robot_mode != ROBOT_MODE_RUNNING or self.safety_mode != SAFETY_NORMAL:
            log.warning(
                "program %s not started: robot mode %d, safety mode %d",
                name,
                self.robot_mode,
                self.safety_mode,
            )
            return
        if self.program_kind is not None:
            self._end_program("replaced by a new program")
        self.program_name = name
        self.runtime_state = RUNTIME_PLAYING
        if name == "rtde_control" or "rtde_cmd()" in text:
            self.program_kind = "rtde_control"
            self._start_rtde_control(text)
        else:
            self.program_kind = "custom"
            pattern = (
                r"write_output_integer_register\(\s*(\d+)\s*(?:\+\s*(\d+))?\s*,\s*(-?\d+)\s*\)"
            )
            for reg, plus, value in re.findall(pattern, text):
                idx = int(reg) + (int(plus) if plus else 0)
                if 0 <= idx < 48:
                    self.out_int[idx] = int32(int(value))
            try:
                ops = parse_script(text)
            except ValueError as e:
                self._script_error(f"program {name}: {e}")
                return
            if ops is not None:
                self.script_ops = ops
                self.script_running = True
                self.script_sleep_until = 0
                log.info("program %s runs %d motion statements", name, len(ops))
                return
            self.custom_end_cycle = self.cycle + 2
            log.info("program %s run (only its integer register writes are simulated)", name)

    # dashboard hooks
    def power_on(self) -> None:
        if self.robot_mode == ROBOT_MODE_POWER_OFF:
            self.robot_mode = ROBOT_MODE_IDLE

    def power_off(self) -> None:
        self._end_program("power off")
        self.motion = None
        self.queue = None
        self._finish_job()
        self.robot_mode = ROBOT_MODE_POWER_OFF

    def brake_release(self) -> None:
        if self.robot_mode in (ROBOT_MODE_IDLE, 4):
            self.robot_mode = ROBOT_MODE_RUNNING

    def play(self) -> bool:
        if self.loaded_program is None or self.robot_mode != ROBOT_MODE_RUNNING:
            return False
        if self.safety_mode != SAFETY_NORMAL:
            return False
        if self.program_kind is None:
            self.program_kind = "loaded"
            self.program_name = self.loaded_program
        self.runtime_state = RUNTIME_PLAYING
        return True

    def pause(self) -> bool:
        if self.runtime_state != RUNTIME_PLAYING:
            return False
        self.runtime_state = RUNTIME_PAUSED
        return True

    def stop_program(self) -> None:
        self._end_program("dashboard stop")

    # ------------------------------------------------------------------ I/O

    def apply_inputs(self, values: dict[str, Any]) -> None:
        self.inputs.update(values)
        if values.get("speed_slider_mask") == 1 and "speed_slider_fraction" in values:
            self.speed_slider = min(max(float(values["speed_slider_fraction"]), 0.0), 1.0)
        for mask_name, value_name, shift in (
            ("standard_digital_output_mask", "standard_digital_output", 0),
            ("configurable_digital_output_mask", "configurable_digital_output", 8),
            ("tool_digital_output_mask", "tool_digital_output", 16),
        ):
            if mask_name in values and value_name in values:
                mask = int(values[mask_name]) << shift
                self.digital_out = (self.digital_out & ~mask) | (
                    (int(values[value_name]) << shift) & mask
                )

    # ------------------------------------------------------------------ the running program

    def _script_step(self) -> None:
        """One cycle of the running program (a custom one here, ``rtde_control`` one layer up)."""
        if self.program_kind == "custom" and self.script_running:
            if self.runtime_state == RUNTIME_PLAYING:
                self._script_statements()
            return
        if self.program_kind == "custom" and self.cycle >= self.custom_end_cycle:
            self._end_program("finished")
            return
        if self.program_kind != "rtde_control" or self.runtime_state != RUNTIME_PLAYING:
            return
        self._rtde_control_step()

    def _script_statements(self) -> None:
        """Run the program's statements: start the next motion when the arm is idle."""
        if self._moving():
            return
        now = self.cycle * self.period_ns
        if now < self.script_sleep_until:
            return
        ops = self.script_ops
        while ops:
            op = ops.pop(0)
            if op.kind == "set_tcp":
                self._set_tcp(op.target)
                continue
            if op.kind == "sleep":
                self.script_sleep_until = now + round(op.t * 1e9)
                return
            try:
                if op.kind == "movej":
                    self._script_movej(op)
                else:
                    group = [op]
                    while group[-1].r > 0 and ops and ops[0].kind in ("movel", "movep"):
                        group.append(ops.pop(0))
                    self._script_linear(group)
            except (MotionFault, kinematics.Unreachable, ValueError) as e:
                self._script_error(f"line {op.line}: {op.kind}: {e}")
            return
        if self._caught_up():  # the program ends when the reported arm has stopped
            self._end_program("finished")

    def _script_movej(self, op: ScriptOp) -> None:
        a, v = op.a, op.v
        if op.is_pose:
            T = se3.pose_to_matrix(np.asarray(op.target, dtype=np.float64))

            def plan(q0: FloatArray) -> Motion:
                q = self._ik_tcp(T, q0)
                return self._plan_movej(q, v, a)(q0)

            self._schedule(Job("movej", plan), a)
        else:
            q = np.asarray(op.target, dtype=np.float64)
            self._schedule(Job("movej", self._plan_movej(q, v, a)), a)

    def _script_linear(self, group: list[ScriptOp]) -> None:
        v = min(group[0].v, self.cfg.max_tool_speed_m_s)
        a = group[0].a
        targets = [se3.pose_to_matrix(np.asarray(g.target, dtype=np.float64)) for g in group]
        tcp = self.tcp2flange.copy()
        if len(targets) == 1:
            job = Job(group[0].kind, self._plan_movel(targets[0], v, a))
        else:
            job = Job(
                group[0].kind,
                lambda q0: PathMotion(PolylinePath(self.model, tcp, q0, targets), v, a),
            )
        self._schedule(job, a)
