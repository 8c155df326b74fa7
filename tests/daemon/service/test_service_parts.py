"""The service's bookkeeping on its own: what a reload changes (and so rebuilds), counters carried
over reloads, and how ``wristscan status`` shows a degraded daemon."""

from __future__ import annotations

from typing import Any

import pytest

from wristscan.daemon.cli.status import render, state_text
from wristscan.daemon.config import parse_config
from wristscan.daemon.service.changes import config_changes
from wristscan.daemon.service.totals import CarriedCounters, counters_line
from wristscan.daemon.simcell.cell import dump_toml, free_sim_config

BASE = free_sim_config()


def _cfg(**changes: dict[str, Any]) -> Any:
    doc: dict[str, Any] = {k: (dict(v) if isinstance(v, dict) else v) for k, v in BASE.items()}
    for section, values in changes.items():
        node = doc
        parts = section.split(".")
        for part in parts[:-1]:
            node[part] = dict(node[part])
            node = node[part]
        node[parts[-1]] = {**node.get(parts[-1], {}), **values}
    return parse_config(dump_toml(doc), "cell.toml")


def test_a_reload_rebuilds_only_what_changed() -> None:
    old = _cfg()
    port = old.sensor.options.port
    ch = config_changes(old, _cfg(**{"sensor.options": {"port": port + 1}}))
    assert ch.names() == ["sensor.options.port"]
    assert ch.device_kinds == {"sensor"} and ch.pipeline and not ch.session and not ch.face
    assert ch.describe() == f"sensor.options.port {port} -> {port + 1}"

    # the calibration alone, or the [service] section: no new pipeline
    assert not config_changes(old, _cfg(calibration={"check_identity": False})).pipeline
    assert not config_changes(old, _cfg(service={"outage_after_s": 3.0})).pipeline
    archive = config_changes(old, _cfg(archive={"keep": 5}))
    assert archive.names() == ["archive.keep"] and not archive.pipeline
    assert config_changes(old, _cfg()).names() == []

    # zenoh: the publishers' settings re-declare the face, the endpoints open a new session
    face = config_changes(old, _cfg(zenoh={"prefix": "plant/cell9"}))
    assert face.face and not face.session and not face.devices and face.pipeline
    listen = config_changes(old, _cfg(zenoh={"listen": ["tcp/127.0.0.1:7999"]}))
    assert listen.session and listen.face

    both = config_changes(old, _cfg(robot={"frequency_hz": 125.0}, table={"poll_hz": 50.0}))
    assert both.device_kinds == {"robot", "table"}
    assert both.names() == ["robot.frequency_hz", "table.poll_hz"]


def _final(received: int, published: int, dropped: dict[str, int], pending: int) -> dict[str, Any]:
    return {
        "received": received,
        "published": published,
        "dropped": dropped,
        "pending": pending,
        "published_points": published * 10,
        "published_batches": published // 5,
        "robot_states": 1000,
        "robot_states_dropped": 0,
        "sensor": {"received": received, "lost": 2},
        "robot": {"received": 1000, "lost": 0},
        "table": None,
        "slow_ticks": 1,
        "state_waited_s": 0.5,
        "tick_ms_max": 12.0,
        "read_errors": {},
        "gc_pauses_over_20ms": {},
        "worker_cpu_s": {"read": 0.1},
        "latency_ms": {"total": {"p99": 3.0}},
    }


def test_counters_stay_cumulative_and_add_up_over_reloads() -> None:
    totals = CarriedCounters()
    # a pipeline stopped by a reload that replaced the sensor only, 3 profiles still held
    totals.carry(_final(100, 90, {"before_buffer": 7}, 3), replaced={"sensor"})
    now = totals.merge(_final(50, 45, {"before_buffer": 1, "flushed": 2}, 2))
    assert now["received"] == 150 and now["published"] == 135
    assert now["dropped"] == {"before_buffer": 8, "flushed": 2, "reload": 3}
    assert now["received"] == now["published"] + sum(now["dropped"].values()) + now["pending"]
    assert now["published_batches"] == 18 + 9 and now["published_points"] == 1350
    # the replaced sensor's counters are carried, the robot kept open counts on by itself
    assert now["sensor"] == {"received": 150, "lost": 4}
    assert now["robot"] == {"received": 1000, "lost": 0} and now["robot_states"] == 1000
    assert now["tick_ms_max"] == 12.0 and now["state_waited_s"] == pytest.approx(1.0)
    assert now["latency_ms"] == {"total": {"p99": 3.0}}  # the running pipeline's window
    line = counters_line(now)
    assert line.startswith("received 150 = published 135 + dropped 13 (before_buffer 8, ")
    # after the last pipeline stopped: the carried counters alone
    totals.carry(_final(50, 45, {"before_buffer": 1, "flushed": 2}, 0))
    end = totals.snapshot()
    assert (end["received"], end["published"], end["pending"]) == (150, 135, 0)
    assert end["robot_states"] == 1000 and totals.pipelines == 2


def test_status_shows_what_is_degraded() -> None:
    waiting = {
        "state": "waiting",
        "waiting_for": "robot",
        "degraded": ["waiting for robot for 12 s (connection refused)"],
    }
    assert state_text(waiting) == "waiting: waiting for robot for 12 s (connection refused)"
    degraded = {"state": "degraded", "degraded": ["no profiles for 3.0 s"], "received": 5}
    snap = {
        "prefix": "wristscan/sim",
        "alive": True,
        "status": degraded,
        "status_age_s": 0.2,
        "stats": None,
    }
    lines = render(snap, 3.0)
    assert "state    degraded: no profiles for 3.0 s" in lines
    assert state_text({"state": "running", "degraded": []}) == "running"
    assert state_text("not json") is None
