"""``wristscan demo``: the embedded default end to end, with no hardware.

It starts the simulated cell of ``config/sim.toml`` on free loopback addresses, starts the daemon
(``wristscan run``, a process of its own as under systemd), and scans the demo part on the
rotary table in several passes at two table angles while subscribing to the daemon's clouds in
the part frame. The merged cloud is written as binary PLY (voxel down-sampled), and the demo
reports what it did and how well the passes agree with the known geometry.
"""

from __future__ import annotations

import logging
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import kinematics, se3
from wristscan.calib.merge import voxel_mean_chunks
from wristscan.daemon.cloud.client import CloudClient
from wristscan.daemon.config import Config, load_config
from wristscan.daemon.simcell.cell import (
    dump_toml,
    free_sim_config,
    start_cell,
    write_truth_calibrations,
)

__all__ = ["SENSORS", "DemoResult", "demo_config", "run_demo"]

log = logging.getLogger(__name__)

STANDOFF_M = 0.085
"""Sensor origin above the part's top face: the top sits at 85 mm in a 50-150 mm range."""
PASS_SPEED_M_S = 0.05
TABLE_ANGLES_DEG = (0.0, 90.0)
PASS_OFFSETS_M = (-0.04, 0.0, 0.04)
"""Lateral offsets of the passes across the part (the laser line is 50 mm wide)."""


@dataclass
class DemoResult:
    out: Path
    passes: int
    points_received: int
    points_written: int
    batches: int
    lost_batches: int
    top_height_m: float
    top_flatness_m: float
    pass_offsets_m: list[float] = field(default_factory=list)
    stats: dict[str, Any] = field(default_factory=dict)
    preview: Path | None = None
    """The PNG preview next to ``out``, or None when it could not be drawn."""
    preview_skipped: str = ""
    """Why there is no preview (e.g. the ``plot`` extra is missing)."""


class _Collector:
    """Receives the daemon's batches in a thread; tags them with the pass running at the time."""

    def __init__(self, client: CloudClient) -> None:
        self.client = client
        self.current_pass = -1
        self.chunks: list[tuple[int, NDArray[np.float32]]] = []
        self.seqs: list[int] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="demo-collector", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            cloud = self.client.recv(timeout=0.1)
            if cloud is None:
                continue
            self.seqs.append(cloud.seq)
            if self.current_pass >= 0 and cloud.n_points:
                self.chunks.append((self.current_pass, np.array(cloud.xyz)))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)


SENSORS = {"lpf1": "LPF1", "rf627": "Riftek RF627", "gocator": "LMI Gocator"}
"""The sensor pairs the demo runs: ``[sensor] driver`` with its simulated counterpart."""


def demo_config(sensor: str = "lpf1") -> tuple[dict[str, Any], dict[str, Any]]:
    """The demo's configuration document (on loopback addresses of its own) for ``sensor`` (a
    key of :data:`SENSORS`), and the overrides its simulated sensor needs."""
    if sensor not in SENSORS:
        raise ValueError(f"unknown demo sensor {sensor!r}; one of {', '.join(SENSORS)}")
    doc = free_sim_config(
        {
            "calibration": {"file": "sensor2flange.json", "table_file": "table.json"},
            "pipeline": {"frame": "part"},
            "sim.sensor": {"rate_hz": 500.0},
        }
    )
    host = doc["robot"]["host"]
    overrides: dict[str, Any] = {}
    if sensor == "rf627":
        doc["sensor"]["driver"] = "rf627-udp"
        doc["sim"]["sensor"]["kind"] = "rf627-udp"
    elif sensor == "gocator":
        # Its three TCP channels at the standard ports on the cell's own loopback address.
        doc["sensor"]["driver"] = "gocator"
        doc["sensor"]["options"] = {"host": host}
        doc["sim"]["sensor"]["kind"] = "gocator"
        overrides["host"] = host
    return doc, overrides


def run_demo(
    out: Path,
    voxel_m: float = 0.0005,
    progress: Callable[[str], None] = print,
    workdir: Path | None = None,
    sensor: str = "lpf1",
) -> DemoResult:
    """Run the demo with ``sensor`` (a key of :data:`SENSORS`); returns what it measured.
    Raises ``RuntimeError`` when a part of the cell or the daemon does not come up."""
    tmp = tempfile.TemporaryDirectory(prefix="wristscan-demo-")
    folder = Path(workdir or tmp.name)
    doc, overrides = demo_config(sensor)
    cfg_path = folder / "cell.toml"
    cfg_path.write_text(dump_toml(doc))
    cfg = load_config(cfg_path)
    progress(f"starting the simulated cell (UR5e, {SENSORS[sensor]} sensor, Modbus rotary table)")
    cell = start_cell(cfg, **overrides)
    daemon: subprocess.Popen[bytes] | None = None
    try:
        truth = cell.truth()
        write_truth_calibrations(cfg, truth, method="simulation ground truth (demo)")
        progress("starting the daemon: wristscan run --config " + str(cfg_path))
        log_file = open(folder / "daemon.log", "wb")
        daemon = subprocess.Popen(
            [sys.executable, "-m", "wristscan.daemon.cli.app", "run", "--config", str(cfg_path)],
            stdout=log_file,
            stderr=subprocess.STDOUT,
        )
        endpoint = cfg.zenoh.listen[0]
        # The demo's own daemon is unsecured: the user's client credentials do not apply to it.
        with CloudClient(
            cfg.zenoh.prefix, connect=[endpoint], capacity=4096, user_config=False
        ) as client:
            deadline = time.monotonic() + 60
            while not client.alive(timeout=0.5):
                if daemon.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(
                        f"the daemon did not come up; see {folder / 'daemon.log'}:\n"
                        + (folder / "daemon.log").read_text()[-2000:]
                    )
            collector = _Collector(client)
            try:
                offsets = _scan_passes(cfg, cell, truth, collector, progress)
            finally:
                collector.stop()
            stats = client.query("stats")
        return _write_result(out, collector, offsets, stats, voxel_m)
    finally:
        if daemon is not None:
            daemon.terminate()
            try:
                daemon.wait(timeout=30)
            except subprocess.TimeoutExpired:
                daemon.kill()
                daemon.wait()
        cell.stop()
        tmp.cleanup()


def _write_result(
    out: Path,
    collector: _Collector,
    offsets: list[float],
    stats: dict[str, Any],
    voxel_m: float,
) -> DemoResult:
    """Merge the clouds the passes received, write them to ``out`` (PLY) and measure them."""
    chunks = collector.chunks
    if not chunks:
        raise RuntimeError("the daemon published no points during the passes")
    clouds = [c for _, c in chunks]
    seqs = np.array(sorted(set(collector.seqs)))
    lost = int(seqs[-1] - seqs[0] + 1 - seqs.size) if seqs.size else 0
    # The grid starts at the coordinate origin (the same voxels whatever the points); batch by
    # batch, not one float64 copy of tens of millions of points.
    merged = voxel_mean_chunks(clouds, voxel_m).astype(np.float32)
    from wristscan.daemon.io.ply import write_ply

    write_ply(out, merged)
    preview, skipped = _write_preview(out.with_suffix(".png"), merged, len(offsets))
    height, flat = _top_face(clouds)
    return DemoResult(
        out=out,
        passes=len(offsets),
        points_received=sum(int(c.shape[0]) for c in clouds),
        points_written=int(merged.shape[0]),
        batches=int(seqs.size),
        lost_batches=lost,
        top_height_m=height,
        top_flatness_m=flat,
        pass_offsets_m=offsets,
        stats=stats,
        preview=preview,
        preview_skipped=skipped,
    )


def _write_preview(path: Path, merged: NDArray[np.float32], passes: int) -> tuple[Path | None, str]:
    """The PNG preview of the merged cloud, or (None, why not): a missing extra never fails
    the demo."""
    from wristscan.daemon.io.preview import PreviewUnavailable, write_preview

    title = f"wristscan demo: {merged.shape[0]} points from {passes} passes (part frame)"
    try:
        return write_preview(path, merged, title=title), ""
    except PreviewUnavailable as exc:
        return None, str(exc)


def _scan_passes(
    cfg: Config,
    cell: Any,
    truth: dict[str, Any],
    collector: _Collector,
    progress: Callable[[str], None],
) -> list[float]:
    """Linear passes at constant orientation (the paper's best mode) over the part, at each table
    angle; returns the pass offsets used."""
    from wristscan.drivers.table_modbus import ModbusTable
    from wristscan.drivers.ur.robot import URRobot

    s2f = np.array(truth["sensor2flange"])
    axis_point = np.array(truth["table_axis_point_m"])
    top_z = 0.07  # the demo part's top face above the table top (drivers/sim/scene.py)
    r = cfg.robot
    robot = URRobot(
        r.host,
        motion_enabled=True,
        max_speed_m_s=r.max_speed_m_s,
        max_accel_m_s2=r.max_accel_m_s2,
        max_joint_speed_rad_s=r.max_joint_speed_rad_s,
        max_joint_accel_rad_s2=r.max_joint_accel_rad_s2,
        workspace_min_m=r.workspace_min_m,
        workspace_max_m=r.workspace_max_m,
        model=r.model,
    )
    assert cfg.table is not None
    t = cfg.table
    table = ModbusTable(host=t.host or "127.0.0.1", port=t.port, poll_hz=20.0)
    n_pass = 0
    offsets: list[float] = []
    with robot, table:
        state = None
        while state is None:
            state = robot.read(timeout=1.0)
        q = np.asarray(state.q)
        for angle_deg in TABLE_ANGLES_DEG:
            progress(f"turning the table to {angle_deg:.0f} deg")
            table.move_to(np.radians(angle_deg))
            for dy in PASS_OFFSETS_M:
                centre = axis_point + np.array([0.0, dy, top_z])
                flange2sensor = se3.invert(s2f)
                down = se3.rot_x(np.pi)
                start = se3.make(down, centre + np.array([-0.11, 0.0, STANDOFF_M])) @ flange2sensor
                end = se3.make(down, centre + np.array([0.11, 0.0, STANDOFF_M])) @ flange2sensor
                q = kinematics.inverse_nearest(r.model, start, q)
                robot.move_j(q, min(1.0, r.max_joint_speed_rad_s), r.max_joint_accel_rad_s2)
                progress(f"pass {n_pass + 1}: table {angle_deg:.0f} deg, offset {dy * 1e3:+.0f} mm")
                collector.current_pass = n_pass
                robot.move_l(
                    se3.matrix_to_pose(end), min(PASS_SPEED_M_S, r.max_speed_m_s), r.max_accel_m_s2
                )
                time.sleep(0.3)  # let the last profiles of the pass be paired and published
                collector.current_pass = -1
                q = kinematics.inverse_nearest(r.model, end, q)
                offsets.append(dy)
                n_pass += 1
    return offsets


def _top_face(clouds: list[NDArray[np.float32]]) -> tuple[float, float]:
    """Height above the table top and RMS flatness of the part's top face (part frame), from
    the batches' points."""
    pts = np.concatenate([c[_on_top_face(c)] for c in clouds]).astype(np.float64)
    if pts.shape[0] < 100:
        return float("nan"), float("nan")
    centred = pts - pts.mean(axis=0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][2]
    flat = float(np.sqrt(np.mean((centred @ normal) ** 2)))
    return float(np.median(pts[:, 2])), flat


def _on_top_face(xyz: NDArray[np.float32]) -> NDArray[np.bool_]:
    box_top = 0.07
    sel = (
        (np.abs(xyz[:, 2] - box_top) < 0.002)
        & (np.abs(xyz[:, 0] - 0.02) < 0.035)
        & (np.abs(xyz[:, 1] - 0.01) < 0.025)
    )
    # The boss stands on the top face: keep away from it.
    return sel & (np.hypot(xyz[:, 0] - 0.04, xyz[:, 1] - 0.01) > 0.015)
