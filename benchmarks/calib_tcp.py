"""Benchmark: the TCP estimators' Monte Carlo covariance against the analytic formulas.

Setup of Borangiu et al. 2009 section 3 (TCP (60, 10, 200) mm, exact orientations, sigma = 0.1 mm
per position axis), with many more trials than the paper's 200 so the comparison is sharp:

* least squares on a cone of n poses: sample covariance vs ``sigma^2 [(A^T A)^-1]_{p block}``;
* Eq. (7) on the paper's three poses: sample covariance vs ``1.5 sigma^2 M^-1 M^-T``.

Two figures per case: the Frobenius relative error ``|C_mc - C|_F / |C|_F`` (the target, < 10 %;
it covers the off-diagonal terms too) and the largest relative error of a per-axis standard
deviation (reported, same target).  With 20000 trials the sampling error of either is about 1 %.

Run: ``.venv/bin/python benchmarks/calib_tcp.py`` (exit 1 on a miss).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from wristscan.calib import montecarlo

sys.path.insert(0, str(Path(__file__).parent))
from _report import Figure, report

TRIALS = 20_000
SIGMA_M = montecarlo.PAPER_SIGMA_M
TARGET = 0.10
CASES = (  # (label, alpha_deg, n poses or None for Eq. 7 on the paper's poses)
    ("three a=20", 20.0, None),
    ("three a=45", 45.0, None),
    ("three a=90", 90.0, None),
    ("lstsq-n3 a=30", 30.0, 3),
    ("lstsq-n6 a=45", 45.0, 6),
    ("lstsq-n12 a=60", 60.0, 12),
)


def _compare(alpha_deg: float, n: int | None, rng: np.random.Generator) -> tuple[float, float]:
    a = np.radians(alpha_deg)
    R = montecarlo.paper_poses(a) if n is None else montecarlo.cone_poses(a, n)
    method: montecarlo.Method = "three" if n is None else "lstsq"
    err = montecarlo.monte_carlo_errors(R, SIGMA_M, TRIALS, rng, method)
    cov = montecarlo.analytic_cov(R, SIGMA_M, method)
    mc = np.cov(err.T)
    frob = float(np.linalg.norm(mc - cov) / np.linalg.norm(cov))
    std = float(np.max(np.abs(np.sqrt(np.diag(mc)) / np.sqrt(np.diag(cov)) - 1.0)))
    return frob, std


def run() -> list[Figure]:
    rng = np.random.default_rng(2009)
    figures: list[Figure] = []
    t0 = time.perf_counter()
    for label, alpha, n in CASES:
        frob, std = _compare(alpha, n, rng)
        figures.append(
            Figure(f"{label} cov Frobenius rel err", frob, "", f"< {TARGET:g}", frob < TARGET)
        )
        figures.append(
            Figure(f"{label} max axis std rel err", std, "", f"< {TARGET:g}", std < TARGET)
        )
    elapsed = time.perf_counter() - t0
    figures.append(Figure(f"time for {len(CASES)} x {TRIALS} trials", elapsed, "s", "(info)", None))
    return figures


def main() -> int:
    return report(f"calib.tcp Monte Carlo vs analytic covariance ({TRIALS} trials)", run())


if __name__ == "__main__":
    sys.exit(main())
