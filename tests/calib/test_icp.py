"""calib.icp: normals, point-to-plane ICP on partially overlapping samplings of a known surface."""

from __future__ import annotations

import numpy as np
import pytest
from support import sample_surface

from wristscan.calib import icp, se3


def perturbation(translation_m: float, rotation_deg: float) -> np.ndarray:
    t = np.array([0.6, -0.3, 0.74])
    w = np.array([0.5, 0.7, -0.2])
    return se3.make(
        se3.rotvec_to_matrix(np.deg2rad(rotation_deg) * w / np.linalg.norm(w)),
        translation_m * t / np.linalg.norm(t),
    )


@pytest.fixture(scope="module")
def pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(source in its own frame, target, true source2target): overlap x in [-0.03, 0.03]."""
    rng = np.random.default_rng(5)
    target = sample_surface(rng, (-0.03, 0.045), 0.0008)
    truth = perturbation(0.3e-3, 0.2)
    source = se3.apply(se3.invert(truth), sample_surface(rng, (-0.045, 0.03), 0.0011))
    return source, target, truth


def test_normals_of_known_surface() -> None:
    rng = np.random.default_rng(2)
    pts = sample_surface(rng, (-0.02, 0.02), 0.001)
    n = icp.estimate_normals(pts, k=12, viewpoint=[0.0, 0.0, 1.0])
    x, y = pts[:, 0], pts[:, 1]
    # Analytic normal of z = f(x, y): (-fx, -fy, 1) normalised (bump included).
    e = np.exp(-((x - 0.01) ** 2 + (y + 0.015) ** 2) / (2 * 0.01**2))
    fx = 6 * x + 6 * x**2 - 0.005 * e * (x - 0.01) / 0.01**2
    fy = 2 * y - 0.005 * e * (y + 0.015) / 0.01**2
    true = np.column_stack([-fx, -fy, np.ones_like(x)])
    true /= np.linalg.norm(true, axis=1, keepdims=True)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    angle = np.degrees(np.arccos(np.clip(np.einsum("ni,ni->n", n, true), -1, 1)))
    assert np.median(angle) < 0.5 and angle.max() < 3.0
    assert np.all(n[:, 2] > 0)  # oriented towards the viewpoint


def test_recovers_small_perturbation_partial_overlap(
    pair: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> None:
    source, target, truth = pair
    res = icp.icp_point_to_plane(source, target, max_distance=3e-3, trim_fraction=0.9)
    err = res.source2target @ se3.invert(truth)
    assert np.linalg.norm(err[:3, 3]) < 5e-6  # < 5 um
    assert np.degrees(se3.rotation_angle(err[:3, :3])) < 2e-3
    assert res.converged
    assert res.rmse_after < res.rmse_before / 20
    assert res.rmse_after < 5e-6
    assert res.correction_translation_m == pytest.approx(np.linalg.norm(truth[:3, 3]), abs=5e-6)
    assert res.correction_rotation_deg == pytest.approx(0.2, abs=2e-3)
    # The source's part beyond the target's edge is left out.
    assert res.n_pairs < 0.9 * source.shape[0]


def test_init_and_given_normals(pair: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    source, target, truth = pair
    normals = icp.estimate_normals(target)
    res = icp.icp_point_to_plane(
        source, target, normals, init=truth, max_distance=3e-3, trim_fraction=0.9
    )
    # Starting at the truth, ICP barely moves.
    assert res.correction_translation_m < 5e-6
    assert res.correction_rotation_deg < 2e-3
    rms = icp.point_to_plane_rms(se3.apply(truth, source), target, normals, max_distance=1e-3)
    assert rms < 5e-6
    moved = icp.point_to_plane_rms(source, target, normals, max_distance=3e-3)
    assert moved > 20 * rms


def test_noisy_target_still_recovers(pair: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    source, target, truth = pair
    rng = np.random.default_rng(9)
    noisy = target + rng.normal(scale=10e-6, size=target.shape)
    res = icp.icp_point_to_plane(source, noisy, max_distance=3e-3, trim_fraction=0.85)
    err = res.source2target @ se3.invert(truth)
    assert np.linalg.norm(err[:3, 3]) < 20e-6
    assert np.degrees(se3.rotation_angle(err[:3, :3])) < 0.01
    assert res.rmse_after < res.rmse_before
    assert res.converged  # trimming flips a few pairs; the repeat detection ends that cycle


def test_unconstrained_geometry_is_refused() -> None:
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-0.05, 0.05, (500, 2)), np.zeros(500)])
    with pytest.raises(ValueError, match="6 degrees of freedom"):
        icp.icp_point_to_plane(pts + np.array([0.0, 0.0, 1e-4]), pts)
    # A nearly flat patch: slides along its weak direction, refused as well.
    g = rng.uniform(-0.05, 0.05, (2, 3000, 2))
    patch = np.concatenate([g, 0.5 * g[..., :1] ** 2 + 0.3 * g[..., 1:] ** 2], axis=-1)
    with pytest.raises(ValueError, match="6 degrees of freedom"):
        icp.icp_point_to_plane(patch[0] + np.array([1e-4, 0.0, 0.0]), patch[1])
    # A spherical cap with exact normals: the rotations about its centre are free.
    u = rng.normal(size=(2, 4000, 3))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    src, tgt = u[0][u[0, :, 2] > 0.3], u[1][u[1, :, 2] > 0.3]
    with pytest.raises(ValueError, match="6 degrees of freedom"):
        icp.icp_point_to_plane(0.0127 * src, 0.0127 * tgt, tgt)


def test_bad_input_is_refused(pair: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    source, target, _ = pair
    with pytest.raises(ValueError, match=r"source: expected shape \(N, 3\)"):
        icp.icp_point_to_plane(source[:, :2], target)
    with pytest.raises(ValueError, match="target: need at least"):
        icp.icp_point_to_plane(source, target[:5])
    with pytest.raises(ValueError, match="target_normals"):
        icp.icp_point_to_plane(source, target, target_normals=np.ones((3, 3)))
    with pytest.raises(ValueError, match="unit vectors"):
        icp.icp_point_to_plane(source, target, target_normals=np.ones_like(target))
    with pytest.raises(ValueError, match="trim_fraction"):
        icp.icp_point_to_plane(source, target, trim_fraction=0.0)
    with pytest.raises(ValueError, match="init"):
        icp.icp_point_to_plane(source, target, init=2 * np.eye(4))
    bad = source.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        icp.icp_point_to_plane(bad, target)
    with pytest.raises(ValueError, match="within max_distance"):
        icp.icp_point_to_plane(source + np.array([1.0, 0.0, 0.0]), target, max_distance=1e-3)
    with pytest.raises(ValueError, match="k must be"):
        icp.estimate_normals(target, k=2)
    with pytest.raises(ValueError, match="within max_distance"):
        icp.point_to_plane_rms(
            source + 1.0, target, icp.estimate_normals(target), max_distance=1e-3
        )
