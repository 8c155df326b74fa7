"""Device ABCs: one small base class per device kind, one exception tree, shared bookkeeping.

The public methods (``open``, ``close``, ``read``) handle idempotence, deadlines and counters; a
backend implements the ``_open``, ``_close`` and ``_read_internal`` hooks only (the python-can
``BusABC`` pattern). ``read`` returns ``None`` when nothing arrived before the timeout, so a caller
polls without exceptions; I/O faults that the driver cannot recover from raise ``DriverIOError``.
"""

from __future__ import annotations

import enum
import logging
import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Generic, Self, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.drivers.records import Profile, ProfileBlock, RobotState, TableState

if TYPE_CHECKING:
    from wristscan.calib.kinematics import DHParams

__all__ = [
    "Backoff",
    "Counters",
    "Device",
    "DriverError",
    "DriverIOError",
    "DriverInitError",
    "DriverNotAvailable",
    "DriverTimeout",
    "Health",
    "LinkState",
    "MotionFailed",
    "MotionNotEnabled",
    "MoveStatus",
    "ProfileSensor",
    "ProtectiveStop",
    "RawFrameLog",
    "Robot",
    "RotaryTable",
    "WorkspaceViolation",
]

log = logging.getLogger(__name__)

R = TypeVar("R")


class DriverError(Exception):
    """Base of every driver error."""


class DriverNotAvailable(DriverError):
    """The driver cannot be loaded here (a missing optional dependency: the message names the
    extra to install)."""


class DriverInitError(DriverError):
    """The device was found but could not be opened or configured (bad address, refused, bad
    reply to the handshake)."""


class DriverIOError(DriverError):
    """The link failed while in use and could not be recovered."""


class DriverTimeout(DriverError):
    """An operation with a deadline (open, a command) did not complete in time."""


class MotionNotEnabled(DriverError):
    """A motion command was refused because motion is not enabled in the configuration."""


class WorkspaceViolation(DriverError):
    """A motion command was refused because its target or speed is outside the configured limits."""


class MoveStatus(enum.Enum):
    """Outcome of a robot's last motion command."""

    IDLE = "idle"
    """No command issued since the control link started."""
    MOVING = "moving"
    DONE = "done"
    """Reached the target (confirmed by the state stream)."""
    STOPPED = "stopped"
    """Decelerated by :meth:`Robot.stop` before reaching the target."""
    PROTECTIVE_STOP = "protective_stop"
    """Ended by a safety stop (protective, safeguard or emergency)."""
    FAILED = "failed"
    """Refused by the controller, program stopped, or control link lost."""


class MotionFailed(DriverIOError):
    """A motion command did not complete; ``status`` says how it ended."""

    def __init__(self, message: str, status: MoveStatus = MoveStatus.FAILED) -> None:
        super().__init__(message)
        self.status = status


class ProtectiveStop(MotionFailed):
    """The robot is, or went, into a safety stop (protective, safeguard or emergency)."""

    def __init__(self, message: str) -> None:
        super().__init__(message, MoveStatus.PROTECTIVE_STOP)


class LinkState(enum.Enum):
    CLOSED = "closed"
    CONNECTING = "connecting"
    OPEN = "open"
    RECONNECTING = "reconnecting"
    FAILED = "failed"


@dataclass
class Counters:
    """What a driver has seen since it was opened."""

    received: int = 0
    """Records delivered to the caller."""
    malformed: int = 0
    """Frames rejected by the decoder (truncated, bad CRC, bad checksum, garbage)."""
    lost: int = 0
    """Records the device sent that never arrived, from frame-counter gaps."""
    shed: int = 0
    """Records shed on purpose before they were read (kernel-side admission under overload,
    :meth:`ProfileSensor.set_admission`): the frame-counter gaps while it is in force."""
    duplicates: int = 0
    """Records suppressed because their counter was already delivered."""
    reordered: int = 0
    """Records that arrived after a newer one (delivered, counted)."""
    reconnects: int = 0
    bytes: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


@dataclass
class Health:
    state: LinkState
    counters: Counters
    last_error: str | None = None
    state_since_ns: int = 0
    detail: dict[str, Any] = field(default_factory=dict)


class Backoff:
    """Exponential backoff for reconnect attempts: initial, doubled per failure, capped."""

    def __init__(self, initial_s: float = 0.05, maximum_s: float = 2.0, factor: float = 2.0):
        self.initial_s = initial_s
        self.maximum_s = maximum_s
        self.factor = factor
        self._next = initial_s

    def next_delay(self) -> float:
        d = self._next
        self._next = min(self._next * self.factor, self.maximum_s)
        return d

    def reset(self) -> None:
        self._next = self.initial_s


class RawFrameLog:
    """The last few raw frames, dumped with an error so malformed input can be diagnosed."""

    def __init__(self, size: int = 8) -> None:
        self._frames: deque[bytes] = deque(maxlen=size)

    def add(self, frame: bytes | bytearray | memoryview) -> None:
        self._frames.append(bytes(frame[:256]))

    def dump(self) -> str:
        return " | ".join(f.hex() for f in self._frames)


class Device(ABC, Generic[R]):
    """Common life cycle: open/close (idempotent, context manager), read with timeout, iterate,
    health and counters."""

    kind: ClassVar[str] = "device"

    def __init__(self) -> None:
        self.counters = Counters()
        self._state = LinkState.CLOSED
        self._state_since_ns = time.monotonic_ns()
        self._last_error: str | None = None
        self._lock = threading.RLock()
        self._open_flag = False
        self.raw_log = RawFrameLog()

    # --- life cycle -------------------------------------------------------------------------
    def open(self) -> Self:
        with self._lock:
            if self._open_flag:
                return self
            self._set_state(LinkState.CONNECTING)
            try:
                self._open()
            except DriverError as exc:
                self._set_state(LinkState.FAILED, str(exc))
                raise
            except OSError as exc:
                self._set_state(LinkState.FAILED, str(exc))
                raise DriverInitError(f"{self.kind}: cannot open: {exc}") from exc
            self._open_flag = True
            self._set_state(LinkState.OPEN)
            return self

    def close(self) -> None:
        with self._lock:
            if not self._open_flag:
                return
            self._open_flag = False
            try:
                self._close()
            finally:
                self._set_state(LinkState.CLOSED)

    @property
    def is_open(self) -> bool:
        return self._open_flag

    @property
    def stamped_on_receipt(self) -> bool:
        """True when records carry a receipt time taken before :meth:`read` is called (by the
        kernel, or by a receiving process of the driver's own): a caller may then read them
        late and in bursts without changing their timing."""
        return False

    def __enter__(self) -> Self:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- reading ----------------------------------------------------------------------------
    def read(self, timeout: float | None = None) -> R | None:
        """Next record, or ``None`` if none arrived within ``timeout`` seconds (``None``: wait)."""
        if not self._open_flag:
            raise DriverIOError(f"{self.kind}: read on a closed device")
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            rec = self._read_internal(remaining)
            if rec is not None:
                self.counters.received += 1
                return rec
            if deadline is not None and time.monotonic() >= deadline:
                return None
            if not self._open_flag:
                return None

    def read_for(self, duration_s: float, drain: bool = True) -> list[R]:
        """Every record that arrives within ``duration_s`` seconds, then (``drain``) whatever
        the driver already holds at the end, without waiting."""
        out: list[R] = []
        end = time.monotonic() + duration_s
        while (remaining := end - time.monotonic()) > 0:
            rec = self.read(timeout=min(0.1, remaining))
            if rec is not None:
                out.append(rec)
        while drain and (rec := self.read(timeout=0)) is not None:
            out.append(rec)
        return out

    def __iter__(self) -> Iterator[R]:
        while self._open_flag:
            rec = self.read(timeout=0.1)
            if rec is not None:
                yield rec

    def health(self) -> Health:
        return Health(
            state=self._state,
            counters=Counters(**self.counters.as_dict()),
            last_error=self._last_error,
            state_since_ns=self._state_since_ns,
            detail=self._health_detail(),
        )

    # --- for subclasses ---------------------------------------------------------------------
    def _set_state(self, state: LinkState, error: str | None = None) -> None:
        if state is not self._state:
            log.info(
                "%s: %s -> %s%s",
                self.kind,
                self._state.value,
                state.value,
                f" ({error})" if error else "",
            )
            self._state = state
            self._state_since_ns = time.monotonic_ns()
        if error is not None:
            self._last_error = error

    def _health_detail(self) -> dict[str, Any]:
        return {}

    @abstractmethod
    def _open(self) -> None: ...

    @abstractmethod
    def _close(self) -> None: ...

    @abstractmethod
    def _read_internal(self, timeout: float | None) -> R | None:
        """One record or ``None`` after at most ``timeout`` seconds. Reconnects by itself (with
        :class:`Backoff`) after a dropped link, counting ``reconnects``."""


class ProfileSensor(Device[Profile]):
    """A laser profile sensor."""

    kind = "sensor"
    admission: float | None = None
    """The fraction of profile frames let through before reading (None: all), see
    :meth:`set_admission`."""

    def __init__(self, sensor_id: int = 0) -> None:
        super().__init__()
        self.sensor_id = sensor_id
        self._last_counter: int | None = None
        """The frame counter of the last delivered profile (None: no history)."""
        self._held_error: DriverError | None = None
        self._gaps_shed = False
        """Frame-counter gaps are booked as ``shed``, not ``lost`` (admission in force)."""

    def set_admission(self, fraction: float | None) -> bool:
        """Admit only ``fraction`` of the profile frames, evenly spread, shedding the rest
        before they are read (None or 1: all); the gaps are counted as ``shed``. False when
        this driver cannot shed before reading (the caller sheds after reading instead)."""
        return False

    def _count_missing(self, n: int) -> None:
        if self._gaps_shed:
            self.counters.shed += n
        else:
            self.counters.lost += n

    def read_blocks(self, max_profiles: int = 4096) -> list[ProfileBlock]:
        """What the driver holds now, without waiting, as blocks of profiles of equal length
        (at most ``max_profiles`` profiles): the hot path's read. This default collects
        :meth:`read` records; drivers that can decode many profiles at once override it. A
        driver error met after some profiles is raised by the next call (nothing is lost)."""
        if self._held_error is not None:
            exc, self._held_error = self._held_error, None
            raise exc
        records: list[Profile] = []
        for _ in range(max_profiles):
            try:
                rec = self.read(timeout=0.0)
            except DriverError as exc:
                if not records:
                    raise
                self._held_error = exc
                break
            if rec is None:
                break
            records.append(rec)
        return ProfileBlock.from_profiles(records)

    def _account_counter(self, counter: int, modulo: int = 1 << 64) -> bool:
        """Book-keep a frame counter: count gaps as lost, drop duplicates. Returns False for a
        frame that must not be delivered (duplicate or older than the last delivered)."""
        last = self._last_counter
        if last is None:
            self._last_counter = counter
            return True
        step = (counter - last) % modulo
        if step == 0:
            self.counters.duplicates += 1
            return False
        if step > modulo // 2:  # behind the last delivered frame: late or duplicated
            self.counters.reordered += 1
            return False
        if step > 1:
            self._count_missing(step - 1)
        self._last_counter = counter
        return True


def _opt_vec(v: ArrayLike | None) -> np.ndarray | None:
    return None if v is None else np.asarray(v, dtype=np.float64)


class Robot(Device[RobotState]):
    """A robot controller: a state stream, and motion commands when motion is enabled.

    The procedures (calibration, scanning, teaching) use, besides the state stream: the motion
    commands, :meth:`latest_state`, :meth:`tcp_offset`, :meth:`kinematic_model` and the
    attributes declared below. A plug-in robot implements the abstract methods and sets the
    identity attributes it knows; everything else has a working default.
    """

    kind = "robot"

    model: str | DHParams | None = None
    """Nominal kinematic model, a UR model name (``"UR5e"``) or DH parameters; None if unknown."""
    serial: str | None = None
    """The robot's serial number, when the driver knows it."""
    host: str | None = None
    """Address of the controller (named in messages); None for a link without one."""
    motion_enabled: bool
    """Unless True, every motion command is refused with :class:`MotionNotEnabled`."""
    max_speed_m_s: float
    """Cap on the TCP speed of linear moves (m/s); the procedures plan within it."""
    max_accel_m_s2: float
    """Cap on the TCP acceleration of linear moves (m/s^2)."""
    max_joint_speed_rad_s: float
    """Cap on the joint speed of joint moves (rad/s)."""
    max_joint_accel_rad_s2: float
    """Cap on the joint acceleration of joint moves (rad/s^2)."""
    workspace_min_m: np.ndarray | None
    """Lower corner of the box the TCP must stay in (base frame, m); None: no box."""
    workspace_max_m: np.ndarray | None
    """Upper corner of that box."""

    def __init__(
        self,
        motion_enabled: bool = False,
        max_speed_m_s: float = 0.25,
        max_accel_m_s2: float = 1.2,
        max_joint_speed_rad_s: float = 1.0,
        max_joint_accel_rad_s2: float = 1.4,
        workspace_min_m: ArrayLike | None = None,
        workspace_max_m: ArrayLike | None = None,
    ) -> None:
        super().__init__()
        self.motion_enabled = motion_enabled
        self.max_speed_m_s = max_speed_m_s
        self.max_accel_m_s2 = max_accel_m_s2
        self.max_joint_speed_rad_s = max_joint_speed_rad_s
        self.max_joint_accel_rad_s2 = max_joint_accel_rad_s2
        self.workspace_min_m = (
            None if workspace_min_m is None else np.asarray(workspace_min_m, float)
        )
        self.workspace_max_m = (
            None if workspace_max_m is None else np.asarray(workspace_max_m, float)
        )
        self._last_read: RobotState | None = None

    def check_motion(
        self, target_xyz_m: ArrayLike | None, speed: float, accel: float, joint: bool = False
    ) -> None:
        """Refuse a command unless motion is enabled, the speeds are within the caps and the
        target lies inside the workspace box."""
        if not self.motion_enabled:
            raise MotionNotEnabled(
                "motion is not enabled: set [robot] motion_enabled = true in the configuration"
            )
        vmax = self.max_joint_speed_rad_s if joint else self.max_speed_m_s
        amax = self.max_joint_accel_rad_s2 if joint else self.max_accel_m_s2
        unit = "rad/s" if joint else "m/s"
        if not 0 < speed <= vmax:
            raise WorkspaceViolation(f"speed {speed:g} {unit} outside (0, {vmax:g}]")
        if not 0 < accel <= amax:
            raise WorkspaceViolation(f"acceleration {accel:g} {unit}^2 outside (0, {amax:g}]")
        if target_xyz_m is not None and self.workspace_min_m is not None:
            p = np.asarray(target_xyz_m, float)
            lo, hi = self.workspace_min_m, self.workspace_max_m
            assert hi is not None
            if np.any(p < lo) or np.any(p > hi):
                raise WorkspaceViolation(
                    f"target {np.round(p, 4).tolist()} m outside the workspace box "
                    f"{lo.tolist()} .. {hi.tolist()} m"
                )

    def read(self, timeout: float | None = None) -> RobotState | None:
        state = super().read(timeout)
        if state is not None:
            self._last_read = state
        return state

    def latest_state(self) -> RobotState | None:
        """The newest state known, without waiting; None before the first. By default the
        newest one :meth:`read` returned (the acquisition reads the stream all along); a driver
        that receives in the background returns the newest received, read or not."""
        return self._last_read

    @abstractmethod
    def tcp_offset(self) -> NDArray[np.float64]:
        """The controller's active TCP: its UR pose ``[x, y, z, rx, ry, rz]`` in the flange
        frame (m, rad). The procedures take the flange pose from the reported TCP pose with it."""

    def kinematic_model(self) -> DHParams | None:
        """The robot's own kinematic model (e.g. its factory calibration), or None: the
        procedures then use the configured nominal model."""
        return None

    @abstractmethod
    def move_l(
        self, pose: ArrayLike, speed: float, accel: float, asynchronous: bool = False
    ) -> None:
        """Linear move of the TCP to UR pose ``p[x,y,z,rx,ry,rz]`` (m, rad), speed m/s."""

    @abstractmethod
    def move_j(self, q: ArrayLike, speed: float, accel: float, asynchronous: bool = False) -> None:
        """Joint move to ``q`` (rad), speed rad/s."""

    @abstractmethod
    def stop(self) -> None:
        """Decelerate and stop any motion."""


class RotaryTable(Device[TableState]):
    """A rotary table read through its encoder; turned on command for calibration."""

    kind = "table"

    @abstractmethod
    def angle(self) -> float:
        """Current angle (rad), read now."""

    @abstractmethod
    def move_to(self, angle_rad: float, wait: bool = True, timeout_s: float = 30.0) -> None:
        """Turn to ``angle_rad``; with ``wait`` return once it has arrived."""

    @abstractmethod
    def stop(self) -> None:
        """Stop turning (the procedures' guard calls it after a failure)."""
