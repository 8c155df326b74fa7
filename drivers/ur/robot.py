"""Universal Robots arm over RTDE: a state stream (own client or ``ur_rtde``), and guarded motion
(``ur_rtde``).

Why child processes
-------------------
``ur_rtde``'s Python constructors (and ``reconnect``) hold the GIL while they block on the network,
so in the caller's process they would freeze every other thread, the sensor path included, for as
long as a connection takes (PROTOCOLS.md). Both ``ur_rtde`` interfaces therefore live in child
processes of their own (``multiprocessing`` spawn); the native receive client does too, which
keeps its decoding off the caller's GIL and the two backends interchangeable. The caller's
process only ever waits on pipes, which releases the GIL. A child that hangs or crashes is
killed and restarted; the caller sees a state change, never an exception from the link.

Receiving
---------
The receive child subscribes to a small recipe (:data:`REQUIRED_VARIABLES`) with one of two
clients (``receive_backend``) and sends each controller sample to the caller's process as one
fixed-size binary row (:data:`~.receive_child.ROW_DTYPE`, 168 bytes) over a socket pair,
stamped with the host's ``time.monotonic_ns()`` when the child got it.

* ``"native"`` (default): :class:`~wristscan.drivers.ur.receive.RtdeReceiver`, this package's
  own RTDE client, reads the TCP stream itself. It sleeps in ``poll()`` until packets arrive
  and ships every data package, in order; each is stamped right after the ``recv()`` that
  completed it. Nothing is lost while the child is not scheduled: the kernel holds the
  packets (a controller drops a client only after ~10 s of not reading), and they come out
  together, with the stamp of the call that took them in, when the child runs again. No data
  for ``stall_timeout_s`` counts as a lost link.
* ``"ur_rtde"``: ``RTDEReceiveInterface``, polled faster than the controller rate, since ur_rtde
  keeps only the newest packet and offers no wait for a new one. Its getters read the latest
  packet one call at a time, so two calls can see two packets; the child reads ``timestamp``
  before and after the other getters and retries when it changed (``torn_reads`` in the health
  detail). Each new sample (deduplicated by timestamp) is stamped when the poll saw it (up to
  one poll interval, ~0.4 ms, plus ur_rtde's own hand-over after its arrival).

Why native is the default: the polling costs about a fifth of a core at 500 Hz and still loses
the samples that arrive while the child waits for a CPU (5-14 % on a busy 2-core machine),
which leaves gaps in the robot track (``docs/drivers.md``, "UR robot receive path"). ``ur_rtde``
stays as the reference client.

The child never blocks on the pipe to the caller: rows wait in the child while the pipe is full
and the oldest are dropped past ``queue_size`` (they then count as lost).

The caller's process turns rows into :class:`~wristscan.drivers.records.RobotState` records in
order. Counters: ``duplicates`` (a timestamp delivered twice), ``reordered`` (older than the last
delivered, dropped), ``lost`` (controller samples never delivered: a timestamp step larger than 1.5
nominal periods counts ``round(step / period) - 1``; samples dropped from a full queue). The
nominal period is ``1 / frequency_hz``; without ``frequency_hz`` the client asks for the
controller's maximum, 500 Hz (e-Series) or 125 Hz (CB3), told apart by the steps seen (the count
is corrected once a step under 6 ms proves a 500 Hz stream). A controller restart (the timestamp
falls by more than a second) starts a new sequence.

Link loss: the native client raises (end of stream, reset, silence); with ur_rtde the child
sees ``isConnected()`` false (or a getter failing). Either way the child lets the link go and
connects again with exponential :class:`~wristscan.drivers.base.Backoff`; unknown variable
names (``NOT_FOUND``, native client) fail for good instead. For ur_rtde, ``reconnect()`` is not
used: in ur_rtde's source (1.5) it resets the frequency to the controller's maximum and waits
without a timeout for the first packet. Dead ur_rtde interfaces are not destroyed either:
ur_rtde's ``disconnect()`` (and so its destructor) sleeps 500 ms (measured with 1.6.5), which
would stop the loop; a child exits without running them. The health state is ``RECONNECTING``
until data flows again; every recovery counts one ``reconnects``. The child sends a heartbeat
every 0.25 s; a child silent for ``stall_timeout_s`` (or ``connect_timeout_s`` while
connecting) is killed and restarted. All of this is driven from :meth:`read` / :meth:`health`
calls: the caller's process runs no thread of the driver's.

Motion
------
Only with ``motion_enabled``: every command first passes :meth:`Robot.check_motion` (speed and
acceleration caps, the TCP target inside the workspace box); :meth:`move_j` also checks the TCP
along the joint-space path (16 samples from the latest state to the target) with the kinematic
model (factory calibration when read, else ``model``, else the controller's own forward
kinematics). Refusals raise :class:`MotionNotEnabled` / :class:`WorkspaceViolation` before
anything reaches the controller.

The control child (``RTDEControlInterface`` and a dashboard client) starts at the first command,
not at :meth:`open`: uploading the control script takes over the robot's program, which a
receive-only run must never do. It always issues ur_rtde's asynchronous moves and tracks them
itself, so :meth:`stop` works while a blocking :meth:`move_l` / :meth:`move_j` waits in another
thread. Outcome of a move (:class:`~wristscan.drivers.base.MoveStatus`): ``DONE`` (the
controller reports it finished and the state stream shows the arm at the target: TCP within 1 mm
and 0.01 rad, or every joint within 0.01 rad; without a fresh state it stays unconfirmed, with a
warning); ``STOPPED`` by :meth:`stop`; ``PROTECTIVE_STOP`` (the control program stopped and the
dashboard reports a safety stop: protective, safeguard or emergency); ``FAILED`` (refused by the
controller, program stopped otherwise, link lost). A blocking move raises
:class:`~wristscan.drivers.base.ProtectiveStop` or :class:`~wristscan.drivers.base.MotionFailed`
(both :class:`~wristscan.drivers.base.DriverIOError`, with ``.status``) for anything but
``DONE``; an asynchronous one returns at once and :meth:`wait_until_idle` returns its final
status. After a protective stop is cleared on the robot, the next command re-uploads the control
script.

Control link loss: ur_rtde's control interface reconnects from inside its own receive thread and
then keeps two threads on one socket (its 1.5 source; with 1.6.5 it reconnects over and over). So
the control child watches ur_rtde's console messages and ``isConnected()``, and exits at the first
sign of a lost link; a fresh child starts at the next command, which is sent once more when the
old child reports the loss instead of an answer (moves are absolute: repeating one is harmless,
and the fresh ur_rtde first stops a script the old one left running). A new command after the
receive link dropped also starts a fresh child first. A move in progress when the link drops
ends ``FAILED`` ("link lost"); the arm may still finish it, so check the stream.

Factory kinematics: with ``read_kinematics``, :meth:`open` reads the primary interface's
KinematicsInfo (:mod:`.primary`); :meth:`kinematic_model` then returns the calibrated model.

Where the code is
-----------------
:class:`URRobot` (this module) is the facade: settings, life cycle, health, kinematics. It
stacks two layers: :class:`~.stream.URStateStream` (the receive child seen from the caller's
process) under :class:`~.motion.URMotion` (the motion commands and the control child seen from
the caller's process). The children themselves are :mod:`.receive_child` and :mod:`.control`;
:mod:`.process` holds what they share (starting and stopping a child, the pipe's messages).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from wristscan.drivers.base import DriverError, DriverInitError, Health
from wristscan.drivers.ur.motion import URMotion
from wristscan.drivers.ur.stream import E_SERIES_PERIOD_S

if TYPE_CHECKING:
    from wristscan.calib.kinematics import DHParams
    from wristscan.drivers.ur.primary import KinematicsInfo

__all__ = ["RECEIVE_BACKENDS", "REQUIRED_VARIABLES", "URRobot"]

REQUIRED_VARIABLES: tuple[str, ...] = (
    "timestamp",
    "actual_q",
    "actual_qd",
    "actual_TCP_pose",
    "safety_status_bits",
    "runtime_state",
)
"""RTDE outputs the receive child always subscribes to."""

RECEIVE_BACKENDS: tuple[str, ...] = ("native", "ur_rtde")
"""Clients the receive child can read the stream with (see the module doc, "Receiving")."""


class URRobot(URMotion):
    """A UR arm through ``ur_rtde`` (RTDE 30004, dashboard 29999, script 30003; optionally the
    primary interface 30001 for the factory kinematics).

    ``frequency_hz``: RTDE output rate; None asks for the controller's maximum (500 Hz e-Series,
    125 Hz CB3). ``variables``: extra RTDE outputs to subscribe (the receive child always reads
    :data:`REQUIRED_VARIABLES`; extra ones only widen the recipe). ``model``: UR model name or
    DH parameters for the ``move_j`` workspace check (the factory calibration wins when
    ``read_kinematics`` is set). ``receive_backend``: the client of the receive child,
    ``"native"`` (default: lossless, nearly no CPU) or ``"ur_rtde"`` (the reference client;
    see the module doc, "Receiving"). ``poll_interval_s`` applies to ``"ur_rtde"`` only.
    Caps and the workspace box: see :class:`Robot`.
    """

    def __init__(
        self,
        host: str,
        frequency_hz: float | None = None,
        motion_enabled: bool = False,
        max_speed_m_s: float = 0.25,
        max_accel_m_s2: float = 1.2,
        max_joint_speed_rad_s: float = 1.0,
        max_joint_accel_rad_s2: float = 1.4,
        workspace_min_m: ArrayLike | None = None,
        workspace_max_m: ArrayLike | None = None,
        *,
        model: str | DHParams | None = None,
        variables: Sequence[str] | None = None,
        read_kinematics: bool = False,
        kinematics_port: int = 30001,
        connect_timeout_s: float = 10.0,
        command_timeout_s: float = 10.0,
        stall_timeout_s: float = 3.0,
        backoff_initial_s: float = 0.05,
        backoff_max_s: float = 2.0,
        poll_interval_s: float | None = None,
        queue_size: int = 8192,
        receive_backend: str = "native",
    ) -> None:
        super().__init__(
            motion_enabled=motion_enabled,
            max_speed_m_s=max_speed_m_s,
            max_accel_m_s2=max_accel_m_s2,
            max_joint_speed_rad_s=max_joint_speed_rad_s,
            max_joint_accel_rad_s2=max_joint_accel_rad_s2,
            workspace_min_m=workspace_min_m,
            workspace_max_m=workspace_max_m,
        )
        extra = self._check_options(host, frequency_hz, receive_backend, variables)
        self.host = host
        self.frequency_hz = frequency_hz
        self.receive_backend = receive_backend
        self.model = model
        self.variables = (*REQUIRED_VARIABLES, *dict.fromkeys(extra))
        self.read_kinematics = read_kinematics
        self.kinematics_port = kinematics_port
        self.connect_timeout_s = connect_timeout_s
        self.command_timeout_s = command_timeout_s
        self.stall_timeout_s = stall_timeout_s
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        nominal = 1.0 / frequency_hz if frequency_hz else E_SERIES_PERIOD_S
        self.poll_interval_s = poll_interval_s or min(0.0004, nominal / 5)
        self.queue_size = queue_size
        self.kinematics_info: KinematicsInfo | None = None
        """The factory calibration, when ``read_kinematics`` read it at :meth:`open`."""
        self._init_stream()
        self._init_control()

    def _check_options(
        self,
        host: str,
        frequency_hz: float | None,
        receive_backend: str,
        variables: Sequence[str] | None,
    ) -> list[str]:
        """Refuse unusable settings (:class:`DriverInitError`); returns the extra RTDE outputs
        asked for (those not in :data:`REQUIRED_VARIABLES`)."""
        if not isinstance(host, str) or not host:
            raise DriverInitError("robot: host must be a non-empty address string")
        if frequency_hz is not None and not 0 < frequency_hz <= 500:
            raise DriverInitError(f"robot: frequency_hz must be in (0, 500], got {frequency_hz}")
        if (self.workspace_min_m is None) != (self.workspace_max_m is None):
            raise DriverInitError("robot: give both workspace_min_m and workspace_max_m, or none")
        if self.workspace_min_m is not None:
            assert self.workspace_max_m is not None
            if self.workspace_min_m.shape != (3,) or self.workspace_max_m.shape != (3,):
                raise DriverInitError("robot: the workspace box corners need 3 values each")
            if not np.all(self.workspace_min_m < self.workspace_max_m):
                raise DriverInitError("robot: workspace_max_m must exceed workspace_min_m")
        if receive_backend not in RECEIVE_BACKENDS:
            raise DriverInitError(
                f"robot: receive_backend must be one of {', '.join(RECEIVE_BACKENDS)}, "
                f"got {receive_backend!r}"
            )
        extra = [v for v in (variables or ()) if v not in REQUIRED_VARIABLES]
        if not all(isinstance(v, str) and v for v in extra):
            raise DriverInitError("robot: variables must be RTDE output names")
        return extra

    # ------------------------------------------------------------------ life cycle

    def _open(self) -> None:
        if self.read_kinematics:
            from wristscan.drivers.ur.primary import read_kinematics_info

            try:
                self.kinematics_info = read_kinematics_info(
                    self.host, self.kinematics_port, self.connect_timeout_s
                )
            except (DriverError, OSError) as exc:
                raise DriverInitError(
                    f"robot: cannot read the factory kinematics from {self.host}:"
                    f"{self.kinematics_port} ({exc}); set read_kinematics = false to use the "
                    "nominal model"
                ) from exc
        self._open_stream()

    def _close(self) -> None:
        try:
            self._stop_ctl()
        finally:
            self._stop_rx()
            self._rx_restart_at = None

    # ------------------------------------------------------------------ health

    def health(self) -> Health:
        """State, counters and detail, after taking in what the children reported."""
        if self._open_flag:
            self._pump(0.0, wait_lock=False)
        self._drain_ctl()
        return super().health()

    def _health_detail(self) -> dict[str, Any]:
        rx = self._rx
        return {
            "host": self.host,
            "receive": rx.state if rx is not None else "stopped",
            "receive_backend": self.receive_backend,
            "period_s": self._period_s,
            "queued": len(self._queue),
            "queue_overflow": self._overflow,
            "receive_restarts": self._rx_restarts,
            **self._rx_stats,
            "control": self._ctl_state,
            "control_starts": self._ctl_starts,
            "control_error": self._ctl_error,
            "move_status": self._move_status.value,
            "kinematics": (
                "factory"
                if self.kinematics_info is not None
                else "nominal"
                if self.model is not None
                else "controller"
            ),
        }

    # ------------------------------------------------------------------ kinematics

    def kinematic_model(self) -> DHParams | None:
        """The factory-calibrated model when read, else the nominal ``model``, else None."""
        if self.kinematics_info is not None:
            return self.kinematics_info.model(f"{self.host} factory calibration")
        if self.model is None:
            return None
        from wristscan.calib import kinematics

        return kinematics.get_model(self.model)
