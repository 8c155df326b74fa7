"""TCP from n poses (Borangiu 2009 Eq. 2-9): exact recovery, agreement of the three solvers,
covariance against Monte Carlo, degenerate pose sets refused with advice, shape checks."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from wristscan.calib import se3, tcp
from wristscan.calib.montecarlo import paper_poses

DOWN = se3.rot_x(np.pi)
P_TOOL = np.array([0.060, 0.010, 0.200])
P_WORLD = np.array([0.40, -0.20, 0.10])


def tilted_poses(rng: np.random.Generator, n: int, max_tilt_rad: float = 1.0) -> np.ndarray:
    """n down-looking orientations tilted about random horizontal axes and spun about tool Z."""
    phi = rng.uniform(0, 2 * np.pi, n)
    tilt = rng.uniform(0.3, max_tilt_rad, n)
    axes = np.stack([np.cos(phi), np.sin(phi), np.zeros(n)], axis=-1)
    spin = se3.rot_z(rng.uniform(-np.pi, np.pi, n))
    return se3.rotvec_to_matrix(axes * tilt[:, None]) @ DOWN @ spin


def translations(R: np.ndarray, p_tool: np.ndarray = P_TOOL, p_world: np.ndarray = P_WORLD):
    """Flange positions that put the tool point p_tool onto p_world for every orientation."""
    return p_world - R @ p_tool


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


# ---------------------------------------------------------------------------- exact recovery


def test_noise_free_recovery_all_methods(rng: np.random.Generator) -> None:
    R = tilted_poses(rng, 6)
    T = translations(R)
    for sol in (
        tcp.solve_tcp(R, T, "lstsq"),
        tcp.solve_tcp(R, T, "variance"),
        tcp.solve_tcp_three(R[:3], T[:3]),
    ):
        np.testing.assert_allclose(sol.p_tool, P_TOOL, atol=1e-12)
        np.testing.assert_allclose(sol.p_world, P_WORLD, atol=1e-12)
        assert np.abs(sol.residuals).max() < 1e-12
        assert sol.sigma < 1e-12
        assert np.abs(sol.cov).max() < 1e-20


def test_recovery_matches_se3_frame_convention(rng: np.random.Generator) -> None:
    """Poses given as flange2base transforms: flange2base @ p_tool must be p_world."""
    flange2base = se3.make(tilted_poses(rng, 4), rng.uniform(-0.5, 0.5, (4, 3)))
    # Move each flange so that it holds P_TOOL at P_WORLD (keep the orientation).
    R = flange2base[:, :3, :3]
    flange2base[:, :3, 3] = translations(R)
    sol = tcp.solve_tcp(R, flange2base[:, :3, 3])
    world = se3.apply(flange2base, sol.p_tool[None, :])[:, 0]
    np.testing.assert_allclose(world, np.broadcast_to(sol.p_world, (4, 3)), atol=1e-12)
    np.testing.assert_allclose(sol.p_tool, P_TOOL, atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(3, 9),
    p=st.tuples(*[st.floats(-0.5, 0.5)] * 3),
)
def test_recovery_property(seed: int, n: int, p: tuple[float, float, float]) -> None:
    # Any world rotation of a well-spread set (three random tilted poses may share an axis).
    rng = np.random.default_rng(seed)
    paper = paper_poses(np.radians(rng.uniform(45, 90)))
    spread = np.concatenate([paper, tilted_poses(rng, n - 3)])
    R = se3.rotvec_to_matrix(rng.uniform(-1.8, 1.8, 3)) @ spread
    p_tool = np.array(p)
    T = translations(R, p_tool)
    np.testing.assert_allclose(tcp.solve_tcp(R, T).p_tool, p_tool, atol=1e-10)
    np.testing.assert_allclose(tcp.solve_tcp_three(R[:3], T[:3]).p_tool, p_tool, atol=1e-9)


# ---------------------------------------------------------------------------- noisy agreement


def test_lstsq_equals_variance_on_noisy_data(rng: np.random.Generator) -> None:
    R = tilted_poses(rng, 7)
    T = translations(R) + rng.normal(scale=2e-4, size=(7, 3))
    a = tcp.solve_tcp(R, T, "lstsq")
    b = tcp.solve_tcp(R, T, "variance")
    assert np.linalg.norm(a.p_tool - tcp.solve_tcp_three(R[:3], T[:3]).p_tool) > 1e-6  # noisy
    np.testing.assert_allclose(a.p_tool, b.p_tool, rtol=0, atol=1e-13)
    np.testing.assert_allclose(a.p_world, b.p_world, rtol=0, atol=1e-13)
    np.testing.assert_allclose(a.residuals, b.residuals, rtol=0, atol=1e-13)
    np.testing.assert_allclose(a.cov, b.cov, rtol=1e-9, atol=0)
    assert a.sigma == pytest.approx(b.sigma, rel=1e-10)
    assert a.method == "lstsq" and b.method == "variance"


def test_variance_solution_minimises_eq8(rng: np.random.Generator) -> None:
    """Eq. (8): the summed variances of the world points is smallest at the solution."""
    R = tilted_poses(rng, 5)
    T = translations(R) + rng.normal(scale=2e-4, size=(5, 3))

    def e(p: np.ndarray) -> np.ndarray:  # Eq. (8)-(9) for many p at once: (k, 3) -> (k,)
        w = np.einsum("nij,kj->kni", R, p) + T
        return np.sum((w - w.mean(axis=1, keepdims=True)) ** 2, axis=(1, 2))

    p = tcp.solve_tcp(R, T, "variance").p_tool
    trial = p + rng.normal(scale=1e-4, size=(500, 3))
    assert np.all(e(trial) > e(p[None])[0])
    assert e(p[None])[0] == pytest.approx(np.sum(tcp.solve_tcp(R, T).residuals ** 2), rel=1e-9)


def test_all_pairs_difference_formulation_gives_same_estimate(rng: np.random.Generator) -> None:
    """Stacking every (R_i - R_j) p = -(T_i - T_j) gives the lstsq estimate (documented claim)."""
    R = tilted_poses(rng, 6)
    T = translations(R) + rng.normal(scale=2e-4, size=(6, 3))
    i, j = np.triu_indices(6, k=1)
    A = (R[i] - R[j]).reshape(-1, 3)
    b = -(T[i] - T[j]).reshape(-1)
    p, *_ = np.linalg.lstsq(A, b, rcond=None)
    np.testing.assert_allclose(p, tcp.solve_tcp(R, T).p_tool, atol=1e-13)


def test_three_is_eq7_exactly(rng: np.random.Generator) -> None:
    R = tilted_poses(rng, 3)
    T = translations(R) + rng.normal(scale=1e-4, size=(3, 3))
    sol = tcp.solve_tcp_three(R, T)
    M = R[0] - (R[1] + R[2]) / 2
    b = -(T[0] - (T[1] + T[2]) / 2)
    np.testing.assert_allclose(M @ sol.p_tool, b, atol=1e-15)
    # Eq. (7) reproduces world point 1 exactly: its residual is zero and r2 = -r3.
    np.testing.assert_allclose(sol.residuals[0], 0.0, atol=1e-15)
    np.testing.assert_allclose(sol.residuals[1], -sol.residuals[2], atol=1e-15)
    assert sol.cond == pytest.approx(np.linalg.cond(M))


def test_batch_solvers_match_single_solvers(rng: np.random.Generator) -> None:
    R = tilted_poses(rng, 5)
    T = translations(R) + rng.normal(scale=1e-4, size=(4, 5, 3))
    p_b, w_b = tcp.solve_tcp_batch(R, T)
    p3_b = tcp.solve_tcp_three_batch(R[:3], T[:, :3])
    for k in range(4):
        np.testing.assert_allclose(p_b[k], tcp.solve_tcp(R, T[k]).p_tool, atol=1e-13)
        np.testing.assert_allclose(w_b[k], tcp.solve_tcp(R, T[k]).p_world, atol=1e-13)
        np.testing.assert_allclose(p3_b[k], tcp.solve_tcp_three(R[:3], T[k, :3]).p_tool, atol=1e-13)


def test_three_and_lstsq_agree_statistically() -> None:
    """Same three poses, same noise: both unbiased; least squares never worse (Gauss-Markov)."""
    sigma, N = 1e-4, 4000
    R = paper_poses(np.radians(60.0))
    rng = np.random.default_rng(3)
    T = translations(R) + rng.normal(scale=sigma, size=(N, 3, 3))
    e3 = tcp.solve_tcp_three_batch(R, T) - P_TOOL
    el = tcp.solve_tcp_batch(R, T)[0] - P_TOOL
    c3, cl = tcp.covariance_three(R, sigma), tcp.covariance_lstsq(R, sigma)
    for e, c in ((e3, c3), (el, cl)):
        # Means within 4 standard errors of zero (unbiased estimators).
        assert np.all(np.abs(e.mean(axis=0)) < 4 * np.sqrt(np.diag(c) / N))
    assert np.linalg.eigvalsh(c3 - cl).min() > -1e-20
    assert np.all(np.diag(np.cov(e3.T)) > np.diag(np.cov(el.T)))
    # And the two estimates of one trial differ by no more than the Eq. (7) spread suggests.
    assert np.all(np.abs(e3 - el).std(axis=0) < 1.5 * np.sqrt(np.diag(c3)))


# ---------------------------------------------------------------------------- covariance


def test_reported_covariance_formulas(rng: np.random.Generator) -> None:
    R = tilted_poses(rng, 5)
    T = translations(R) + rng.normal(scale=1e-4, size=(5, 3))
    sol = tcp.solve_tcp(R, T, noise_sigma_m=1e-4)
    A = tcp.design_matrix(R)
    np.testing.assert_allclose(sol.cov, 1e-8 * np.linalg.inv(A.T @ A)[:3, :3], rtol=1e-12)
    C = (R - R.mean(axis=0)).reshape(-1, 3)
    np.testing.assert_allclose(sol.cov, 1e-8 * np.linalg.inv(C.T @ C), rtol=1e-9)  # Schur block
    s3 = tcp.solve_tcp_three(R[:3], T[:3], noise_sigma_m=1e-4)
    Mi = np.linalg.inv(R[0] - (R[1] + R[2]) / 2)
    np.testing.assert_allclose(s3.cov, 1.5e-8 * Mi @ Mi.T, rtol=1e-12)
    np.testing.assert_allclose(s3.std, np.sqrt(np.diag(s3.cov)))
    # Without a given noise level, the estimated sigma scales the same unit covariance.
    est = tcp.solve_tcp(R, T)
    np.testing.assert_allclose(est.cov, sol.cov * (est.sigma / 1e-4) ** 2, rtol=1e-12)


def test_covariance_matches_monte_carlo(rng: np.random.Generator) -> None:
    sigma, N = 1e-4, 5000
    R = tilted_poses(rng, 5)
    T = translations(R) + rng.normal(scale=sigma, size=(N, 5, 3))
    err = tcp.solve_tcp_batch(R, T)[0] - P_TOOL
    cov = tcp.covariance_lstsq(R, sigma)
    rel = np.linalg.norm(np.cov(err.T) - cov) / np.linalg.norm(cov)
    assert rel < 0.1
    err3 = tcp.solve_tcp_three_batch(R[:3], T[:, :3]) - P_TOOL
    cov3 = tcp.covariance_three(R[:3], sigma)
    assert np.linalg.norm(np.cov(err3.T) - cov3) / np.linalg.norm(cov3) < 0.1


@pytest.mark.parametrize("method", ["three", "lstsq"])
def test_sigma_estimate_is_unbiased(method: str) -> None:
    """Mean of sigma_hat^2 over trials equals the true variance (3 residual degrees of freedom)."""
    sigma, N = 1e-4, 400
    rng = np.random.default_rng(11)
    R = paper_poses(np.radians(50.0))
    T = translations(R) + rng.normal(scale=sigma, size=(N, 3, 3))
    solve = tcp.solve_tcp_three if method == "three" else tcp.solve_tcp
    s2 = np.array([solve(R, T[k]).sigma ** 2 for k in range(N)])
    # sigma_hat^2 ~ sigma^2 chi2(3)/3 for least squares: standard error of the mean ~ 4 %.
    assert s2.mean() / sigma**2 == pytest.approx(1.0, abs=0.15)


# ---------------------------------------------------------------------------- degenerate sets


def test_identical_orientations_raise_with_advice() -> None:
    R = np.stack([DOWN] * 4)
    with pytest.raises(tcp.DegeneratePoses, match="nearly identical") as exc:
        tcp.solve_tcp(R, translations(R))
    assert "two different axes" in str(exc.value)
    assert isinstance(exc.value, ValueError)


@pytest.mark.parametrize(
    ("rot", "axis", "advice"), [(se3.rot_x, "x", "y"), (se3.rot_y, "y", "x"), (se3.rot_z, "z", "x")]
)
def test_common_rotation_axis_raises_with_advice(rot, axis: str, advice: str) -> None:
    R = rot(np.radians([0.0, 40.0, 80.0, -60.0])) @ DOWN
    T = translations(R)
    expected = f"add a pose tilted about {advice} by >= 45 degrees"
    for solve in (tcp.solve_tcp, lambda R, T: tcp.solve_tcp(R, T, "variance")):
        with pytest.raises(tcp.DegeneratePoses, match=f"same axis \\({axis};") as exc:
            solve(R, T)
        assert expected in str(exc.value)
    with pytest.raises(tcp.DegeneratePoses, match=expected):
        tcp.solve_tcp_three(R[:3], T[:3])


def test_oblique_common_axis_is_named_by_its_direction() -> None:
    u = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    R = se3.rotvec_to_matrix(np.radians([0.0, 30.0, 70.0])[:, None] * u) @ DOWN
    with pytest.raises(tcp.DegeneratePoses, match=r"axis \(\[0\.71, 0\.71, 0\.00\];") as exc:
        tcp.solve_tcp(R, translations(R))
    assert "add a pose rotated about z by >= 45 degrees" in str(exc.value)


def test_small_tilt_threshold_and_warning(caplog: pytest.LogCaptureFixture) -> None:
    R = paper_poses(np.radians(3.0))  # effective tilt about 2 degrees
    T = translations(R)
    assert tcp.effective_tilt_deg(R) == pytest.approx(2.0, abs=0.1)
    with pytest.raises(tcp.DegeneratePoses):
        tcp.solve_tcp(R, T)
    with caplog.at_level(logging.WARNING, logger="wristscan.calib.tcp"):
        sol = tcp.solve_tcp(R, T, min_tilt_deg=1.0)
    np.testing.assert_allclose(sol.p_tool, P_TOOL, atol=1e-9)
    assert "small effective tilt" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="wristscan.calib.tcp"):
        tcp.solve_tcp(paper_poses(np.radians(90.0)), translations(paper_poses(np.radians(90.0))))
    assert caplog.text == ""


def test_effective_tilt_of_two_poses_is_their_angle() -> None:
    R = np.stack([DOWN, se3.rot_x(np.radians(37.0)) @ DOWN @ se3.rot_z(0.0)])
    # Two poses about one axis: the worst axis has tilt 0, the others exactly the rotation angle.
    assert tcp.effective_tilt_deg(R) == pytest.approx(0.0, abs=1e-6)
    lam = np.linalg.eigvalsh(np.eye(3) - R.mean(0).T @ R.mean(0))
    assert np.degrees(2 * np.arcsin(np.sqrt(lam[-1]))) == pytest.approx(37.0)


# ---------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    ("R", "T", "match"),
    [
        (np.tile(np.eye(4), (3, 1, 1)), np.zeros((3, 3)), r"flange2base\[:, :3, :3\]"),
        (np.tile(np.eye(3), (2, 1, 1)), np.zeros((2, 3)), "at least 3 poses"),
        (np.eye(3), np.zeros(3), r"shape \(n, 3, 3\)"),
        (paper_poses(1.0), np.zeros((3, 4)), r"T must have shape \(n, 3\)"),
        (paper_poses(1.0), np.zeros((4, 3)), "4 translations but R holds 3"),
        (paper_poses(1.0) * 1.01, np.zeros((3, 3)), "not a set of rotation"),
        (paper_poses(1.0) * np.array([1, 1, -1.0]), np.zeros((3, 3)), "reflection"),
        (paper_poses(1.0), np.full((3, 3), np.nan), "NaN"),
    ],
)
def test_bad_inputs_raise_clear_errors(R: np.ndarray, T: np.ndarray, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        tcp.solve_tcp(R, T)


def test_three_needs_exactly_three_and_methods_are_checked(rng: np.random.Generator) -> None:
    R = tilted_poses(rng, 4)
    with pytest.raises(ValueError, match="exactly 3"):
        tcp.solve_tcp_three(R, translations(R))
    with pytest.raises(ValueError, match="'lstsq' or 'variance'"):
        tcp.solve_tcp(R, translations(R), "svd")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="noise_sigma_m"):
        tcp.solve_tcp(R, translations(R), noise_sigma_m=-1.0)
    with pytest.raises(ValueError, match=r"\(\.\.\., n, 3\)"):
        tcp.solve_tcp_batch(R, np.zeros(3))


def test_solution_is_immutable(rng: np.random.Generator) -> None:
    R = tilted_poses(rng, 4)
    sol = tcp.solve_tcp(R, translations(R))
    with pytest.raises(dataclasses.FrozenInstanceError):
        sol.sigma = 1.0  # type: ignore[misc]
    with pytest.raises(ValueError, match="read-only"):
        sol.p_tool[0] = 1.0
    assert sol.residuals.shape == (4, 3) and sol.cov.shape == (3, 3)
    assert sol.cond >= 1.0 and sol.tilt_deg > 30.0
