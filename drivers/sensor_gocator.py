"""LMI Gocator driver: the Gocator Protocol's control, data and health channels (TCP).

Opening connects the three channels of ``host`` (control 3190, data 3196, health 3194 by
default), asks the protocol version (``Protocol Version``) and the sensor's identity and state
(``Get System Info``), starts acquisition (``Start``) unless the sensor already runs, and reads
the sensor clock (``Get Timestamp``); ``close`` sends ``Stop`` when this driver started it.
Framing and decoding are :mod:`wristscan.drivers.gocator` (vectorised; see ``docs/gocator.md``).

Each frame's message group (Stamp, then the uniform profile or profile point cloud, then the
optional intensity) becomes one :class:`~wristscan.drivers.records.Profile`: ``y`` the Gocator
X, ``z`` the Gocator Z (metres, the sensor's own frame: the hand-eye calibration finds where it
sits), ``frame_counter`` the Stamp's frame index (gaps counted as loss), ``sensor_time_ns`` its
timestamp (µs) times 1000 (into the clock mapping), ``encoder`` its encoder, ``sensor_id`` its
serial number. Unknown message types are skipped by their size.

A TCP stream carries no checksum, so, as for RF627, two plausibility checks catch header damage:
the stream's constant fields (profile type, attribute size, width, scales, offsets, serial) are
locked on the first group and a group that differs is rejected (two consecutive newer groups
that agree re-lock), and the frame index and the timestamp must advance together (a group
failing it is held back; the next one confirms a reboot or rejects it as damage).

The health channel's indicators (processing drops, Ethernet drops, temperature, uptime, ...)
show in ``health().detail["device"]``; a health message every second keeps the link alive while
the sensor is stopped. A dropped link reconnects like the other stream drivers; a sensor still
running is not restarted, so its frame index goes on and the outage counts as lost frames.
"""

from __future__ import annotations

import contextlib
import logging
import select
import socket
import statistics
import time
from collections import deque
from collections.abc import Callable
from typing import Any, ClassVar

from wristscan.drivers import gocator
from wristscan.drivers._stream import Chunk, LinkDown, StreamProfileSensor, Transport
from wristscan.drivers.base import DriverInitError
from wristscan.drivers.gocator_reader import GdpReader
from wristscan.drivers.records import Profile

__all__ = ["GocatorSensor"]

log = logging.getLogger(__name__)

INDICATORS = {
    20000: "sensor_state",
    20001: "current_speed_hz",
    2017: "uptime_s",
    2002: "internal_temperature_cdeg",
    21000: "processing_drops",
    21003: "ethernet_output_bytes",
    21005: "ethernet_drops",
    1003: "encoder_value",
}
"""Health indicators named in ``health().detail["device"]`` (others keep their numeric id)."""


class _Channels(Transport):
    """The control, data and health connections of one sensor, read as one transport: ``read``
    returns data-channel bytes and hands health-channel bytes to ``on_health``."""

    def __init__(
        self,
        host: str,
        ports: tuple[int, int, int],
        timeout_s: float,
        on_health: Callable[[bytes], None],
    ) -> None:
        self.description = f"gocator {host}:{ports[0]}"
        self._socks: list[socket.socket] = []
        try:
            for port in ports:
                s = socket.create_connection((host, port), timeout=timeout_s)
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self._socks.append(s)
        except OSError:
            self.close()
            raise
        self.control, self.data, self.health = self._socks
        for s in (self.data, self.health):
            s.setblocking(False)
        self._on_health = on_health
        self._buf = bytearray(1 << 18)
        self._view = memoryview(self._buf)

    def read(self, timeout: float) -> Chunk:
        try:
            ready, _, _ = select.select([self.data, self.health], [], [], timeout)
            if self.health in ready:
                chunk = self.health.recv(65536)
                if not chunk:
                    raise LinkDown(f"{self.description}: health channel closed by the device")
                self._on_health(chunk)
            if self.data in ready:
                n = self.data.recv_into(self._buf)
                if n == 0:
                    raise LinkDown(f"{self.description}: data channel closed by the device")
                return self._view[:n]
        except (BlockingIOError, InterruptedError):
            return b""
        except (OSError, ValueError) as exc:  # ValueError: a socket closed by another thread
            raise LinkDown(f"{self.description}: {exc}") from exc
        return b""

    def write(self, data: bytes) -> None:
        try:
            self.control.sendall(data)
        except OSError as exc:
            raise LinkDown(f"{self.description}: write failed: {exc}") from exc

    def command(self, cmd_id: int, timeout_s: float, payload: bytes = b"") -> tuple[int, bytes]:
        """Send a control command; ``(status, reply fields)``. Raises :class:`LinkDown`."""
        self.write(gocator.encode_command(cmd_id, payload))
        deadline = time.monotonic() + timeout_s
        reply = bytearray()
        need = gocator.REPLY_HEADER.size
        while len(reply) < need:
            left = deadline - time.monotonic()
            if left <= 0:
                raise LinkDown(f"{self.description}: no reply to command 0x{cmd_id:04x}")
            try:
                self.control.settimeout(left)
                chunk = self.control.recv(need - len(reply))
            except TimeoutError:
                continue
            except OSError as exc:
                raise LinkDown(f"{self.description}: control channel: {exc}") from exc
            if not chunk:
                raise LinkDown(f"{self.description}: control channel closed by the device")
            reply += chunk
            if len(reply) == gocator.REPLY_HEADER.size:
                need = gocator.REPLY_HEADER.unpack_from(reply)[0]
                if not gocator.REPLY_HEADER.size <= need <= gocator.MAX_COMMAND:
                    raise LinkDown(f"{self.description}: reply length {need} out of range")
        try:
            got, status, fields = gocator.parse_reply(reply)
        except gocator.FrameError as exc:
            raise LinkDown(f"{self.description}: {exc}") from exc
        if got != cmd_id:
            raise LinkDown(f"{self.description}: reply 0x{got:04x} to command 0x{cmd_id:04x}")
        return status, fields

    def close(self) -> None:
        for s in self._socks:
            with contextlib.suppress(OSError):
                s.close()


class GocatorSensor(StreamProfileSensor):
    """An LMI Gocator line profiler on its three TCP channels (see the module docstring).

    ``sensor_id`` (the serial number) keeps that sensor's profiles only.
    """

    kind: ClassVar[str] = "gocator"
    release_after_s = 0.005
    """A group waiting for the next one's header is released after this long without data."""
    reply_timeout_s = 5.0
    """Wait for each control reply (a sensor answers in milliseconds; a loaded host running the
    simulated one may take a second or more)."""

    def __init__(
        self,
        host: str,
        sensor_id: int | None = None,
        control_port: int = gocator.CONTROL_PORT,
        data_port: int = gocator.DATA_PORT,
        health_port: int = gocator.HEALTH_PORT,
        connect_timeout_s: float = 2.0,
    ) -> None:
        if not host:
            raise DriverInitError("gocator: host is empty")
        for name, port in (("control_port", control_port), ("data_port", data_port),
                           ("health_port", health_port)):  # fmt: skip
            if not 0 < port < 65536:
                raise DriverInitError(f"gocator: {name} {port} outside 1..65535")
        if connect_timeout_s <= 0:
            raise DriverInitError("gocator: connect_timeout_s must be positive")
        super().__init__(sensor_id)
        self.host = host
        self.ports = (int(control_port), int(data_port), int(health_port))
        self.connect_timeout_s = float(connect_timeout_s)
        self.info: gocator.SensorInfo | None = None
        """The sensor's Get System Info (serial number, model, firmware, state)."""
        self.protocol_version: tuple[int, int] | None = None
        self.indicators: dict[tuple[int, int], int] = {}
        """The latest health indicators ``{(id, instance): value}``."""
        self._started = False
        self._data = GdpReader()
        self._health = GdpReader(lookahead=False)
        self._last_data = 0.0
        self._group: list[Any] | None = None
        """[stamp, profile, intensity] of the group being read."""
        self._signature: tuple[int, ...] | None = None
        self._candidate: tuple[tuple[int, ...], int] | None = None
        self._ref: tuple[int, int] | None = None
        """(frame index, timestamp µs) of the last delivered frame."""
        self._held: tuple[int, int] | None = None
        self._holds = 0
        self._steps: deque[int] = deque(maxlen=9)
        self._period: float | None = None

    # --- link -------------------------------------------------------------------------------
    def _connect(self) -> Transport:
        return _Channels(self.host, self.ports, self.connect_timeout_s, self._on_health)

    def _reset_decoder(self) -> None:
        self._data.reset()
        self._health.reset()
        self._group = None
        self._held = None

    def _start(self, transport: Transport) -> None:
        assert isinstance(transport, _Channels)
        t = self.reply_timeout_s
        status, fields = transport.command(gocator.Cmd.PROTOCOL_VERSION, t)
        if status == gocator.Status.OK and len(fields) >= 2:
            self.protocol_version = (fields[0], fields[1])
        status, fields = transport.command(gocator.Cmd.GET_SYSTEM_INFO, t)
        if status != gocator.Status.OK:
            raise DriverInitError(f"gocator: Get System Info refused with status {status}")
        try:
            self.info = gocator.parse_system_info(fields)
        except gocator.FrameError as exc:
            raise LinkDown(f"{transport.description}: {exc}") from exc
        if self.info.state != 1:  # not running: start it
            status, _ = transport.command(gocator.Cmd.START, t)
            if status not in (gocator.Status.OK, gocator.Status.INVALID_STATE):
                raise DriverInitError(f"gocator: Start refused with status {status}")
            self._started = True
        status, fields = transport.command(gocator.Cmd.GET_TIMESTAMP, t)
        if status == gocator.Status.OK and len(fields) >= 8:
            self.stats["device_time_us_at_start"] = int.from_bytes(fields[:8], "little")
        self._valid()

    def _stop(self, transport: Transport) -> None:
        if self._started and isinstance(transport, _Channels):
            self._started = False
            transport.command(gocator.Cmd.STOP, 0.5)

    def _on_health(self, data: bytes) -> None:
        self.counters.bytes += len(data)
        bad0 = self._health.bad
        for kind, _, msg, _ in self._health.feed(data):
            if kind != gocator.Msg.HEALTH:
                continue
            try:
                self.indicators.update(gocator.decode_health(msg))
            except gocator.FrameError as exc:
                self._reject(str(exc))
                continue
            self.stats["health_messages"] += 1
            self._valid()
        self.stats["health_resyncs"] += self._health.bad - bad0

    # --- data -------------------------------------------------------------------------------
    def _read_internal(self, timeout: float | None) -> Profile | None:
        if not self._data.holding:
            return super()._read_internal(timeout)
        # A group waits for the next one's header: after a short quiet spell (a pause, the end
        # of acquisition) it is released as it stands.
        wait = self.release_after_s if timeout is None else min(timeout, self.release_after_s)
        profile = super()._read_internal(wait)
        if profile is None and time.monotonic() - self._last_data >= self.release_after_s:
            for kind, last, msg, received_ns in self._data.release():
                self._message(kind, last, msg, received_ns)
            profile = self._pop()
        return profile

    def _consume(self, data: Chunk, host_time_ns: int) -> None:
        self._last_data = time.monotonic()
        reader = self._data
        bad0 = reader.bad
        msgs = reader.feed(data, host_time_ns)
        for _ in range(reader.bad - bad0):
            self._group = None
            self._reject("damaged Gocator data: resynchronised")
        for kind, last, msg, received_ns in msgs:
            self._message(kind, last, msg, received_ns)

    def _message(self, kind: int, last: bool, msg: bytes, host_time_ns: int) -> None:
        Msg = gocator.Msg
        group = self._group
        try:
            if kind == Msg.STAMP:
                if group is not None:
                    self._reject("Gocator group without its last message")
                group = self._group = [gocator.decode_stamp(msg), None, None]
            elif kind in (Msg.UNIFORM_PROFILE, Msg.PROFILE_POINT_CLOUD, Msg.PROFILE_INTENSITY):
                if group is None:
                    self._reject(f"Gocator message type {kind} outside a group")
                    return
                slot = 2 if kind == Msg.PROFILE_INTENSITY else 1
                if group[slot] is not None:
                    # One profile per frame: a second one means the stream realigned on a
                    # message boundary after damage (a cut-short message completed by the next).
                    raise gocator.FrameError("Gocator group with two profile messages")
                if slot == 2:
                    group[2] = gocator.decode_intensity(msg)
                else:
                    group[1] = gocator.decode_profile(msg)
            else:
                self.stats["skipped_messages"] += 1
        except gocator.FrameError as exc:
            self._group = None
            self._reject(str(exc))
            return
        if last and group is not None:
            self._group = None
            self._finish(group, host_time_ns)

    def _alive(self) -> None:
        """A good group: the link is alive, unless it is a held group released after the link
        dropped (old data says nothing about the link)."""
        if self._transport is not None:
            self._valid()

    def _finish(self, group: list[Any], host_time_ns: int) -> None:
        stamp, prof, inten = group
        if prof is None:
            self.stats["stamp_only_groups"] += 1
            self._alive()
            return
        if inten is not None and inten.shape != prof.z.shape:
            self._reject("Gocator intensity and profile widths differ")
            return
        if self.expected_sensor_id is not None and stamp.serial != self.expected_sensor_id:
            self.stats["foreign"] += 1
            return
        if not self._plausible_group((*prof.signature, stamp.serial, stamp.stamp_size), stamp):
            return
        self._alive()
        profile = Profile(
            sensor_id=stamp.serial,
            frame_counter=stamp.frame_index,
            sensor_time_ns=stamp.timestamp_us * 1000,
            host_time_ns=host_time_ns,
            y=prof.x,
            z=prof.z,
            valid=prof.valid,
            intensity=inten,
            encoder=stamp.encoder,
        )
        if not self._deliver(profile):
            return
        ref, count, stamp_us = self._ref, stamp.frame_index, stamp.timestamp_us
        if ref is not None and count - ref[0] == 1:
            self._steps.append(stamp_us - ref[1])
            if len(self._steps) >= 3:
                self._period = float(statistics.median(self._steps))
        self._ref = (count, stamp_us)

    # --- plausibility -------------------------------------------------------------------------
    def _agrees(self, ref: tuple[int, int], count: int, stamp_us: int) -> bool:
        period = self._period
        if period is None:
            return True
        dc = count - ref[0]
        return abs(stamp_us - ref[1] - dc * period) <= 0.5 * period + 0.01 * abs(dc) * period

    def _plausible_group(self, sig: tuple[int, ...], stamp: gocator.Stamp) -> bool:
        """The locked stream fields and the frame index / timestamp check (module docstring)."""
        count, stamp_us = stamp.frame_index, stamp.timestamp_us
        if self._signature is None:
            self._signature = sig
        elif sig != self._signature:
            cand = self._candidate
            if cand is None or cand[0] != sig or not 0 < count - cand[1] < 1 << 16:
                self._candidate = (sig, count)
                self._reject("Gocator stream fields differ from the stream's")
                return False
            log.info("%s: stream parameters changed, re-locking", self.kind)
            self.stats["relocks"] += 1
            self._signature = sig
            self._restart("stream parameters changed")
            self._ref = self._held = None
            self._forget_period()
        self._candidate = None
        ref = self._ref
        if ref is not None and not self._agrees(ref, count, stamp_us):
            held = self._held
            self._holds += 1
            if self._holds >= 3:
                self._restart("frame period changed")
                self._forget_period()
            elif held is None or count <= held[0] or not self._agrees(held, count, stamp_us):
                self._held = (count, stamp_us)
                self._reject("Gocator frame index and timestamp disagree")
                return False
            else:
                self._restart("frame index or timestamp jumped")
            self._ref = None
        self._held = None
        self._holds = 0
        return True

    def _forget_period(self) -> None:
        self._steps.clear()
        self._period = None
        self._holds = 0

    def _health_detail(self) -> dict[str, Any]:
        info = self.info
        device = {INDICATORS.get(i, str(i)) + (f"[{inst}]" if inst else ""): v
                  for (i, inst), v in self.indicators.items()}  # fmt: skip
        return {
            **super()._health_detail(),
            "model": None if info is None else info.model,
            "serial": None if info is None else info.device_id,
            "firmware": None if info is None else ".".join(map(str, info.firmware)),
            "protocol_version": self.protocol_version,
            "period_us": self._period,
            "resyncs": self._data.bad,
            "device": device,
        }
