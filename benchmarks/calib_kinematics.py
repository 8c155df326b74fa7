"""Benchmark calib.kinematics: vectorised forward() against a per-sample loop, and the accuracy
of inverse() round trips (nominal and calibrated models).

Run: .venv/bin/python benchmarks/calib_kinematics.py [--json-out FILE]
Targets: forward() on 100k joint vectors at least 20x faster than calling it per sample; every IK
solution maps back to its target within 1e-9 m and 1e-9 rad, and the joint vector the target came
from is among the solutions.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))
from _report import Figure, report
from support import REAL_UR10E

from wristscan.calib import kinematics as kin
from wristscan.calib import se3

N_FORWARD = 100_000
SPEEDUP_TARGET = 20.0
IK_ERROR_TARGET = 1e-9


def _median_seconds(fn: Callable[[], object], runs: int) -> float:
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _ik_round_trip(model: kin.DHParams, q_all: np.ndarray) -> tuple[float, float, int, float]:
    """Worst position (m) and rotation (rad) error over all solutions, misses, mean s per call."""
    worst_pos = worst_rot = 0.0
    misses = 0
    t0 = time.perf_counter()
    for q in q_all:
        T = kin.forward(model, q)
        sols = kin.inverse(model, T)
        if sols.shape[0] == 0:
            misses += 1
            continue
        F = kin.forward(model, sols)
        worst_pos = max(worst_pos, float(np.linalg.norm(F[:, :3, 3] - T[:3, 3], axis=-1).max()))
        worst_rot = max(worst_rot, float(se3.rotation_angle(F[:, :3, :3] @ T[:3, :3].T).max()))
        if np.abs(kin.wrap_angle(sols - q)).max(axis=1).min() > 1e-7:
            misses += 1
    return worst_pos, worst_rot, misses, (time.perf_counter() - t0) / len(q_all)


def run() -> list[Figure]:
    """The figures (``calib_accuracy.py`` runs every calib topic through its ``run()``)."""
    rng = np.random.default_rng(2009)
    model = kin.UR_MODELS["UR5e"]
    q = rng.uniform(-2 * np.pi, 2 * np.pi, size=(N_FORWARD, 6))

    # Same answers first, then time: vectorised (median of 7) beside per-sample calls (median of 3).
    looped = np.stack([kin.forward(model, qi) for qi in q[:1000]])
    if not np.array_equal(looped, kin.forward(model, q[:1000])):
        raise SystemExit("vectorised and per-sample forward() disagree")
    t_vec = _median_seconds(lambda: kin.forward(model, q), runs=7)
    t_loop = _median_seconds(lambda: [kin.forward(model, qi) for qi in q], runs=3)
    ratio = t_loop / t_vec

    figures = [
        Figure("forward 100k vectorised (median of 7)", t_vec * 1e3, "ms", "-", None),
        Figure("forward 100k per-sample loop (median of 3)", t_loop * 1e3, "ms", "-", None),
        Figure("forward speed-up", ratio, "x", f">= {SPEEDUP_TARGET:g}", ratio >= SPEEDUP_TARGET),
    ]

    worst_pos = worst_rot = 0.0
    misses = 0
    n_nominal = 0
    t_nominal: list[float] = []
    for m in kin.UR_MODELS.values():
        q_ik = rng.uniform(-np.pi, np.pi, size=(100, 6))
        p, r, miss, t_call = _ik_round_trip(m, q_ik)
        worst_pos, worst_rot, misses = max(worst_pos, p), max(worst_rot, r), misses + miss
        n_nominal += len(q_ik)
        t_nominal.append(t_call)

    # Calibrated models, away from the wrist singularity (see inverse()).
    calibrated = [
        kin.with_deltas("UR5e", *(rng.normal(0.0, 1e-3, 6) for _ in range(4))),
        REAL_UR10E,
    ]
    c_pos = c_rot = 0.0
    c_misses = 0
    n_cal = 0
    t_cal: list[float] = []
    for m in calibrated:
        q_ik = rng.uniform(-np.pi, np.pi, size=(200, 6))
        q_ik = q_ik[np.abs(np.sin(q_ik[:, 4])) >= 0.05][:100]
        kin.inverse(m, kin.forward(m, q_ik[0]))  # fit of the seed model, once per model
        p, r, miss, t_call = _ik_round_trip(m, q_ik)
        c_pos, c_rot, c_misses = max(c_pos, p), max(c_rot, r), c_misses + miss
        n_cal += len(q_ik)
        t_cal.append(t_call)

    tgt = f"<= {IK_ERROR_TARGET:g}"
    figures += [
        Figure(f"IK nominal: worst position error ({n_nominal} poses)", worst_pos, "m", tgt,
               worst_pos <= IK_ERROR_TARGET),
        Figure("IK nominal: worst rotation error", worst_rot, "rad", tgt,
               worst_rot <= IK_ERROR_TARGET),
        Figure("IK nominal: original q missing", misses, "poses", "0", misses == 0),
        Figure("IK nominal: time per call", statistics.mean(t_nominal) * 1e3, "ms", "-", None),
        Figure(f"IK calibrated: worst position error ({n_cal} poses)", c_pos, "m", tgt,
               c_pos <= IK_ERROR_TARGET),
        Figure("IK calibrated: worst rotation error", c_rot, "rad", tgt,
               c_rot <= IK_ERROR_TARGET),
        Figure("IK calibrated: original q missing", c_misses, "poses", "0", c_misses == 0),
        Figure("IK calibrated: time per call", statistics.mean(t_cal) * 1e3, "ms", "-", None),
    ]  # fmt: skip
    return figures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json-out", help="also write the figures to this JSON file")
    args = parser.parse_args(argv)
    return report("calib.kinematics", run(), json_out=args.json_out)


if __name__ == "__main__":
    sys.exit(main())
