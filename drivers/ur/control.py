"""The UR driver's control child: ur_rtde's ``RTDEControlInterface`` and a dashboard client.

It runs in a process of its own (see :mod:`.robot`, "Why child processes" and "Motion"), started
at the first motion command, and answers the caller's requests (``move``, ``wait``, ``status``,
``stop``, ``fk``, ``set_tcp``, ``close``) with ``("reply", id, status, payload)``; status is
``"ok"``, ``"failed"``, ``"pstop"`` (a safety stop) or ``"lost"`` (the control link broke).
Moves are always issued asynchronously and tracked here, so a stop works while the caller waits.
At the first sign of a lost link (ur_rtde's console messages, ``isConnected()``) the child says
``("state", "lost", ...)`` and ends. The caller's side is :class:`~.motion.URMotion`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

from wristscan.drivers.ur.process import ChildLink, OutputPump, child_setup

__all__ = ["CtlSpec", "control_main"]

log = logging.getLogger(__name__)

_LOSS_GRACE_S = 0.1


@dataclass(frozen=True)
class CtlSpec:
    """Which controller the control child drives."""

    host: str
    log_level: int
    script_start_timeout_s: float = 5.0


def control_main(spec: CtlSpec, conn: Connection) -> None:
    """Body of the control child."""
    link = ChildLink(conn)
    trouble = threading.Event()
    output = child_setup(link, spec.log_level, trouble)
    try:
        import dashboard_client
        import rtde_control
    except ImportError as exc:
        link.send_obj(("state", "failed", f"ur_rtde is not installed ({exc}): pip install ur-rtde"))
        return
    session = _ControlSession(spec, conn, link, output, rtde_control, dashboard_client)
    session.run()
    # Leave without ur_rtde's destructors (``session`` holds the interface until here): after a
    # broken link ur_rtde may have two threads on one socket, and its disconnect() sleeps 500 ms
    # by design; the OS closes the sockets.
    os._exit(0)


@dataclass
class _Move:
    kind: str
    before: int
    op_id: int | None = None
    """Async operation id of this move, when it was seen running right after the command."""
    seen_running: bool = False
    stop_requested: bool = False
    status: str = "moving"
    detail: str = ""


class _ControlSession:
    """The control child's work: ur_rtde's control interface and a dashboard client, serving
    the caller's requests (``("req", id, op, args)``) one at a time until the link breaks or the
    caller closes it. Moves are always asynchronous; the session tracks them itself."""

    def __init__(
        self,
        spec: CtlSpec,
        conn: Connection,
        link: ChildLink,
        output: OutputPump,
        rtde_control: Any,
        dashboard_client: Any,
    ) -> None:
        self.spec = spec
        self.conn = conn
        self.link = link
        self.output = output
        assert output.trouble is not None
        self.trouble = output.trouble
        self.rc = rtde_control
        self.dc = dashboard_client
        self.ctrl: Any = None
        self.dash: Any = None
        self.move: _Move | None = None

    # --- helpers --------------------------------------------------------------------------
    def safety_status(self) -> str | None:
        """Dashboard safety status word (``NORMAL``, ``PROTECTIVE_STOP`` ...), None if unknown."""
        for _ in range(2):
            try:
                if self.dash is None or not self.dash.isConnected():
                    self.dash = self.dc.DashboardClient(self.spec.host)
                    self.dash.connect(2000)
                text = str(self.dash.safetystatus())
                return text.split(":")[-1].strip().upper()
            except Exception as exc:
                log.warning("dashboard query failed: %s", exc)
                self.dash = None
        return None

    def classify_program_stop(self) -> tuple[str, str]:
        status = self.safety_status()
        if status is None:
            return "failed", "the control program stopped (safety status unknown)"
        if status in ("NORMAL", "REDUCED"):
            return "failed", "the control program stopped"
        return "pstop", status

    def ensure_program(self) -> tuple[str, str] | None:
        """Make the control script run; an error tuple when it cannot."""
        if self.ctrl.isProgramRunning():
            return None
        status, detail = self.classify_program_stop()
        if status == "pstop":
            return status, f"the robot is in a safety stop ({detail})"
        if not self.ctrl.reuploadScript():
            return "failed", "cannot upload the control script"
        deadline = time.monotonic() + self.spec.script_start_timeout_s
        while time.monotonic() < deadline:
            if self.ctrl.isProgramRunning():
                return None
            time.sleep(0.01)
        return "failed", "the control script did not start"

    def update_move(self) -> None:
        m = self.move
        if m is None or m.status != "moving":
            return
        if not self.ctrl.isProgramRunning():
            m.status, m.detail = self.classify_program_stop()
            return
        st = self.ctrl.getAsyncOperationProgressEx()
        if st.isAsyncOperationRunning():
            m.seen_running = True
            return
        if m.op_id is not None and int(st.operationId()) != m.op_id:
            # Another control script replaced ours (a late upload from a previous session).
            m.status, m.detail = "failed", "the control program was replaced"
            return
        if m.seen_running or st.value() != m.before:
            m.status = "stopped" if m.stop_requested else "done"

    def move_state(self) -> tuple[str, str]:
        if self.move is None:
            return "idle", ""
        return self.move.status, self.move.detail

    # --- operations -----------------------------------------------------------------------
    def op_move(self, kind: str, target: list[float], speed: float, accel: float) -> Any:
        if self.move is not None and self.move.status == "moving":
            self.move.status, self.move.detail = "stopped", "superseded by a new command"
        err = self.ensure_program()
        if err is not None:
            return err
        before = int(self.ctrl.getAsyncOperationProgressEx().value())
        if kind == "l":
            ok = self.ctrl.moveL(target, speed, accel, True)
        else:
            ok = self.ctrl.moveJ(target, speed, accel, True)
        if not ok:
            if not self.ctrl.isProgramRunning():
                return self.classify_program_stop()
            return "failed", f"the controller refused move{kind.upper()}"
        self.move = _Move(kind, before)
        st = self.ctrl.getAsyncOperationProgressEx()
        if st.isAsyncOperationRunning():
            self.move.op_id = int(st.operationId())
            self.move.seen_running = True
        return "ok", None

    def op_wait(self, slice_s: float) -> Any:
        deadline = time.monotonic() + slice_s
        while True:
            self.update_move()
            state = self.move_state()
            if state[0] != "moving" or time.monotonic() >= deadline or self.link_lost():
                return "ok", state
            time.sleep(0.002)

    def op_stop(self, decel_l: float, decel_j: float) -> Any:
        m = self.move
        self.update_move()
        if m is None or m.status != "moving":
            return "ok", self.move_state()
        m.stop_requested = True
        if m.kind == "l":
            self.ctrl.stopL(decel_l, False)
        else:
            self.ctrl.stopJ(decel_j, False)
        self.update_move()
        if m.status == "moving":
            m.status = "stopped"
        return "ok", self.move_state()

    def op_fk(self, qs: list[list[float]], tcp: list[float]) -> Any:
        err = self.ensure_program()
        if err is not None:
            return err
        poses = [list(self.ctrl.getForwardKinematics(q, tcp)) for q in qs]
        if any(len(p) != 6 for p in poses):
            return "failed", "the controller did not return forward kinematics"
        return "ok", poses

    def op_set_tcp(self, pose: list[float]) -> Any:
        err = self.ensure_program()
        if err is not None:
            return err
        if not self.ctrl.setTcp(pose):
            return "failed", "the controller refused setTcp"
        return "ok", list(self.ctrl.getTCPOffset())

    def handle(self, op: str, args: tuple[Any, ...]) -> Any:
        if op == "move":
            return self.op_move(*args)
        if op == "wait":
            return self.op_wait(*args)
        if op == "status":
            self.update_move()
            return "ok", self.move_state()
        if op == "stop":
            return self.op_stop(*args)
        if op == "fk":
            return self.op_fk(*args)
        if op == "set_tcp":
            return self.op_set_tcp(*args)
        return "failed", f"unknown control operation {op!r}"

    # --- main loop ------------------------------------------------------------------------
    def run(self) -> bool:
        """Serve requests; True after an orderly close, False when the link broke."""
        try:
            self.ctrl = self.rc.RTDEControlInterface(
                self.spec.host, flags=self.rc.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
            )
        except Exception as exc:
            self.link.send_obj(("state", "failed", f"{type(exc).__name__}: {exc}"))
            return False
        tcp = list(self.ctrl.getTCPOffset())
        self.link.send_obj(("state", "ready", {"tcp": tcp}))
        while True:
            if self.link_lost():
                if self.move is not None and self.move.status == "moving":
                    self.move.status, self.move.detail = "failed", "the control link was lost"
                self.link.send_obj(("state", "lost", "the control link was lost"))
                return False
            active = self.move is not None and self.move.status == "moving"
            try:
                if not self.conn.poll(0.005 if active else 0.05):
                    if active:
                        self.update_move()
                    continue
                msg = self.conn.recv()
            except (EOFError, OSError):
                self.close()
                return True
            _, rid, op, args = msg
            if op == "close":
                self.close()
                self.link.send_obj(("reply", rid, "ok", None))
                return True
            if self.link_lost():
                self.link.send_obj(("reply", rid, "lost", "the control link was lost"))
                continue  # the check at the top of the loop reports it and ends the session
            try:
                status, payload = self.handle(op, args)
            except Exception as exc:  # a ur_rtde error must reach the caller, not kill us
                status, payload = "failed", f"{op}: {type(exc).__name__}: {exc}"
            if status != "ok":
                # A command that fails just as the link breaks fails because of it: give
                # ur_rtde's messages a moment to arrive before blaming the command.
                time.sleep(_LOSS_GRACE_S)
                if self.link_lost():
                    status, payload = "lost", "the control link was lost"
            self.link.send_obj(("reply", rid, status, payload))

    def link_lost(self) -> bool:
        self.output.drain()  # take in ur_rtde's messages written so far
        return self.trouble.is_set() or not self.ctrl.isConnected()

    def close(self) -> None:
        ctrl = self.ctrl
        if ctrl is None:
            return
        with contextlib.suppress(Exception):
            if ctrl.isConnected() and ctrl.isProgramRunning():
                ctrl.stopScript()  # ends the control program, and with it any motion
