"""The simulated LMI Gocator: the three TCP channels of the Gocator Protocol and what it sends.

Channels (:class:`GocatorLink`): control, data and health servers on ``config.host`` (any
127.x.y.z). ``config.port`` 0 gives each a free port; otherwise the control channel listens on
``port``, the data channel on ``port + 6`` and the health channel on ``port + 4`` (3190, 3196
and 3194 for the standard port 3190). As on the other simulated TCP sensors, one client per
channel at a time; faults apply to the data channel's message groups (one group per frame is
one wire unit), never to control replies or health messages.

Conversation (:class:`GocatorProtocol`): ``Protocol Version``, ``Get System Info`` (serial =
``sensor_id``, state ready or running), ``Start`` (invalid state when running), ``Stop`` and
``Get Timestamp`` (the device clock in µs) are answered; other commands get "invalid command".
The sensor boots ready and exposes only while running; a reboot makes it ready again. Each
frame is sent as a Stamp (frame index, device time in µs, encoder, serial), a uniform profile
(``gocator_uniform``; else a profile point cloud) and, with ``intensity``, the profile
intensity. Every ``heartbeat_s`` a health message reports the sensor state, speed, uptime,
internal temperature, processing drops (the simulator's overruns), Ethernet output and drops.
"""

from __future__ import annotations

import selectors
import struct
from collections import defaultdict
from typing import Any

from wristscan.drivers import gocator
from wristscan.drivers.sim.clock import DeviceClock
from wristscan.drivers.sim.sensor_config import SensorSimConfig
from wristscan.drivers.sim.sensor_links import Link, TcpLink
from wristscan.drivers.sim.sensor_protocols import Batch, SensorProtocol

__all__ = ["GocatorLink", "GocatorProtocol"]

PROTOCOL_VERSION = (1, 0)
"""What the simulated sensor reports (a real sensor reports its firmware's)."""
FIRMWARE = (6, 1, 0, 0)


class GocatorLink(Link):
    """Control, data and health TCP servers; ``send`` goes to the data channel."""

    def __init__(self, stats: dict[str, int], host: str, port: int) -> None:
        super().__init__(stats)
        ports = (0, 0, 0) if port == 0 else (port, port + 6, port + 4)
        self.host = host
        self.data = TcpLink(stats, host, ports[1])
        # Replies and health messages are not the sensor's wire units: separate counters.
        self.control = TcpLink(defaultdict(int), host, ports[0])
        self.health = TcpLink(defaultdict(int), host, ports[2])
        self.links = (self.control, self.data, self.health)

    @property
    def connected(self) -> bool:  # type: ignore[override]
        return self.data.connected

    def register(self, sel: selectors.BaseSelector) -> None:
        for link in self.links:
            link.register(sel)

    def send(self, unit: bytes) -> None:
        self.data.send(unit)

    def flush(self, now_ns: int) -> None:
        for link in self.links:
            link.flush(now_ns)

    def wants_write(self) -> bool:
        return any(link.wants_write() for link in self.links)

    def go_down(self, sel: selectors.BaseSelector) -> None:
        for link in self.links:
            link.go_down(sel)

    def come_back(self, sel: selectors.BaseSelector) -> None:
        for link in self.links:
            link.come_back(sel)

    def endpoint(self) -> dict[str, Any]:
        return {
            "host": self.host,
            "port": self.control.port,
            "data_port": self.data.port,
            "health_port": self.health.port,
        }

    def close(self) -> None:
        for link in self.links:
            link.close()


class GocatorProtocol(SensorProtocol):
    """The sensor side of the Gocator Protocol (see the module docstring)."""

    def __init__(self, cfg: SensorSimConfig, link: Link, clock: DeviceClock) -> None:
        super().__init__(cfg, link, clock)
        assert isinstance(link, GocatorLink)
        self.glink = link
        link.control.on_data = self.on_command_bytes
        link.control.on_connect = self.inbuf_clear
        self.inbuf = bytearray()
        self.running = False
        self.boot_ns = clock.now_ns()
        self.next_health_ns = 0
        self.bytes_out = 0
        self.encoder = gocator.GocatorEncoder(
            cfg.sensor_id,
            cfg.n_points,
            uniform=cfg.gocator_uniform,
            intensity=cfg.intensity,
            z_range_m=(cfg.z_min_m, cfg.z_max_m),
            x_half_width_m=cfg.half_width_m,
        )

    def inbuf_clear(self) -> None:
        self.inbuf.clear()

    def wants_exposures(self) -> bool:
        return self.running and self.link.connected

    # --- control ------------------------------------------------------------------------------
    def on_command_bytes(self, data: bytes) -> None:
        buf = self.inbuf
        buf += data
        while len(buf) >= gocator.CMD_HEADER.size:
            length, cmd_id = gocator.CMD_HEADER.unpack_from(buf)
            if not gocator.CMD_HEADER.size <= length <= gocator.MAX_COMMAND:
                buf.clear()  # not the Gocator Protocol: forget it
                return
            if len(buf) < length:
                return
            del buf[:length]
            self.glink.control.send_now(self.answer(cmd_id))

    def answer(self, cmd_id: int) -> bytes:
        Cmd, Status = gocator.Cmd, gocator.Status
        if cmd_id == Cmd.PROTOCOL_VERSION:
            return gocator.encode_reply(cmd_id, Status.OK, bytes(PROTOCOL_VERSION))
        if cmd_id == Cmd.GET_SYSTEM_INFO:
            info = gocator.SensorInfo(
                self.cfg.sensor_id,
                self.glink.host,
                "wristscan-sim Gocator",
                FIRMWARE,
                1 if self.running else 0,
                0,
                0,
            )
            return gocator.encode_reply(cmd_id, Status.OK, gocator.encode_system_info(info))
        if cmd_id == Cmd.START:
            status = Status.INVALID_STATE if self.running else Status.OK
            self.running = True
            return gocator.encode_reply(cmd_id, status)
        if cmd_id == Cmd.STOP:
            self.running = False
            return gocator.encode_reply(cmd_id, Status.OK)
        if cmd_id == Cmd.GET_TIMESTAMP:
            now_us = max(0, self.clock.now_ns() // 1000)
            return gocator.encode_reply(cmd_id, Status.OK, struct.pack("<Q", now_us))
        return gocator.encode_reply(cmd_id, Status.INVALID_COMMAND)

    # --- data ---------------------------------------------------------------------------------
    def encode(self, batch: Batch) -> list[list[bytes]]:
        intensity = batch.intensity
        if self.cfg.intensity and intensity is None:
            raise ValueError("intensity configured but not measured")
        groups = self.encoder.encode(
            batch.counters,
            batch.stamps_ns // 1000,
            batch.meas.y,
            batch.meas.z,
            batch.meas.valid,
            intensity=intensity,
            encoder=batch.encoder,
        )
        self.bytes_out += sum(len(g) for g in groups)
        return [[g] for g in groups]

    def periodic(self, now_ns: int, counter: int) -> None:
        if self.cfg.heartbeat_s <= 0 or now_ns < self.next_health_ns:
            return
        self.next_health_ns = now_ns + int(self.cfg.heartbeat_s * 1e9)
        stats = self.link.stats
        indicators = {
            (20000, 0): 1 if self.running else 0,
            (20001, 0): round(self.cfg.rate_hz) if self.running else 0,
            (2017, 0): max(0, (self.clock.now_ns() - self.boot_ns) // 1_000_000_000),
            (2002, 0): 4150,
            (21000, 0): stats.get("overrun", 0),
            (21003, 0): self.bytes_out,
            (21005, 0): stats.get("tx_overflow", 0),
        }
        self.glink.health.send_now(gocator.encode_health(indicators))

    def on_reboot(self) -> None:
        self.running = False
        self.boot_ns = self.clock.now_ns()
        self.inbuf.clear()
