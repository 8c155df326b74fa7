"""Simulated rotary table: a real pymodbus client reads and turns it, over TCP and RTU on a pty."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np
import pytest
from pymodbus.client import ModbusSerialClient, ModbusTcpClient

from wristscan.drivers.sim.table import REG, SimulatedTable, TableMotion, TableSimConfig
from wristscan.drivers.sim.truth import TruthRing

CPR = 3_600_000


def _count(regs: Sequence[int]) -> int:
    return (regs[0] << 16) | regs[1]


def _move(client: ModbusTcpClient | ModbusSerialClient, angle_rad: float, dev: int) -> None:
    target = round(angle_rad / (2 * math.pi) * CPR) % (1 << 32)
    rr = client.write_registers(REG["target"], [target >> 16, target & 0xFFFF, 1, 0], device_id=dev)
    assert not rr.isError()


def _wait_still(client: ModbusTcpClient | ModbusSerialClient, dev: int, timeout: float) -> int:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        rr = client.read_input_registers(REG["encoder"], count=3, device_id=dev)
        assert not rr.isError()
        if rr.registers[2] & 2:
            return _count(rr.registers)
        time.sleep(0.05)
    raise AssertionError("table did not reach its target")


def test_tcp_read_turn_and_truth() -> None:
    with TruthRing.create(width=1) as ring:
        cfg = TableSimConfig(max_speed_deg_s=180.0, accel_deg_s2=720.0)
        with SimulatedTable(cfg, ring.name) as table:
            client = ModbusTcpClient(table.endpoint["host"], port=table.endpoint["port"])
            assert client.connect()
            try:
                rr = client.read_holding_registers(REG["encoder"], count=3, device_id=1)
                assert not rr.isError() and _count(rr.registers) == 0
                # The move takes 30/180 + 180/720 = 0.42 s of host time (the table is evaluated
                # at the host time of each request). The status read straight after says moving,
                # as long as it came within that time: checked against the times around it, not
                # assumed, since a loaded machine may take longer.
                t_sent = time.monotonic()
                _move(client, math.radians(30.0), 1)
                moving = client.read_input_registers(REG["status"], count=1, device_id=1)
                within_move = time.monotonic() - t_sent < 0.4
                assert moving.registers[0] & (1 if within_move else 3)
                count = _wait_still(client, 1, 30.0)
                assert count == round(30.0 / 360.0 * CPR)
                assert table.true_angle() == pytest.approx(math.radians(30.0), abs=1e-12)
                latest = ring.latest()
                assert latest is not None
                assert latest[1][0] == pytest.approx(math.radians(30.0), abs=1e-9)
                # Going to 350 degrees takes the shorter way (-40 degrees), through zero.
                _move(client, math.radians(350.0), 1)
                count = _wait_still(client, 1, 30.0)
                assert count == (round(-10.0 / 360.0 * CPR) % (1 << 32))
                assert table.true_angle() == pytest.approx(math.radians(-10.0), abs=1e-12)
                # The encoder registers are read-only.
                assert client.write_register(REG["encoder"], 5, device_id=1).isError()
            finally:
                client.close()


def test_rtu_over_pty() -> None:
    cfg = TableSimConfig(transport="rtu", max_speed_deg_s=360.0, accel_deg_s2=3600.0)
    with SimulatedTable(cfg) as table:
        client = ModbusSerialClient(table.endpoint["port_path"], baudrate=115200, timeout=1)
        assert client.connect()
        try:
            _move(client, math.radians(90.0), 1)
            assert _wait_still(client, 1, 30.0) == CPR // 4
        finally:
            client.close()


def test_trapezoid_profile_shape() -> None:
    m = TableMotion(0.0, vmax_rad_s=1.0, accel_rad_s2=2.0)
    m.move_to(0.0, 2.0)
    t = np.linspace(0, 3, 3001)
    a = np.array([m.angle(x) for x in t])
    v = np.gradient(a, t)
    assert v.max() == pytest.approx(1.0, abs=1e-2)  # cruises at vmax
    assert a[-1] == pytest.approx(2.0) and not m.moving(3.0)
    assert np.all(np.diff(a) >= -1e-12)
    short = TableMotion(0.0, vmax_rad_s=10.0, accel_rad_s2=1.0)
    short.move_to(0.0, 0.25)  # triangular: peak speed sqrt(a*d) = 0.5
    assert short.angle(0.5) == pytest.approx(0.125)
    assert short.angle(1.0) == pytest.approx(0.25)
