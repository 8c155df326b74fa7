"""Simulated profile sensors speaking the real wire formats, each in a process of its own.

Kinds and transports
--------------------
========================  ===========================================================
``"lpf1-udp"``            LPF1 datagrams sent to ``config.target`` (fragments above
                          ``max_datagram``)
``"lpf1-tcp"``            LPF1 stream to the client connected to the listening port; a
                          HELLO message on connect
``"lpf1-serial"``         LPF1 messages COBS-framed on a pseudo-terminal
``"rf627-udp"``           Riftek RF627 profile datagrams sent to ``config.target``
``"scip-tcp"``            Hokuyo SCIP 2.0 server (commands in, replies and scans out)
``"scip-serial"``         the same on a pseudo-terminal
========================  ===========================================================

``endpoint`` (after start): ``{"host", "port"}`` for TCP, ``{"target": (host, port)}`` for UDP
(the sender's address is ``{"host", "port"}`` too), ``{"port_path"}`` for serial kinds: the pty
slave path that pyserial opens like a real port.

Timing model
------------
Exposures happen every ``1 / rate_hz`` seconds of the *device* clock, so on the host they are
``period / (1 + drift)`` apart: ``t_k = t0 + k * period_host`` (``info()`` gives ``t0_ns`` and
``period_ns``). At each exposure the sensor samples the robot's true joint positions from the
robot :class:`~.truth.TruthRing` (waiting up to ``truth_wait_s`` for the ring to cover the
instant; after that the newest sample is used and counted in ``truth_clamped``) and the table
angle from the table ring, and ray-casts the scene from
``sensor2base = forward(robot_model, q) @ sensor2flange``. Without a robot ring the flange stays
at ``standalone_flange_pose``. The device stamps the frame at ``t_k + stamp_delay_s`` (default
``latency_s``) on its own :class:`~.clock.DeviceClock` and sends it at ``t_k + latency_s``.
Several exposures are ray-cast in one numpy call when they fall due together (high rates).
If the process falls more than ``max_lag_s`` behind, exposures are skipped (counter gaps, as a
real sensor with a full buffer does) and counted in ``overrun``.

Fault injection (per wire unit: a datagram, a framed message or a SCIP scan block): drop,
duplicate, reorder (hold back behind the next unit), truncate (cut at a random length) and
corrupt (flip one bit), each with its probability; :meth:`SimulatedSensor.disconnect` makes the
sensor vanish for a while (TCP: the connection is closed and the port refuses; UDP and serial:
silence) and come back, optionally rebooted (frame counters and clock restart).

SCIP mapping
------------
The SCIP sensor is a scanning range finder whose scan plane is the laser plane: step ``i``
(``0 .. n_points-1``) looks along ``theta_i = 2 pi (i - AFRT) / ARES`` from sensor +Z towards
+Y (``AFRT = (n_points - 1) // 2``, the front step), so the point is
``(0, r sin theta, r cos theta)``. Ranges are millimetres; a step without a return in
``[scip_range_min_m, scip_range_max_m]`` reports 1 (an error code below DMIN, as URG sensors do).
A cluster reports the smallest valid range of its steps. The whole scan is taken at one instant.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import selectors
import socket
import time
import tty
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from multiprocessing.connection import Connection
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import se3
from wristscan.drivers import lpf1, rf627, scip
from wristscan.drivers.sim.clock import DeviceClock
from wristscan.drivers.sim.laser import LaserModel, Measurement
from wristscan.drivers.sim.process import SimProcess
from wristscan.drivers.sim.scene import Scene, demo_scene, sensor_looking_down

__all__ = [
    "DEFAULT_SENSOR2FLANGE_POSE",
    "KINDS",
    "FaultConfig",
    "SensorSimConfig",
    "SimulatedSensor",
]

log = logging.getLogger(__name__)

_PRECISE_NS = 1_500_000
"""A send due sooner than this is waited for with ``time.sleep`` (microseconds) rather than the
selector (milliseconds), so that profiles leave at their send time as a real sensor's do."""

SensorKind = Literal["lpf1-udp", "lpf1-tcp", "lpf1-serial", "rf627-udp", "scip-tcp", "scip-serial"]
KINDS: tuple[str, ...] = (
    "lpf1-udp",
    "lpf1-tcp",
    "lpf1-serial",
    "rf627-udp",
    "scip-tcp",
    "scip-serial",
)

DEFAULT_SENSOR2FLANGE_POSE = (0.060, 0.010, 0.200, 0.020, -0.015, 0.010)
"""Ground-truth tool transformation as a UR pose (m, rotation vector in rad): near the paper's
TCP (60, 10, 200) mm with a small known rotation."""


@dataclass(frozen=True)
class FaultConfig:
    """Probabilities (0-1) applied to every wire unit the sensor sends."""

    drop: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    truncate: float = 0.0
    corrupt: float = 0.0

    def __post_init__(self) -> None:
        for k, v in asdict(self).items():
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"fault probability {k}={v} outside [0, 1]")

    @property
    def any(self) -> bool:
        return (self.drop + self.duplicate + self.reorder + self.truncate + self.corrupt) > 0


@dataclass(frozen=True)
class SensorSimConfig:
    """Everything a simulated sensor needs; SI units (m, rad, s), device times in ns."""

    kind: SensorKind = "lpf1-udp"
    rate_hz: float = 1000.0
    n_points: int = 2048
    half_width_m: float = 0.025
    z_min_m: float = 0.05
    z_max_m: float = 0.15
    noise_std_m: float = 20e-6
    noise_model: Literal["gaussian", "table"] = "table"
    """``"table"``: fast discretised Gaussian (truncated at 4.3 sigma), see :mod:`.laser`."""
    dropout_prob: float = 0.0
    outlier_prob: float = 0.0
    latency_s: float = 0.002
    """Exposure to send."""
    stamp_delay_s: float | None = None
    """Exposure to the device timestamp (None: ``latency_s``, the device stamps when it sends)."""
    clock_offset_ns: int = 0
    clock_drift_ppm: float = 0.0
    clock_jitter_ns: float = 0.0
    sensor_id: int = 1
    sensor2flange: tuple[float, ...] | tuple[tuple[float, ...], ...] = DEFAULT_SENSOR2FLANGE_POSE
    """Ground truth: a UR pose ``(x, y, z, rx, ry, rz)`` or a 4x4 matrix (nested tuples)."""
    robot_model: str = "UR5e"
    standalone_flange_pose: tuple[float, ...] | None = None
    """Flange pose (UR pose) without a robot ring; None: the sensor 0.1 m above the scene's
    ``"ball"`` primitive (or the base origin), looking down."""
    standalone_table_angle_rad: float = 0.0
    encoder: Literal["none", "table", "time"] = "none"
    """Encoder count source: the table angle, or a constant rate since start."""
    encoder_counts_per_rev: int = 36000
    encoder_counts_per_s: float = 1000.0
    intensity: bool = False
    host: str = "127.0.0.1"
    port: int = 0
    """TCP listening port (0: any free port)."""
    target: tuple[str, int] | None = None
    """UDP destination; None: ``(host, 50001)`` for RF627, ``(host, 50002)`` for LPF1."""
    max_datagram: int = lpf1.DEFAULT_MAX_MESSAGE
    lpf1_point_format: Literal["i16", "i32", "f32"] = "i16"
    lpf1_z_scale_nm: int = 2000
    lpf1_z_offset_um: int = 100_000
    serial_baud: int | None = None
    """Throttle a serial link to ``baud / 10`` bytes/s; None: as fast as the pty goes."""
    heartbeat_s: float = 1.0
    """LPF1 heartbeat period (0: none)."""
    scip_ares: int = 1440
    scip_range_min_m: float = 0.02
    scip_range_max_m: float = 30.0
    scip_model: str = "WRISTSCAN-SIM"
    truth_wait_s: float = 0.05
    max_lag_s: float = 1.0
    """Exposures more than this late (an overloaded host) are skipped, leaving counter gaps."""
    batch_s: float = 0.001
    """Exposures are ray-cast together when they fall due within this window (at most a
    quarter of ``latency_s + precompute_s``, so that they are still sent on time)."""
    precompute_s: float = 0.003
    """Exposures are ray-cast up to this long before they happen, as soon as the truth rings
    cover them (the controller and the table write them ahead), and sent at their send time:
    a sensor process scheduled a little late still sends on time, as a real sensor does."""
    seed: int | None = None
    faults: FaultConfig = field(default_factory=FaultConfig)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown sensor kind {self.kind!r}; one of {', '.join(KINDS)}")
        if not 0 < self.rate_hz <= 100_000:
            raise ValueError("rate_hz must be in (0, 100000]")
        if self.n_points < 1:
            raise ValueError("n_points must be >= 1")
        if self.precompute_s < 0:
            raise ValueError("precompute_s must be >= 0")
        if self.latency_s < 0 or (self.stamp_delay_s is not None and self.stamp_delay_s < 0):
            raise ValueError("latency_s and stamp_delay_s must be >= 0")
        if self.is_scip and self.n_points > self.scip_ares:
            raise ValueError("a SCIP scan cannot have more steps (n_points) than ARES")
        if self.kind == "rf627-udp" and self.n_points > 16383:
            raise ValueError("RF627 carries at most 16383 points")
        self.sensor2flange_matrix()  # validates the shape

    @classmethod
    def for_kind(cls, kind: SensorKind, **overrides: Any) -> SensorSimConfig:
        """Defaults that suit ``kind`` (RF627: 648 points; SCIP: a 270-degree 1081-step scanner
        at 40 Hz), then ``overrides``."""
        base: dict[str, Any] = {"kind": kind}
        if kind == "rf627-udp":
            base.update(n_points=648)
        elif kind.startswith("scip"):
            base.update(n_points=1081, scip_ares=1440, rate_hz=40.0, latency_s=0.001)
        base.update(overrides)
        return cls(**base)

    @property
    def is_scip(self) -> bool:
        return self.kind.startswith("scip")

    @property
    def transport(self) -> str:
        return self.kind.split("-")[1]

    def sensor2flange_matrix(self) -> NDArray[np.float64]:
        a = np.asarray(self.sensor2flange, dtype=np.float64)
        if a.shape == (6,):
            return se3.pose_to_matrix(a)
        if a.shape == (4, 4):
            return se3.check_transform(a, "sensor2flange")
        raise ValueError("sensor2flange must be a UR pose (6,) or a 4x4 matrix")

    def scip_angles_rad(self) -> NDArray[np.float64]:
        front = (self.n_points - 1) // 2
        return 2.0 * np.pi * (np.arange(self.n_points) - front) / self.scip_ares

    def laser_model(self, rng: np.random.Generator | int | None = None) -> LaserModel:
        """The :class:`LaserModel` this sensor measures with."""
        if self.is_scip:
            return LaserModel(
                self.n_points,
                z_min_m=self.scip_range_min_m,
                z_max_m=self.scip_range_max_m,
                noise_std_m=self.noise_std_m,
                dropout_prob=self.dropout_prob,
                outlier_prob=self.outlier_prob,
                rng=rng,
                geometry="fan",
                angles_rad=self.scip_angles_rad(),
                noise_model=self.noise_model,
            )
        return LaserModel(
            self.n_points,
            self.half_width_m,
            self.z_min_m,
            self.z_max_m,
            self.noise_std_m,
            self.dropout_prob,
            self.outlier_prob,
            rng,
            noise_model=self.noise_model,
        )


# ----------------------------------------------------------------------------------------------
# Parent side


class SimulatedSensor(SimProcess):
    """Run a simulated sensor in its own process (spawn); a context manager.

    ``scene`` defaults to :func:`~.scene.demo_scene`; ``robot_ring``/``table_ring`` are
    :class:`~.truth.TruthRing` names (joint positions, width 6; table angle, width 1).
    """

    def __init__(
        self,
        config: SensorSimConfig | None = None,
        scene: Scene | None = None,
        robot_ring: str | None = None,
        table_ring: str | None = None,
    ) -> None:
        super().__init__()
        self.config = config or SensorSimConfig()
        self.process_name = f"sim-sensor-{self.config.kind}"
        self.scene = scene
        self.robot_ring = robot_ring
        self.table_ring = table_ring

    def _target(self) -> tuple[Callable[..., None], tuple[Any, ...]]:
        return _serve, (self.config, self.scene, self.robot_ring, self.table_ring)

    def _call(self, *msg: Any, timeout_s: float = 10.0) -> Any:
        if self._conn is None:
            raise RuntimeError("simulated sensor is not running")
        try:
            self._conn.send(msg)
        except (BrokenPipeError, OSError):
            raise RuntimeError("the simulated sensor process has died") from None
        if not self._conn.poll(timeout_s):
            raise RuntimeError(f"simulated sensor did not answer {msg[0]!r}")
        try:
            kind, payload = self._conn.recv()
        except EOFError:
            raise RuntimeError("the simulated sensor process has died") from None
        if kind != "ok":
            raise RuntimeError(f"simulated sensor: {payload}")
        return payload

    def set_faults(self, faults: FaultConfig | None = None, **probabilities: float) -> None:
        """Replace the fault probabilities (``FaultConfig`` or keyword arguments)."""
        self._call("faults", faults if faults is not None else FaultConfig(**probabilities))

    def disconnect(self, duration_s: float, reboot: bool = False) -> None:
        """Vanish now for ``duration_s``; ``reboot`` restarts counters and clock on return."""
        self._call("disconnect", float(duration_s), bool(reboot))

    def stats(self) -> dict[str, int]:
        """Counters: exposures, profiles_sent, units_sent, dropped, duplicated, reordered,
        truncated, corrupted, overrun, unsent (nobody listening/disconnected), truth_clamped,
        tx_overflow, clients, sent_late_5ms (profiles sent over 5 ms after their send time: the
        simulator fell behind and sent a burst), max_send_late_us."""
        result: dict[str, int] = self._call("stats")
        return result

    def info(self) -> dict[str, Any]:
        """Ground truth of the timing: ``t0_ns``, ``period_ns`` (exposure ``k`` at
        ``t0 + k * period``), ``counter_base`` (frame counter = k - base), ``latency_ns``,
        ``stamp_delay_ns``, the clock (``clock_offset_ns``, ``clock_drift_ppm``,
        ``clock_epoch_host_ns``), ``sensor2flange`` (4x4 list), ``endpoint``."""
        result: dict[str, Any] = self._call("info")
        return result

    close = SimProcess.stop


# ----------------------------------------------------------------------------------------------
# Child side: transports


class _Link:
    """A transport as the device sees it. ``send`` queues bytes; ``flush`` pushes them out."""

    connected = True

    def __init__(self, stats: dict[str, int]) -> None:
        self.stats = stats
        self.down_until_ns = 0

    def register(self, sel: selectors.BaseSelector) -> None:
        """Register readable file objects with ``data`` = a callable handling the event."""

    def send(self, unit: bytes) -> None:
        raise NotImplementedError

    def flush(self, now_ns: int) -> None:
        """Push queued bytes out (stream transports)."""

    def wants_write(self) -> bool:
        return False

    def go_down(self, sel: selectors.BaseSelector) -> None:
        """Disconnect (until :meth:`come_back`)."""

    def come_back(self, sel: selectors.BaseSelector) -> None:
        """Reconnect after :meth:`go_down`."""

    def endpoint(self) -> dict[str, Any]:
        return {}

    def close(self) -> None:
        pass


class _UdpLink(_Link):
    def __init__(self, stats: dict[str, int], host: str, target: tuple[str, int]) -> None:
        super().__init__(stats)
        self.target = target
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
        self.sock.bind((host, 0))
        self.sock.setblocking(False)
        self.up = True

    def send(self, unit: bytes) -> None:
        if not self.up:
            self.stats["unsent"] += 1
            return
        try:
            self.sock.sendto(unit, self.target)
            self.stats["units_sent"] += 1
        except (BlockingIOError, ConnectionRefusedError):
            # Nobody listening (ICMP port unreachable) or the socket buffer is full: like a
            # real sensor, the datagram is simply gone.
            self.stats["unsent"] += 1
        except OSError as exc:
            log.debug("UDP send failed: %s", exc)
            self.stats["unsent"] += 1

    def go_down(self, sel: selectors.BaseSelector) -> None:
        self.up = False

    def come_back(self, sel: selectors.BaseSelector) -> None:
        self.up = True

    def endpoint(self) -> dict[str, Any]:
        host, port = self.sock.getsockname()[:2]
        return {"host": host, "port": port, "target": self.target}

    def close(self) -> None:
        self.sock.close()


class _StreamLink(_Link):
    """Shared output buffering of TCP and pty links."""

    max_pending = 8 << 20

    def __init__(self, stats: dict[str, int]) -> None:
        super().__init__(stats)
        self.pending = bytearray()
        self.on_data: Callable[[bytes], None] = lambda data: None
        self.on_connect: Callable[[], None] = lambda: None

    @property
    def connected(self) -> bool:  # type: ignore[override]
        return self._out_fd() is not None

    def _out_fd(self) -> int | None:
        raise NotImplementedError

    def _budget(self, now_ns: int) -> int:
        return 1 << 30

    def _spend(self, n: int) -> None:
        pass

    def send(self, unit: bytes) -> None:
        if not self.connected:
            self.stats["unsent"] += 1
            return
        if len(self.pending) > self.max_pending:
            self.stats["tx_overflow"] += 1
            return
        self.pending += unit
        self.stats["units_sent"] += 1

    def send_now(self, data: bytes) -> None:
        """Command replies: queued ahead of nothing, never subject to faults."""
        if self.connected:
            self.pending += data

    def wants_write(self) -> bool:
        return bool(self.pending)

    def flush(self, now_ns: int) -> None:
        fd = self._out_fd()
        if fd is None:
            self.pending.clear()
            return
        while self.pending:
            budget = self._budget(now_ns)
            if budget <= 0:
                return
            try:
                with memoryview(self.pending) as view, view[: min(budget, 1 << 20)] as part:
                    n = self._write(part)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                log.debug("stream write failed: %s", exc)
                self._lost()
                return
            self._spend(n)
            del self.pending[:n]

    def _write(self, data: memoryview) -> int:
        raise NotImplementedError

    def _lost(self) -> None:
        self.pending.clear()


class _TcpLink(_StreamLink):
    def __init__(self, stats: dict[str, int], host: str, port: int) -> None:
        super().__init__(stats)
        self.host = host
        self.listener: socket.socket | None = None
        self.client: socket.socket | None = None
        self.sel: selectors.BaseSelector | None = None
        self._listen(port)

    def _listen(self, port: int) -> None:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((self.host, port))
        s.listen(2)
        s.setblocking(False)
        self.listener = s
        self.port = s.getsockname()[1]

    def register(self, sel: selectors.BaseSelector) -> None:
        self.sel = sel
        if self.listener is not None:
            sel.register(self.listener, selectors.EVENT_READ, self._accept)

    def _accept(self) -> None:
        assert self.listener is not None
        try:
            conn, _ = self.listener.accept()
        except BlockingIOError:
            return
        # One client at a time, as on the devices: a new connection replaces the old one.
        self._drop_client()
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.client = conn
        self.stats["clients"] += 1
        assert self.sel is not None
        self.sel.register(conn, selectors.EVENT_READ, self._read)
        self.on_connect()

    def _read(self) -> None:
        if self.client is None:
            return
        try:
            data = self.client.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self._drop_client()
            return
        self.on_data(data)

    def _drop_client(self) -> None:
        if self.client is not None:
            if self.sel is not None:
                with contextlib.suppress(KeyError, ValueError):
                    self.sel.unregister(self.client)
            self.client.close()
            self.client = None
        self.pending.clear()

    def _lost(self) -> None:
        self._drop_client()

    def _out_fd(self) -> int | None:
        return None if self.client is None else self.client.fileno()

    def _write(self, data: memoryview) -> int:
        assert self.client is not None
        return self.client.send(data)

    def go_down(self, sel: selectors.BaseSelector) -> None:
        self._drop_client()
        if self.listener is not None:
            with contextlib.suppress(KeyError, ValueError):
                sel.unregister(self.listener)
            self.listener.close()
            self.listener = None

    def come_back(self, sel: selectors.BaseSelector) -> None:
        self._listen(self.port)
        self.register(sel)

    def endpoint(self) -> dict[str, Any]:
        return {"host": self.host, "port": self.port}

    def close(self) -> None:
        self._drop_client()
        if self.listener is not None:
            self.listener.close()
            self.listener = None


class _PtyLink(_StreamLink):
    max_pending = 1 << 20

    def __init__(self, stats: dict[str, int], baud: int | None) -> None:
        super().__init__(stats)
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # binary link: no echo, no newline translation
        self.path = os.ttyname(self.slave)
        os.set_blocking(self.master, False)
        self.bytes_per_s = None if baud is None else baud / 10.0
        self._credit = 0.0
        self._credit_t = time.monotonic_ns()
        self.up = True

    def register(self, sel: selectors.BaseSelector) -> None:
        sel.register(self.master, selectors.EVENT_READ, self._read)

    def _read(self) -> None:
        try:
            data = os.read(self.master, 65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            return
        if data and self.up:
            self.on_data(data)

    def _out_fd(self) -> int | None:
        return self.master if self.up else None

    def _budget(self, now_ns: int) -> int:
        if self.bytes_per_s is None:
            return 1 << 30
        self._credit = min(
            self._credit + (now_ns - self._credit_t) * 1e-9 * self.bytes_per_s,
            max(4096.0, 0.01 * self.bytes_per_s),
        )
        self._credit_t = now_ns
        return int(self._credit)

    def _spend(self, n: int) -> None:
        if self.bytes_per_s is not None:
            self._credit -= n

    def _write(self, data: memoryview) -> int:
        return os.write(self.master, data)

    def go_down(self, sel: selectors.BaseSelector) -> None:
        self.up = False
        self.pending.clear()

    def come_back(self, sel: selectors.BaseSelector) -> None:
        self.up = True

    def endpoint(self) -> dict[str, Any]:
        return {"port_path": self.path}

    def close(self) -> None:
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)


# ----------------------------------------------------------------------------------------------
# Child side: protocols


@dataclass
class _Batch:
    """Exposures computed together."""

    counters: NDArray[np.int64]
    t_exp_ns: NDArray[np.int64]
    stamps_ns: NDArray[np.int64]
    meas: Measurement
    encoder: NDArray[np.int64] | None
    intensity: NDArray[np.uint8] | None


class _Protocol:
    def __init__(self, cfg: SensorSimConfig, link: _Link, clock: DeviceClock) -> None:
        self.cfg = cfg
        self.link = link
        self.clock = clock

    def wants_exposures(self) -> bool:
        return self.link.connected

    def encode(self, batch: _Batch) -> list[list[bytes]]:
        """Wire units per profile (faults are applied to each unit)."""
        raise NotImplementedError

    def periodic(self, now_ns: int, counter: int) -> None:
        pass

    def on_reboot(self) -> None:
        pass


class _Lpf1Protocol(_Protocol):
    def __init__(self, cfg: SensorSimConfig, link: _Link, clock: DeviceClock) -> None:
        super().__init__(cfg, link, clock)
        fmt = {
            "i16": lpf1.PointFormat.I16,
            "i32": lpf1.PointFormat.I32,
            "f32": lpf1.PointFormat.F32,
        }
        step = 2 * cfg.half_width_m / max(1, cfg.n_points - 1)
        self.encoder = lpf1.ProfileEncoder(
            cfg.sensor_id,
            fmt[cfg.lpf1_point_format],
            z_scale_nm=cfg.lpf1_z_scale_nm,
            z_offset_um=cfg.lpf1_z_offset_um,
            x_uniform=(-cfg.half_width_m, step),
            intensity=cfg.intensity,
            max_message_bytes=cfg.max_datagram if cfg.transport == "udp" else None,
        )
        self.serial = cfg.transport == "serial"
        self.last_counter = 0
        self.next_heartbeat_ns = 0
        if isinstance(link, _StreamLink):
            link.on_connect = self.hello

    def _frame(self, msg: bytes) -> bytes:
        return lpf1.cobs_frame(msg) if self.serial else msg

    def hello(self) -> None:
        info = {
            "model": "wristscan-sim",
            "kind": self.cfg.kind,
            "n_points": self.cfg.n_points,
            "rate_hz": self.cfg.rate_hz,
            "z_range_m": [self.cfg.z_min_m, self.cfg.z_max_m],
        }
        msg = lpf1.encode_control(
            lpf1.MsgType.HELLO, self.cfg.sensor_id, self.last_counter, self.clock.now_ns(), info
        )
        self.link.send(self._frame(msg))

    def encode(self, batch: _Batch) -> list[list[bytes]]:
        msgs = self.encoder.encode(
            batch.counters,
            batch.stamps_ns,
            batch.meas.z,
            batch.meas.valid,
            intensity=batch.intensity,
            encoder=batch.encoder,
        )
        self.last_counter = int(batch.counters[-1])
        if self.serial:
            return [[lpf1.cobs_frame(m) for m in frags] for frags in msgs]
        return msgs

    def periodic(self, now_ns: int, counter: int) -> None:
        if self.cfg.heartbeat_s <= 0 or now_ns < self.next_heartbeat_ns:
            return
        self.next_heartbeat_ns = now_ns + int(self.cfg.heartbeat_s * 1e9)
        if self.link.connected:
            msg = lpf1.encode_control(
                lpf1.MsgType.HEARTBEAT, self.cfg.sensor_id, self.last_counter, self.clock.now_ns()
            )
            self.link.send(self._frame(msg))

    def on_reboot(self) -> None:
        self.last_counter = 0
        if self.cfg.transport != "tcp":
            self.hello()


class _Rf627Protocol(_Protocol):
    def __init__(self, cfg: SensorSimConfig, link: _Link, clock: DeviceClock) -> None:
        super().__init__(cfg, link, clock)
        self.encoder = rf627.RF627Encoder(cfg.sensor_id, intensity=cfg.intensity)

    def encode(self, batch: _Batch) -> list[list[bytes]]:
        grams = self.encoder.encode(
            batch.counters,
            batch.stamps_ns,
            batch.meas.y,
            batch.meas.z,
            batch.meas.valid,
            intensity=batch.intensity,
            step_count=batch.encoder,
        )
        return [[g] for g in grams]

    def on_reboot(self) -> None:
        self.encoder.packet_count = 0


class _ScipProtocol(_Protocol):
    """The sensor side of SCIP 2.0: a small state machine plus the scan encoder."""

    def __init__(self, cfg: SensorSimConfig, link: _Link, clock: DeviceClock) -> None:
        super().__init__(cfg, link, clock)
        assert isinstance(link, _StreamLink)
        self.stream_link = link
        link.on_data = self.on_data
        link.on_connect = self.on_connect
        self.inbuf = bytearray()
        self.laser_on = False
        self.time_adjust = False
        self.stream: scip.Command | None = None
        self.stream_left = 0  # scans still to send; -1: endless
        self.stream_skip = 0
        self.singles: deque[scip.Command] = deque()
        self.amax = cfg.n_points - 1
        self.afrt = (cfg.n_points - 1) // 2

    def on_connect(self) -> None:
        self.inbuf.clear()
        self.stream = None
        self.singles.clear()

    def wants_exposures(self) -> bool:
        return self.link.connected and (self.stream is not None or bool(self.singles))

    def on_data(self, data: bytes) -> None:
        self.inbuf += data
        while True:
            i = self.inbuf.find(b"\n")
            if i < 0:
                if len(self.inbuf) > 4096:
                    self.inbuf.clear()
                return
            line = bytes(self.inbuf[:i]).rstrip(b"\r")
            del self.inbuf[: i + 1]
            if line:
                self.handle(line)

    def _reply(self, echo: bytes, status: bytes, lines: tuple[bytes, ...] = ()) -> None:
        self.stream_link.send_now(scip.make_reply(echo, status, lines))

    def _ms(self, device_ns: int) -> int:
        return (device_ns // 1_000_000) % scip.TIMESTAMP_MODULO_MS

    def handle(self, line: bytes) -> None:
        try:
            cmd = scip.parse_command(line)
        except scip.FrameError:
            self._reply(line, b"0E")
            return
        code = cmd.code
        cfg = self.cfg
        if code == "VV":
            self._reply(line, b"00", (
                scip.info_line("VEND", "wristscan simulator"),
                scip.info_line("PROD", cfg.scip_model),
                scip.info_line("FIRM", "1.0.0"),
                scip.info_line("PROT", "SCIP 2.0"),
                scip.info_line("SERI", f"H{cfg.sensor_id:07d}"),
            ))  # fmt: skip
        elif code == "PP":
            self._reply(line, b"00", (
                scip.info_line("MODL", cfg.scip_model),
                scip.info_line("DMIN", round(cfg.scip_range_min_m * 1000)),
                scip.info_line("DMAX", round(cfg.scip_range_max_m * 1000)),
                scip.info_line("ARES", cfg.scip_ares),
                scip.info_line("AMIN", 0),
                scip.info_line("AMAX", self.amax),
                scip.info_line("AFRT", self.afrt),
                scip.info_line("SCAN", round(cfg.rate_hz * 60)),
            ))  # fmt: skip
        elif code == "II":
            self._reply(line, b"00", (
                scip.info_line("MODL", cfg.scip_model),
                scip.info_line("LASR", "ON" if self.laser_on else "OFF"),
                scip.info_line("SCSP", f"{round(cfg.rate_hz * 60)}[rpm]"),
                scip.info_line("MESM", "Measuring by Normal Mode"),
                scip.info_line("SBPS", "Ethernet 100 [Mbps]" if cfg.transport == "tcp" else "USB"),
                scip.info_line("TIME", f"{self._ms(self.clock.now_ns()):06X}"),
                scip.info_line("STAT", "Stable 000 no error."),
            ))  # fmt: skip
        elif code == "%ST":
            state = "004" if self.stream else "002" if self.time_adjust else (
                "003" if self.laser_on else "000")  # fmt: skip
            self._reply(line, b"00", (scip.with_checksum(state.encode()),))
        elif code == "BM":
            status = b"02" if self.laser_on else b"00"
            self.laser_on = True
            self._reply(line, status)
        elif code == "QT":
            self.stream = None
            self.singles.clear()
            self.laser_on = False
            self._reply(line, b"00")
        elif code in ("RS", "RT"):
            self.stream = None
            self.singles.clear()
            self.laser_on = False
            self.time_adjust = False
            self.clock.reset(offset_ns=0)
            self._reply(line, b"00")
        elif code == "TM":
            self._time_adjust(cmd, line)
        elif code in scip.SCAN_COMMANDS:
            self._scan_command(cmd, line)
        else:
            self._reply(line, b"0E")

    def _time_adjust(self, cmd: scip.Command, line: bytes) -> None:
        if cmd.params == "0":
            status = b"02" if self.time_adjust else b"00"
            self.time_adjust = True
            self.stream = None
            self._reply(line, status)
        elif cmd.params == "1":
            if not self.time_adjust:
                self._reply(line, b"04")
                return
            ts = scip.encode_values([self._ms(self.clock.now_ns())], 4)
            self._reply(line, b"00", (scip.with_checksum(ts),))
        elif cmd.params == "2":
            status = b"00" if self.time_adjust else b"03"
            self.time_adjust = False
            self._reply(line, status)
        else:
            self._reply(line, b"01")

    def _scan_command(self, cmd: scip.Command, line: bytes) -> None:
        try:
            start, end, _, _, scans = cmd.scan_params()
        except scip.FrameError:
            self._reply(line, b"01")
            return
        if end > self.amax or start > self.amax:
            self._reply(line, b"04")
            return
        if end < start:
            self._reply(line, b"05")
            return
        if self.time_adjust:
            self._reply(line, b"0L")
            return
        if cmd.code.startswith("G"):
            if not self.laser_on:
                self._reply(line, b"10")
                return
            self.singles.append(cmd)
            return
        self.laser_on = True
        self.stream = cmd
        self.stream_left = scans if scans > 0 else -1
        self.stream_skip = 0
        self._reply(line, b"00")

    def _ranges(self, t_m: NDArray[np.float64], valid: NDArray[np.bool_], cmd: scip.Command,
                n_chars: int) -> NDArray[np.int64]:  # fmt: skip
        start, end, cluster, _, _ = cmd.scan_params()
        mm = np.where(valid, np.rint(t_m * 1000.0), np.inf)[start : end + 1]
        cluster = max(1, cluster)
        pad = (-mm.size) % cluster
        if pad:
            mm = np.concatenate([mm, np.full(pad, np.inf)])
        grouped = mm.reshape(-1, cluster).min(axis=1)
        limit = (1 << (6 * n_chars)) - 1
        return np.where(np.isfinite(grouped) & (grouped <= limit), grouped, 1).astype(np.int64)

    def _intensity(self, inten: NDArray[np.uint8] | None, cmd: scip.Command) -> NDArray[Any]:
        start, end, cluster, _, _ = cmd.scan_params()
        cluster = max(1, cluster)
        n = -(-(end + 1 - start) // cluster)
        if inten is None:
            return np.full(n, 1000, dtype=np.int64)
        sel = inten[start : end + 1].astype(np.int64) * 40  # u8 to a URG-like scale
        sel = np.concatenate([sel, np.zeros((-sel.size) % cluster, dtype=np.int64)])
        return np.asarray(sel.reshape(n, cluster).max(axis=1))

    def _block(self, cmd: scip.Command, echo: bytes, status: bytes, batch: _Batch,
               p: int) -> bytes:  # fmt: skip
        _, n_chars, with_int = scip.SCAN_COMMANDS[cmd.code]
        ranges = self._ranges(batch.meas.t[p], batch.meas.valid[p], cmd, n_chars)
        inten = None
        if with_int:
            inten = self._intensity(None if batch.intensity is None else batch.intensity[p], cmd)
        ts = self._ms(int(batch.stamps_ns[p]))
        return scip.scan_reply(echo, status, ts, ranges, inten, n_chars)

    def encode(self, batch: _Batch) -> list[list[bytes]]:
        out: list[list[bytes]] = []
        for p in range(batch.counters.size):
            units: list[bytes] = []
            if self.singles:
                cmd = self.singles.popleft()
                units.append(self._block(cmd, cmd.raw, b"00", batch, p))
            if self.stream is not None:
                cmd = self.stream
                interval = int(cmd.params[10:11])
                if self.stream_skip > 0:
                    self.stream_skip -= 1
                else:
                    self.stream_skip = interval
                    if self.stream_left > 0:
                        self.stream_left -= 1
                    remaining = max(self.stream_left, 0)
                    head = cmd.code.encode() + cmd.params[:11].encode() + b"%02d" % remaining
                    echo = head + (b";" + cmd.string.encode() if cmd.string else b"")
                    units.append(self._block(cmd, echo, b"99", batch, p))
                    if self.stream_left == 0:
                        self.stream = None
            out.append(units)
        return out

    def on_reboot(self) -> None:
        self.stream = None
        self.singles.clear()
        self.laser_on = False
        self.time_adjust = False


# ----------------------------------------------------------------------------------------------
# Child side: the runtime


_STAT_KEYS = (
    "exposures",
    "profiles_sent",
    "units_sent",
    "dropped",
    "duplicated",
    "reordered",
    "truncated",
    "corrupted",
    "overrun",
    "unsent",
    "truth_clamped",
    "tx_overflow",
    "clients",
    "sent_late_5ms",
    "max_send_late_us",
)


class _Runtime:
    def __init__(
        self,
        cfg: SensorSimConfig,
        scene: Scene | None,
        robot_ring: str | None,
        table_ring: str | None,
        conn: Connection,
    ) -> None:
        from wristscan.drivers.sim.truth import TruthRing

        self.cfg = cfg
        self.conn = conn
        self.scene = scene if scene is not None else demo_scene()
        seeds = np.random.SeedSequence(cfg.seed).spawn(3)
        self.rng = np.random.default_rng(seeds[0])
        self.laser = cfg.laser_model(np.random.default_rng(seeds[1]))
        self.clock = DeviceClock(
            cfg.clock_offset_ns,
            cfg.clock_drift_ppm,
            cfg.clock_jitter_ns,
            np.random.default_rng(seeds[2]),
        )
        self.faults = cfg.faults
        self.stats = dict.fromkeys(_STAT_KEYS, 0)
        self.s2f = cfg.sensor2flange_matrix()
        self.robot_ring = TruthRing.attach(robot_ring) if robot_ring else None
        self.table_ring = TruthRing.attach(table_ring) if table_ring else None
        if cfg.standalone_flange_pose is not None:
            self.flange2base = se3.pose_to_matrix(cfg.standalone_flange_pose)
        else:
            try:
                target = self.scene.find("ball").pose[:3, 3]
            except KeyError:
                target = np.zeros(3)
            s2b = sensor_looking_down(target, 0.1)
            self.flange2base = s2b @ se3.invert(self.s2f)
        if cfg.transport == "udp":
            default_port = 50001 if cfg.kind == "rf627-udp" else 50002
            target_addr = cfg.target or (cfg.host, default_port)
            self.link: _Link = _UdpLink(self.stats, cfg.host, target_addr)
        elif cfg.transport == "tcp":
            self.link = _TcpLink(self.stats, cfg.host, cfg.port)
        else:
            self.link = _PtyLink(self.stats, cfg.serial_baud)
        self.proto: _Protocol
        if cfg.kind.startswith("lpf1"):
            self.proto = _Lpf1Protocol(cfg, self.link, self.clock)
        elif cfg.kind == "rf627-udp":
            self.proto = _Rf627Protocol(cfg, self.link, self.clock)
        else:
            self.proto = _ScipProtocol(cfg, self.link, self.clock)
        self.sel = selectors.DefaultSelector()
        self.sel.register(conn, selectors.EVENT_READ, self._control)
        self.link.register(self.sel)
        self.period_ns = 1e9 / cfg.rate_hz / self.clock.rate
        self.latency_ns = round(cfg.latency_s * 1e9)
        self.precompute_ns = round(cfg.precompute_s * 1e9)
        # Gather exposures for one vectorised ray-cast, for at most a quarter of the time
        # between computing ahead and sending: the batch must still go out at its send time.
        self.gather_ns = min(round(cfg.batch_s * 1e9), (self.latency_ns + self.precompute_ns) // 4)
        stamp = cfg.latency_s if cfg.stamp_delay_s is None else cfg.stamp_delay_s
        self.stamp_delay_ns = round(stamp * 1e9)
        self.t0_ns = time.monotonic_ns() + round(self.period_ns)
        self.k_next = 0
        self.counter_base = 0
        self.queue: deque[tuple[int, list[bytes]]] = deque()
        self.max_chunk = 32
        self.held: bytes | None = None
        self.down_until_ns = 0
        self.reboot_on_return = False
        self.running = True
        self._warned_truth = False
        if cfg.transport != "tcp" and isinstance(self.proto, _Lpf1Protocol):
            self.proto.hello()  # TCP says hello to each client instead

    # -- control --------------------------------------------------------------------------------

    def _control(self) -> None:
        try:
            msg = self.conn.recv()
        except EOFError:
            self.running = False
            return
        cmd = msg[0]
        try:
            if cmd == "stop":
                self.running = False
                return
            if cmd == "faults":
                self.faults = msg[1]
                self.conn.send(("ok", None))
            elif cmd == "disconnect":
                self._go_down(float(msg[1]), bool(msg[2]))
                self.conn.send(("ok", None))
            elif cmd == "stats":
                self.conn.send(("ok", dict(self.stats)))
            elif cmd == "info":
                self.conn.send(("ok", self._info()))
            else:
                self.conn.send(("error", f"unknown command {cmd!r}"))
        except Exception as exc:  # report to the parent rather than dying silently
            log.exception("control command %r failed", cmd)
            self.conn.send(("error", repr(exc)))

    def _info(self) -> dict[str, Any]:
        return {
            "t0_ns": self.t0_ns,
            "period_ns": self.period_ns,
            "counter_base": self.counter_base,
            "latency_ns": self.latency_ns,
            "stamp_delay_ns": self.stamp_delay_ns,
            "clock_offset_ns": self.clock.offset_ns,
            "clock_drift_ppm": self.clock.drift_ppm,
            "clock_epoch_host_ns": self.clock.epoch_host_ns,
            "sensor2flange": self.s2f.tolist(),
            "standalone_flange2base": self.flange2base.tolist(),
            "endpoint": self.link.endpoint(),
        }

    def _go_down(self, duration_s: float, reboot: bool) -> None:
        self.link.go_down(self.sel)
        self.queue.clear()
        self.held = None
        self.down_until_ns = time.monotonic_ns() + round(duration_s * 1e9)
        self.reboot_on_return = reboot

    def _come_back(self, now_ns: int) -> None:
        self.down_until_ns = 0
        self.link.come_back(self.sel)
        if self.reboot_on_return:
            # Exposures before the restarted clock's zero would get negative device times.
            self.k_next = max(self.k_next, math.ceil((now_ns - self.t0_ns) / self.period_ns))
            self.counter_base = self.k_next
            self.clock.reset(now_ns)
            self.proto.on_reboot()

    # -- exposures ------------------------------------------------------------------------------

    def _t_exp(self, k: int) -> int:
        return self.t0_ns + int(k * self.period_ns)

    def _truth_until(self, limit_ns: int) -> int:
        """Latest exposure time the truth rings cover, at most ``limit_ns``."""
        limit = limit_ns
        for ring in (self.robot_ring, self.table_ring):
            if ring is None:
                continue
            latest = ring.latest()
            t = latest[0] if latest is not None else -1
            limit = min(limit, t)
        return limit

    def _produce(self, now_ns: int) -> bool:
        """Compute the exposures that are due (one chunk); True if more are due already."""
        t_next = self._t_exp(self.k_next)
        ahead_ns = now_ns + self.precompute_ns
        # A gather window's worth at once (one vectorised ray-cast), not one per loop turn.
        if t_next + self.gather_ns > ahead_ns:
            return False
        k_now = int((now_ns - self.t0_ns) // self.period_ns) + 1  # exposures up to now
        if not self.proto.wants_exposures() or self.down_until_ns:
            # Nobody to send to: the device keeps exposing, nothing needs computing.
            if k_now <= self.k_next:
                return False
            self.stats["exposures"] += k_now - self.k_next
            self.stats["unsent"] += k_now - self.k_next
            self.k_next = k_now
            return False
        # Too far behind: skip exposures (they show as counter gaps).
        lag_limit = now_ns - int(self.cfg.max_lag_s * 1e9)
        if t_next < lag_limit:
            k_new = math.ceil((lag_limit - self.t0_ns) / self.period_ns)
            self.stats["exposures"] += k_new - self.k_next
            self.stats["overrun"] += k_new - self.k_next
            self.k_next = k_new
            t_next = self._t_exp(self.k_next)
        ripe = self._truth_until(ahead_ns)
        waited_out = now_ns - t_next > self.cfg.truth_wait_s * 1e9
        if ripe < t_next and not waited_out:
            return False
        until = now_ns if waited_out else ripe
        k_end = int((until - self.t0_ns) // self.period_ns) + 1
        # Small chunks keep the arrays in cache; run() comes back for the rest at once.
        k_end = max(self.k_next + 1, min(k_end, self.k_next + self.max_chunk))
        ks = np.arange(self.k_next, k_end, dtype=np.int64)
        self.k_next = k_end
        self.stats["exposures"] += ks.size
        t_exp = self.t0_ns + (ks * self.period_ns).astype(np.int64)
        batch = self._measure(ks, t_exp)
        send_due = t_exp + self.latency_ns
        for p, units in enumerate(self.proto.encode(batch)):
            if units:
                self.queue.append((int(send_due[p]), units))
        return self._t_exp(self.k_next) <= until

    def _truth(
        self, ring: Any, t_exp: NDArray[np.int64], fallback: ArrayLike
    ) -> NDArray[np.float64]:
        """Ring values at the exposures; rows the ring does not cover take its newest sample
        (or ``fallback`` when it is empty) and are counted."""
        values: NDArray[np.float64] = ring.sample(t_exp)
        bad = np.isnan(values).any(axis=1)
        if bad.any():
            latest = ring.latest()
            values[bad] = np.asarray(fallback) if latest is None else latest[1]
            self.stats["truth_clamped"] += int(bad.sum())
            if not self._warned_truth:
                log.warning("truth ring does not cover some exposures: newest sample used")
                self._warned_truth = True
        return values

    def _measure(self, ks: NDArray[np.int64], t_exp: NDArray[np.int64]) -> _Batch:
        cfg = self.cfg
        n_prof = ks.size
        if self.robot_ring is not None:
            from wristscan.calib.kinematics import forward

            q = self._truth(self.robot_ring, t_exp, np.full(6, np.nan))
            flange2base = forward(cfg.robot_model, q)
            # An empty ring gives NaN joints: stand at the standalone pose meanwhile.
            flange2base[np.isnan(flange2base).any(axis=(1, 2))] = self.flange2base
        else:
            flange2base = np.broadcast_to(self.flange2base, (n_prof, 4, 4))
        if self.table_ring is not None:
            angle = self._truth(self.table_ring, t_exp, [cfg.standalone_table_angle_rad])[:, 0]
        else:
            angle = np.full(n_prof, cfg.standalone_table_angle_rad)
        sensor2base = flange2base @ self.s2f
        meas = self.laser.measure(sensor2base, self.scene, angle)
        stamps = self.clock.device_ns(t_exp + self.stamp_delay_ns)
        encoder = None
        if cfg.encoder == "table":
            encoder = np.rint(angle / (2 * np.pi) * cfg.encoder_counts_per_rev).astype(np.int64)
        elif cfg.encoder == "time":
            encoder = np.rint((t_exp - self.t0_ns) * 1e-9 * cfg.encoder_counts_per_s).astype(
                np.int64
            )
        intensity = None
        if cfg.intensity:
            # Brighter when closer; a little speckle. Only a plausible signal, not a model.
            span = max(cfg.z_max_m - cfg.z_min_m, 1e-9)
            base = 230.0 - 150.0 * (np.nan_to_num(meas.t) - cfg.z_min_m) / span
            speck = self.rng.integers(-8, 9, size=base.shape)
            intensity = np.where(meas.valid, np.clip(base + speck, 1, 255), 0).astype(np.uint8)
        return _Batch(ks - self.counter_base, t_exp, stamps, meas, encoder, intensity)

    # -- sending --------------------------------------------------------------------------------

    def _emit(self, unit: bytes) -> None:
        f = self.faults
        if not f.any:
            self.link.send(unit)
            return
        r = self.rng.random(5)
        if r[0] < f.drop:
            self.stats["dropped"] += 1
            return
        if r[1] < f.truncate and len(unit) > 1:
            unit = unit[: int(self.rng.integers(1, len(unit)))]
            self.stats["truncated"] += 1
        if r[2] < f.corrupt:
            b = bytearray(unit)
            i = int(self.rng.integers(0, len(b)))
            b[i] ^= 1 << int(self.rng.integers(0, 8))
            unit = bytes(b)
            self.stats["corrupted"] += 1
        units = [unit, unit] if r[3] < f.duplicate else [unit]
        self.stats["duplicated"] += len(units) - 1
        if r[4] < f.reorder and self.held is None:
            self.held = units.pop(0)  # goes out behind the next unit
            self.stats["reordered"] += 1
        for u in units:
            self.link.send(u)
        if units and self.held is not None:
            self.link.send(self.held)
            self.held = None

    def _send_due(self, now_ns: int) -> None:
        q = self.queue
        stats = self.stats
        while q and q[0][0] <= now_ns:
            due, units = q.popleft()
            for u in units:
                self._emit(u)
            stats["profiles_sent"] += 1
            # A late simulator sends in a burst, which a real sensor never does: counted so a
            # benchmark can tell the simulator's stalls from the daemon's.
            late_us = (now_ns - due) // 1000
            if late_us > 5000:
                stats["sent_late_5ms"] += 1
            if late_us > stats["max_send_late_us"]:
                stats["max_send_late_us"] = late_us

    # -- loop -----------------------------------------------------------------------------------

    def run(self) -> None:
        self.conn.send(("ready", self.link.endpoint()))
        batch_ns = self.gather_ns - self.precompute_ns  # wake this long after the next exposure
        while self.running:
            now = time.monotonic_ns()
            if self.down_until_ns and now >= self.down_until_ns:
                self._come_back(now)
            # Send what is due before and after computing: a chunk of exposures takes a good
            # part of a millisecond to compute, which would otherwise make every send late.
            self._send_due(now)
            more = self._produce(now)
            self._send_due(time.monotonic_ns())
            self.proto.periodic(now, self.k_next)
            self.link.flush(now)
            if more:  # behind: keep computing, only glance at the control pipe and sockets
                for key, _ in self.sel.select(0):
                    key.data()
                continue
            wake = now + 50_000_000
            if self.proto.wants_exposures() and not self.down_until_ns:
                wake = min(wake, self._t_exp(self.k_next) + batch_ns)
            if self.queue:
                wake = min(wake, self.queue[0][0])
            if self.link.wants_write():
                wake = min(wake, now + 200_000)
            if self.down_until_ns:
                wake = min(wake, self.down_until_ns)
            now = time.monotonic_ns()
            if self.queue and wake == self.queue[0][0] and wake - now < _PRECISE_NS:
                # The selector's timeout has 1 ms resolution (epoll): send on time instead.
                time.sleep(max(0, wake - now) * 1e-9)
                for key, _ in self.sel.select(0):
                    key.data()
                continue
            timeout = max(wake - now, 100_000) * 1e-9
            for key, _ in self.sel.select(timeout):
                key.data()

    def close(self) -> None:
        self.link.close()
        self.sel.close()
        for ring in (self.robot_ring, self.table_ring):
            if ring is not None:
                ring.close()


def _serve(
    config: SensorSimConfig,
    scene: Scene | None,
    robot_ring: str | None,
    table_ring: str | None,
    conn: Connection,
) -> None:
    """Child-process body."""
    try:
        rt = _Runtime(config, scene, robot_ring, table_ring, conn)
    except Exception as exc:
        conn.send(("error", repr(exc)))
        return
    try:
        rt.run()
    finally:
        rt.close()
