"""The simulated controller's state, whole: one cycle, and what it publishes.

:class:`Controller` stacks the layers of the controller's state (the arm :mod:`.arm`, programs
and I/O :mod:`.program`, the emulated ``rtde_control`` script :mod:`.rtde_control`) and adds the
cycle, the RTDE output variables and the faults and queries of the parent process. It lives in
the controller process's event loop (:mod:`.server`).

``actual_q`` and ``actual_TCP_pose`` carry the encoder noise (``joint_noise_rad``), the
``target_*`` values do not; ``actual_TCP_pose`` is what the controller computes with its factory
calibration (:attr:`~.config.ControllerConfig.reported_model`). Other outputs:
``actual_TCP_speed`` = TCP Jacobian x ``actual_qd``; ``actual_tool_accelerometer``
is gravity in tool coordinates; currents, forces, ``elbow_position`` and the like read zero.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from wristscan.calib import se3
from wristscan.drivers.sim.truth import TruthRing
from wristscan.drivers.sim.ur.config import ControllerConfig
from wristscan.drivers.sim.ur.fastkin import rotvec_of
from wristscan.drivers.sim.ur.program import (
    ROBOT_MODE_RUNNING,
    SAFETY_PROTECTIVE_STOP,
)
from wristscan.drivers.sim.ur.rtde_control import RtdeControlHost
from wristscan.drivers.ur import rtde_wire

__all__ = ["Controller", "RtdeClient"]

JOINT_RUNNING_MODE, JOINT_POWER_OFF_MODE, JOINT_IDLE_MODE = 253, 239, 255


class RtdeClient(Protocol):
    """What the controller needs of an RTDE client connection (:mod:`.rtde_server`)."""

    started: bool
    transport: asyncio.Transport | None

    def due(self, k: int) -> bool: ...
    def outputs_for(self, k: int, values: dict[str, Any], defaults: dict[str, Any]) -> bytes: ...
    def send_packets(self, data: bytes) -> None: ...
    def reply(self, ptype: int, payload: bytes) -> None: ...
    def close(self) -> None: ...


class Controller(RtdeControlHost):
    """State of the simulated controller; lives in the controller process's event loop."""

    def __init__(self, config: ControllerConfig, ring: TruthRing | None) -> None:
        super().__init__(config, ring)
        self._out_int_names = [f"output_int_register_{i}" for i in range(48)]
        self._out_double_names = [f"output_double_register_{i}" for i in range(48)]
        self.defaults = {n: rtde_wire.zero_value(t) for n, t in rtde_wire.VARIABLE_TYPES.items()}
        self.stall_until_ns = 0
        # connections
        self.rtde_conns: set[RtdeClient] = set()
        self.other_transports: set[asyncio.BaseTransport] = set()
        self.stopping = asyncio.Event()
        self.skipped_cycles = 0
        """Cycles not published because the controller ran late (what a client can never get)."""

    def run_cycle(
        self, k: int, publish: bool, before_send: Callable[[], None] | None = None
    ) -> None:
        """Run cycle ``k``; ``before_send`` is called between computing and sending it."""
        self.cycle = k
        t_k = self.start_ns + k * self.period_ns
        self._advance(t_k + self.lookahead_ns)
        self._settle(t_k)
        self._check_watches()
        self._script_step()
        self._check_watches()
        if publish:
            self._publish(k, before_send)
        else:
            self.skipped_cycles += 1

    # ------------------------------------------------------------------ output

    def values(self) -> dict[str, Any]:
        """Current output variables by name (missing names read as zero)."""
        q = self.q
        dt = self.period_ns * 1e-9
        key = q.tobytes()
        if key != self._pose_key:
            T = self._tcp_pose_matrix(q)
            self._pose_key = key
            self._pose_cache = (*T[:3, 3].tolist(), *rotvec_of(T[:3, :3]))
            self._tool_z = T[2, :3].copy()
        if np.any(self.qd):
            J, _ = self.kin.tcp_jacobian(q, self.tcp2flange)
            twist: tuple[float, ...] = tuple((J @ self.qd).tolist())
        else:
            twist = (0.0,) * 6
        pose_t = self._pose_cache
        q_t, qd_t = tuple(q.tolist()), tuple(self.qd.tolist())
        actual_q, actual_pose = self._actual(q_t, pose_t)
        powered = self.robot_mode >= 4
        pstop = self.safety_mode == SAFETY_PROTECTIVE_STOP
        joint_mode = (
            JOINT_RUNNING_MODE
            if self.robot_mode == ROBOT_MODE_RUNNING
            else JOINT_IDLE_MODE
            if powered
            else JOINT_POWER_OFF_MODE
        )
        accel_tool = self._tool_z * 9.82  # gravity reaction (0, 0, 9.82) in tool coordinates
        v: dict[str, Any] = {
            "timestamp": self.cycle * dt,
            "target_q": q_t,
            "actual_q": actual_q,
            "target_qd": qd_t,
            "actual_qd": qd_t,
            "target_qdd": tuple(self.qdd.tolist()),
            "actual_TCP_pose": actual_pose,
            "target_TCP_pose": pose_t,
            "actual_TCP_speed": twist,
            "target_TCP_speed": twist,
            "tcp_offset": self._tcp_offset_pose,
            "robot_mode": self.robot_mode,
            "joint_mode": (joint_mode,) * 6,
            "safety_mode": self.safety_mode,
            "safety_status": self.safety_mode,
            "runtime_state": self.runtime_state,
            "robot_status_bits": (1 if powered else 0) | (2 if self.runtime_state == 2 else 0),
            "safety_status_bits": (4 if pstop else 0) | (1 if self.safety_mode == 1 else 0),
            "speed_scaling": 0.0 if pstop else 1.0,
            "target_speed_fraction": self.speed_slider,
            "actual_tool_accelerometer": tuple(accel_tool.tolist()),
            "joint_temperatures": (35.0,) * 6,
            "actual_main_voltage": 48.0,
            "actual_robot_voltage": 48.0 if powered else 0.0,
            "actual_joint_voltage": (48.0,) * 6 if powered else (0.0,) * 6,
            "actual_robot_current": 0.5 if powered else 0.0,
            "actual_execution_time": 0.3,
            "target_execution_time": dt * 1e3,
            "actual_digital_output_bits": self.digital_out,
            "payload": self.payload[0],
            "payload_cog": self.payload[1],
            "target_gravity": (0.0, 0.0, -9.82),
            "control_step": self.cycle,
        }
        v.update(zip(self._out_int_names, self.out_int, strict=True))
        v.update(zip(self._out_double_names, self.out_double, strict=True))
        for name, value in self.inputs.items():
            v.setdefault(name, value)
        return v

    def _publish(self, k: int, before_send: Callable[[], None] | None = None) -> None:
        if time.monotonic_ns() < self.stall_until_ns:
            return
        due = [c for c in self.rtde_conns if c.started and c.due(k)]
        if not due:
            return
        values = self.values()
        packets = [(c, c.outputs_for(k, values, self.defaults)) for c in due]
        if before_send is not None:
            before_send()
        for c, data in packets:
            c.send_packets(data)

    # ------------------------------------------------------------------ faults and queries

    def send_text_message(self, text: str, source: str, level: int) -> int:
        """An RTDE text message ('M') to every started client, between data packages."""
        payload = rtde_wire.encode_text_message(text, source, level)
        conns = [c for c in self.rtde_conns if c.started and c.transport is not None]
        for c in conns:
            c.reply(rtde_wire.TEXT_MESSAGE, payload)
        return len(conns)

    def drop_connections(self) -> int:
        conns = list(self.rtde_conns)
        for c in conns:
            c.close()
        return len(conns)

    def state(self) -> dict[str, Any]:
        return {
            "timestamp": self.cycle * self.period_ns * 1e-9,
            "start_time_ns": self.start_ns,
            "q": self.q.tolist(),
            "q_true": self.q_true.tolist(),
            "qd": self.qd.tolist(),
            "tcp_pose": se3.matrix_to_pose(self._tcp_pose_matrix(self.q)).tolist(),
            "tcp_pose_true": se3.matrix_to_pose(self._true_tcp_pose_matrix()).tolist(),
            "tcp_offset": list(self._tcp_offset_pose),
            "moving": self._moving() or not self._caught_up(),
            "runtime_state": self.runtime_state,
            "robot_mode": self.robot_mode,
            "safety_mode": self.safety_mode,
            "program": self.program_name,
            "program_kind": self.program_kind,
            "rtde_clients": len(self.rtde_conns),
            "skipped_cycles": self.skipped_cycles,
            "speed_slider": self.speed_slider,
        }
