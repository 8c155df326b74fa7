"""Simulated Universal Robots controller, run as a process of its own.

It serves, on one loopback address (any ``127.x.y.z``, so several run side by side):

* RTDE on TCP 30004 - protocol version 2, per-connection recipes (output recipe ids from 1, input
  recipe ids 1, 2, 3 ... as ur_rtde expects), output at the requested frequency on the controller
  cycle: 500 Hz (2 ms) for an e-Series version (major > 3), 125 Hz (8 ms) for CB3;
* the dashboard server on TCP 29999 (:mod:`.dashboard`);
* the script port on TCP 30003: a program ending in a top-level ``end`` line starts; the
  ``rtde_control`` program that ur_rtde's ``RTDEControlInterface`` uploads is emulated natively
  (its command-register state machine, :mod:`.rtde_control`); other programs have their
  ``write_output_integer_register`` calls applied and, when they hold motion statements, run a
  minimal URScript subset (:mod:`.script`).

So the real ``rtde_receive.RTDEReceiveInterface`` and ``rtde_control.RTDEControlInterface`` work
against it unmodified.

The controller's parts, in this room:

* :mod:`.config` - :class:`ControllerConfig` and the fixed ports;
* :mod:`.server` - the controller process: listening ports, the cycle clock, the parent's
  requests; :mod:`.rtde_server` - one RTDE connection (recipes, start/pause, inputs, outputs);
  :mod:`.dashboard` and :mod:`.primary` - the other ports;
* the controller's state, in layers: :mod:`.arm` (time, motion, truth ring; moves from
  :mod:`.motion` with the tick kinematics of :mod:`.fastkin`), :mod:`.program` (modes, safety,
  programs, I/O; the URScript subset of :mod:`.script`), :mod:`.rtde_control` (the emulated
  ``rtde_control`` script), :mod:`.engine` (the cycle and its outputs);
* here: :class:`SimulatedController`, the parent-side handle, and
  :func:`pick_free_loopback_host`.

Faults on request (from the parent, :class:`SimulatedController`): drop every RTDE connection
(clients see end-of-file), stall the RTDE output for a while (ur_rtde clients give up after 2.5 s
without data), protective stop, an RTDE text message ('M') to the streaming clients. Note:
after a dropped connection ur_rtde 1.6.5's ``RTDEControlInterface`` reconnects over and over (its
receive thread never clears its reconnect flag), re-uploading the script each time;
``RTDEReceiveInterface`` simply reports ``isConnected() == False`` until ``reconnect()``.
"""

from __future__ import annotations

import dataclasses
import logging
import random
import socket
from collections.abc import Callable, Sequence
from typing import Any, Self

from wristscan.drivers.sim.process import SimProcess
from wristscan.drivers.sim.ur.config import (
    DASHBOARD_PORT,
    PRIMARY_PORT,
    RTDE_PORT,
    SCRIPT_PORT,
    ControllerConfig,
)
from wristscan.drivers.sim.ur.server import run_controller

__all__ = ["ControllerConfig", "SimulatedController", "pick_free_loopback_host"]

log = logging.getLogger(__name__)


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
    """A random loopback address ``127.a.b.c`` (a 1..255, b 0..255, c 1..254) whose ports 29999,
    30001, 30003, 30004 are free now.

    The whole of 127.0.0.0/8 reaches loopback on Linux; ``127.0.x.y`` is left out, where fixed
    addresses live (127.0.0.1, the configurations' 127.0.0.2, 127.0.0.53 of systemd-resolved,
    127.0.1.1 of Debian's host name). Among 16 million addresses two test runs on one machine
    (two CI jobs, say) do not meet, so whatever a run binds on an address of its own, free ports
    chosen by binding port 0 and releasing it included, cannot collide with another run; nor
    with this machine's outgoing connections, whose local address is 127.0.0.1."""
    r = rng or random.Random()  # seeded from os.urandom: independent of random.seed()
    for _ in range(attempts):
        host = f"127.{r.randint(1, 255)}.{r.randint(0, 255)}.{r.randint(1, 254)}"
        if _ports_free(host):
            return host
    raise RuntimeError("no loopback address with free UR ports found")


class SimulatedController(SimProcess):
    """A simulated UR controller in a process of its own; a context manager.

    >>> with SimulatedController(ControllerConfig(host="127.0.0.7")) as sim:  # doctest: +SKIP
    ...     rtde_receive.RTDEReceiveInterface(sim.host)

    ``truth_ring_name`` names a :class:`~wristscan.drivers.sim.truth.TruthRing` of width 6 that
    the controller fills with the true joint positions (rad) at ``config.truth_rate_hz``.
    """

    def __init__(
        self, config: ControllerConfig | None = None, truth_ring_name: str | None = None
    ) -> None:
        super().__init__()
        self.config = config or ControllerConfig()
        self.process_name = f"sim-ur-{self.config.host}"
        self.truth_ring_name = truth_ring_name
        self.start_time_ns = 0
        """Host ``time.monotonic_ns()`` at controller timestamp 0."""

    def _target(self) -> tuple[Callable[..., None], tuple[Any, ...]]:
        return run_controller, (self.config, self.truth_ring_name)

    @property
    def host(self) -> str:
        return self.config.host

    @property
    def frequency_hz(self) -> float:
        return self.config.frequency_hz

    def host_time_ns(self, timestamp_s: float) -> int:
        """Host monotonic time (ns) of an RTDE ``timestamp`` (s)."""
        return self.start_time_ns + round(timestamp_s * 1e9)

    def start(self, timeout_s: float = 60.0) -> Self:
        """Start the process and wait until it listens; a running controller stays as it is."""
        if self._proc is not None:
            return self
        return super().start(timeout_s)

    def _on_ready(self) -> None:
        self.start_time_ns = int(self.endpoint["start_time_ns"])

    @classmethod
    def on_free_loopback(
        cls,
        config: ControllerConfig | None = None,
        truth_ring_name: str | None = None,
        attempts: int = 5,
    ) -> SimulatedController:
        """Start on a random free ``127.a.b.c`` (``config.host`` is replaced), retrying when
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
        """Snapshot: ``timestamp``, ``q`` (the controller's joints, without encoder noise),
        ``q_true``, ``tcp_pose`` (the controller's model at ``q``; ``tcp_pose_true``: the true
        model at ``q_true``), ``tcp_offset`` (the active TCP), ``moving``,
        ``runtime_state``, ``robot_mode``, ``safety_mode``, ``program``, ``rtde_clients``,
        ``skipped_cycles`` (cycles left unpublished because the controller process ran late) ..."""
        return dict(self._request("state"))

    def program_text(self) -> str:
        """The last program received on the script port."""
        return str(self._request("program_text"))

    def set_joint_positions(self, q: Sequence[float]) -> bool:
        """Place the arm at ``q`` (rad) at once; refused (False) while it moves."""
        return bool(self._request("set_q", [float(v) for v in q]))
