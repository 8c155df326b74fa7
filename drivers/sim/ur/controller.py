"""Simulated Universal Robots controller, run as a process of its own.

It serves, on one loopback address (any ``127.x.y.z``, so several run side by side):

* RTDE on TCP 30004 - protocol version 2, per-connection recipes (output recipe ids from 1, input
  recipe ids 1, 2, 3 ... as ur_rtde expects), output at the requested frequency on the controller
  cycle: 500 Hz (2 ms) for an e-Series version (major > 3), 125 Hz (8 ms) for CB3;
* the dashboard server on TCP 29999 (:mod:`.dashboard`);
* the script port on TCP 30003: a program ending in a top-level ``end`` line starts; the
  ``rtde_control`` program that ur_rtde's ``RTDEControlInterface`` uploads is emulated natively
  (its command-register state machine, below); other programs have their
  ``write_output_integer_register`` calls applied and, when they hold motion statements, run a
  minimal URScript subset (below).

So the real ``rtde_receive.RTDEReceiveInterface`` and ``rtde_control.RTDEControlInterface`` work
against it unmodified.

Time and state
--------------
The controller starts at host time ``start_time_ns`` (``time.monotonic_ns()``); cycle ``k`` happens
at ``start_time_ns + k * period`` and reports ``timestamp = k * period`` (seconds, exact multiples
of 2 ms or 8 ms). Internally the arm is simulated on a 1 ms grid (``truth_rate_hz``): each tick
steps the current motion (:mod:`.ur_motion`) and appends the TRUE joint positions to the
:class:`~wristscan.drivers.sim.truth.TruthRing` when one is given. ``actual_q`` / ``target_q`` are
the controller's own joint positions (its encoders); the true arm differs from them by the
repeatability model :class:`~.ur_motion.RepeatabilityNoise` (``true_q = actual_q + offset``; zero
offset with the default ``repeatability_m = 0``). ``actual_TCP_pose`` is ``FK(actual_q) @ tcp``
as a UR pose. Velocities and accelerations are finite differences over the last tick. The motion
is computed ``motion_lookahead_s`` (4 ms) ahead of the cycle being reported, and the truth ring
written that far ahead, so that a simulated sensor finds the true pose of an exposure in the ring
when it exposes; commands therefore take effect that much later, as a controller's own planning
delays them.

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

Stops decelerate along the current path with the given deceleration in the path's own units
(m/s^2 for a linear move, rad/s^2 of the leading joint for a joint move); stopl/stopj also end a
speedl/speedj (the real script would leave its speed thread running until speed_stop). A new
move while the arm still moves first decelerates it with the new move's acceleration.

A protective stop (fault request, command 31, or a linear move / speedl hitting a singularity or
the workspace boundary) decelerates the arm (``protective_stop_decel_*``), sets ``safety_mode`` 3
and bit 2 of ``safety_status_bits``, and stops the program; the dashboard's ``unlock protective
stop`` clears it after ``pstop_unlock_delay_s``.

Faults on request (from the parent, :class:`SimulatedController`): drop every RTDE connection
(clients see end-of-file), stall the RTDE output for a while (ur_rtde clients give up after 2.5 s
without data), protective stop, an RTDE text message ('M') to the streaming clients. Note:
after a dropped connection ur_rtde 1.6.5's ``RTDEControlInterface`` reconnects over and over (its
receive thread never clears its reconnect flag), re-uploading the script each time;
``RTDEReceiveInterface`` simply reports ``isConnected() == False`` until ``reconnect()``.

Minimal URScript programs
------------------------
A program sent to the script port that calls ``movel``, ``movep``, ``movej`` or ``set_tcp`` runs
those statements in order, one per line (literal arguments only: ``p[...]`` poses, ``[...]``
joint vectors, numbers, positional or ``a=``/``v=``/``t=``/``r=``): ``set_tcp(p[...])``,
``movej(q | p[...], a, v, t, r)`` (a pose target is solved for the joints nearest the current
ones), ``movel(p[...], a, v, t, r)``, ``movep(p[...], a, v, r)``, ``sleep(t)``. Consecutive
linear moves with a blend radius ``r > 0`` run as one :class:`~.ur_motion.PolylinePath` at the
first move's speed and acceleration: the blends are approximated by passing through each
waypoint without stopping (no corner rounding). Other statements (``textmsg``, ``popup``,
assignments, control flow) are skipped with a log line. The program ends after the last
statement; a protective stop or an unreachable target stops it as on a robot.
``state()`` reports the active TCP (``tcp_offset``) and the true TCP pose (``tcp_pose_true``,
from the true joints) for tests.

Other outputs: ``actual_TCP_speed`` = TCP Jacobian x ``actual_qd``; ``actual_tool_accelerometer``
is gravity in tool coordinates; currents, forces, ``elbow_position`` and the like read zero.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import multiprocessing as mp
import os
import random
import re
import socket
import struct
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import kinematics, se3
from wristscan.drivers.sim.truth import TruthRing
from wristscan.drivers.sim.ur import dashboard
from wristscan.drivers.sim.ur.motion import (
    CartesianPath,
    JointPath,
    Motion,
    MotionFault,
    PathMotion,
    PolylinePath,
    RepeatabilityNoise,
    SpeedJMotion,
    SpeedLMotion,
    fast_kinematics,
    rotvec_of,
)
from wristscan.drivers.ur import rtde_wire

__all__ = [
    "DASHBOARD_PORT",
    "PRIMARY_PORT",
    "RTDE_PORT",
    "SCRIPT_PORT",
    "ControllerConfig",
    "ScriptOp",
    "SimulatedController",
    "parse_script",
    "pick_free_loopback_host",
    "run_controller",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003
PRIMARY_PORT = 30001
CB3_MAJOR_VERSION = 3

ROBOT_MODE_POWER_OFF, ROBOT_MODE_IDLE, ROBOT_MODE_RUNNING = 3, 5, 7
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP = 1, 3
RUNTIME_STOPPED, RUNTIME_PLAYING, RUNTIME_PAUSED = 1, 2, 4
JOINT_RUNNING_MODE, JOINT_POWER_OFF_MODE, JOINT_IDLE_MODE = 253, 239, 255

# Commands the script processes every cycle without a done handshake.
REALTIME_COMMANDS = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
# Accepted without effect on the simulated arm (settings with no physical model here; 66-71 are
# placeholders in the script itself).
IGNORED_COMMANDS = frozenset({7, 8, 18, 19, 20, 21, 35, 59, 62, 63, 64, 66, 67, 68, 69, 70, 71, 99})

_U32 = 0xFFFFFFFF


def _int32(value: int) -> int:
    value &= _U32
    return value - (1 << 32) if value >= 1 << 31 else value


@dataclass(frozen=True)
class ControllerConfig:
    """Configuration of one simulated controller (SI units)."""

    host: str = "127.0.0.2"
    """Loopback address to listen on (ports 29999, 30003, 30004 are fixed, as on a robot)."""
    model: str | kinematics.DHParams = "UR5e"
    """Arm model: a key of :data:`wristscan.calib.kinematics.UR_MODELS`, or DH parameters (for
    example a calibrated arm), which the controller's own kinematics then uses."""
    version: tuple[int, int, int, int] = (5, 15, 0, 0)
    """Controller software version; major > 3 is e-Series (500 Hz), 3 is CB3 (125 Hz)."""
    serial_number: str = "20235500001"
    initial_q: tuple[float, ...] = (0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0)
    """Joint positions at start-up (rad)."""
    tcp_offset: tuple[float, ...] = (0.0,) * 6
    """TCP in the flange frame as a UR pose ``[x, y, z, rx, ry, rz]`` (m, rad); zero = flange."""
    max_joint_speed_rad_s: float = math.pi
    max_joint_accel_rad_s2: float = 40.0
    max_tool_speed_m_s: float = 3.0
    speed_slider: float = 1.0
    """Speed slider fraction (0..1]: scales the time of every motion."""
    repeatability_m: float = 0.0
    """RMS distance (m) between the true and the reported TCP position (UR5e spec: 3e-5)."""
    noise_corr_rad: float = 0.5
    """Joint travel (rad, summed over joints) over which the repeatability offset decorrelates."""
    noise_seed: int | None = None
    powered_on: bool = True
    """Start with power on and brakes released (robot mode RUNNING); else POWER_OFF."""
    pstop_unlock_delay_s: float = 5.0
    """Time after a protective stop before the dashboard may unlock it (5 s on a real robot)."""
    protective_stop_decel_rad_s2: float = 10.0
    protective_stop_decel_m_s2: float = 5.0
    program_stop_decel_rad_s2: float = 4.0
    program_stop_decel_m_s2: float = 2.0
    truth_rate_hz: float = 1000.0
    """Internal simulation rate and truth-ring sample rate (must divide into the cycle)."""
    motion_lookahead_s: float = 0.004
    """The arm's motion is computed (and written to the truth ring) this far ahead of the cycle
    being reported; commands take effect after it. Simulated sensors then find the true pose of
    each exposure in the ring when they expose instead of waiting up to a cycle for it, which
    would delay every profile they send (a real sensor waits for nothing)."""
    payload_kg: float = 0.0
    primary_interface: bool = False
    """Also serve the primary interface on TCP 30001 (:mod:`.primary`: version message and
    ROBOT_STATE with KinematicsInfo reporting ``model``'s DH parameters)."""
    log_level: str = "WARNING"
    """Logging level set up in the controller process."""

    def __post_init__(self) -> None:
        kinematics.get_model(self.model)  # raises for an unknown model
        if len(self.version) != 4:
            raise ValueError(f"version must have 4 numbers, got {self.version}")
        if len(self.initial_q) != 6 or len(self.tcp_offset) != 6:
            raise ValueError("initial_q and tcp_offset need 6 values each")
        if not 0.0 < self.speed_slider <= 1.0:
            raise ValueError(f"speed_slider must be in (0, 1], got {self.speed_slider}")
        if self.repeatability_m < 0:
            raise ValueError("repeatability_m must be >= 0")
        if not 0.0 <= self.motion_lookahead_s <= 0.1:
            raise ValueError("motion_lookahead_s must be in [0, 0.1]")
        socket.inet_aton(self.host)  # a dotted IPv4 address
        if self.period_ns % self.tick_ns != 0:
            raise ValueError(
                f"truth_rate_hz {self.truth_rate_hz} does not divide the {self.period_ns} ns cycle"
            )

    @property
    def e_series(self) -> bool:
        return self.version[0] > CB3_MAJOR_VERSION

    @property
    def frequency_hz(self) -> float:
        """Controller cycle rate: 500 Hz e-Series, 125 Hz CB3."""
        return 500.0 if self.e_series else 125.0

    @property
    def period_ns(self) -> int:
        return 2_000_000 if self.e_series else 8_000_000

    @property
    def tick_ns(self) -> int:
        return round(1e9 / self.truth_rate_hz)

    @property
    def lookahead_ns(self) -> int:
        """``motion_lookahead_s`` rounded up to whole ticks."""
        return math.ceil(self.motion_lookahead_s * 1e9 / self.tick_ns) * self.tick_ns


_MOTION_DEFAULTS = {
    "movel": {"a": 1.2, "v": 0.25, "t": 0.0, "r": 0.0},
    "movep": {"a": 1.2, "v": 0.25, "t": 0.0, "r": 0.0},
    "movej": {"a": 1.4, "v": 1.05, "t": 0.0, "r": 0.0},
}
_POSITIONAL = {"movel": "avtr", "movej": "avtr", "movep": "avr"}
_SCRIPT_STATEMENTS = frozenset({"movel", "movep", "movej", "set_tcp", "sleep"})
_CALL = re.compile(r"^\s*([A-Za-z_]\w*)\s*\((.*)\)\s*$")


@dataclass(frozen=True)
class ScriptOp:
    """One statement of a minimal URScript program (SI units)."""

    kind: str
    """``movel``, ``movep``, ``movej``, ``set_tcp`` or ``sleep``."""
    target: tuple[float, ...] = ()
    """Pose ``[x, y, z, rx, ry, rz]`` or joint vector (rad)."""
    is_pose: bool = False
    a: float = 0.0
    v: float = 0.0
    t: float = 0.0
    r: float = 0.0
    line: int = 0


def _split_args(text: str) -> list[str]:
    out: list[str] = []
    cur: list[str] = []
    depth = 0
    for ch in text:
        if ch in "[(":
            depth += 1
        elif ch in "])":
            depth -= 1
        if ch == "," and depth == 0:
            out.append("".join(cur).strip())
            cur = []
        else:
            cur.append(ch)
    if "".join(cur).strip():
        out.append("".join(cur).strip())
    return out


def _literal(text: str) -> tuple[tuple[float, ...], bool] | float:
    t = text.strip()
    is_pose = t.startswith("p[")
    if is_pose:
        t = t[1:]
    if t.startswith("[") and t.endswith("]"):
        return tuple(float(v) for v in t[1:-1].split(",")), is_pose
    return float(t)


def parse_script(text: str) -> list[ScriptOp] | None:
    """The motion statements of a URScript program, or None when it has none (see the module
    docstring). Raises ValueError for a motion statement it cannot read."""
    ops: list[ScriptOp] = []
    for no, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        m = _CALL.match(line)
        if m is None or m.group(1) not in _SCRIPT_STATEMENTS:
            if line and not re.match(r"(def|sec)\s+\w+\s*\(|end$", line):
                log.debug("script line %d not simulated: %s", no, line[:80])
            continue
        name, args = m.group(1), _split_args(m.group(2))
        try:
            if name == "sleep":
                ops.append(ScriptOp("sleep", t=float(args[0]), line=no))
                continue
            first = _literal(args[0])
            if not isinstance(first, tuple) or len(first[0]) != 6:
                raise ValueError("the target must be a pose p[...] or 6 joint values")
            target, is_pose = first
            if name == "set_tcp":
                if not is_pose:
                    raise ValueError("set_tcp needs a pose p[...]")
                ops.append(ScriptOp("set_tcp", target, True, line=no))
                continue
            if name in ("movel", "movep") and not is_pose:
                raise ValueError(f"{name} needs a pose p[...]")
            values = dict(_MOTION_DEFAULTS[name])
            for i, arg in enumerate(args[1:]):
                if "=" in arg:
                    key, _, val = arg.partition("=")
                    key = key.strip()
                else:
                    key, val = _POSITIONAL[name][i], arg
                if key not in values:
                    raise ValueError(f"unknown argument {key!r}")
                v = _literal(val)
                if not isinstance(v, float):
                    raise ValueError(f"argument {key} must be a number")
                values[key] = v
            ops.append(ScriptOp(name, target, is_pose, line=no, **values))
        except (ValueError, IndexError) as e:
            raise ValueError(f"line {no}: {line[:60]}: {e}") from None
    return ops or None


class _Watch:
    """Run ``action`` once, in the first cycle where ``done()`` holds."""

    __slots__ = ("action", "active", "done")

    def __init__(self, done: Callable[[], bool], action: Callable[[], None]) -> None:
        self.done, self.action, self.active = done, action, True


class _Job:
    """A motion to start (now, or once the arm has stopped)."""

    def __init__(self, kind: str, plan: Callable[[FloatArray], Motion]) -> None:
        self.kind = kind
        self.plan = plan
        self.finished = False
        self.error: str | None = None
        self.params: tuple[Any, ...] = ()


_EARLY_NS = 1_000_000
"""The clock loop wakes this long before a cycle is due and sends it at the due time: a real
controller sends within microseconds of its cycle, and a simulator sending up to a timer
resolution late would shift the robot stream's timing by that much."""


class _Controller:
    """State of the simulated controller; lives in the controller process's event loop."""

    def __init__(self, config: ControllerConfig, ring: TruthRing | None) -> None:
        self.cfg = config
        self.model = kinematics.get_model(config.model)
        self.kin = fast_kinematics(self.model)
        v = config.version
        self.version: tuple[int, int, int, int] = (int(v[0]), int(v[1]), int(v[2]), int(v[3]))
        self.serial_number = config.serial_number
        self.model_name = self.model.name
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
        self.robot_mode = ROBOT_MODE_RUNNING if config.powered_on else ROBOT_MODE_POWER_OFF
        self.safety_mode = SAFETY_NORMAL
        self.pstop_ns = 0
        self.runtime_state = RUNTIME_STOPPED
        self.program_name = ""
        self.program_kind: str | None = None
        self.program_text = ""
        self.loaded_program: str | None = None
        self.speed_slider = config.speed_slider
        self.payload = (config.payload_kg, (0.0, 0.0, 0.0))
        self.digital_out = 0
        # motion
        self.motion: Motion | None = None
        self.job: _Job | None = None
        self.queue: _Job | None = None
        self.watches: list[_Watch] = []
        # script emulation
        self.executing = False
        self.busy: Callable[[], bool] | None = None
        self.reg_off_int = 0
        self.reg_off_float = 0
        self.async_wr_count = 0
        self.async_op_id = 0
        self.async_watch: _Watch | None = None
        self.stop_watch: _Watch | None = None
        self.custom_end_cycle = -1
        self.script_ops: list[ScriptOp] = []
        self.script_running = False
        self.script_sleep_until = 0
        # registers
        self.inputs: dict[str, Any] = {}
        self.input_owner: dict[str, object] = {}
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self._out_int_names = [f"output_int_register_{i}" for i in range(48)]
        self._out_double_names = [f"output_double_register_{i}" for i in range(48)]
        self.defaults = {n: rtde_wire.zero_value(t) for n, t in rtde_wire.VARIABLE_TYPES.items()}
        # time
        self.start_ns = 0
        self.t_tick_ns = 0
        self.cycle = 0
        self.stall_until_ns = 0
        self._tool_z = np.zeros(3)
        self._pose_key = b""
        self._pose_cache: tuple[float, ...] = (0.0,) * 6
        self._tcp_offset_pose = tuple(se3.matrix_to_pose(self.tcp2flange).tolist())
        # connections
        self.rtde_conns: set[_RtdeProtocol] = set()
        self.other_transports: set[asyncio.BaseTransport] = set()
        self.stopping = asyncio.Event()
        self.skipped_cycles = 0
        """Cycles not published because the controller ran late (what a client can never get)."""

    # ------------------------------------------------------------------ clock and physics

    def begin(self, start_ns: int) -> None:
        self.start_ns = start_ns
        self.t_tick_ns = start_ns
        self._history.clear()
        self._append_truth([start_ns], self._pq[None], np.zeros((1, 6)), np.zeros((1, 6)))

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

    def _start_job(self, job: _Job) -> None:
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

    def _watch(self, done: Callable[[], bool], action: Callable[[], None]) -> _Watch:
        w = _Watch(done, action)
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

    def _schedule(self, job: _Job, preempt_decel: float) -> None:
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
        self.executing = False
        self.busy = None
        for w in self.watches:
            w.active = False
        self.watches = []
        self.async_watch = self.stop_watch = None
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
        else:
            self.program_kind = "custom"
            pattern = (
                r"write_output_integer_register\(\s*(\d+)\s*(?:\+\s*(\d+))?\s*,\s*(-?\d+)\s*\)"
            )
            for reg, plus, value in re.findall(pattern, text):
                idx = int(reg) + (int(plus) if plus else 0)
                if 0 <= idx < 48:
                    self.out_int[idx] = _int32(int(value))
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

    # ------------------------------------------------------------------ registers

    def _in_int(self, i: int) -> int:
        return int(self.inputs.get(f"input_int_register_{self.reg_off_int + i}", 0))

    def _in_double(self, i: int) -> float:
        return float(self.inputs.get(f"input_double_register_{self.reg_off_float + i}", 0.0))

    def _in_doubles(self, first: int, n: int = 6) -> FloatArray:
        return np.array([self._in_double(first + i) for i in range(n)])

    def _write_int(self, i: int, value: int) -> None:
        self.out_int[self.reg_off_int + i] = _int32(value)

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

    # ------------------------------------------------------------------ script emulation

    def _script_step(self) -> None:
        if self.program_kind == "custom" and self.script_running:
            if self.runtime_state == RUNTIME_PLAYING:
                self._script_statements()
            return
        if self.program_kind == "custom" and self.cycle >= self.custom_end_cycle:
            self._end_program("finished")
            return
        if self.program_kind != "rtde_control" or self.runtime_state != RUNTIME_PLAYING:
            return
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
                self.tcp2flange = se3.pose_to_matrix(np.asarray(op.target, dtype=np.float64))
                self._tcp_offset_pose = tuple(float(v) for v in op.target)
                self._pose_key = b""
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

            self._schedule(_Job("movej", plan), a)
        else:
            q = np.asarray(op.target, dtype=np.float64)
            self._schedule(_Job("movej", self._plan_movej(q, v, a)), a)

    def _script_linear(self, group: list[ScriptOp]) -> None:
        v = min(group[0].v, self.cfg.max_tool_speed_m_s)
        a = group[0].a
        targets = [se3.pose_to_matrix(np.asarray(g.target, dtype=np.float64)) for g in group]
        tcp = self.tcp2flange.copy()
        if len(targets) == 1:
            job = _Job(group[0].kind, self._plan_movel(targets[0], v, a))
        else:
            job = _Job(
                group[0].kind,
                lambda q0: PathMotion(PolylinePath(self.model, tcp, q0, targets), v, a),
            )
        self._schedule(job, a)

    def _tcp_pose_matrix(self, q: FloatArray) -> FloatArray:
        return self.kin.forward(q) @ self.tcp2flange

    def _ik_tcp(self, tcp2base: FloatArray, seed: FloatArray) -> FloatArray:
        flange2base = tcp2base @ se3.invert(self.tcp2flange)
        return kinematics.inverse_nearest(self.model, flange2base, seed)

    def _stop_async_move(self) -> None:
        w = self.async_watch
        if w is not None and w.active:
            w.active = False
            self._write_async(-1)
        self.async_watch = None

    def _cmd_move(self, kind: str, plan: Callable[[FloatArray], Motion], accel: float) -> None:
        is_async = self._in_int(1) == 1
        self._stop_async_move()
        job = _Job(kind, plan)
        if is_async:
            self._write_async(0)
            self.async_watch = self._watch(lambda: job.finished, lambda: self._write_async(-1))
        self._schedule(job, accel)
        if job.error is not None:
            return
        if not is_async:
            self.busy = lambda: job.finished

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
        job = _Job(kind, lambda q0: self._plan_speed(job, q0))
        job.params = (target, accel)
        self._schedule(job, accel)

    def _plan_speed(self, job: _Job, q0: FloatArray) -> Motion:
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
        if cmd == 1:
            q = self._in_doubles(0)
            self._cmd_move(
                "movej",
                self._plan_movej(q, self._in_double(6), self._in_double(7)),
                self._in_double(7),
            )
        elif cmd == 2:
            T = se3.pose_to_matrix(self._in_doubles(0))
            q = self._ik_tcp(T, self.q)
            self._cmd_move(
                "movej",
                self._plan_movej(q, self._in_double(6), self._in_double(7)),
                self._in_double(7),
            )
        elif cmd == 3:
            T = se3.pose_to_matrix(self._in_doubles(0))
            self._cmd_move(
                "movel",
                self._plan_movel(T, self._in_double(6), self._in_double(7)),
                self._in_double(7),
            )
        elif cmd == 4:
            T = self._tcp_pose_matrix(self._in_doubles(0))
            self._cmd_move(
                "movel",
                self._plan_movel(T, self._in_double(6), self._in_double(7)),
                self._in_double(7),
            )
        elif cmd == 9:
            self._cmd_speed("speedj", self._in_doubles(0), self._in_double(6))
        elif cmd == 10:
            self._cmd_speed("speedl", self._in_doubles(0), self._in_double(6))
        elif cmd in (15, 16):
            self._cmd_speed_stop(self._in_double(0))
        elif cmd in (17, 65):
            self.payload = (self._in_double(0), tuple(self._in_doubles(1, 3)))
        elif cmd == 29:
            self.tcp2flange = se3.pose_to_matrix(self._in_doubles(0))
            self._tcp_offset_pose = tuple(self._in_doubles(0).tolist())
            self._pose_key = b""
        elif cmd in (30, 46):
            T = se3.pose_to_matrix(self._in_doubles(0))
            seed = self._in_doubles(6) if cmd == 30 else self.q
            self._write_doubles(0, self._ik_tcp(T, seed))
        elif cmd == 31:
            self.enter_protective_stop("requested by the program (protective_stop())")
        elif cmd in (33, 34):
            self._cmd_stop(self._in_double(0), self._in_int(1) == 1)
        elif cmd == 36:
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
        elif cmd in (60, 61):
            T = se3.pose_to_matrix(self._in_doubles(0))
            ok = kinematics.inverse(self.model, T @ se3.invert(self.tcp2flange)).shape[0] > 0
            self._write_int(1, int(ok))
        elif cmd == 255:
            log.info("rtde_control: stop script received")
            self._end_program("stop script command")
        elif cmd in IGNORED_COMMANDS or cmd == 6:
            log.debug("rtde_control: command %d accepted without effect", cmd)
        else:
            self._script_error(f"command {cmd} is not simulated")

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
            "actual_q": q_t,
            "target_qd": qd_t,
            "actual_qd": qd_t,
            "target_qdd": tuple(self.qdd.tolist()),
            "actual_TCP_pose": pose_t,
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
            c._reply(rtde_wire.TEXT_MESSAGE, payload)
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
            "tcp_pose_true": se3.matrix_to_pose(self._tcp_pose_matrix(self.q_true)).tolist(),
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

    def set_joint_positions(self, q: Sequence[float]) -> bool:
        if self._moving():
            return False
        self.q = np.asarray(q, dtype=np.float64).copy()
        self.qd = np.zeros(6)
        self._pq, self._pqd, self._pqdd = self.q.copy(), np.zeros(6), np.zeros(6)
        self._history.clear()
        self._pose_key = b""
        return True


class _RtdeProtocol(asyncio.Protocol):
    """One RTDE client connection."""

    def __init__(self, ctrl: _Controller) -> None:
        self.ctrl = ctrl
        self.reader = rtde_wire.PacketReader()
        self.transport: asyncio.Transport | None = None
        self.started = False
        self.outputs: list[tuple[rtde_wire.Recipe, int]] = []
        self.outputs_valid = True
        self.inputs: dict[int, rtde_wire.Recipe] = {}
        self.next_input_id = 1
        self.protocol_version = 2
        self._drop_limit = 1 << 20

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        sock = transport.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.ctrl.rtde_conns.add(self)
        log.debug("RTDE client connected from %s", transport.get_extra_info("peername"))

    def connection_lost(self, exc: Exception | None) -> None:
        self.ctrl.rtde_conns.discard(self)
        for name, owner in list(self.ctrl.input_owner.items()):
            if owner is self:
                del self.ctrl.input_owner[name]
        self.transport = None
        log.debug("RTDE client gone (%s)", exc)

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()
            # The controller forgets the client at once, like a robot dropping the socket.
            self.connection_lost(None)

    def _reply(self, ptype: int, payload: bytes) -> None:
        if self.transport is not None:
            self.transport.write(rtde_wire.encode(ptype, payload))

    def data_received(self, data: bytes) -> None:
        try:
            for ptype, payload in self.reader.feed(data):
                self._handle(ptype, payload)
        except (ValueError, struct.error) as e:
            log.warning("RTDE client sent a malformed packet (%s); closing", e)
            self.close()

    def _handle(self, ptype: int, payload: bytes) -> None:
        ctrl = self.ctrl
        if ptype == rtde_wire.REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", payload[:2])
            ok = version == 2
            if ok:
                self.protocol_version = version
            self._reply(ptype, bytes((int(ok),)))
        elif ptype == rtde_wire.GET_URCONTROL_VERSION:
            self._reply(ptype, struct.pack(">IIII", *ctrl.version))
        elif ptype == rtde_wire.SETUP_OUTPUTS:
            self._setup_outputs(payload)
        elif ptype == rtde_wire.SETUP_INPUTS:
            self._setup_inputs(payload)
        elif ptype == rtde_wire.START:
            self.started = self.outputs_valid
            self._reply(ptype, bytes((int(self.started),)))
        elif ptype == rtde_wire.PAUSE:
            self.started = False
            self._reply(ptype, b"\x01")
        elif ptype == rtde_wire.DATA_PACKAGE:
            if not payload:
                return
            recipe = self.inputs.get(payload[0])
            if recipe is None:
                log.warning("RTDE data for unknown input recipe %d ignored", payload[0])
                return
            ctrl.apply_inputs(recipe.unpack(payload[1:]))
        elif ptype == rtde_wire.TEXT_MESSAGE:
            log.debug("RTDE text message from client: %r", payload)
        else:
            log.warning("RTDE packet type %d not handled", ptype)

    def _setup_outputs(self, payload: bytes) -> None:
        (freq,) = struct.unpack(">d", payload[:8])
        names = rtde_wire.split_names(payload[8:])
        types = [
            rtde_wire.VARIABLE_TYPES[n] if n in rtde_wire.OUTPUT_NAMES else "NOT_FOUND"
            for n in names
        ]
        max_freq = self.ctrl.cfg.frequency_hz
        ok = bool(names) and "NOT_FOUND" not in types and 0.0 < freq <= max_freq + 1e-9
        recipe_id = 0
        if ok:
            recipe_id = len(self.outputs) + 1
            divisor = max(1, round(max_freq / freq))
            recipe = rtde_wire.Recipe(recipe_id, names, types)
            self.outputs.append((recipe, divisor))
            bytes_per_s = (recipe.struct.size + 4) * max_freq / divisor
            self._drop_limit = max(1 << 16, int(10 * bytes_per_s))
            self.outputs_valid = True  # a valid setup after a rejected one (client retry)
        else:
            log.warning("output recipe rejected (frequency %g Hz, types %s)", freq, types)
            self.outputs_valid = False
        self._reply(rtde_wire.SETUP_OUTPUTS, bytes((recipe_id,)) + ",".join(types).encode())

    def _setup_inputs(self, payload: bytes) -> None:
        names = rtde_wire.split_names(payload)
        owner = self.ctrl.input_owner
        types = []
        for n in names:
            if n not in rtde_wire.INPUT_NAMES:
                types.append("NOT_FOUND")
            elif owner.get(n, self) is not self:
                types.append("IN_USE")
            else:
                types.append(rtde_wire.VARIABLE_TYPES[n])
        recipe_id = 0
        if names and all(t in rtde_wire.TYPE_FORMAT for t in types):
            recipe_id = self.next_input_id
            self.next_input_id += 1
            self.inputs[recipe_id] = rtde_wire.Recipe(recipe_id, names, types)
            for n in names:
                owner[n] = self
        else:
            log.warning("input recipe rejected: %s", dict(zip(names, types, strict=True)))
        self._reply(rtde_wire.SETUP_INPUTS, bytes((recipe_id,)) + ",".join(types).encode())

    def due(self, k: int) -> bool:
        return any(k % div == 0 for _, div in self.outputs)

    def outputs_for(self, k: int, values: dict[str, Any], defaults: dict[str, Any]) -> bytes:
        """The data packages of cycle ``k`` for this client (its recipes due at ``k``)."""
        return b"".join(
            rtde_wire.encode(rtde_wire.DATA_PACKAGE, recipe.pack(values, defaults))
            for recipe, div in self.outputs
            if k % div == 0
        )

    def send_packets(self, data: bytes) -> None:
        t = self.transport
        if t is None or not data:
            return
        if t.get_write_buffer_size() > self._drop_limit:
            log.warning("RTDE client stopped reading for about 10 s; dropping it")
            self.close()
            return
        t.write(data)


class _LineProtocol(asyncio.Protocol):
    """Base for the text ports: tracks the transport for shutdown."""

    def __init__(self, ctrl: _Controller) -> None:
        self.ctrl = ctrl
        self.transport: asyncio.Transport | None = None
        self.buf = b""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        self.ctrl.other_transports.add(transport)

    def connection_lost(self, exc: Exception | None) -> None:
        if self.transport is not None:
            self.ctrl.other_transports.discard(self.transport)
        self.transport = None


class _DashboardProtocol(_LineProtocol):
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        assert self.transport is not None
        self.transport.write((dashboard.WELCOME + "\n").encode())

    def data_received(self, data: bytes) -> None:
        self.buf += data
        while b"\n" in self.buf and self.transport is not None:
            line, self.buf = self.buf.split(b"\n", 1)
            text, close = dashboard.reply(self.ctrl, line.decode("utf-8", errors="replace"))
            self.transport.write((text + "\n").encode())
            if close:
                self.transport.close()


class _ScriptProtocol(_LineProtocol):
    """Port 30003: collects URScript programs (``def``/``sec`` ... top-level ``end``)."""

    def __init__(self, ctrl: _Controller) -> None:
        super().__init__(ctrl)
        self.program: list[str] | None = None

    def data_received(self, data: bytes) -> None:
        self.buf += data
        while b"\n" in self.buf:
            raw, self.buf = self.buf.split(b"\n", 1)
            line = raw.decode("utf-8", errors="replace").rstrip("\r")
            if self.program is None:
                if re.match(r"(def|sec)\s+\w+\s*\(", line):
                    self.program = [line]
                elif line.strip():
                    log.info("single script line ignored: %r", line[:80])
                continue
            self.program.append(line)
            if line.rstrip() == "end":
                text = "\n".join(self.program) + "\n"
                self.program = None
                self.ctrl.start_program(text)


async def _serve(
    config: ControllerConfig,
    truth_ring_name: str | None,
    conn: Connection | None,
    stop_event: Any,
) -> None:
    ring = TruthRing.attach(truth_ring_name) if truth_ring_name else None
    ctrl = _Controller(config, ring)
    loop = asyncio.get_running_loop()
    servers: list[asyncio.base_events.Server] = []
    primary: Any = None
    ctrl.begin(time.monotonic_ns())
    try:
        for port, factory in (
            (RTDE_PORT, lambda: _RtdeProtocol(ctrl)),
            (DASHBOARD_PORT, lambda: _DashboardProtocol(ctrl)),
            (SCRIPT_PORT, lambda: _ScriptProtocol(ctrl)),
        ):
            servers.append(await loop.create_server(factory, config.host, port, reuse_address=True))
        if config.primary_interface:
            from wristscan.drivers.sim.ur.primary import KinematicsValues, PrimaryServer

            primary = await PrimaryServer.start(
                config.host, KinematicsValues.from_model(ctrl.model), version=ctrl.version
            )
    except OSError as e:
        if primary is not None:
            primary.close()
        for s in servers:
            s.close()
        if conn is not None:
            conn.send(("error", f"cannot listen on {config.host}: {e}"))
        if ring is not None:
            ring.close()
        return

    def on_control() -> None:
        assert conn is not None
        try:
            while conn.poll():
                msg = conn.recv()
                conn.send(_control(ctrl, msg))
        except (EOFError, OSError):
            ctrl.stopping.set()

    if conn is not None:
        loop.add_reader(conn.fileno(), on_control)
        conn.send(("ready", {"host": config.host, "start_time_ns": ctrl.start_ns}))

    async def clock() -> None:
        period = ctrl.period_ns
        k = 0
        last_published = 0
        while not ctrl.stopping.is_set():
            k += 1
            due = ctrl.start_ns + k * period
            now = time.monotonic_ns()
            # asyncio's timers have 1 ms resolution (epoll): wake up to _EARLY_NS before the
            # cycle, compute it (its state is known ahead), and send it on time (below).
            if due - _EARLY_NS > now:
                await asyncio.sleep((due - _EARLY_NS - now) * 1e-9)
            elif k % 8 == 0:
                await asyncio.sleep(0)  # let I/O through while catching up
            now = time.monotonic_ns()
            late = now - due
            if late > 500_000_000 and k % 500 == 0:
                log.warning("controller cycle running %.0f ms late", late * 1e-6)
            # Send the newest cycle, and older ones only while they are still fresh; while
            # catching up, still send every 5th so clients never starve.
            publish = late < 3 * period or now < due + period or k - last_published >= 5
            if publish:
                last_published = k

            def on_time(due: int = due) -> None:
                wait = due - time.monotonic_ns()
                if wait > 0:
                    time.sleep(wait * 1e-9)

            try:
                ctrl.run_cycle(k, publish, on_time)
            except Exception as e:  # a bug must not freeze the controller silently
                log.exception("controller cycle %d failed", k)
                ctrl.enter_protective_stop(f"internal error: {e}")

    async def watchdog() -> None:
        parent = os.getppid()
        while not ctrl.stopping.is_set():
            if (stop_event is not None and stop_event.is_set()) or os.getppid() != parent:
                ctrl.stopping.set()
                break
            await asyncio.sleep(0.05)

    tasks = [asyncio.create_task(clock()), asyncio.create_task(watchdog())]
    try:
        await ctrl.stopping.wait()
    finally:
        for t in tasks:
            t.cancel()
        for t in tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await t
        if conn is not None:
            loop.remove_reader(conn.fileno())
        for s in servers:
            s.close()
        if primary is not None:
            primary.close()
        ctrl.drop_connections()
        for tr in list(ctrl.other_transports):
            tr.close()
        for s in servers:
            await s.wait_closed()
        if primary is not None:
            await primary.wait_closed()
        if ring is not None:
            ring.close()


def _control(ctrl: _Controller, msg: tuple[Any, ...]) -> tuple[str, Any]:
    """Handle one request from the parent process."""
    kind = msg[0]
    try:
        if kind == "stop":
            ctrl.stopping.set()
            return ("ok", None)
        if kind == "drop":
            return ("ok", ctrl.drop_connections())
        if kind == "message":
            return ("ok", ctrl.send_text_message(str(msg[1]), str(msg[2]), int(msg[3])))
        if kind == "stall":
            ctrl.stall_until_ns = time.monotonic_ns() + int(float(msg[1]) * 1e9)
            return ("ok", None)
        if kind == "pstop":
            ctrl.enter_protective_stop(str(msg[1]) if len(msg) > 1 else "requested")
            return ("ok", None)
        if kind == "clear_pstop":
            ctrl.clear_protective_stop()
            return ("ok", None)
        if kind == "state":
            return ("ok", ctrl.state())
        if kind == "program_text":
            return ("ok", ctrl.program_text)
        if kind == "set_q":
            return ("ok", ctrl.set_joint_positions(msg[1]))
        return ("error", f"unknown request {kind!r}")
    except Exception as e:  # the controller must survive a bad request from the parent
        log.exception("control request %r failed", msg)
        return ("error", f"{type(e).__name__}: {e}")


def run_controller(
    config: ControllerConfig,
    truth_ring_name: str | None = None,
    conn: Connection | None = None,
    stop_event: Any = None,
) -> None:
    """Body of the controller process; returns when stopped.

    ``conn`` (one end of a duplex ``multiprocessing.Pipe``) receives ``("ready", {"host",
    "start_time_ns"})`` or ``("error", message)`` once, then answers requests (see
    :class:`SimulatedController`). The controller stops on a ``("stop",)`` request, when
    ``stop_event`` (a ``multiprocessing.Event``) is set, when the pipe closes, or when the parent
    process dies.
    """
    if not logging.getLogger().handlers:
        logging.basicConfig(
            level=config.log_level, format=f"sim-ur {config.host} %(levelname)s %(message)s"
        )
    asyncio.run(_serve(config, truth_ring_name, conn, stop_event))


def _ports_free(host: str) -> bool:
    for port in (PRIMARY_PORT, DASHBOARD_PORT, SCRIPT_PORT, RTDE_PORT):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((host, port))
            except OSError:
                return False
    return True


def pick_free_loopback_host(rng: random.Random | None = None, attempts: int = 100) -> str:
    """A random ``127.0.0.x`` (x in 2..250) whose ports 29999, 30001, 30003, 30004 are free now."""
    r = rng or random.Random()
    for _ in range(attempts):
        host = f"127.0.0.{r.randint(2, 250)}"
        if _ports_free(host):
            return host
    raise RuntimeError("no loopback address with free UR ports found")


class SimulatedController:
    """A simulated UR controller in a process of its own; a context manager.

    >>> with SimulatedController(ControllerConfig(host="127.0.0.7")) as sim:  # doctest: +SKIP
    ...     rtde_receive.RTDEReceiveInterface(sim.host)

    ``truth_ring_name`` names a :class:`~wristscan.drivers.sim.truth.TruthRing` of width 6 that
    the controller fills with the true joint positions (rad) at ``config.truth_rate_hz``.
    """

    def __init__(
        self, config: ControllerConfig | None = None, truth_ring_name: str | None = None
    ) -> None:
        self.config = config or ControllerConfig()
        self.truth_ring_name = truth_ring_name
        self.start_time_ns = 0
        """Host ``time.monotonic_ns()`` at controller timestamp 0."""
        self._proc: Any = None
        self._conn: Connection | None = None

    @property
    def host(self) -> str:
        return self.config.host

    @property
    def frequency_hz(self) -> float:
        return self.config.frequency_hz

    def host_time_ns(self, timestamp_s: float) -> int:
        """Host monotonic time (ns) of an RTDE ``timestamp`` (s)."""
        return self.start_time_ns + round(timestamp_s * 1e9)

    def start(self, timeout_s: float = 60.0) -> SimulatedController:
        if self._proc is not None:
            return self
        ctx = mp.get_context("spawn")
        parent, child = ctx.Pipe(duplex=True)
        self._proc = ctx.Process(
            target=run_controller,
            args=(self.config, self.truth_ring_name, child),
            name=f"sim-ur-{self.config.host}",
            daemon=True,
        )
        self._proc.start()
        child.close()
        self._conn = parent
        try:
            if not parent.poll(timeout_s):
                raise RuntimeError(f"simulated controller on {self.host} did not start")
            kind, info = parent.recv()
        except (EOFError, OSError) as e:
            self.stop()
            raise RuntimeError(f"simulated controller on {self.host} died while starting") from e
        except RuntimeError:
            self.stop()
            raise
        if kind != "ready":
            self.stop()
            raise RuntimeError(str(info))
        self.start_time_ns = int(info["start_time_ns"])
        return self

    @classmethod
    def on_free_loopback(
        cls,
        config: ControllerConfig | None = None,
        truth_ring_name: str | None = None,
        attempts: int = 5,
    ) -> SimulatedController:
        """Start on a random free ``127.0.0.x`` (``config.host`` is replaced), retrying when
        another process takes the address between the check and the bind. Stop it (or use it as
        a context manager) as usual."""
        base = config or ControllerConfig()
        for attempt in range(attempts):
            sim = cls(dataclasses.replace(base, host=pick_free_loopback_host()), truth_ring_name)
            try:
                return sim.start()
            except RuntimeError as e:
                if "cannot listen" not in str(e) or attempt == attempts - 1:
                    raise
                log.info("%s; trying another address", e)
        raise AssertionError("unreachable")

    def _request(self, *msg: Any, timeout_s: float = 10.0) -> Any:
        if self._conn is None:
            raise RuntimeError("simulated controller is not running")
        self._conn.send(msg)
        if not self._conn.poll(timeout_s):
            raise TimeoutError(f"simulated controller did not answer {msg[0]!r}")
        kind, value = self._conn.recv()
        if kind != "ok":
            raise RuntimeError(str(value))
        return value

    def drop_connections(self) -> int:
        """Close every RTDE client connection (clients see end-of-file); returns how many."""
        return int(self._request("drop"))

    def send_text_message(self, text: str, source: str = "sim", level: int = 3) -> int:
        """Send an RTDE text message ('M'; level 0 exception .. 3 info) to every streaming client,
        as a controller does mid-stream; returns how many got it."""
        return int(self._request("message", text, source, level))

    def stall_output(self, seconds: float) -> None:
        """Send no RTDE data packages for ``seconds`` (the controller keeps running)."""
        self._request("stall", seconds)

    def protective_stop(self, reason: str = "requested by the test") -> None:
        """Trigger a protective stop: the arm decelerates and the program stops."""
        self._request("pstop", reason)

    def clear_protective_stop(self) -> None:
        """Clear a protective stop at once (the dashboard's unlock waits for the delay)."""
        self._request("clear_pstop")

    def state(self) -> dict[str, Any]:
        """Snapshot: ``timestamp``, ``q`` (reported), ``q_true``, ``tcp_pose`` (and
        ``tcp_pose_true`` from ``q_true``), ``tcp_offset`` (the active TCP), ``moving``,
        ``runtime_state``, ``robot_mode``, ``safety_mode``, ``program``, ``rtde_clients``,
        ``skipped_cycles`` (cycles left unpublished because the controller process ran late) ..."""
        return dict(self._request("state"))

    def program_text(self) -> str:
        """The last program received on the script port."""
        return str(self._request("program_text"))

    def set_joint_positions(self, q: Sequence[float]) -> bool:
        """Place the arm at ``q`` (rad) at once; refused (False) while it moves."""
        return bool(self._request("set_q", [float(v) for v in q]))

    def stop(self) -> None:
        proc, conn = self._proc, self._conn
        if proc is None:
            return
        if getattr(proc, "_popen", None) is None:  # start() failed before the process ran
            if conn is not None:
                conn.close()
            self._proc = self._conn = None
            return
        try:
            if conn is not None:
                conn.send(("stop",))
        except (BrokenPipeError, OSError):
            pass
        proc.join(timeout=10)
        if proc.is_alive():
            proc.terminate()
            proc.join(timeout=5)
        if proc.is_alive():
            proc.kill()
            proc.join(timeout=5)
        if conn is not None:
            conn.close()
        self._proc = None
        self._conn = None

    def __enter__(self) -> SimulatedController:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
