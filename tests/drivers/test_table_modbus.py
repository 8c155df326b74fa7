"""Modbus rotary-table driver against the simulated table, over TCP and RTU on a pty.

Ports are on a loopback address of the run's own or held while in use (two test runs on one
machine never collide); waits are for states, with generous timeouts."""

from __future__ import annotations

import math
import time

import pytest
from support import RefusingPort, free_tcp_port, own_loopback_host

from wristscan.drivers.base import DriverInitError, LinkState
from wristscan.drivers.registry import load
from wristscan.drivers.sim.table import SimulatedTable, TableSimConfig
from wristscan.drivers.table_modbus import ModbusTable

FAST = {"max_speed_deg_s": 360.0, "accel_deg_s2": 3600.0}


def test_registry_names_the_driver() -> None:
    assert load("tables", "modbus") is ModbusTable


@pytest.mark.parametrize("transport", ["tcp", "rtu"])
def test_reads_states_and_turns(transport: str) -> None:
    cfg = TableSimConfig(transport=transport, **FAST)  # type: ignore[arg-type]
    with SimulatedTable(cfg) as sim:
        ep = sim.endpoint
        kwargs = (
            {"host": ep["host"], "port": ep["port"]}
            if transport == "tcp"
            else {"serial_port": ep["port_path"]}
        )
        with ModbusTable(transport=transport, poll_hz=200.0, **kwargs) as table:  # type: ignore[arg-type]
            states = [table.read(timeout=10.0) for _ in range(10)]
            assert all(s is not None for s in states)
            times = [s.host_time_ns for s in states if s is not None]
            assert times == sorted(times)
            table.move_to(math.radians(45.0))
            assert table.angle() == pytest.approx(math.radians(45.0), abs=1e-6)
            assert sim.true_angle() == pytest.approx(math.radians(45.0), abs=1e-6)
            table.move_to(math.radians(-20.0))
            st = table.read(timeout=10.0)
            assert st is not None and st.angle_rad == pytest.approx(math.radians(-20.0), abs=1e-6)
            assert table.counters.received == 11


def test_offset_and_little_word_order() -> None:
    cfg = TableSimConfig(word_order="little", initial_angle_rad=math.radians(10.0), **FAST)
    with SimulatedTable(cfg) as sim:
        table = ModbusTable(
            host=sim.endpoint["host"],
            port=sim.endpoint["port"],
            word_order="little",
            offset_rad=math.radians(-10.0),
        )
        with table:
            assert table.angle() == pytest.approx(0.0, abs=1e-6)
            table.move_to(math.radians(30.0))  # table angle 30 = encoder angle 40
            assert sim.true_angle() == pytest.approx(math.radians(40.0), abs=1e-6)


def test_unreachable_table_is_an_init_error() -> None:
    with RefusingPort() as refusing:  # bound, not listening: nobody can take it meanwhile
        table = ModbusTable(host=refusing.host, port=refusing.port, timeout_s=0.3)
        with pytest.raises(DriverInitError, match="cannot connect"):
            table.open()
    assert table.health().state is LinkState.FAILED
    table.close()  # idempotent on a device that never opened


def test_reconnects_when_the_table_comes_back() -> None:
    # The table comes back on the same port: one on an address of this run's own, which no
    # other process takes while the table is away.
    host = own_loopback_host()
    port = free_tcp_port(host)
    cfg = TableSimConfig(host=host, port=port, **FAST)
    sim = SimulatedTable(cfg).start()
    table = ModbusTable(host=host, port=port, poll_hz=100.0, timeout_s=0.3).open()
    try:
        assert table.read(timeout=10.0) is not None
        sim.stop()
        # Reads during the outage return None, no exception reaches the caller, until the
        # driver knows the link is lost (at least 1 s of reads; generous deadline).
        t_min = time.monotonic() + 1.0
        deadline = time.monotonic() + 30.0
        while time.monotonic() < t_min or table.health().state is not LinkState.RECONNECTING:
            assert time.monotonic() < deadline, table.health()
            assert table.read(timeout=0.2) is None
        sim = SimulatedTable(cfg).start()
        # Back: states again (how soon depends on the load and is not asserted).
        deadline = time.monotonic() + 30.0
        state = None
        while state is None and time.monotonic() < deadline:
            state = table.read(timeout=0.2)
        assert state is not None
        assert table.counters.reconnects >= 1
        assert table.health().state is LinkState.OPEN
    finally:
        table.close()
        sim.stop()
