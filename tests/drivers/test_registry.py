"""Driver registry: built-in names, entry points, clear errors, and the ``drivers`` command."""

from __future__ import annotations

import json
from importlib.metadata import EntryPoint

import pytest

from wristscan.daemon.cli.app import main
from wristscan.drivers import registry
from wristscan.drivers.base import DriverNotAvailable


def test_unknown_name_lists_the_known_ones() -> None:
    with pytest.raises(KeyError, match="known: lpf1-udp"):
        registry.load("sensors", "nope")


def test_missing_dependency_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(
        registry.BUILTIN["sensors"],
        "gocator",
        registry._Builtin("wristscan_no_such_module:Gocator", "gocator", "LMI Gocator"),
    )
    with pytest.raises(DriverNotAvailable, match=r"pip install 'wristscan\[gocator\]'"):
        registry.load("sensors", "gocator")


def test_entry_point_drivers_are_found(monkeypatch: pytest.MonkeyPatch) -> None:
    ep = EntryPoint(
        name="plugin-table",
        value="wristscan.drivers.table_modbus:ModbusTable",
        group="wristscan.tables",
    )

    def fake_entry_points(group: str) -> list[EntryPoint]:
        return [ep] if group == "wristscan.tables" else []

    monkeypatch.setattr(registry, "entry_points", fake_entry_points)
    assert "plugin-table" in registry.names("tables")
    assert registry.load("tables", "plugin-table").__name__ == "ModbusTable"


def test_drivers_command_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["drivers", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    by_name = {(r["kind"], r["name"]): r for r in rows}
    assert by_name[("tables", "modbus")]["loadable"] is True
    assert {"sensors", "robots", "tables"} == {r["kind"] for r in rows}
