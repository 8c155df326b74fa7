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
``"gocator"``             LMI Gocator Protocol: control, data and health TCP servers
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
``latency_s``) on its own :class:`~.clock.DeviceClock` and sends it at ``t_k + latency_s`` (with
``send_late_s``, 5-50 ms later say, in bursts: a sender that cannot keep its timing).
Several exposures are ray-cast in one numpy call when they fall due together (high rates).
If the process falls more than ``max_lag_s`` behind, exposures are skipped (counter gaps, as a
real sensor with a full buffer does) and counted in ``overrun``.

Fault injection (per wire unit: a datagram, a framed message or a SCIP scan block): drop,
duplicate, reorder (hold back behind the next unit), truncate (cut at a random length) and
corrupt (flip one bit), each with its probability; :meth:`SimulatedSensor.disconnect` makes the
sensor vanish for a while (TCP: the connection is closed and the port refuses; UDP and serial:
silence) and come back, optionally rebooted (frame counters and clock restart).

The parts: the configuration (:mod:`.sensor_config`), the transports (:mod:`.sensor_links`), the
wire formats (:mod:`.sensor_protocols` for LPF1 and RF627, :mod:`.sensor_scip` for SCIP, with
the scan mapping); here the parent-side handle (:class:`SimulatedSensor`) and the sensor loop of
the child process (exposures, faults, sending on time).
"""

from __future__ import annotations

import logging
import math
import selectors
import time
from array import array
from collections import deque
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import se3
from wristscan.drivers.sim.clock import DeviceClock
from wristscan.drivers.sim.late_sender import LateSender
from wristscan.drivers.sim.process import SimProcess
from wristscan.drivers.sim.scene import Scene, demo_scene, sensor_looking_down
from wristscan.drivers.sim.sensor_config import (
    DEFAULT_SENSOR2FLANGE_POSE,
    KINDS,
    FaultConfig,
    SensorSimConfig,
)
from wristscan.drivers.sim.sensor_gocator import GocatorLink, GocatorProtocol
from wristscan.drivers.sim.sensor_links import Link, PtyLink, TcpLink, UdpLink
from wristscan.drivers.sim.sensor_protocols import (
    Batch,
    Lpf1Protocol,
    Rf627Protocol,
    SensorProtocol,
)
from wristscan.drivers.sim.sensor_scip import ScipProtocol

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

    def record_sends(self, on: bool = True) -> None:
        """Start keeping (``on``, what was kept is cleared) or stop keeping the true exposure
        instant of every profile the sensor sends: ground truth for a benchmark that measures
        latency against the real exposures (:meth:`sent_log`). Off by default."""
        self._call("record_sends", bool(on))

    def sent_log(self) -> dict[str, NDArray[np.int64]]:
        """The profiles sent since :meth:`record_sends` or the previous call (which this one
        clears), in sending order: ``exposure_ns`` (the true host instant of each exposure),
        ``frame_counter`` (as sent: exposure index minus the counter base of the moment) and
        ``sent_ns`` (host time its sending began)."""
        result: dict[str, NDArray[np.int64]] = self._call("sent_log")
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
    late: LateSender | None = None  # with send_late_s, from run() on

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
            self.link: Link = UdpLink(self.stats, cfg.host, target_addr)
        elif cfg.kind == "gocator":
            self.link = GocatorLink(self.stats, cfg.host, cfg.port)
        elif cfg.transport == "tcp":
            self.link = TcpLink(self.stats, cfg.host, cfg.port)
        else:
            self.link = PtyLink(self.stats, cfg.serial_baud)
        self.proto: SensorProtocol
        if cfg.kind.startswith("lpf1"):
            self.proto = Lpf1Protocol(cfg, self.link, self.clock)
        elif cfg.kind == "rf627-udp":
            self.proto = Rf627Protocol(cfg, self.link, self.clock)
        elif cfg.kind == "gocator":
            self.proto = GocatorProtocol(cfg, self.link, self.clock)
        else:
            self.proto = ScipProtocol(cfg, self.link, self.clock)
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
        self.queue: deque[tuple[int, list[bytes], int]] = deque()  # (send at, units, due)
        self.max_chunk = 32
        self.held: bytes | None = None
        self.down_until_ns = 0
        self.reboot_on_return = False
        self.sent: tuple[array[int], array[int]] | None = None
        """With ``record_sends``: (due send time, actual send time) of each profile sent."""
        self.running = True
        self._warned_truth = False
        if cfg.transport != "tcp" and isinstance(self.proto, Lpf1Protocol):
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
            elif cmd == "record_sends":
                self.sent = (array("q"), array("q")) if msg[1] else None
                self.conn.send(("ok", None))
            elif cmd == "sent_log":
                self.conn.send(("ok", self._sent_log()))
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

    def _sent_log(self) -> dict[str, NDArray[np.int64]]:
        due, at = self.sent if self.sent is not None else (array("q"), array("q"))
        exposure = np.array(due, dtype=np.int64) - self.latency_ns
        k = np.rint((exposure - self.t0_ns) / self.period_ns).astype(np.int64)
        if self.sent is not None:
            self.sent = (array("q"), array("q"))
        return {
            "exposure_ns": exposure,
            "frame_counter": k - self.counter_base,
            "sent_ns": np.array(at, dtype=np.int64),
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
        send_at = send_due if self.late is None else self.late.send_times(send_due)
        for p, units in enumerate(self.proto.encode(batch)):
            if units:
                self.queue.append((int(send_at[p]), units, int(send_due[p])))
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

    def _measure(self, ks: NDArray[np.int64], t_exp: NDArray[np.int64]) -> Batch:
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
        return Batch(ks - self.counter_base, t_exp, stamps, meas, encoder, intensity)

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
            at, units, due = q.popleft()
            for u in units:
                self._emit(u)
            stats["profiles_sent"] += 1
            if self.sent is not None:
                self.sent[0].append(due)
                self.sent[1].append(now_ns)
            # A late simulator sends in a burst, which a real sensor never does: counted so a
            # benchmark can tell the simulator's stalls from the daemon's.
            late_us = (now_ns - at) // 1000  # beyond the send time (and send_late_s)
            if late_us > 5000:
                stats["sent_late_5ms"] += 1
            if late_us > stats["max_send_late_us"]:
                stats["max_send_late_us"] = late_us

    # -- loop -----------------------------------------------------------------------------------

    def run(self) -> None:
        if self.cfg.send_late_s[1] > 0.0:
            self.late = LateSender(self.cfg, self.rng, self.t0_ns)
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
