"""Benchmark: Eq. (1) alignment throughput and point-to-plane ICP accuracy.

Alignment: 1000 profiles x 2048 points, ``calib.align.align`` against a per-profile Python loop
written with the same building blocks (``se3.compose`` + ``se3.apply`` per profile). Runs are
interleaved so that both see the same machine load; medians are compared. A leaner hand-written
loop (one ``@`` per profile) and the general, unordered-index path are reported for information.

ICP: two partially overlapping samplings of a smooth asymmetric surface, the source moved by a
known 0.3 mm / 0.2 deg; the estimate must match it within 0.01 mm / 0.005 deg.

Run: ``.venv/bin/python benchmarks/calib_align.py``; exits non-zero when a target is missed.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))
from _report import Figure, report
from support import sample_surface

from wristscan.calib import align, icp, se3, table

N_PROFILES = 1000
N_POINTS = 2048
REPEATS = 9
# Memory-bound at 2048 points per profile: a per-profile loop only adds ~40 us per profile.
ALIGN_RATIO_TARGET = 2.0
ICP_TRANSLATION_TARGET_MM = 0.01
ICP_ROTATION_TARGET_DEG = 0.005


def _medians(funcs: dict[str, Callable[[], object]], repeats: int) -> dict[str, float]:
    times: dict[str, list[float]] = {k: [] for k in funcs}
    for _ in range(repeats):
        for name, f in funcs.items():
            t0 = time.perf_counter()
            f()
            times[name].append(time.perf_counter() - t0)
    return {k: float(np.median(v)) for k, v in times.items()}


def _align_figures() -> list[Figure]:
    rng = np.random.default_rng(0)
    p, n = N_PROFILES, N_POINTS
    f2b = se3.make(se3.rotvec_to_matrix(rng.normal(size=(p, 3))), rng.normal(size=(p, 3)))
    s2f = se3.make(se3.rotvec_to_matrix([0.1, -0.2, 0.3]), [0.01, 0.02, 0.15])
    b2t = table.base2table_from([0.01, 0.02, 1.0], [0.6, 0.0, 0.0])
    theta = np.linspace(0.0, 2 * np.pi, p)
    y = rng.uniform(-0.05, 0.05, p * n)
    z = rng.uniform(0.1, 0.3, p * n)
    idx = np.repeat(np.arange(p), n).astype(np.uint32)
    perm = rng.permutation(p * n)
    y_sh, z_sh, idx_sh = y[perm], z[perm], idx[perm]

    def vectorised() -> np.ndarray:
        return align.align(y, z, idx, f2b, s2f)

    def loop_se3() -> np.ndarray:
        out = np.empty((p * n, 3))
        for i in range(p):
            s = slice(i * n, (i + 1) * n)
            out[s] = se3.apply(se3.compose(f2b[i], s2f), align.profile_points(y[s], z[s]))
        return out

    def loop_lean() -> np.ndarray:
        out = np.empty((p * n, 3))
        zeros = np.zeros(n)
        for i in range(p):
            s = slice(i * n, (i + 1) * n)
            T = f2b[i] @ s2f
            out[s] = np.stack([zeros, y[s], z[s]], axis=-1) @ T[:3, :3].T + T[:3, 3]
        return out

    def general() -> np.ndarray:
        return align.align(y_sh, z_sh, idx_sh, f2b, s2f)

    def part_vectorised() -> np.ndarray:
        return align.align(y, z, idx, f2b, s2f, b2t, theta, 0.1, "part")

    def part_loop() -> np.ndarray:
        out = np.empty((p * n, 3))
        for i in range(p):
            s = slice(i * n, (i + 1) * n)
            T = se3.compose(table.table2part(theta[i], 0.1), b2t, f2b[i], s2f)
            out[s] = se3.apply(T, align.profile_points(y[s], z[s]))
        return out

    ref = loop_se3()
    if not (
        np.allclose(vectorised(), ref, atol=1e-12)
        and np.allclose(loop_lean(), ref, atol=1e-12)
        and np.allclose(general(), ref[perm], atol=1e-12)
        and np.allclose(part_vectorised(), part_loop(), atol=1e-12)
    ):
        return [Figure("align agrees with the per-profile loop", 0.0, "bool", "1", False)]

    t = _medians(
        {
            "vec": vectorised,
            "loop": loop_se3,
            "lean": loop_lean,
            "general": general,
            "part_vec": part_vectorised,
            "part_loop": part_loop,
        },
        REPEATS,
    )
    npts = p * n
    ratio = t["loop"] / t["vec"]
    return [
        Figure("align vectorised, frame base", npts / t["vec"], "pts/s", "info", None),
        Figure("align per-profile loop (se3), base", npts / t["loop"], "pts/s", "info", None),
        Figure("align median vectorised", t["vec"] * 1e3, "ms", "info", None),
        Figure("align median loop (se3)", t["loop"] * 1e3, "ms", "info", None),
        Figure(
            "align speed-up vs loop (se3)",
            ratio,
            "x",
            f">= {ALIGN_RATIO_TARGET:g}",
            ratio >= ALIGN_RATIO_TARGET,
        ),
        Figure("align speed-up vs lean loop (@)", t["lean"] / t["vec"], "x", "info", None),
        Figure("align general path (shuffled idx)", npts / t["general"], "pts/s", "info", None),
        Figure("align speed-up, frame part", t["part_loop"] / t["part_vec"], "x", "info", None),
    ]


def _icp_figures() -> list[Figure]:
    rng = np.random.default_rng(5)
    target = sample_surface(rng, (-0.03, 0.045), 0.0008)
    w = np.array([0.5, 0.7, -0.2])
    t = np.array([0.6, -0.3, 0.74])
    truth = se3.make(
        se3.rotvec_to_matrix(np.deg2rad(0.2) * w / np.linalg.norm(w)),
        0.3e-3 * t / np.linalg.norm(t),
    )
    source = se3.apply(se3.invert(truth), sample_surface(rng, (-0.045, 0.03), 0.0011))
    figures: list[Figure] = []
    for label, noise in (("noise-free", 0.0), ("10 um noise", 10e-6)):
        tgt = target + rng.normal(scale=noise, size=target.shape) if noise else target
        t0 = time.perf_counter()
        res = icp.icp_point_to_plane(source, tgt, max_distance=3e-3, trim_fraction=0.85)
        elapsed = time.perf_counter() - t0
        err = res.source2target @ se3.invert(truth)
        e_t = float(np.linalg.norm(err[:3, 3])) * 1e3
        e_r = float(np.degrees(se3.rotation_angle(err[:3, :3])))
        figures += [
            Figure(
                f"icp translation error, {label}",
                e_t,
                "mm",
                f"<= {ICP_TRANSLATION_TARGET_MM:g}",
                e_t <= ICP_TRANSLATION_TARGET_MM,
            ),
            Figure(
                f"icp rotation error, {label}",
                e_r,
                "deg",
                f"<= {ICP_ROTATION_TARGET_DEG:g}",
                e_r <= ICP_ROTATION_TARGET_DEG,
            ),
            Figure(f"icp rmse before, {label}", res.rmse_before * 1e3, "mm", "info", None),
            Figure(f"icp rmse after, {label}", res.rmse_after * 1e3, "mm", "info", None),
            Figure(f"icp iterations, {label}", res.iterations, "", "info", None),
            Figure(f"icp converged, {label}", float(res.converged), "bool", "1", res.converged),
            Figure(f"icp time, {label}", elapsed * 1e3, "ms", "info", None),
        ]
    figures.append(Figure("icp source/target points", source.shape[0], "pts", "info", None))
    return figures


def run() -> list[Figure]:
    return _align_figures() + _icp_figures()


if __name__ == "__main__":
    sys.exit(report("calib: Eq. (1) alignment and ICP", run()))
