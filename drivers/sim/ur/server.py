"""The simulated controller's process: its ports, the cycle clock and the parent's requests.

:func:`run_controller` is the body of the process that
:class:`~.controller.SimulatedController` starts. It listens on RTDE (:mod:`.rtde_server`),
the dashboard (:mod:`.dashboard`), the script port (programs, for
:meth:`~.program.ProgramHost.start_program`) and, when asked, the primary interface
(:mod:`.primary`); it runs the controller's cycles on time (:class:`~.engine.Controller`) and
answers the parent over its pipe.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
import time
from multiprocessing.connection import Connection
from typing import Any

from wristscan.drivers.sim.truth import TruthRing
from wristscan.drivers.sim.ur import dashboard
from wristscan.drivers.sim.ur.config import (
    DASHBOARD_PORT,
    RTDE_PORT,
    SCRIPT_PORT,
    ControllerConfig,
)
from wristscan.drivers.sim.ur.engine import Controller
from wristscan.drivers.sim.ur.primary import KinematicsValues, PrimaryServer
from wristscan.drivers.sim.ur.rtde_server import RtdeConnection

__all__ = ["run_controller"]

log = logging.getLogger(__name__)

_EARLY_NS = 1_000_000
"""The clock loop wakes this long before a cycle is due and sends it at the due time: a real
controller sends within microseconds of its cycle, and a simulator sending up to a timer
resolution late would shift the robot stream's timing by that much."""


class _LineProtocol(asyncio.Protocol):
    """Base for the text ports: tracks the transport for shutdown."""

    def __init__(self, ctrl: Controller) -> None:
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

    def __init__(self, ctrl: Controller) -> None:
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


class _Server:
    """The controller in its event loop: listening ports, cycle clock, parent pipe, watchdog."""

    def __init__(
        self,
        config: ControllerConfig,
        truth_ring_name: str | None,
        conn: Connection | None,
        stop_event: Any,
    ) -> None:
        self.config = config
        self.conn = conn
        self.stop_event = stop_event
        self.ring = TruthRing.attach(truth_ring_name) if truth_ring_name else None
        self.ctrl = Controller(config, self.ring)
        self.servers: list[asyncio.base_events.Server] = []
        self.primary: PrimaryServer | None = None

    async def run(self) -> None:
        ctrl, conn, config = self.ctrl, self.conn, self.config
        loop = asyncio.get_running_loop()
        ctrl.begin(time.monotonic_ns())
        try:
            await self._listen()
        except OSError as e:
            if self.primary is not None:
                self.primary.close()
            for s in self.servers:
                s.close()
            if conn is not None:
                conn.send(("error", f"cannot listen on {config.host}: {e}"))
            if self.ring is not None:
                self.ring.close()
            return
        if conn is not None:
            loop.add_reader(conn.fileno(), self._on_control)
            conn.send(("ready", {"host": config.host, "start_time_ns": ctrl.start_ns}))
        tasks = [asyncio.create_task(self._clock()), asyncio.create_task(self._watchdog())]
        try:
            await ctrl.stopping.wait()
        finally:
            await self._shut_down(tasks)

    async def _listen(self) -> None:
        ctrl, config = self.ctrl, self.config
        loop = asyncio.get_running_loop()
        for port, factory in (
            (RTDE_PORT, lambda: RtdeConnection(ctrl)),
            (DASHBOARD_PORT, lambda: _DashboardProtocol(ctrl)),
            (SCRIPT_PORT, lambda: _ScriptProtocol(ctrl)),
        ):
            self.servers.append(
                await loop.create_server(factory, config.host, port, reuse_address=True)
            )
        if config.primary_interface:
            self.primary = await PrimaryServer.start(
                config.host, KinematicsValues.from_model(ctrl.model), version=ctrl.version
            )

    def _on_control(self) -> None:
        conn, ctrl = self.conn, self.ctrl
        assert conn is not None
        try:
            while conn.poll():
                msg = conn.recv()
                conn.send(_control(ctrl, msg))
        except (EOFError, OSError):
            ctrl.stopping.set()

    async def _clock(self) -> None:
        ctrl = self.ctrl
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

    async def _watchdog(self) -> None:
        ctrl, stop_event = self.ctrl, self.stop_event
        parent = os.getppid()
        while not ctrl.stopping.is_set():
            if (stop_event is not None and stop_event.is_set()) or os.getppid() != parent:
                ctrl.stopping.set()
                break
            await asyncio.sleep(0.05)

    async def _shut_down(self, tasks: list[asyncio.Task[None]]) -> None:
        ctrl, conn = self.ctrl, self.conn
        for t in tasks:
            t.cancel()
        for t in tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await t
        if conn is not None:
            asyncio.get_running_loop().remove_reader(conn.fileno())
        for s in self.servers:
            s.close()
        if self.primary is not None:
            self.primary.close()
        ctrl.drop_connections()
        for tr in list(ctrl.other_transports):
            tr.close()
        for s in self.servers:
            await s.wait_closed()
        if self.primary is not None:
            await self.primary.wait_closed()
        if self.ring is not None:
            self.ring.close()


def _control(ctrl: Controller, msg: tuple[Any, ...]) -> tuple[str, Any]:
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
    :class:`~.controller.SimulatedController`). The controller stops on a ``("stop",)`` request,
    when ``stop_event`` (a ``multiprocessing.Event``) is set, when the pipe closes, or when the
    parent process dies.
    """
    if not logging.getLogger().handlers:
        logging.basicConfig(
            level=config.log_level, format=f"sim-ur {config.host} %(levelname)s %(message)s"
        )
    asyncio.run(_serve(config, truth_ring_name, conn, stop_event))


async def _serve(
    config: ControllerConfig,
    truth_ring_name: str | None,
    conn: Connection | None,
    stop_event: Any,
) -> None:
    await _Server(config, truth_ring_name, conn, stop_event).run()
