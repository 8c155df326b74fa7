"""Latency from forward/backward sweeps: recovers a known offset, refuses degenerate sweeps."""

from __future__ import annotations

import numpy as np
import pytest

from wristscan.calib.latency import estimate_latency, latency_from_shifts

DT = 1.5e-3  # s
P_STAR = np.array([0.45, -0.12, 0.08])  # m


def sweeps(seed: int, noise_m: float = 5e-6) -> tuple[np.ndarray, np.ndarray]:
    """Apparent ball centres of sweeps along +-x and +-y at 50..250 mm/s."""
    rng = np.random.default_rng(seed)
    speeds = np.array([0.05, 0.1, 0.15, 0.2, 0.25])
    dirs = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], dtype=float)
    V = (speeds[:, None, None] * dirs[None]).reshape(-1, 3)
    P = P_STAR + V * DT + rng.normal(0, noise_m, V.shape)
    return P, V


def test_recovers_latency_and_position() -> None:
    P, V = sweeps(0)
    est = estimate_latency(P, V)
    assert abs(est.latency_s - DT) < 3 * est.std_s
    assert abs(est.latency_s - DT) < 0.05e-3
    np.testing.assert_allclose(est.feature_position, P_STAR, atol=1e-5)
    assert est.n_sweeps == 20 and est.residuals.shape == (20, 3)
    assert 2e-6 < est.rms_m < 10e-6


def test_std_matches_the_spread_of_estimates() -> None:
    est = [estimate_latency(*sweeps(s)) for s in range(300)]
    spread = np.std([e.latency_s for e in est])
    std = np.mean([e.std_s for e in est])
    assert 0.8 < spread / std < 1.25


def test_edge_positions_in_one_dimension() -> None:
    rng = np.random.default_rng(1)
    v = np.array([0.05, -0.05, 0.1, -0.1, 0.2, -0.2])
    x = 0.3 + v * -0.4e-3 + rng.normal(0, 2e-6, v.shape)  # configured latency 0.4 ms too large
    est = estimate_latency(x, v)
    assert abs(est.latency_s + 0.4e-3) < 0.05e-3
    assert est.feature_position.shape == (1,)


def test_weights_discount_bad_sweeps() -> None:
    P, V = sweeps(2)
    P[3] += 2e-3  # a sweep that went wrong (2 mm off)
    w = np.ones(P.shape[0])
    assert abs(estimate_latency(P, V).latency_s - DT) > 0.1e-3
    w[3] = 0.0
    assert abs(estimate_latency(P, V, w).latency_s - DT) < 0.05e-3


def test_one_direction_is_degenerate() -> None:
    v = np.array([[0.1, 0, 0]] * 4)
    with pytest.raises(ValueError, match="opposite"):
        estimate_latency(P_STAR + v * DT, v)


def test_shape_errors() -> None:
    with pytest.raises(ValueError, match="differ"):
        estimate_latency(np.zeros((4, 3)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="NaN"):
        estimate_latency(np.full(4, np.nan), np.ones(4))


def test_latency_from_shifts() -> None:
    rng = np.random.default_rng(3)
    v = np.array([0.05, 0.1, 0.15, 0.2, 0.25])
    shifts = 2 * v * DT + rng.normal(0, 3e-6, v.shape)
    est = latency_from_shifts(shifts, v)
    assert abs(est.latency_s - DT) < 0.05e-3
    assert est.std_s > 0
    with pytest.raises(ValueError):
        latency_from_shifts(shifts, -v)
