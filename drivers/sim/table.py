"""Simulated rotary table: a pymodbus server (TCP, or RTU over a pty) in its own process.

Register map (one shared register space, so function codes 3 and 4 read the same addresses):

======  ==========================  =====================================================
addr    name                        meaning
======  ==========================  =====================================================
0-1     encoder count               uint32, ``counts_per_rev`` per turn, wraps at 2^32
2       status                      bit0 moving, bit1 at target
10-11   target count                uint32, written by the client
12      command                     write 1: move to target, 2: stop (reads back 0)
13      speed limit                 0.1 deg/s units (0: the configured maximum)
======  ==========================  =====================================================

32-bit values span two registers; ``word_order`` "big" puts the high word at the lower address.
The table turns with a trapezoidal velocity profile along the shorter way to the target and
publishes its true angle (radians) to a :class:`~wristscan.drivers.sim.truth.TruthRing` at
1 kHz, so the simulated sensors see objects mounted on it turn.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any, Literal

from wristscan.drivers.sim.process import SimProcess
from wristscan.drivers.sim.truth import TruthRing

__all__ = ["REG", "SimulatedTable", "TableMotion", "TableSimConfig"]

log = logging.getLogger(__name__)

REG = {"encoder": 0, "status": 2, "target": 10, "command": 12, "speed": 13}
_N_REGS = 16
CMD_MOVE, CMD_STOP = 1, 2


@dataclass(frozen=True)
class TableSimConfig:
    host: str = "127.0.0.1"
    port: int = 0
    """TCP port; 0 picks a free one."""
    transport: Literal["tcp", "rtu"] = "tcp"
    device_id: int = 1
    baudrate: int = 115200
    counts_per_rev: int = 3_600_000
    word_order: Literal["big", "little"] = "big"
    max_speed_deg_s: float = 90.0
    accel_deg_s2: float = 180.0
    initial_angle_rad: float = 0.0
    truth_rate_hz: float = 1000.0
    motion_lookahead_s: float = 0.004
    """Commands take effect this long after they arrive and the truth ring is written this far
    ahead, so that a simulated sensor finds the true angle of an exposure in the ring when it
    exposes (as with the controller's ``motion_lookahead_s``)."""
    extra: dict[str, Any] = field(default_factory=dict)


class TableMotion:
    """Trapezoidal single-axis motion, evaluated analytically at any host time (seconds)."""

    def __init__(self, angle_rad: float, vmax_rad_s: float, accel_rad_s2: float) -> None:
        self.vmax = vmax_rad_s
        self.accel = accel_rad_s2
        self._start_angle = angle_rad
        self._delta = 0.0
        self._t0 = 0.0
        self._ta = 0.0  # acceleration phase duration
        self._tc = 0.0  # cruise phase duration
        self._v = 0.0  # cruise speed

    def angle(self, t: float) -> float:
        """Unwrapped angle (rad) at host time ``t`` (s)."""
        s = t - self._t0
        if self._delta == 0.0 or s <= 0:
            return self._start_angle
        sign = math.copysign(1.0, self._delta)
        ta, tc, v, a = self._ta, self._tc, self._v, self.accel
        if s < ta:
            d = 0.5 * a * s * s
        elif s < ta + tc:
            d = 0.5 * a * ta * ta + v * (s - ta)
        elif s < 2 * ta + tc:
            r = 2 * ta + tc - s
            d = abs(self._delta) - 0.5 * a * r * r
        else:
            d = abs(self._delta)
        return self._start_angle + sign * d

    def moving(self, t: float) -> bool:
        return self._delta != 0.0 and t - self._t0 < 2 * self._ta + self._tc

    def move_to(self, t: float, target_rad: float, vmax_rad_s: float | None = None) -> None:
        """Start a move from rest at ``t`` along the shorter way to ``target_rad`` (mod 2 pi)."""
        start = self.angle(t)
        delta = math.remainder(target_rad - start, 2 * math.pi)
        vmax = min(vmax_rad_s or self.vmax, self.vmax)
        ta = vmax / self.accel
        if self.accel * ta * ta >= abs(delta):  # triangular: never reaches vmax
            ta = math.sqrt(abs(delta) / self.accel)
            vmax = self.accel * ta
        tc = (abs(delta) - self.accel * ta * ta) / vmax if vmax > 0 else 0.0
        self._start_angle, self._delta, self._t0 = start, delta, t
        self._ta, self._tc, self._v = ta, max(tc, 0.0), vmax

    def stop(self, t: float) -> None:
        # A hard stop keeps the model simple; the real tables we target decelerate in < 10 ms.
        self._start_angle, self._delta = self.angle(t), 0.0


def _split32(value: int, word_order: str) -> list[int]:
    hi, lo = (value >> 16) & 0xFFFF, value & 0xFFFF
    return [hi, lo] if word_order == "big" else [lo, hi]


def _join32(words: list[int], word_order: str) -> int:
    hi, lo = (words[0], words[1]) if word_order == "big" else (words[1], words[0])
    return (hi << 16) | lo


def _serve(config: TableSimConfig, ring_name: str | None, conn: Connection) -> None:
    """Child-process body: Modbus server plus the truth publisher, until the parent says stop."""
    from pymodbus.simulator import DataType, SimData, SimDevice

    motion = TableMotion(
        config.initial_angle_rad,
        math.radians(config.max_speed_deg_s),
        math.radians(config.accel_deg_s2),
    )
    ring = TruthRing.attach(ring_name) if ring_name else None
    device = SimDevice(
        id=config.device_id,
        simdata=[SimData(0, count=_N_REGS, values=0, datatype=DataType.REGISTERS)],
        action=_register_action(config, motion),
    )
    logging.getLogger("pymodbus").setLevel(logging.ERROR)
    asyncio.run(_run(config, device, motion, ring, conn))


def _register_action(config: TableSimConfig, motion: TableMotion) -> Callable[..., Any]:
    """The device's register hook: the encoder and status on every access, commands on write."""
    from pymodbus.constants import ExcCodes

    cpr = config.counts_per_rev
    ahead_s = config.motion_lookahead_s

    def count_now(t: float) -> int:
        return round(motion.angle(t) / (2 * math.pi) * cpr) % (1 << 32)

    async def action(
        func_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        t = time.monotonic()
        enc = REG["encoder"] - start_address
        registers[enc : enc + 2] = _split32(count_now(t), config.word_order)
        if set_values is not None:
            first, last = address, address + count
            if first < REG["status"] + 1:
                return ExcCodes.ILLEGAL_ADDRESS  # encoder and status are read-only
            if first <= REG["command"] < last:
                cmd = int(set_values[REG["command"] - address])
                values = [int(v) for v in set_values]
                regs = list(registers)
                regs[address - start_address : address - start_address + count] = values
                if cmd == CMD_MOVE:
                    tgt = _join32(regs[REG["target"] : REG["target"] + 2], config.word_order)
                    tgt = tgt - (1 << 32) if tgt >= 1 << 31 else tgt  # int32
                    speed = regs[REG["speed"]] * 0.1
                    motion.move_to(
                        t + ahead_s,
                        tgt / cpr * 2 * math.pi,
                        math.radians(speed) if speed > 0 else None,
                    )
                elif cmd == CMD_STOP:
                    motion.stop(t + ahead_s)
                set_values[REG["command"] - address] = 0  # type: ignore[call-overload]
        registers[REG["status"] - start_address] = (1 if motion.moving(t) else 0) | (
            0 if motion.moving(t) else 2
        )
        return None

    return action


async def _run(
    config: TableSimConfig,
    device: Any,
    motion: TableMotion,
    ring: TruthRing | None,
    conn: Connection,
) -> None:
    """Serve ``device`` and publish the true angle until the parent says stop."""
    from pymodbus.server import ModbusSerialServer, ModbusTcpServer

    from wristscan.drivers.sim.ptypair import PtyPair

    ahead_s = config.motion_lookahead_s
    pty: PtyPair | None = None
    server: ModbusTcpServer | ModbusSerialServer
    if config.transport == "tcp":
        server = ModbusTcpServer(device, address=(config.host, config.port))
    else:
        pty = PtyPair()
        server = ModbusSerialServer(device, port=pty.paths[0], baudrate=config.baudrate)
    await server.serve_forever(background=True)
    if config.transport == "tcp":
        transport: Any = server.transport
        port = transport.sockets[0].getsockname()[1]
        conn.send(("ready", {"host": config.host, "port": port}))
    else:
        assert pty is not None
        conn.send(("ready", {"port_path": pty.paths[1]}))
    period = 1.0 / config.truth_rate_hz
    loop = asyncio.get_running_loop()
    try:
        while True:
            if conn.poll():
                msg = conn.recv()
                if msg[0] == "stop":
                    break
                if msg[0] == "angle":
                    conn.send(("angle", motion.angle(time.monotonic())))
            if ring is not None:
                t_ns = time.monotonic_ns() + round(ahead_s * 1e9)
                ring.append(t_ns, [motion.angle(t_ns * 1e-9)])
            await asyncio.sleep(period - (loop.time() % period))
    finally:
        await server.shutdown()
        if pty is not None:
            pty.close()
        if ring is not None:
            ring.close()


class SimulatedTable(SimProcess):
    """Start the simulated table in a process of its own; a context manager.

    ``endpoint`` holds ``{"host", "port"}`` for TCP or ``{"port_path"}`` (a pty path that pyserial
    and pymodbus open like a serial port) for RTU.
    """

    process_name = "sim-table"

    def __init__(self, config: TableSimConfig | None = None, ring_name: str | None = None) -> None:
        super().__init__()
        self.config = config or TableSimConfig()
        self.ring_name = ring_name

    def _target(self) -> tuple[Callable[..., None], tuple[Any, ...]]:
        return _serve, (self.config, self.ring_name)

    def true_angle(self) -> float:
        """The table's true unwrapped angle (rad), asked from its process."""
        assert self._conn is not None
        self._conn.send(("angle",))
        _, value = self._conn.recv()
        return float(value)
