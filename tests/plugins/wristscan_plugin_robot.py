"""A robot driver written as a third party would write one: outside wristscan, registered through
the ``wristscan.robots`` entry point, built only on the public
:class:`~wristscan.drivers.base.Robot`
contract and on ur_rtde's own interfaces (``RTDEReceiveInterface``, ``RTDEControlInterface``),
with none of the built-in ``URRobot``'s machinery (no child processes, no native receiver).

The tests run wristscan's procedures through it against the simulated controller: if a procedure
needed something the contract does not declare, it would fail here.
"""

from __future__ import annotations

import threading
import time
from typing import Any, NoReturn

import numpy as np
import rtde_control
import rtde_receive
from numpy.typing import ArrayLike, NDArray

from wristscan.drivers.base import (
    DriverInitError,
    DriverIOError,
    MotionFailed,
    ProtectiveStop,
    Robot,
)
from wristscan.drivers.records import RobotState

_POLL_S = 0.0005
_MOVE_TIMEOUT_S = 120.0


class PluginRobot(Robot):
    """A UR robot over ur_rtde, in-process. ``frequency_hz``: RTDE output rate asked for (None:
    the controller's maximum)."""

    def __init__(
        self,
        host: str,
        frequency_hz: float | None = None,
        model: str = "UR5e",
        read_kinematics: bool = False,
        **limits: Any,
    ) -> None:
        super().__init__(**limits)
        self.host = host
        self.model = model
        self.frequency_hz = frequency_hz
        self._rx: Any = None
        self._ctl: Any = None
        self._last_t: float | None = None
        self._latest: RobotState | None = None
        self._lock = threading.Lock()  # ur_rtde's control interface is not thread-safe

    # --- Device ---------------------------------------------------------------------------
    def _open(self) -> None:
        try:
            self._rx = rtde_receive.RTDEReceiveInterface(
                self.host, -1.0 if self.frequency_hz is None else self.frequency_hz
            )
            if self.motion_enabled:
                self._ctl = rtde_control.RTDEControlInterface(self.host)
        except RuntimeError as exc:
            raise DriverInitError(f"plugin robot: cannot connect to {self.host}: {exc}") from exc

    def _close(self) -> None:
        for iface in (self._ctl, self._rx):
            if iface is not None:
                iface.disconnect()
        self._ctl = self._rx = None

    def _read_internal(self, timeout: float | None) -> RobotState | None:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            state = self._sample()
            if state is not None:
                with self._lock:
                    self._latest = state
                return state
            if deadline is not None and time.monotonic() >= deadline:
                return None
            time.sleep(_POLL_S)

    def _sample(self) -> RobotState | None:
        """The newest controller sample if it is new, read without tearing (the timestamp is
        read again after the values)."""
        rx = self._rx
        if not rx.isConnected():
            raise DriverIOError("plugin robot: RTDE connection lost")
        t = rx.getTimestamp()
        if t == self._last_t:
            return None
        host_ns = time.monotonic_ns()
        q, tcp = rx.getActualQ(), rx.getActualTCPPose()
        stopped = rx.isProtectiveStopped()
        if rx.getTimestamp() != t:
            return None  # torn: the next call reads the newer sample whole
        self._last_t = t
        return RobotState(
            controller_time_s=float(t),
            host_time_ns=host_ns,
            q=np.asarray(q, dtype=np.float64),
            tcp_pose=np.asarray(tcp, dtype=np.float64),
            protective_stop=bool(stopped),
        )

    # --- Robot ----------------------------------------------------------------------------
    def latest_state(self) -> RobotState | None:
        with self._lock:
            return self._latest

    def tcp_offset(self) -> NDArray[np.float64]:
        if self._ctl is None:
            return np.zeros(6)
        with self._lock:
            return np.asarray(self._ctl.getTCPOffset(), dtype=np.float64)

    def move_l(
        self, pose: ArrayLike, speed: float, accel: float, asynchronous: bool = False
    ) -> None:
        target = np.asarray(pose, dtype=np.float64).reshape(6)
        self.check_motion(target[:3], speed, accel)
        self._move("moveL", target, speed, accel, asynchronous)

    def move_j(self, q: ArrayLike, speed: float, accel: float, asynchronous: bool = False) -> None:
        target = np.asarray(q, dtype=np.float64).reshape(6)
        self.check_motion(None, speed, accel, joint=True)
        self._move("moveJ", target, speed, accel, asynchronous)

    def stop(self) -> None:
        if self._ctl is not None:
            with self._lock:
                self._ctl.stopL(2.0, False)

    def _move(
        self,
        command: str,
        target: NDArray[np.float64],
        speed: float,
        accel: float,
        asynchronous: bool,
    ) -> None:
        """An asynchronous ur_rtde move, then (unless ``asynchronous``) a wait that sleeps, so
        that the pipeline's threads keep running while the arm moves."""
        with self._lock:
            before = int(self._ctl.getAsyncOperationProgressEx().value())
            ok = getattr(self._ctl, command)(target.tolist(), speed, accel, True)
        if not ok:
            self._raise_failed(f"the controller refused {command}")
        if asynchronous:
            return
        seen_running = False
        deadline = time.monotonic() + _MOVE_TIMEOUT_S
        while time.monotonic() < deadline:
            with self._lock:
                st = self._ctl.getAsyncOperationProgressEx()
            if st.isAsyncOperationRunning():
                seen_running = True
            elif seen_running or int(st.value()) != before:
                if self._rx.isProtectiveStopped():
                    self._raise_failed(f"{command} ended early")
                return
            if self._rx.isProtectiveStopped():
                self._raise_failed(f"{command} interrupted")
            time.sleep(0.005)
        raise MotionFailed(f"plugin robot: {command} did not finish in {_MOVE_TIMEOUT_S:.0f} s")

    def _raise_failed(self, what: str) -> NoReturn:
        if self._rx is not None and self._rx.isProtectiveStopped():
            raise ProtectiveStop(f"plugin robot: protective stop ({what})")
        raise MotionFailed(f"plugin robot: {what}")
