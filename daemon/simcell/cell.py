"""Build the simulated cell described by a configuration's ``[sim]`` section.

The simulated sensor sends where the configured sensor driver listens (UDP) or listens where the
driver connects (TCP), so ``wristscan run`` with the same file talks to it unchanged.
"""

from __future__ import annotations

import dataclasses
import socket
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from wristscan.daemon.config import Config, SimConfig
from wristscan.drivers.sim.cell import CellSpec, SimulatedCell
from wristscan.drivers.sim.scene import demo_scene
from wristscan.drivers.sim.sensors import SensorSimConfig
from wristscan.drivers.sim.table import TableSimConfig
from wristscan.drivers.sim.ur.controller import ControllerConfig

__all__ = ["cell_spec", "dump_toml", "free_sim_config", "start_cell", "write_truth_calibrations"]


def _sensor_endpoint(cfg: Config) -> dict[str, Any]:
    """Where the simulated sensor must send to / listen on to meet the configured driver."""
    opts = cfg.sensor.options
    driver = cfg.sensor.driver
    if driver in ("lpf1-udp", "rf627-udp"):
        host = getattr(opts, "bind_host", "127.0.0.1")
        host = "127.0.0.1" if host in ("0.0.0.0", "", None) else host
        return {"target": (host, int(opts.port))}  # type: ignore[union-attr]
    if driver == "lpf1-tcp":
        return {"host": opts.host, "port": int(opts.port)}  # type: ignore[union-attr]
    if driver == "gocator":  # the simulated Gocator serves control_port and the two after it
        return {"host": opts.host, "port": int(opts.control_port)}  # type: ignore[union-attr]
    url = str(getattr(opts, "url", ""))
    if url.startswith("socket://"):
        host, _, port = url.removeprefix("socket://").partition(":")
        return {"host": host, "port": int(port)}
    return {}


def cell_spec(cfg: Config, **sensor_overrides: Any) -> CellSpec:
    """The :class:`CellSpec` for ``cfg.sim`` (an absent ``[sim]`` means the defaults)."""
    sim = cfg.sim or SimConfig()
    c = sim.controller
    controller = ControllerConfig(
        host=c.host,
        model=c.model,
        version=(c.version[0], c.version[1], c.version[2], c.version[3]),
        serial_number=c.serial_number,
        kinematic_errors=c.error_sizes(),
        kinematic_seed=c.kinematic_seed,
        factory_calibration=c.factory_calibration,
        factory_residual=c.factory_residual,
        joint_noise_rad=c.joint_noise_rad,
        repeatability_m=c.repeatability_m,
        noise_seed=c.noise_seed,
        primary_interface=True,  # so use_factory_kinematics works against the simulated arm
    )
    if c.q0_rad is not None:
        controller = dataclasses.replace(controller, initial_q=tuple(c.q0_rad))
    s = sim.sensor
    sensor_kwargs: dict[str, Any] = {
        "sensor_id": s.sensor_id,
        "rate_hz": s.rate_hz,
        "n_points": s.n_points,
        "half_width_m": s.fov_lateral_m / 2,
        "z_min_m": s.depth_min_m,
        "z_max_m": s.depth_max_m,
        "noise_std_m": s.noise_m,
        "dropout_prob": s.dropout_prob,
        "outlier_prob": s.outlier_prob,
        "latency_s": s.latency_s,
        "clock_offset_ns": round(s.clock_offset_s * 1e9),
        "clock_drift_ppm": s.clock_drift_ppm,
        "clock_jitter_ns": s.clock_jitter_s * 1e9,
        "send_late_s": tuple(s.send_late_s),
        "send_late_spike_prob": s.send_late_spike_prob,
        "sensor2flange": tuple(sim.truth.sensor2flange_pose),
        # The sensor sees the scene from where the flange really is: the arm's true model.
        "robot_model": controller.true_model if c.kinematic_errors != "none" else c.model,
        "encoder": "table" if s.encoder else "none",
        "intensity": s.intensity,
        "seed": s.seed,
    }
    sensor_kwargs.update(_sensor_endpoint(cfg) if cfg.sensor.driver != "plugin" else {})
    sensor_kwargs.update(sensor_overrides)
    sensor = SensorSimConfig.for_kind(s.kind, **sensor_kwargs)
    t = sim.table
    table = (
        TableSimConfig(
            host=t.host,
            port=t.port,
            transport=t.transport,
            device_id=t.device_id,
            counts_per_rev=t.counts_per_rev,
            word_order=t.word_order,
            max_speed_deg_s=t.max_speed_deg_s,
            accel_deg_s2=t.accel_deg_s2,
            initial_angle_rad=t.initial_angle_rad,
        )
        if t.enabled
        else None
    )
    scene = demo_scene(
        ball_radius_m=sim.scene.ball_radius_m,
        ball_centre=sim.scene.ball_centre_m,
        table_zero2base=sim.truth.table_zero2base(),
        with_part=sim.scene.with_part,
    )
    return CellSpec(controller=controller, sensor=sensor, table=table, scene=scene)


def start_cell(
    cfg: Config,
    controller_host: str | None = None,
    table_port: int | None = None,
    **sensor_overrides: Any,
) -> SimulatedCell:
    """Start the cell of ``cfg``. ``controller_host`` and ``table_port`` replace the configured
    addresses so that tests can run several cells side by side; ``sensor_overrides`` go to
    :class:`SensorSimConfig` (for example ``target=(host, port)``)."""
    spec = cell_spec(cfg, **sensor_overrides)
    if controller_host is not None:
        spec = dataclasses.replace(
            spec, controller=dataclasses.replace(spec.controller, host=controller_host)
        )
    if table_port is not None and spec.table is not None:
        spec = dataclasses.replace(spec, table=dataclasses.replace(spec.table, port=table_port))
    return SimulatedCell(spec).start()


def write_truth_calibrations(
    cfg: Config,
    truth: Mapping[str, Any] | None = None,
    *,
    method: str = "simulation ground truth",
) -> list[Path]:
    """Write the simulated cell's true calibrations as the calibrations in force of ``cfg``
    (with its robot and sensor identities), so that the procedures run with perfect ones: the
    sensor2flange to ``[calibration] file`` and, when ``table_file`` is set and the truth has a
    table, base2table (encoder offset 0) to ``table_file``.

    ``truth``: :meth:`SimulatedCell.truth` of the running cell, or any mapping with
    ``sensor2flange`` and optionally ``table_zero2base`` (4x4); None: the ``[sim.truth]`` of
    ``cfg`` (no cell needed). Returns the files written; ValueError without ``[calibration]
    file``."""
    from wristscan.calib import se3
    from wristscan.daemon.io.calibfile import Calibration, Residuals, identities, write_calibration

    c = cfg.calibration
    if c.file is None:
        raise ValueError(f"{cfg.source}: [calibration] file is not set")
    if truth is None:
        t = (cfg.sim or SimConfig()).truth
        truth = {"sensor2flange": t.sensor2flange(), "table_zero2base": t.table_zero2base()}
    robot, sensor = identities(cfg)
    common: dict[str, Any] = {
        "robot": robot,
        "sensor": sensor,
        "method": method,
        "residuals": Residuals(0.0),
    }
    s2f = np.asarray(truth["sensor2flange"], dtype=np.float64)
    paths = [write_calibration(c.file, Calibration("sensor2flange", s2f, **common))]
    if c.table_file is not None and truth.get("table_zero2base") is not None:
        base2table = se3.invert(np.asarray(truth["table_zero2base"], dtype=np.float64))
        table = Calibration("table", base2table, parameters={"encoder_offset_rad": 0.0}, **common)
        paths.append(write_calibration(c.table_file, table))
    return paths


# --------------------------------------------------------------------------------------------
# A copy of the embedded default on free loopback addresses (tests, demo, several cells at once)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dump_toml(doc: dict[str, Any]) -> str:
    """Plain TOML for a document of scalars, arrays and nested tables (no arrays of tables)."""
    lines: list[str] = []

    def table(prefix: str, d: dict[str, Any]) -> None:
        scalars = {k: v for k, v in d.items() if not isinstance(v, dict)}
        if prefix and scalars:
            lines.append(f"\n[{prefix}]")
        for k, v in scalars.items():
            lines.append(f"{k} = {_toml_value(v)}")
        for k, v in d.items():
            if isinstance(v, dict):
                table(f"{prefix}.{k}" if prefix else k, v)

    table("", doc)
    return "\n".join(lines) + "\n"


def _free_tcp_port(host: str) -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _free_udp_port(host: str) -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def free_sim_config(changes: dict[str, dict[str, Any]] | None = None) -> dict[str, Any]:
    """The embedded default as a TOML document (dict) on a loopback address of its own, so that
    it runs beside other cells, of this process or of another test run on the machine.

    Everything the cell and the daemon listen on is on one random ``127.a.b.c``
    (:func:`~wristscan.drivers.sim.ur.controller.pick_free_loopback_host`): the controller's
    fixed UR ports, the sensor's UDP port, the table's and zenoh's TCP ports. The ports are
    chosen by binding port 0 and releasing it, which is safe here because nothing else binds on
    that address (another run picks another of 16 million; outgoing connections use 127.0.0.1).
    ``changes`` are merged section by section (``{"robot": {...}, "sim.sensor": {...}}``). Its scan
    archive is off unless ``changes`` turn it on."""
    from wristscan.drivers.sim.ur.controller import pick_free_loopback_host

    doc: dict[str, Any] = tomllib.loads(
        (Path(__file__).parent.parent / "default_sim.toml").read_text(encoding="utf-8")
    )
    host = pick_free_loopback_host()
    table_port = _free_tcp_port(host)
    doc["robot"]["host"] = host
    doc["sim"]["controller"]["host"] = host
    doc["sensor"]["options"]["port"] = _free_udp_port(host)
    doc["sensor"]["options"]["bind_host"] = host
    doc["table"]["host"] = host
    doc["table"]["port"] = table_port
    doc["sim"]["table"]["host"] = host
    doc["sim"]["table"]["port"] = table_port
    doc["zenoh"]["listen"] = [f"tcp/{host}:{_free_tcp_port(host)}"]
    # A throw-away cell keeps no scan archive (it would land in the user's state folder)
    # unless asked to: ``{"archive": {"enabled": True, "dir": ...}}``.
    doc["archive"] = {"enabled": False}
    for dotted, values in (changes or {}).items():
        node = doc
        for part in dotted.split("."):
            node = node.setdefault(part, {})
        node.update(values)
    return doc
