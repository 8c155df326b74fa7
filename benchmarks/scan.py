"""Scan jobs on the simulated cell: the demo part scanned in several passes at two table angles.

Run: ``.venv/bin/python benchmarks/scan.py [--speed-mm-s 20] [--keep DIR]``

1. The simulated cell (UR5e, LPF1 sensor 512 points at 500 Hz, 20 um noise, Modbus table) with
   its true sensor and table calibrations written as the calibrations in force.
2. A plan generated over the demo part's bounding box (part frame): line 50 mm, overlap 30 %,
   standoff 100 mm, table at 0 and 90 deg, views tilted +-15 deg about the pass direction.
3. ``run_scan`` executes it (motion, recording, alignment, ICP merge, outputs).
4. Figures against the ground truth of the scene (analytic distances to the part's primitives,
   in the part frame = the scene's table frame):

   * merged cloud (voxel 0.25 mm) deviation from the true surface, RMS, before ICP (passes as
     the calibration aligned them) and after ICP;
   * the largest ICP correction with the true calibration;
   * the same recorded passes aligned with a sensor calibration off by 0.3 mm (along the
     sensor's X, Y and Z in turn): whether the report flags it;
   * coverage, measured in the recorded clouds: the part's surface visible from the plan's
     views (dense ray casting of the true scene from each view direction over the whole box)
     against the merged cloud; the largest distance from a visible surface sample to the nearest
     scanned point (a gap between strips would show here); the overlap of neighbouring strips
     (the share of the smaller cloud, thinned to 0.5 mm voxels, within 0.5 mm of the other),
     with the planner's own figure beside it as information.

Exits non-zero when a target is missed.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import pickle
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))
from _report import Figure, report
from support import primitive_signed_distance

from wristscan.calib import se3
from wristscan.calib.merge import MergeOptions, corrected_clouds, merge_passes, voxel_mean
from wristscan.daemon.config import load_config
from wristscan.daemon.scan.job import ScanCalibration, align_passes, report_lines, run_scan
from wristscan.daemon.scan.plan import describe_plan
from wristscan.daemon.scan.plan_file import ScanPlan, down_matrix
from wristscan.daemon.scan.plan_generate import generate_plan
from wristscan.daemon.simcell.cell import (
    dump_toml,
    free_sim_config,
    start_cell,
    write_truth_calibrations,
)
from wristscan.drivers.sim.scene import Scene, demo_scene

FloatArray = NDArray[np.float64]

PART_BBOX_MIN = (-0.0893, -0.02, 0.03)
"""The demo part (box, boss, 30 deg ramp) on the platter top, part frame (m)."""
PART_BBOX_MAX = (0.06, 0.04, 0.09)
FOV_M = 0.05
OVERLAP = 0.3
STANDOFF_M = 0.10
DEPTH_RANGE_M = (0.05, 0.15)
TABLE_DEG = (0.0, 90.0)
TILTS_DEG = (15.0, -15.0)
OFF_M = 0.3e-3
OVERLAP_VOXEL_M = 0.5e-3
"""Grid on which the overlap of neighbouring strips is measured in their clouds."""


# --------------------------------------------------------------------------------------------
# Ground truth: distance to the table-mounted primitives (part frame)


def part_distance(scene: Scene, p: FloatArray) -> FloatArray:
    """Distance (m) of part-frame points from the nearest table-mounted surface."""
    prims = [x for x in scene.primitives if x.mount == "table"]
    out = np.full(p.shape[0], np.inf)
    for a in range(0, p.shape[0], 200_000):
        blk = p[a : a + 200_000]
        out[a : a + blk.shape[0]] = np.min(
            [np.abs(primitive_signed_distance(x, blk)) for x in prims], axis=0
        )
    return out


def rms(x: FloatArray) -> float:
    return float(np.sqrt(np.mean(x * x)))


# --------------------------------------------------------------------------------------------
# Coverage: the true surface visible from the plan's views


def visible_samples(
    scene: Scene, plan: ScanPlan, spacing_m: float = 0.0005
) -> tuple[FloatArray, FloatArray]:
    """Part-frame points of the true surface that the plan's views can see inside the plan's
    box, and the view direction of each: for every (table angle, orientation) of the plan, a
    dense grid of rays along the sensor's +Z over the box's whole projection, within the
    measuring range."""
    g = plan.generator or {}
    lo, hi = np.asarray(g["bbox_min_m"]), np.asarray(g["bbox_max_m"])
    views = {
        (p.table_deg, p.orientation.yaw_deg, p.orientation.tilt_deg)
        for p in plan.passes
        if hasattr(p, "orientation")
    }
    corners = np.array(
        [
            [(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]]
            for i in (0, 1)
            for j in (0, 1)
            for k in (0, 1)
        ]
    )
    pts, dirs = [], []
    for table_deg, yaw, tilt in sorted(views, key=str):
        R = down_matrix(yaw, 0.0, tilt)
        proj = corners @ R
        (u0, v0, d0), (u1, v1, d1) = proj.min(axis=0), proj.max(axis=0)
        depth = 0.5 * (d0 + d1) - STANDOFF_M
        uu, vv = np.meshgrid(np.arange(u0, u1, spacing_m), np.arange(v0, v1, spacing_m))
        local = np.column_stack([uu.ravel(), vv.ravel(), np.full(uu.size, depth)])
        o_part = local @ R.T
        theta = math.radians(table_deg or 0.0)
        t2b = scene.table2base(theta)
        o_base = o_part @ t2b[:3, :3].T + t2b[:3, 3]
        d_base = np.broadcast_to(t2b[:3, :3] @ R[:, 2], o_base.shape)
        t, hit = scene.raycast(o_base, d_base, theta)
        ok = hit & (t >= DEPTH_RANGE_M[0]) & (t <= DEPTH_RANGE_M[1])
        p = o_part[ok] + t[ok, None] * R[:, 2]
        inside = np.all((p >= lo - 1e-4) & (p <= hi + 1e-4), axis=1)
        pts.append(p[inside])
        dirs.append(np.broadcast_to(R[:, 2], p[inside].shape))
    return np.concatenate(pts), np.concatenate(dirs)


# --------------------------------------------------------------------------------------------
# Overlap of neighbouring strips, measured in the recorded clouds


def _view_key(p: Any) -> tuple[Any, ...]:
    o = getattr(p, "orientation", None)
    return (p.kind, p.table_deg, None if o is None else (o.yaw_deg, o.pitch_deg, o.tilt_deg))


def measured_overlaps(
    recorded: Any, clouds: list[Any], plan: ScanPlan, voxel_m: float = OVERLAP_VOXEL_M
) -> list[tuple[str, str, float]]:
    """For each pair of neighbouring strips (consecutive passes of the plan with the same table
    angle and view; numbered from 1 as the plan lists them), the share of the surface both
    recorded clouds cover: the clouds are thinned to one point per ``voxel_m`` voxel, and the
    share is that of the smaller cloud's points with a point of the other within ``voxel_m``.
    Where the surface is flat this is the planner's shared width over the line width;
    occlusions, steep faces, the crop and lost profiles count as they fall."""
    thin = [voxel_mean(np.asarray(c.xyz, dtype=np.float64), voxel_m)[0] for c in clouds]
    out = []
    for i in range(len(recorded) - 1):
        a, b = recorded[i], recorded[i + 1]
        if b.index != a.index + 1:
            continue  # a pass that was not recorded between them
        if _view_key(plan.passes[a.index]) != _view_key(plan.passes[b.index]):
            continue
        small, big = sorted((thin[i], thin[i + 1]), key=len)
        if len(small) == 0:
            out.append((f"{a.index + 1}", f"{b.index + 1}", 0.0))
            continue
        d, _ = cKDTree(big).query(small, distance_upper_bound=2 * voxel_m)
        out.append((f"{a.index + 1}", f"{b.index + 1}", float(np.mean(d <= voxel_m))))
    return out


# --------------------------------------------------------------------------------------------
# The simulated cell itself: do the profiles match the scene seen from their paired poses?


def bad_profiles(
    scene: Scene, recorded: Any, cal: ScanCalibration, plan: ScanPlan, limit_m: float = 0.1e-3
) -> tuple[list[NDArray[np.bool_]], list[float]]:
    """Per pass: the profiles whose points (inside the plan's box, aligned with the true
    calibrations) lie off the true surface (90th percentile of the distance above ``limit_m``),
    and the pass's median distance (m). A profile paired with a wrong instant (the simulator
    falling behind on a loaded machine: "truth ring does not cover some exposures", or a
    synchroniser error) shows here, before any merge: along the motion it shows on the faces
    that are not parallel to it."""
    masks, medians = [], []
    assert plan.crop is not None
    lo, hi = np.asarray(plan.crop.min_m), np.asarray(plan.crop.max_m)
    for r, c in zip(recorded, align_passes(recorded, cal, plan.frame), strict=True):
        sw = r.sweep
        idx = sw.profile_index[sw.valid & np.isfinite(sw.y) & np.isfinite(sw.z)]
        inside = np.all((c.xyz >= lo) & (c.xyz <= hi), axis=1)
        d = part_distance(scene, c.xyz[inside])
        idx = idx[inside]
        p90 = np.zeros(sw.n_profiles)
        order = np.argsort(idx, kind="stable")
        cuts = np.flatnonzero(np.diff(idx[order])) + 1
        for grp in np.split(order, cuts):
            if grp.size:
                p90[idx[grp[0]]] = np.percentile(d[grp], 90)
        masks.append(p90 > limit_m)
        medians.append(float(np.median(d)) if d.size else math.inf)
    return masks, medians


def run(speed_m_s: float = 0.02, keep: Path | None = None) -> int:
    logging.basicConfig(level=logging.WARNING)
    tmp = tempfile.TemporaryDirectory(prefix="wristscan-bench-scan-")
    folder = Path(tmp.name) if keep is None else keep
    folder.mkdir(parents=True, exist_ok=True)
    doc = free_sim_config(
        {
            "calibration": {"file": "s2f.json", "table_file": "table.json"},
            "sim.sensor": {"rate_hz": 500.0, "n_points": 512},
        }
    )
    (folder / "cell.toml").write_text(dump_toml(doc))
    cfg = load_config(folder / "cell.toml")
    plan = generate_plan(
        PART_BBOX_MIN,
        PART_BBOX_MAX,
        fov_width_m=FOV_M,
        overlap=OVERLAP,
        standoff_m=STANDOFF_M,
        table_angles_deg=TABLE_DEG,
        tilts_deg=TILTS_DEG,
        depth_range_m=DEPTH_RANGE_M,
        speed_m_s=speed_m_s,
        name="demo part",
    )
    print("\n".join(describe_plan(plan)))
    t0 = time.monotonic()
    cell = start_cell(cfg)
    try:
        truth = cell.truth()
        write_truth_calibrations(cfg, truth)
        res = run_scan(
            cfg,
            plan,
            confirmed=True,
            out_dir=folder / "out",
            progress=lambda e: print(f"[{time.monotonic() - t0:5.1f} s] {e}"),
        )
    finally:
        cell.stop()
    print("\n".join(report_lines(res.report)))
    if keep is not None:
        with open(folder / "recorded.pkl", "wb") as fh:  # for --replay
            pickle.dump((res.recorded, res.calibration, plan, truth, res.duration_s), fh)
    return evaluate(res.recorded, res.calibration, plan, truth, res.duration_s)


@dataclasses.dataclass
class _Merged:
    dev_before: float
    dev_after: float
    shifts: list[float]
    rots: list[float]
    unmeasured: int
    after: FloatArray


def _merge_figures(
    scene: Scene, recorded: Any, cal: ScanCalibration, plan: ScanPlan, opts: MergeOptions
) -> _Merged:
    """Merge as run_scan does; deviation of the merged clouds (voxel 0.25 mm) from the true
    surface before and after ICP, and the corrections."""
    clouds = align_passes(recorded, cal, plan.frame, plan)
    merge = merge_passes(clouds, opts)

    def merged(cs: Any) -> FloatArray:
        return voxel_mean(np.concatenate([c.xyz for c in cs]), opts.voxel_m)[0]

    before = merged(clouds)
    after = merged(corrected_clouds(clouds, merge))
    ok = [c for c in merge.corrections if c.status != "not measured"]
    return _Merged(
        rms(part_distance(scene, before)),
        rms(part_distance(scene, after)),
        [c.shift_m for c in ok],
        [c.rotation_deg for c in ok],
        len(merge.corrections) - len(ok),
        after,
    )


def evaluate(
    recorded: Any, cal: ScanCalibration, plan: ScanPlan, truth: dict[str, Any], duration_s: float
) -> int:
    """The figures of a recorded scan (the merge is computed again, as run_scan does it).

    The cell is checked first: a profile whose points lie off the true surface before any merge
    was paired with a wrong instant (the simulator falls behind on a loaded machine). The
    issue's figures are computed without such profiles, and also as recorded (information), so
    that a fault of the cell is told apart from one of the merge."""
    scene = demo_scene(table_zero2base=np.array(truth["table_zero2base"]))
    opts = MergeOptions()
    bad, med = bad_profiles(scene, recorded, cal, plan)
    n_bad = sum(int(b.sum()) for b in bad)
    n_prof = sum(b.size for b in bad)
    print(
        "recorded passes: median distance to the true surface (um): "
        + ", ".join(f"{e * 1e6:.1f}" for e in med)
        + f"; profiles off it by > 0.1 mm (90th percentile): {n_bad} of {n_prof} ("
        + ", ".join(str(int(b.sum())) for b in bad)
        + ")"
    )
    as_recorded = _merge_figures(scene, recorded, cal, plan, opts)
    clean_rec = [
        dataclasses.replace(
            r, sweep=dataclasses.replace(r.sweep, valid=r.sweep.valid & ~b[r.sweep.profile_index])
        )
        for r, b in zip(recorded, bad, strict=True)
    ]
    m = _merge_figures(scene, clean_rec, cal, plan, opts) if n_bad else as_recorded

    # The same passes with a sensor calibration off by 0.3 mm.
    off_results: dict[str, int] = {}
    for axis, name in enumerate("XYZ"):
        delta = np.zeros(3)
        delta[axis] = OFF_M
        off = ScanCalibration(
            cal.sensor2flange @ se3.make(t=delta), cal.base2table, cal.encoder_offset_rad
        )
        mo = merge_passes(align_passes(clean_rec, off, plan.frame, plan), opts)
        off_results[name] = len(mo.flagged)
        biggest = max(c.shift_m for c in mo.corrections if c.status != "not measured")
        print(
            f"calibration off by 0.3 mm along sensor {name}: {len(mo.flagged)} of "
            f"{len(mo.corrections)} passes flagged, largest correction {biggest * 1e3:.3f} mm"
        )

    # Coverage of the visible surface and the strips' overlap, in the recorded clouds.
    # (as recorded: removing the faulty profiles leaves holes by construction)
    vis, _ = visible_samples(scene, plan)
    dist, _ = cKDTree(as_recorded.after).query(vis, k=1)
    covered = float(np.mean(dist <= 0.5e-3))
    overlaps = measured_overlaps(recorded, align_passes(recorded, cal, plan.frame, plan), plan)
    print(
        "strip overlap measured in the clouds (neighbouring passes: share of the smaller cloud "
        f"within {OVERLAP_VOXEL_M * 1e3:g} mm of the other): "
        + ", ".join(f"passes {a}|{b} {o * 100:.0f} %" for a, b, o in overlaps)
    )
    min_overlap = min((o for _, _, o in overlaps), default=0.0)
    g = plan.generator or {}
    n_angles = len({p.table_deg for p in plan.passes})
    print(
        f"{len(recorded)} passes at {n_angles} table angles, {len(m.after)} merged points, "
        f"{vis.shape[0]} visible surface samples"
    )
    tag = " (cell faults removed)" if n_bad else ""
    figures = [
        Figure(
            "profiles off the true surface before any merge",
            n_bad,
            "",
            "0 (else the cell failed)",
            n_bad == 0,
        ),
        Figure(
            f"passes (at {n_angles} table angles)",
            len(recorded),
            "",
            ">= 4 at >= 2 angles",
            len(recorded) >= 4 and n_angles >= 2,
        ),
        Figure(
            "merged deviation before ICP, RMS" + tag,
            m.dev_before * 1e3,
            "mm",
            "<= 0.05",
            m.dev_before <= 0.05e-3,
        ),
        Figure(
            "merged deviation after ICP, RMS" + tag,
            m.dev_after * 1e3,
            "mm",
            "<= 0.03",
            m.dev_after <= 0.03e-3,
        ),
        Figure(
            "largest ICP correction, true calibration" + tag,
            max(m.shifts) * 1e3,
            "mm",
            "<= 0.02",
            max(m.shifts) <= 0.02e-3 and m.unmeasured == 0,
        ),
        Figure("largest ICP rotation, true calibration" + tag, max(m.rots), "deg", "-", None),
    ]
    if n_bad:
        figures += [
            Figure(
                "  as recorded: deviation before ICP", as_recorded.dev_before * 1e3, "mm", "-", None
            ),
            Figure(
                "  as recorded: deviation after ICP", as_recorded.dev_after * 1e3, "mm", "-", None
            ),
            Figure(
                "  as recorded: largest ICP correction",
                max(as_recorded.shifts) * 1e3,
                "mm",
                "-",
                None,
            ),
        ]
    for name, n_flag in off_results.items():
        figures.append(
            Figure(
                f"0.3 mm off along sensor {name}: passes flagged" + tag,
                n_flag,
                "",
                ">= 1 (flagged)",
                n_flag >= 1,
            )
        )
    figures += [
        Figure(
            f"strip overlap measured in the clouds (smallest of {len(overlaps)} pairs)",
            min_overlap * 100,
            "%",
            f">= {OVERLAP * 100:g}",
            bool(overlaps) and min_overlap >= OVERLAP,
        ),
        Figure(
            "strip overlap the planner computed (smallest)",
            g.get("min_overlap", 0.0) * 100,
            "%",
            "-",
            None,
        ),
        Figure(
            "visible surface within 0.5 mm of the cloud",
            covered * 100,
            "%",
            ">= 99.9",
            covered >= 0.999,
        ),
        Figure(
            "largest gap (visible sample to cloud)",
            float(dist.max()) * 1e3,
            "mm",
            "<= 0.5",
            float(dist.max()) <= 0.5e-3,
        ),
        Figure("scan duration", duration_s, "s", "-", None),
    ]
    return report("scan jobs on the simulated cell", figures)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speed-mm-s", type=float, default=20.0, help="pass speed (mm/s)")
    ap.add_argument("--keep", type=Path, default=None, help="keep the outputs in this folder")
    ap.add_argument(
        "--replay", type=Path, default=None, help="evaluate a recording kept with --keep"
    )
    a = ap.parse_args(argv)
    if a.replay is not None:
        with open(a.replay, "rb") as fh:
            recorded, cal, plan, truth, duration_s = pickle.load(fh)
        return evaluate(recorded, cal, plan, truth, duration_s)
    return run(a.speed_mm_s * 1e-3, a.keep)


if __name__ == "__main__":
    sys.exit(main())
