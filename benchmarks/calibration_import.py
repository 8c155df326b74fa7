"""Benchmark: ``wristscan calibrate import``'s solution on simulator-made stop-and-go sets.

Each run makes a set of 15 poses with ``wristscan.daemon.simcell.stopgo.make_stopgo`` on the
default simulated cell (tooling ball R = 12.7 mm, sensor noise 20 um, true sensor2flange
``p[0.060, 0.010, 0.200, 0.020, -0.015, 0.010]``) with a UR5e as wrong as a real one: seeded
realistic DH deviations (0.1 mm, 0.01 deg per parameter), a partial factory calibration (15 % of
each deviation left) and 30 um repeatability; each run draws another arm and other poses. The set
goes through what ``calibrate import`` runs (:func:`wristscan.daemon.calibrate.imported
.calibrate_dataset`: circles, closed form, side, joint refinement, jackknife over poses).

Figures and targets (issue 17):

* **same optimum** as the joint solver of ``calibrate sensor`` (``calib.handeye.refine``) on the
  same profiles started from the truth: the largest difference over the 6 parameters in units
  of the reported sigma, worst run <= 1 (in practice ~0: the closed form finds that optimum);
* **sigma against the jackknife** over poses: per parameter, the median over the runs of the
  reported sigma / the jackknife sigma within [1/1.5, 1.5];
* **result against truth**: per parameter, the share of runs with the truth within the reported
  2 sigma >= 90 %, and the RMS over runs of error / sigma within [1/1.5, 1.5] (the reported
  sigmas are the observed spread); the translation error RMS (reported);
* the side chosen right in every run, and the seconds per run (reported).

Run: ``.venv/bin/python benchmarks/calibration_import.py [--runs N] [--json FILE]`` (exit 1 on
a miss).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import time
from pathlib import Path

import numpy as np

from wristscan.calib import handeye, perpose, se3
from wristscan.calib.kinematic_errors import RobotErrorModel
from wristscan.daemon.calibrate import imported
from wristscan.daemon.simcell import stopgo

sys.path.insert(0, str(Path(__file__).parent))
from _report import Figure, report

RUNS = 50
N_POSES = 15
PARAMS = ("rot X", "rot Y", "rot Z", "x", "y", "z")
SIGMA_RATIO = 1.5
COVERAGE = 0.90


def _local(X: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """X relative to ref: rotation increment about the sensor axes (rad), origin offset (m)."""
    return np.concatenate([se3.matrix_to_rotvec(ref[:3, :3].T @ X[:3, :3]), X[:3, 3] - ref[:3, 3]])


def one_run(seed: int) -> dict[str, np.ndarray | float]:
    robot = RobotErrorModel("UR5e", seed=seed, factory="partial", repeatability_m=30e-6)
    data = stopgo.make_stopgo(n_poses=N_POSES, seed=seed, robot=robot)
    ds = imported.ImportedDataset(
        Path(f"run{seed}"),
        "ur-rotvec",
        "m",
        data.names,
        data.flange2base,
        tuple(data.points(k) for k in range(N_POSES)),
    )
    t0 = time.perf_counter()
    res = imported.calibrate_dataset(ds, data.ball_radius_m)  # the CLI's defaults
    seconds = time.perf_counter() - t0
    j = res.joint
    sig = np.sqrt(np.clip(np.diag(j.cov), 0.0, None))
    # calibrate sensor's joint solver on the same profiles, started from the truth.
    start = dataclasses.replace(
        j, sensor2flange=data.sensor2flange, ball_centre_base=data.ball_centre_base
    )
    with perpose._quiet_solver():
        ref = handeye.refine(list(res.solution.sweeps), start, data.ball_radius_m, check=False)
    assert res.jackknife is not None
    return {
        "err": _local(j.sensor2flange, data.sensor2flange),
        "sigma": sig,
        "jackknife": np.sqrt(np.clip(np.diag(res.jackknife.cov), 0.0, None)),
        "optimum": np.abs(_local(j.sensor2flange, ref.sensor2flange)) / sig,
        "side_ok": float(res.solution.side == data.side),
        "seconds": seconds,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=RUNS)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    logging.getLogger("wristscan.calib.handeye").setLevel(logging.ERROR)  # weak-constraint notes
    runs = [one_run(s) for s in range(args.runs)]
    err = np.array([r["err"] for r in runs])
    sig = np.array([r["sigma"] for r in runs])
    jk = np.array([r["jackknife"] for r in runs])
    opt = np.array([r["optimum"] for r in runs])
    z = err / sig
    figures = [
        Figure("runs", float(args.runs), "", ">= 50", args.runs >= 50),
        Figure(
            "same optimum as refine (worst)",
            float(opt.max()),
            "sigma",
            "<= 1",
            bool(opt.max() <= 1),
        ),
        Figure(
            "side chosen right",
            float(np.mean([r["side_ok"] for r in runs])),
            "share",
            "1",
            all(r["side_ok"] == 1.0 for r in runs),
        ),
    ]
    for i, name in enumerate(PARAMS):
        unit = "um" if i >= 3 else "mdeg"
        scale = 1e6 if i >= 3 else np.degrees(1.0) * 1e3
        ratio = float(np.median(sig[:, i] / jk[:, i]))
        cover = float(np.mean(np.abs(z[:, i]) <= 2.0))
        honest = float(np.sqrt(np.mean(z[:, i] ** 2)))
        figures += [
            Figure(
                f"{name}: error RMS",
                float(np.sqrt(np.mean(err[:, i] ** 2))) * scale,
                unit,
                "-",
                None,
            ),
            Figure(f"{name}: median sigma", float(np.median(sig[:, i])) * scale, unit, "-", None),
            Figure(
                f"{name}: sigma / jackknife",
                ratio,
                "median",
                "0.67..1.5",
                bool(1 / SIGMA_RATIO <= ratio <= SIGMA_RATIO),
            ),
            Figure(
                f"{name}: truth within 2 sigma", cover, "share", ">= 0.90", bool(cover >= COVERAGE)
            ),
            Figure(
                f"{name}: RMS error / sigma",
                honest,
                "",
                "0.67..1.5",
                bool(1 / SIGMA_RATIO <= honest <= SIGMA_RATIO),
            ),
        ]
    figures.append(
        Figure("seconds per run", float(np.mean([r["seconds"] for r in runs])), "s", "-", None)
    )
    return report("calibrate import on stop-and-go sets (15 poses)", figures, args.json)


if __name__ == "__main__":
    sys.exit(main())
