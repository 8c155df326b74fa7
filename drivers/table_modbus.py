"""Rotary table over Modbus TCP or RTU (pymodbus client).

The angle comes from a 32-bit encoder count in two registers:
``angle_rad = count * scale_rad_per_count + offset_rad`` with the word order and the register
addresses from the configuration. ``read`` polls the encoder at ``poll_hz`` and yields
:class:`TableState` records; ``move_to`` writes a target count and a move command (the register
map of the simulated table, which mirrors common indexer controllers; see drivers/sim/table.py).
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any, Literal

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ModbusException

from wristscan.drivers.base import (
    Backoff,
    DriverInitError,
    DriverIOError,
    DriverTimeout,
    LinkState,
    RotaryTable,
)
from wristscan.drivers.records import TableState

__all__ = ["ModbusTable"]

log = logging.getLogger(__name__)


class ModbusTable(RotaryTable):
    """A rotary table read and turned over Modbus."""

    def __init__(
        self,
        transport: Literal["tcp", "rtu"] = "tcp",
        host: str = "127.0.0.1",
        port: int = 502,
        serial_port: str = "",
        baudrate: int = 115200,
        device_id: int = 1,
        encoder_register: int = 0,
        status_register: int = 2,
        target_register: int = 10,
        command_register: int = 12,
        speed_register: int = 13,
        word_order: Literal["big", "little"] = "big",
        counts_per_rev: int = 3_600_000,
        scale_rad_per_count: float | None = None,
        offset_rad: float = 0.0,
        register_type: Literal["holding", "input"] = "input",
        encoder_bits: Literal[16, 32] = 32,
        parity: Literal["N", "E", "O"] = "N",
        stopbits: Literal[1, 2] = 1,
        poll_hz: float = 100.0,
        timeout_s: float = 1.0,
    ) -> None:
        super().__init__()
        if transport not in ("tcp", "rtu"):
            raise DriverInitError(f"table transport must be 'tcp' or 'rtu', not {transport!r}")
        if word_order not in ("big", "little"):
            raise DriverInitError(f"word_order must be 'big' or 'little', not {word_order!r}")
        if counts_per_rev <= 0 or poll_hz <= 0:
            raise DriverInitError("counts_per_rev and poll_hz must be positive")
        self.transport = transport
        self.host, self.port = host, port
        self.serial_port, self.baudrate = serial_port, baudrate
        self.device_id = device_id
        self.regs = {
            "encoder": encoder_register,
            "status": status_register,
            "target": target_register,
            "command": command_register,
            "speed": speed_register,
        }
        self.word_order = word_order
        self.counts_per_rev = counts_per_rev
        # A signed scale (an encoder counting clockwise) overrides counts_per_rev.
        self.scale_rad_per_count = (
            scale_rad_per_count if scale_rad_per_count is not None else 2 * math.pi / counts_per_rev
        )
        if self.scale_rad_per_count == 0:
            raise DriverInitError("scale_rad_per_count must not be zero")
        if register_type not in ("holding", "input") or encoder_bits not in (16, 32):
            raise DriverInitError("register_type must be holding/input, encoder_bits 16 or 32")
        self.register_type = register_type
        self.encoder_bits = encoder_bits
        self.parity, self.stopbits = parity, stopbits
        self.offset_rad = offset_rad
        self.period_s = 1.0 / poll_hz
        self.timeout_s = timeout_s
        self._client: ModbusTcpClient | ModbusSerialClient | None = None
        self._backoff = Backoff()
        self._next_poll = 0.0

    # --- link -------------------------------------------------------------------------------
    def _make_client(self) -> ModbusTcpClient | ModbusSerialClient:
        if self.transport == "tcp":
            return ModbusTcpClient(
                self.host, port=self.port, timeout=self.timeout_s, retries=0, reconnect_delay=0
            )
        return ModbusSerialClient(
            self.serial_port,
            baudrate=self.baudrate,
            parity=self.parity,
            stopbits=self.stopbits,
            timeout=self.timeout_s,
            retries=0,
        )

    def _where(self) -> str:
        return f"{self.host}:{self.port}" if self.transport == "tcp" else self.serial_port

    def _open(self) -> None:
        client = self._make_client()
        if not client.connect():
            client.close()
            raise DriverInitError(
                f"table: cannot connect to Modbus {self.transport} {self._where()}"
            )
        self._client = client
        self._read_count()  # fail at open, not at the first read, when the map is wrong

    def _close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None

    def _reconnect(self) -> None:
        self.counters.reconnects += 1
        self._set_state(LinkState.RECONNECTING)
        if self._client is not None:
            self._client.close()
        time.sleep(self._backoff.next_delay())
        client = self._make_client()
        if client.connect():
            self._client = client
            self._backoff.reset()
            self._set_state(LinkState.OPEN)
        else:
            client.close()

    # --- registers ----------------------------------------------------------------------------
    def _call(self, fn: str, *args: Any, **kwargs: Any) -> Any:
        if self._client is None:
            raise DriverIOError("table: not connected")
        try:
            rr = getattr(self._client, fn)(*args, device_id=self.device_id, **kwargs)
        except (ModbusException, OSError) as exc:
            raise DriverIOError(f"table: {fn} failed: {exc}") from exc
        if rr.isError():
            raise DriverIOError(f"table: {fn} refused by the device: {rr}")
        return rr

    def _join(self, words: list[int]) -> int:
        hi, lo = (words[0], words[1]) if self.word_order == "big" else (words[1], words[0])
        return (hi << 16) | lo

    def _split(self, value: int) -> list[int]:
        hi, lo = (value >> 16) & 0xFFFF, value & 0xFFFF
        return [hi, lo] if self.word_order == "big" else [lo, hi]

    def _read_count(self) -> tuple[int, int]:
        fn = "read_input_registers" if self.register_type == "input" else "read_holding_registers"
        words = self.encoder_bits // 16
        rr = self._call(fn, self.regs["encoder"], count=words)
        regs = list(rr.registers)
        count = regs[0] if words == 1 else self._join(regs)
        return count, time.monotonic_ns()

    def _count_to_angle(self, count: int) -> float:
        half = 1 << (self.encoder_bits - 1)
        signed = count - (half << 1) if count >= half else count
        return float(signed) * self.scale_rad_per_count + self.offset_rad

    # --- RotaryTable ------------------------------------------------------------------------
    def _read_internal(self, timeout: float | None) -> TableState | None:
        now = time.monotonic()
        wait = self._next_poll - now
        if wait > 0:
            if timeout is not None and wait > timeout:
                time.sleep(timeout)
                return None
            time.sleep(wait)
        self._next_poll = max(self._next_poll + self.period_s, time.monotonic())
        try:
            t_before = time.monotonic_ns()
            count, t_after = self._read_count()
        except DriverIOError as exc:
            self._set_state(LinkState.RECONNECTING, str(exc))
            self._reconnect()
            return None
        if self._state is not LinkState.OPEN:  # pymodbus may have reconnected on its own
            self._backoff.reset()
            self._set_state(LinkState.OPEN)
        # The register was sampled somewhere within the round trip: stamp its middle.
        return TableState(
            angle_rad=self._count_to_angle(count),
            device_time_ns=None,
            host_time_ns=(t_before + t_after) // 2,
        )

    def angle(self) -> float:
        count, _ = self._read_count()
        return self._count_to_angle(count)

    def moving(self) -> bool:
        rr = self._call("read_input_registers", self.regs["status"], count=1)
        return bool(rr.registers[0] & 1)

    def move_to(
        self,
        angle_rad: float,
        wait: bool = True,
        timeout_s: float = 30.0,
        speed_deg_s: float = 0.0,
    ) -> None:
        """Turn to ``angle_rad`` (the table takes the shorter way); ``speed_deg_s`` 0 = default."""
        # One turn's worth of counts: 2^32 is not a whole number of turns.
        count = (
            round((angle_rad - self.offset_rad) / self.scale_rad_per_count) % self.counts_per_rev
        )
        speed = max(0, min(0xFFFF, round(speed_deg_s * 10)))
        if self.regs["command"] == self.regs["target"] + 2 and self.regs["speed"] == (
            self.regs["target"] + 3
        ):
            self._call("write_registers", self.regs["target"], [*self._split(count), 1, speed])
        else:
            self._call("write_registers", self.regs["target"], self._split(count))
            self._call("write_register", self.regs["speed"], speed)
            self._call("write_register", self.regs["command"], 1)
        if not wait:
            return
        deadline = time.monotonic() + timeout_s
        time.sleep(0.02)
        while self.moving():
            if time.monotonic() > deadline:
                raise DriverTimeout(f"table did not reach {math.degrees(angle_rad):.3f} deg")
            time.sleep(0.01)

    def stop(self) -> None:
        self._call("write_register", self.regs["command"], 2)
