"""The UR driver's motion commands, and the control child seen from the caller's process.

:class:`URMotion` starts the control child (:mod:`.control`) at the first command that needs it,
sends it requests and waits for the answers, replaces it when its link is lost (sending a
command once more through the fresh child), and turns its reports into a :class:`MoveStatus`,
confirmed against the state stream (see :mod:`.robot`, "Motion"). Every command first passes
:meth:`Robot.check_motion`; a joint move also checks its path against the workspace box.
It is the layer of :class:`~.robot.URRobot` above the state stream
(:class:`~.stream.URStateStream`).
"""

from __future__ import annotations

import logging
import threading
import time
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.drivers.base import (
    Backoff,
    DriverIOError,
    DriverTimeout,
    MotionFailed,
    MoveStatus,
    ProtectiveStop,
    WorkspaceViolation,
)
from wristscan.drivers.ur.control import CtlSpec, control_main
from wristscan.drivers.ur.process import CHILD_LOG, recv_obj, spawn_child, stop_child
from wristscan.drivers.ur.stream import URStateStream

__all__ = ["URMotion"]

log = logging.getLogger(__name__)

_WAIT_SLICE_S = 0.05
_PATH_SAMPLES = 16
_FK_REFERENCE_TCP = (0.0, 0.0, 0.1, 0.0, 0.0, 0.0)
# A move reported done counts only once the stream shows the arm at the target.
_ARRIVAL_TOL_M = 1e-3
_ARRIVAL_TOL_RAD = 1e-2
_VERIFY_WAIT_S = 0.5
_STALE_NS = 1_000_000_000
_RETRY_ON_LOSS = frozenset({"move", "stop", "fk", "set_tcp"})


class _ControlLost(Exception):
    """The control child lost its link (or ended); a fresh one is needed."""


def _vec6(values: ArrayLike, name: str) -> NDArray[np.float64]:
    v = np.asarray(values, dtype=np.float64)
    if v.shape != (6,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} needs 6 finite numbers, got {np.asarray(values).tolist()!r}")
    return v


class URMotion(URStateStream):
    """The motion side of :class:`~.robot.URRobot` (an abstract layer: the life cycle comes
    from the facade)."""

    # Settings, set by URRobot.__init__ (the receive side declares the rest).
    command_timeout_s: float

    def _init_control(self) -> None:
        """The control side's state (once the settings are set)."""
        self._ctl_proc: BaseProcess | None = None
        self._ctl_conn: Connection | None = None
        self._ctl_lock = threading.RLock()
        self._ctl_seq = 0
        self._ctl_state = "idle"
        self._ctl_error: str | None = None
        self._ctl_backoff = Backoff(self.backoff_initial_s, self.backoff_max_s)
        self._ctl_retry_at = 0.0
        self._ctl_starts = 0
        self._ctl_suspect = False
        self._tcp_offset: NDArray[np.float64] | None = None
        self._move_status = MoveStatus.IDLE
        self._move_detail = ""
        self._move_target: tuple[str, NDArray[np.float64]] = ("l", np.zeros(6))

    def _on_receive_drop(self) -> None:
        # The control link most likely broke too; its child may not have noticed yet.
        self._ctl_suspect = self._ctl_proc is not None

    def _ctl_alive(self) -> bool:
        return self._ctl_proc is not None and self._ctl_proc.is_alive()

    def _drain_ctl(self) -> None:
        """Take the control child's notices (state, log lines) without waiting."""
        if not self._ctl_lock.acquire(blocking=False):
            return
        try:
            conn = self._ctl_conn
            while conn is not None and conn.poll(0):
                msg = recv_obj(conn)
                if msg[0] != "reply":
                    self._on_ctl_message(msg)
        except (EOFError, OSError):
            self._ctl_state = "lost"
        finally:
            self._ctl_lock.release()

    def _drop_ctl(self, reason: str) -> None:
        proc, conn = self._ctl_proc, self._ctl_conn
        self._ctl_proc = self._ctl_conn = None
        self._ctl_state = "down"
        self._ctl_error = reason
        if self._move_status is MoveStatus.MOVING:
            self._set_move(MoveStatus.FAILED, reason)
        stop_child(proc, conn, None, wait_s=2.0)

    def _stop_ctl(self) -> None:
        with self._ctl_lock:
            proc, conn = self._ctl_proc, self._ctl_conn
            if proc is None:
                return
            if conn is not None and proc.is_alive():
                try:
                    self._ctl_seq += 1
                    conn.send(("req", self._ctl_seq, "close", ()))
                    # The child stops the control script (and the arm) before it replies.
                    end = time.monotonic() + 5.0
                    while time.monotonic() < end and conn.poll(end - time.monotonic()):
                        msg = recv_obj(conn)
                        if msg[0] == "reply" and msg[1] == self._ctl_seq:
                            break
                except (EOFError, OSError):
                    pass
            self._ctl_proc = self._ctl_conn = None
            self._ctl_state = "idle"
            stop_child(proc, conn, None, wait_s=5.0)

    def _on_ctl_message(self, msg: tuple[Any, ...]) -> None:
        kind = msg[0]
        if kind == "log":
            CHILD_LOG.log(msg[1], "%s (control): %s", self.host, msg[2])
        elif kind == "state":
            name, info = msg[1], msg[2]
            self._ctl_state = name
            if name == "ready":
                self._ctl_error = None
                self._ctl_backoff.reset()
                self._tcp_offset = np.asarray(info["tcp"], dtype=np.float64)
            else:
                self._ctl_error = str(info)
                if name == "lost":
                    log.warning("robot %s: control link lost", self.host)

    def _ctl_connect(self, deadline: float, command: bool = False) -> Connection:
        """The control child's pipe, starting the child (and waiting for it) if needed. For a
        new ``command``, a child that may have lost its link (the receive link dropped since)
        is replaced first, so the command does not race with the child finding out."""
        if not self._open_flag:
            raise DriverIOError(f"robot {self.host}: not open")
        if command and self._ctl_suspect and self._ctl_proc is not None:
            self._drop_ctl("the receive link dropped meanwhile")
        if self._ctl_alive() and self._ctl_state == "ready":
            conn = self._ctl_conn
            assert conn is not None
            try:  # take a "lost" notice the child may have sent since the last request
                while conn.poll(0):
                    self._on_ctl_message(recv_obj(conn))
            except (EOFError, OSError):
                self._ctl_state = "lost"
            if self._ctl_state == "ready":
                return conn
        if self._ctl_proc is not None:
            self._drop_ctl(self._ctl_error or "the control process ended")
        wait = self._ctl_retry_at - time.monotonic()
        if wait > 0:
            time.sleep(min(wait, max(0.0, deadline - time.monotonic())))
        spec = CtlSpec(host=self.host, log_level=log.getEffectiveLevel())
        proc, parent_conn = spawn_child(control_main, (spec,), f"ur-rtde-control-{self.host}")
        self._ctl_proc, self._ctl_conn = proc, parent_conn
        self._ctl_suspect = False
        self._ctl_state = "connecting"
        self._ctl_starts += 1
        try:
            while self._ctl_state == "connecting":
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not parent_conn.poll(remaining):
                    raise DriverTimeout(
                        f"robot: the control interface of {self.host} did not connect in time"
                    )
                self._on_ctl_message(recv_obj(parent_conn))
        except (EOFError, OSError) as exc:
            self._ctl_state = "failed"
            self._ctl_error = f"the control process ended while connecting ({exc})"
        except DriverTimeout:
            self._ctl_retry_at = time.monotonic() + self._ctl_backoff.next_delay()
            self._drop_ctl("connect timeout")
            raise
        if self._ctl_state != "ready":
            error = self._ctl_error
            self._ctl_retry_at = time.monotonic() + self._ctl_backoff.next_delay()
            self._drop_ctl(error or "failed")
            raise DriverIOError(
                f"robot: cannot connect the control interface of {self.host}: {error}"
            )
        return parent_conn

    def _ctl_call(self, op: str, *args: Any, timeout_s: float | None = None) -> tuple[str, Any]:
        """One request to the control child; returns ``(status, payload)``. When the control
        link turns out to be lost, commands (not waits) are sent once more through a fresh
        control process: moves are absolute, so repeating one is harmless, and the fresh
        process's ur_rtde first stops the script the old one left running."""
        with self._ctl_lock:
            try:
                return self._ctl_call_once(op, args, timeout_s)
            except _ControlLost:
                if op not in _RETRY_ON_LOSS:
                    raise MotionFailed(f"robot: the control link to {self.host} was lost") from None
                log.warning("robot %s: control link lost; %r again on a new link", self.host, op)
            try:
                return self._ctl_call_once(op, args, timeout_s)
            except _ControlLost:
                raise MotionFailed(f"robot: the control link to {self.host} was lost") from None

    def _ctl_call_once(
        self, op: str, args: tuple[Any, ...], timeout_s: float | None
    ) -> tuple[str, Any]:
        with self._ctl_lock:
            conn = self._ctl_connect(
                time.monotonic() + self.connect_timeout_s, command=op in _RETRY_ON_LOSS
            )
            deadline = time.monotonic() + (timeout_s or self.command_timeout_s)
            self._ctl_seq += 1
            rid = self._ctl_seq
            try:
                conn.send(("req", rid, op, args))
                while True:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        self._drop_ctl(f"no answer to {op!r}")
                        raise DriverTimeout(
                            f"robot: the control process gave no answer to {op!r} in time"
                        )
                    if not conn.poll(min(remaining, 0.5)):
                        if not self._ctl_alive():
                            raise EOFError("the control process ended")
                        continue
                    msg = recv_obj(conn)
                    if msg[0] == "reply":
                        if msg[1] != rid:
                            continue  # the late answer to a request that timed out
                        if msg[2] == "lost":
                            raise _ControlLost(msg[3])
                        return msg[2], msg[3]
                    self._on_ctl_message(msg)
                    if msg[0] == "state" and msg[1] == "lost":
                        raise _ControlLost(str(msg[2]))
            except _ControlLost as exc:
                self._drop_ctl(f"the control link was lost ({exc})")
                raise
            except (EOFError, OSError) as exc:
                self._drop_ctl(f"the control process ended ({exc})")
                raise _ControlLost(str(exc)) from exc

    def _set_move(self, status: MoveStatus, detail: str = "") -> None:
        self._move_status, self._move_detail = status, detail

    def _arrived(self) -> tuple[bool, str]:
        """Whether the stream shows the arm at the last move's target (end-to-end check of a
        move the controller reports done); waits up to ``_VERIFY_WAIT_S`` for the stream."""
        kind, target = self._move_target
        t_done = time.monotonic_ns()
        deadline = time.monotonic() + _VERIFY_WAIT_S
        miss = ""
        while True:
            self._pump(0.02)
            s = self._latest
            if s is None or s.host_time_ns < t_done - _STALE_NS:
                if time.monotonic() >= deadline:
                    log.warning("robot %s: no fresh state to confirm the move", self.host)
                    return True, "not confirmed: no fresh robot state"
                continue
            if kind == "j":
                err = float(np.max(np.abs(s.q - target)))
                if err < _ARRIVAL_TOL_RAD:
                    return True, ""
                miss = f"a joint is {err:.4f} rad from the target"
            else:
                from wristscan.calib import se3

                T, G = se3.pose_to_matrix(s.tcp_pose), se3.pose_to_matrix(target)
                dp = float(np.linalg.norm(T[:3, 3] - G[:3, 3]))
                dr = float(se3.rotation_angle(T[:3, :3].T @ G[:3, :3]))
                if dp < _ARRIVAL_TOL_M and dr < _ARRIVAL_TOL_RAD:
                    return True, ""
                miss = f"the TCP is {dp * 1e3:.1f} mm / {dr:.4f} rad from the target"
            if time.monotonic() >= deadline:
                return False, f"reported done, but {miss}"

    def _apply_move_state(self, state: tuple[str, str]) -> MoveStatus:
        name, detail = state
        status = {
            "idle": MoveStatus.IDLE,
            "moving": MoveStatus.MOVING,
            "done": MoveStatus.DONE,
            "stopped": MoveStatus.STOPPED,
            "pstop": MoveStatus.PROTECTIVE_STOP,
            "failed": MoveStatus.FAILED,
        }.get(name, MoveStatus.FAILED)
        if status is MoveStatus.IDLE:
            # A fresh control child knows nothing of earlier moves.
            if self._move_status is MoveStatus.MOVING:
                self._set_move(MoveStatus.FAILED, "the control process lost track of the move")
            return self._move_status
        if status is MoveStatus.DONE and self._move_status is MoveStatus.MOVING:
            ok, why = self._arrived()
            if not ok:
                status, detail = MoveStatus.FAILED, why
            elif why:
                detail = why
        self._set_move(status, detail)
        return status

    def _raise_for(self, status: MoveStatus, what: str) -> None:
        detail = self._move_detail
        if status is MoveStatus.PROTECTIVE_STOP:
            raise ProtectiveStop(f"robot: {what} ended by a safety stop ({detail})")
        if status is MoveStatus.STOPPED:
            raise MotionFailed(f"robot: {what} was stopped before its target", status)
        if status is not MoveStatus.DONE:
            raise MotionFailed(f"robot: {what} failed: {detail or status.value}", status)

    def _move(
        self, kind: str, target: NDArray[np.float64], speed: float, accel: float, wait: bool
    ) -> None:
        what = f"move{kind.upper()}"
        status, payload = self._ctl_call("move", kind, target.tolist(), float(speed), float(accel))
        if status != "ok":
            if status == "pstop":
                self._set_move(MoveStatus.PROTECTIVE_STOP, str(payload))
                raise ProtectiveStop(f"robot: {what} refused: {payload}")
            self._set_move(MoveStatus.FAILED, str(payload))
            raise MotionFailed(f"robot: {what} refused: {payload}")
        self._move_target = (kind, target.copy())
        self._set_move(MoveStatus.MOVING)
        if wait:
            self._raise_for(self.wait_until_idle(None), what)

    def move_l(
        self, pose: ArrayLike, speed: float, accel: float, asynchronous: bool = False
    ) -> None:
        """Linear move of the TCP to UR pose ``[x, y, z, rx, ry, rz]`` (m, rad) at ``speed`` m/s
        and ``accel`` m/s^2. Blocking unless ``asynchronous``; see the module doc for the
        outcome and its exceptions."""
        p = _vec6(pose, "move_l pose")
        self.check_motion(p[:3], speed, accel, joint=False)
        self._move("l", p, speed, accel, not asynchronous)

    def move_j(self, q: ArrayLike, speed: float, accel: float, asynchronous: bool = False) -> None:
        """Joint move to ``q`` (rad) at ``speed`` rad/s and ``accel`` rad/s^2 (of the leading
        joint). With a workspace box, the TCP along the path must stay inside it."""
        qv = _vec6(q, "move_j q")
        self.check_motion(None, speed, accel, joint=True)
        if self.workspace_min_m is not None:
            self._check_joint_path(qv)
        self._move("j", qv, speed, accel, not asynchronous)

    def _check_joint_path(self, q_target: NDArray[np.float64]) -> None:
        latest = self.latest_state()
        if latest is None:
            qs = q_target[None, :]
        else:
            s = np.linspace(0.0, 1.0, _PATH_SAMPLES + 1)[1:, None]
            qs = latest.q[None, :] + s * (q_target - latest.q)[None, :]
        from wristscan.calib import kinematics, se3

        tcp2flange = se3.pose_to_matrix(self.tcp_offset())
        model = self.kinematic_model()
        if model is not None:
            xyz = np.asarray((kinematics.forward(model, qs) @ tcp2flange)[:, :3, 3])
        else:
            # Ask with a non-zero reference TCP, taken off again below: ur_rtde sends a request
            # without TCP (and, seen with 1.6.5, one with an all-zero TCP) in a recipe that
            # leaves the TCP registers alone, while the control script reads the TCP from them,
            # so the previous command's leftovers would be used.
            status, poses = self._ctl_call("fk", qs.tolist(), list(_FK_REFERENCE_TCP))
            if status != "ok":
                raise WorkspaceViolation(
                    f"robot: cannot check the joint path against the workspace box ({poses})"
                )
            ref2base = se3.pose_to_matrix(np.asarray(poses, dtype=np.float64))
            ref2flange = se3.pose_to_matrix(np.asarray(_FK_REFERENCE_TCP))
            tcp2base = ref2base @ se3.invert(ref2flange) @ tcp2flange
            xyz = np.asarray(tcp2base[:, :3, 3])
        lo, hi = self.workspace_min_m, self.workspace_max_m
        assert lo is not None and hi is not None
        outside = np.any((xyz < lo) | (xyz > hi), axis=1)
        if np.any(outside):
            i = int(np.argmax(outside))
            where = "target" if i == len(xyz) - 1 else f"path sample {i + 1}/{len(xyz)}"
            raise WorkspaceViolation(
                f"joint move: TCP at {np.round(xyz[i], 4).tolist()} m ({where}) outside the "
                f"workspace box {lo.tolist()} .. {hi.tolist()} m"
            )

    def stop(self, decel_m_s2: float | None = None, decel_rad_s2: float | None = None) -> None:
        """Decelerate the current move to a standstill (``decel_*`` default: the acceleration
        caps) and wait until the arm has stopped. Without a control link nothing this driver
        commanded can be moving, so it does nothing then."""
        with self._ctl_lock:
            if not self._ctl_alive() and self._move_status is not MoveStatus.MOVING:
                return
            status, payload = self._ctl_call(
                "stop",
                float(decel_m_s2 or self.max_accel_m_s2),
                float(decel_rad_s2 or self.max_joint_accel_rad_s2),
            )
            if status == "ok":
                self._apply_move_state(tuple(payload))
            else:
                raise MotionFailed(f"robot: stop failed: {payload}")

    def wait_until_idle(self, timeout: float | None = None) -> MoveStatus:
        """Wait for the current move to end; returns its final status, or
        :attr:`MoveStatus.MOVING` if it still moves after ``timeout`` seconds. Raises nothing
        for a failed move (a blocking move does)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            if self._move_status is not MoveStatus.MOVING:
                return self._move_status
            if not self._ctl_alive():
                self._set_move(MoveStatus.FAILED, self._ctl_error or "control process ended")
                return self._move_status
            remaining = _WAIT_SLICE_S if deadline is None else deadline - time.monotonic()
            if remaining <= 0:
                return MoveStatus.MOVING
            slice_s = min(_WAIT_SLICE_S, remaining)
            try:
                status, payload = self._ctl_call(
                    "wait", slice_s, timeout_s=slice_s + self.command_timeout_s
                )
            except MotionFailed as exc:
                self._set_move(MoveStatus.FAILED, str(exc))
                return MoveStatus.FAILED
            if status == "ok":
                self._apply_move_state(tuple(payload))

    def move_status(self) -> MoveStatus:
        """Status of the last motion command (asks the control child while one runs)."""
        with self._ctl_lock:
            if self._move_status is MoveStatus.MOVING and self._ctl_alive():
                try:
                    status, payload = self._ctl_call("status")
                except MotionFailed:
                    return self._move_status
                if status == "ok":
                    self._apply_move_state(tuple(payload))
            elif self._move_status is MoveStatus.MOVING:
                self._set_move(MoveStatus.FAILED, self._ctl_error or "control process ended")
            return self._move_status

    def is_moving(self) -> bool:
        """True while a commanded move runs."""
        return self.move_status() is MoveStatus.MOVING

    def connect_control(self) -> None:
        """Start the control link now instead of at the first command (uploads the control
        script, which takes over the robot's program). Needs ``motion_enabled``."""
        self._require_motion()
        with self._ctl_lock:
            self._ctl_connect(time.monotonic() + self.connect_timeout_s)

    def _require_motion(self) -> None:
        """Raise MotionNotEnabled unless motion is enabled (the caps trivially pass)."""
        self.check_motion(None, self.max_speed_m_s, self.max_accel_m_s2)

    def set_tcp(self, pose: ArrayLike) -> None:
        """Set the controller's active TCP (UR pose in the flange frame, m and rad); the
        reported ``tcp_pose`` follows it. Needs ``motion_enabled`` (it uses the control link)."""
        p = _vec6(pose, "set_tcp pose")
        self._require_motion()
        status, payload = self._ctl_call("set_tcp", p.tolist())
        if status != "ok":
            raise DriverIOError(f"robot: set_tcp failed: {payload}")
        self._tcp_offset = np.asarray(payload, dtype=np.float64)

    def tcp_offset(self) -> NDArray[np.float64]:
        """The controller's active TCP offset (UR pose in the flange frame); asks the control
        link, so it needs ``motion_enabled``."""
        if self._tcp_offset is None or not self._ctl_alive():
            self._require_motion()
            with self._ctl_lock:
                self._ctl_connect(time.monotonic() + self.connect_timeout_s)
        assert self._tcp_offset is not None
        return self._tcp_offset.copy()
