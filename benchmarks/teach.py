"""The applications of the calibrated sensor on the simulated cell (issue 8; Borangiu et al.
2009, section 5): plane frame teaching, edge path learning, replay with another tool.

Everything runs as ``wristscan teach ...`` runs it: the simulated UR5e controller and LPF1
sensor in their own processes on loopback, the real drivers, the synchroniser, the procedures.
The sensor calibration in force is the simulator's truth (these are benchmarks of the
applications, not of the calibration); sensor noise 0.02 mm per point along the ray, 512 points
over 50 mm at 500 Hz.

1. **Plane frame.** A plate whose top is tilted 15 degrees about an oblique axis; the sensor starts
   0.1 m above it looking straight down (so the surface is seen at 15 degrees); 4 spots, 30 mm
   apart. Truth: the plate's top plane; the origin where the first spot's sensor Z axis meets it.
   Targets: normal within 0.01 degree, origin within 0.05 mm.
2. **Edge path.** The rim of a boss with a domed top (``drivers/sim/scenes_apps.py``): in plan a
   circle of 60 mm radius, its height varying by 15 mm around it and the top tilting by 7-21
   degrees at the rim, so direction, height and normal all change along the edge. A step edge
   (dome top, side wall, table) learned over ``--length-mm`` (default 60 mm) from a start pose
   1.5 mm off the edge, 3 mm off the standoff and 3 degrees off the normal. Targets: RMS
   distance of the 1 mm path points to the true rim <= 0.1 mm, no gap (largest distance between
   the raw edge points along the path <= the resolution), spacing 1 mm.
3. **Replay.** The learned path replayed with a torch-like tool (TCP 240 mm out and 30 mm to
   the side of the flange, tilted 5.7 degrees; a 10 degree travel angle) by a URScript program
   of blended ``movel`` run by the simulated controller. The tool tip is computed from the true
   joint positions at 1 kHz. Target: it stays within 0.2 mm of the true rim along the whole path.

Run: ``.venv/bin/python benchmarks/teach.py [--length-mm 60] [--json out.json] [--plot
edge.png]``; exits 1 on a miss. Takes about a minute and a half.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from wristscan.calib import kinematics, se3
from wristscan.calib.edge import EdgeModel
from wristscan.daemon.config import Config, load_config
from wristscan.daemon.io.urpose import parse_ur_pose
from wristscan.daemon.simcell.cell import dump_toml, free_sim_config
from wristscan.daemon.simcell.scenarios import cell_with_scene, write_truth_calibration
from wristscan.daemon.teach.edge import EdgeOptions, learn_edge
from wristscan.daemon.teach.edge_path import read_edge_path, write_edge_path
from wristscan.daemon.teach.plane import (
    PlaneOptions,
    teach_plane,
)
from wristscan.daemon.teach.replay import ReplayOptions, plan_replay, run_program
from wristscan.drivers.sim.cell import SimulatedCell
from wristscan.drivers.sim.scene import sensor_looking_down
from wristscan.drivers.sim.scenes_apps import dome_scene, sensor_pose_at_edge, tilted_plate_scene

sys.path.insert(0, str(Path(__file__).parent))
from _report import Figure, report

TOOL = "p[0.0, 0.03, 0.24, 0.1, 0.0, 0.0]"


def _config(folder: Path) -> Config:
    doc = free_sim_config(
        {
            "calibration": {"file": "s2f.json"},
            "sim.sensor": {"n_points": 512, "rate_hz": 500.0},
            "table": {"enabled": False},
            "sim.table": {"enabled": False},
        }
    )
    path = folder / "cell.toml"
    path.write_text(dump_toml(doc))
    return load_config(path)


def _log(text: str) -> None:
    print(f"  .. {text}", flush=True)


def bench_plane(folder: Path) -> list[Figure]:
    cfg = _config(folder)
    scene, truth = tilted_plate_scene(tilt_deg=15.0, tilt_axis_deg=35.0)
    start = sensor_looking_down(truth.point + np.array([-0.02, -0.02, 0.0]), 0.1, 0.3)
    spec = cell_with_scene(cfg, scene, start)
    write_truth_calibration(cfg, spec)
    _log("plane: starting the cell")
    with SimulatedCell(spec):
        res = teach_plane(
            cfg,
            PlaneOptions(spacing_m=0.03, n_spots=4),
            confirmed=True,
            progress=lambda e: _log(f"plane: {e.message}"),
        )
    s0 = res.spots[0].sensor2base
    origin_true = truth.intersect_line(s0[:3, 3], s0[:3, 2])
    n_err = math.degrees(math.acos(min(1.0, float(res.normal @ truth.normal))))
    o_err = float(np.linalg.norm(res.origin - origin_true))
    return [
        Figure("plane normal error", n_err, "deg", "<= 0.01", n_err <= 0.01),
        Figure("plane origin error", o_err * 1e3, "mm", "<= 0.05", o_err <= 5e-5),
        Figure(
            "plane normal 1-sigma (fit)", math.degrees(res.fit.sigma_normal_rad), "deg", "", None
        ),
        Figure("plane form error", res.fit.form_error * 1e3, "mm", "", None),
        Figure("plane teaching time", res.duration_s, "s", "", None),
    ]


def bench_edge_and_replay(folder: Path, length_mm: float) -> tuple[list[Figure], dict[str, Any]]:
    cfg = _config(folder)
    scene, truth = dome_scene()
    phi0 = math.radians(200)
    start = sensor_pose_at_edge(truth, phi0, 0.1) @ se3.make(
        se3.rot_x(math.radians(3)), (0.0, 0.0015, 0.003)
    )
    spec = cell_with_scene(cfg, scene, start)
    write_truth_calibration(cfg, spec)
    model = EdgeModel("step", height_m=(0.005, 0.08))
    figs: list[Figure] = []
    _log("edge: starting the cell")
    with SimulatedCell(spec) as cell:
        t0 = time.monotonic()
        res = learn_edge(
            cfg,
            model,
            EdgeOptions(length_m=length_mm * 1e-3, resolution_m=0.001),
            confirmed=True,
            progress=lambda e: _log(f"edge: {e.message}") if e.step % 10 == 0 else None,
        )
        t_learn = time.monotonic() - t0
        path_file = write_edge_path(folder / "path.json", res, cfg)
        learned = read_edge_path(path_file)
        tool = parse_ur_pose(TOOL)
        plan = plan_replay(
            learned,
            tool,
            ReplayOptions(lead_rad=math.radians(10.0), speed_m_s=0.02),
            cfg=cfg,
        )
        (folder / "replay.script").write_text(plan.script())
        _log(f"replay: {plan.poses.shape[0]} waypoints")
        t_start = time.monotonic_ns()
        outcome = run_program(cfg, plan, timeout_s=120.0)
        t_end = time.monotonic_ns()
        assert cell.robot_ring is not None
        q = cell.robot_ring.sample(np.arange(t_start, t_end, 1_000_000, dtype=np.int64))
    _log(f"replay: {outcome}")
    # Edge path against the true rim.
    p = res.path
    phis = truth.azimuth_of(p.points)
    dense = truth.dense(float(phis.min()) - 0.05, float(phis.max()) + 0.05, 1e-6)
    tree = cKDTree(dense)
    d, _ = tree.query(p.points)
    rms = float(np.sqrt(np.mean(d**2)))
    spacing = np.diff(p.s)
    n_err = np.degrees(
        np.arccos(np.clip(np.einsum("ij,ij->i", p.normals, truth.normals(phis)), -1, 1))
    )
    covered = p.length_m >= 0.95 * length_mm * 1e-3
    figs += [
        Figure("edge RMS deviation (1 mm path)", rms * 1e3, "mm", "<= 0.1", rms <= 1e-4),
        Figure("edge max deviation", float(d.max()) * 1e3, "mm", "", None),
        Figure(
            "edge largest gap in raw points",
            p.max_gap_m * 1e3,
            "mm",
            "<= 1 (resolution)",
            p.max_gap_m <= 1e-3,
        ),
        Figure(
            "edge spacing error (max)",
            float(np.abs(spacing - 1e-3).max()) * 1e3,
            "mm",
            "<= 0.01",
            float(np.abs(spacing - 1e-3).max()) <= 1e-5,
        ),
        Figure("edge length learned", p.length_m * 1e3, "mm", f">= {0.95 * length_mm:g}", covered),
        Figure("edge normal error (max)", float(n_err.max()), "deg", "", None),
        Figure(
            "edge height change along path", float(np.ptp(p.points[:, 2])) * 1e3, "mm", "", None
        ),
        Figure(
            "edge direction change along path",
            math.degrees(math.acos(float(np.clip(p.tangents[0] @ p.tangents[-1], -1, 1)))),
            "deg",
            "",
            None,
        ),
        Figure("edge learning time", t_learn, "s", "", None),
    ]
    # Replay: the tool tip from the true joints, from arrival at the first waypoint to the last.
    q = q[np.all(np.isfinite(q), axis=1)]
    tips = (kinematics.forward(cfg.robot.model, q) @ se3.pose_to_matrix(tool))[:, :3, 3]
    first, last = plan.poses[0, :3, 3], plan.poses[-1, :3, 3]
    at_first = np.flatnonzero(np.linalg.norm(tips - first, axis=1) < 2e-6)
    at_last = np.flatnonzero(np.linalg.norm(tips - last, axis=1) < 2e-6)
    if at_first.size == 0 or at_last.size == 0:
        figs.append(Figure("replay reached the path ends", 0.0, "", "yes", False))
        return figs, {}
    process = tips[int(at_first[0]) : int(at_last[0]) + 1]
    d_tip, _ = tree.query(process)
    travelled = float(np.linalg.norm(np.diff(process, axis=0), axis=1).sum())
    figs += [
        Figure(
            "replay tool tip max deviation",
            float(d_tip.max()) * 1e3,
            "mm",
            "<= 0.2",
            float(d_tip.max()) <= 2e-4,
        ),
        Figure(
            "replay tool tip RMS deviation", float(np.sqrt(np.mean(d_tip**2))) * 1e3, "mm", "", None
        ),
        Figure("replay waypoints", float(plan.poses.shape[0]), "", "", None),
        Figure("replay tip travel / path length", travelled / p.length_m, "", "", None),
    ]
    return figs, {
        "path": p.points,
        "path_dev": d,
        "raw": res.raw_points,
        "tips": process,
        "tip_dev": d_tip,
        "rim": dense[:: max(1, dense.shape[0] // 4000)],
    }


def plot(data: dict[str, Any], out: str) -> None:
    """Top view of the learned path, the raw edge points and the tool tip over the true rim,
    and the deviations along the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    rim, path, tips = data["rim"] * 1e3, data["path"] * 1e3, data["tips"] * 1e3
    a.plot(rim[:, 0], rim[:, 1], "k-", lw=0.8, label="true rim")
    a.plot(data["raw"][:, 0] * 1e3, data["raw"][:, 1] * 1e3, ".", ms=2, color="0.6", label="raw")
    a.plot(path[:, 0], path[:, 1], "o", ms=3, mfc="none", label="learned path (1 mm)")
    a.plot(tips[:, 0], tips[:, 1], "-", lw=0.8, label="tool tip (replay)")
    a.set_aspect("equal")
    a.set_xlabel("base x (mm)")
    a.set_ylabel("base y (mm)")
    a.legend(fontsize=8)
    s_path = np.arange(path.shape[0])
    b.plot(s_path, data["path_dev"] * 1e3, "o-", ms=3, label="learned path")
    s_tip = np.linspace(0, s_path[-1], tips.shape[0])
    b.plot(s_tip, data["tip_dev"] * 1e3, "-", lw=0.8, label="tool tip")
    b.axhline(0.1, color="C0", ls=":", lw=0.8)
    b.axhline(0.2, color="C1", ls=":", lw=0.8)
    b.set_xlabel("along the path (mm)")
    b.set_ylabel("distance to the true rim (mm)")
    b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def run(length_mm: float = 60.0, plot_to: str | None = None) -> list[Figure]:
    """Run the three benchmarks; returns the figures (``plot_to``: a PNG of the edge)."""
    with tempfile.TemporaryDirectory(prefix="wristscan-teach-") as tmp:
        folder = Path(tmp)
        (folder / "plane").mkdir()
        (folder / "edge").mkdir()
        figs = bench_plane(folder / "plane")
        edge_figs, data = bench_edge_and_replay(folder / "edge", length_mm)
    if plot_to and data:
        plot(data, plot_to)
    return figs + edge_figs


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--length-mm", type=float, default=60.0, help="Edge length to learn.")
    ap.add_argument("--json", help="Write the figures as JSON.")
    ap.add_argument("--plot", help="Write a PNG of the learned edge and the tool tip.")
    args = ap.parse_args()
    t0 = time.monotonic()
    figs = run(args.length_mm, args.plot)
    figs.append(Figure("benchmark time", time.monotonic() - t0, "s", "", None))
    return report("teach: plane frame, edge path, replay (simulated cell)", figs, args.json)


if __name__ == "__main__":
    sys.exit(main())
