"""The Gocator pair end to end: ``[sensor] driver = "gocator"`` reading the simulated Gocator
(``[sim.sensor] kind = "gocator"``, its three TCP channels on the cell's own 127.a.b.c at the
standard ports) runs ``wristscan calibrate latency`` and a scan pass on one simulated cell, and
both agree with the simulator's truth; the configuration refuses a Gocator beside another
simulated sensor, naming the fields."""

from __future__ import annotations

import dataclasses
import importlib
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from support import (
    TRUE_POSES_ONLY,
    demo_part_one_pass_plan,
    depth_errors,
    part_signed_distance,
    registration_to_truth,
)
from typer.testing import CliRunner

from wristscan.daemon.cli.app import app
from wristscan.daemon.config import ConfigError, load_config, parse_config
from wristscan.daemon.devices import make_devices
from wristscan.daemon.scan.job import run_scan
from wristscan.daemon.simcell.cell import dump_toml, free_sim_config, write_truth_calibrations
from wristscan.daemon.simcell.demo import demo_config
from wristscan.daemon.simcell.scenarios import table_ball_cell
from wristscan.drivers import registry
from wristscan.drivers.sensor_gocator import GocatorSensor
from wristscan.drivers.sim.cell import SimulatedCell
from wristscan.drivers.sim.scene import demo_scene

SIM_LATENCY_S = 0.0023
NOISE_M = 20e-6


def _config(tmp_path: Path, **sim_sensor: Any) -> tuple[Path, dict[str, Any], str]:
    doc = free_sim_config(
        {
            "sensor": {"driver": "gocator", "latency_s": 0.0},
            "sim.sensor": {
                "kind": "gocator",
                "latency_s": SIM_LATENCY_S,
                "n_points": 512,
                "rate_hz": 500.0,
                **sim_sensor,
            },
            "calibration": {"file": "s2f.json", "table_file": "table.json"},
        }
    )
    host = doc["robot"]["host"]  # the cell's own loopback address: the Gocator's too
    doc["sensor"]["options"] = {"host": host}
    path = tmp_path / "cell.toml"
    path.write_text(dump_toml(doc))
    return path, doc, host


def test_a_gocator_driver_needs_the_simulated_gocator(tmp_path: Path) -> None:
    path, doc, _ = _config(tmp_path)
    cfg = load_config(path)
    assert cfg.sensor.driver == "gocator" and cfg.sim is not None
    assert cfg.sim.sensor.kind == "gocator"
    doc["sim"]["sensor"]["kind"] = "lpf1-udp"
    path.write_text(dump_toml(doc))
    with pytest.raises(ConfigError, match=r'sim\.sensor\.kind: "lpf1-udp" is not what .*"gocator"'):
        load_config(path)
    other, doc2, _ = _config(tmp_path)
    doc2["sensor"] = {"driver": "lpf1-udp", "options": {"bind_host": "127.0.0.1", "port": 50002}}
    other.write_text(dump_toml(doc2))
    with pytest.raises(ConfigError, match=r'sim\.sensor\.kind: "gocator" is not what'):
        load_config(other)


def test_the_driver_as_a_plugin_through_the_sensors_entry_point(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """docs/plugins.md's template: the Gocator driver registered by a distribution of its own
    under another name is listed, configured and built like the built-in one."""
    info = tmp_path / "site" / "wristscan_gocator_plugin-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: wristscan-gocator-plugin\nVersion: 0.1\n"
    )
    (info / "entry_points.txt").write_text(
        "[wristscan.sensors]\nplugin-gocator = wristscan.drivers.sensor_gocator:GocatorSensor\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    importlib.invalidate_caches()
    infos = {i.name: i for i in registry.describe() if i.kind == "sensors"}
    assert infos["gocator"].origin == "builtin" and infos["gocator"].loadable
    assert infos["plugin-gocator"].origin == "wristscan-gocator-plugin"
    assert infos["plugin-gocator"].loadable
    r = CliRunner().invoke(app, ["drivers"])
    assert r.exit_code == 0 and "plugin-gocator" in r.output
    path, doc, host = _config(tmp_path)
    doc["sensor"]["driver"] = "plugin-gocator"
    path.write_text(dump_toml(doc))
    devices = make_devices(load_config(path))
    assert isinstance(devices.sensor, GocatorSensor) and devices.sensor.host == host
    assert devices.sensor.ports == (3190, 3196, 3194)


def test_demo_sensor_choice() -> None:
    for sensor, driver, kind in (("lpf1", "lpf1-udp", "lpf1-udp"),
                                 ("rf627", "rf627-udp", "rf627-udp"),
                                 ("gocator", "gocator", "gocator")):  # fmt: skip
        doc, overrides = demo_config(sensor)
        cfg = parse_config(dump_toml(doc))
        assert cfg.sensor.driver == driver and cfg.sim is not None
        assert cfg.sim.sensor.kind == kind
        assert overrides == ({"host": doc["robot"]["host"]} if sensor == "gocator" else {})
    r = CliRunner().invoke(app, ["demo", "--sensor", "keyence"])
    assert r.exit_code != 0
    assert "--sensor must be one of lpf1, rf627, gocator, not 'keyence'" in r.output
    assert "Traceback" not in r.output


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_the_gocator_pair_runs_calibrate_latency_and_a_scan_pass(tmp_path: Path) -> None:
    path, doc, host = _config(tmp_path)
    cfg = load_config(path)
    write_truth_calibrations(cfg)  # the true sensor2flange and table axis are in force
    # One cell for both: the base ball (latency) and the demo part on the table (scan pass).
    spec = table_ball_cell(cfg, start_above="ball", host=host, **TRUE_POSES_ONLY)
    sim = cfg.sim
    assert sim is not None
    scene = demo_scene(
        ball_radius_m=sim.scene.ball_radius_m,
        ball_centre=sim.scene.ball_centre_m,
        table_zero2base=sim.truth.table_zero2base(),
    )
    spec = dataclasses.replace(spec, scene=scene)
    out = tmp_path / "latency.json"
    t0 = time.monotonic()
    with SimulatedCell(spec) as cell:
        assert cell.endpoints()["sensor"]["port"] == 3190
        # Two speeds rather than three: the test's time, not the procedure's accuracy.
        args = ["--config", str(path), "--yes", "-q", "--out", str(out), "--speeds", "50,100"]
        r = CliRunner().invoke(app, ["calibrate", "latency", *args])
        assert r.exit_code == 0, r.output
        found = json.loads(out.read_text())
        # As for LPF1 (tests/daemon/calibrate): the simulator's latency within 0.3 ms; the
        # Gocator's timestamps are whole microseconds.
        assert abs(found["latency_s"] - SIM_LATENCY_S) < 0.3e-3, found
        assert found["std_s"] < 0.1e-3, found

        t1 = time.monotonic()
        doc["sensor"]["latency_s"] = found["latency_s"]
        path.write_text(dump_toml(doc))
        cfg = load_config(path)
        plan = demo_part_one_pass_plan()
        truth = cell.truth()
        t2 = time.monotonic()
        result = run_scan(cfg, plan, confirmed=True, out_dir=tmp_path / "scan")
        t3 = time.monotonic()
    (rec,) = result.recorded
    sw = rec.sweep
    assert sw.n_profiles > 100
    s2f = np.array(truth["sensor2flange"])
    e = depth_errors(sw, scene, s2f, rec.table_angle_rad)
    assert np.median(np.abs(e[np.isfinite(e)])) < 0.9 * NOISE_M
    (cloud,) = result.clouds
    reg = registration_to_truth(cloud.xyz, lambda p: part_signed_distance(scene, p))
    figures = (
        f"pass {np.round(reg['shift_m'] * 1e6, 1)} um from the true part, "
        f"RMS {reg['rms_after_m'] * 1e6:.1f} um; latency {found['latency_s'] * 1e3:.3f} ms; "
        f"cell start and latency {t1 - t0:.0f} s, scan pass {t3 - t2:.0f} s"
    )
    print(figures)
    assert np.linalg.norm(reg["shift_m"]) < 6e-6 and reg["rms_after_m"] < NOISE_M, figures
