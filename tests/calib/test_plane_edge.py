"""Pure math of the applications (calib/plane.py, calib/edge.py) against known geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from wristscan.calib.edge import EdgeModel, detect_edge, smooth_path
from wristscan.calib.plane import fit_hyperplane, fit_plane, plane_frame

# --------------------------------------------------------------------------------------------
# Planes


def _plane_points(
    n: int, normal: np.ndarray, centre: np.ndarray, noise: float, seed: int = 0
) -> np.ndarray:
    rng = np.random.default_rng(seed)
    normal = normal / np.linalg.norm(normal)
    B = np.linalg.qr(np.column_stack([normal, np.eye(3)]))[0][:, 1:3]
    uv = rng.uniform(-0.04, 0.04, (n, 2))
    return centre + uv @ B.T + rng.normal(0.0, noise, (n, 1)) * normal


def test_plane_fit_with_outliers_and_a_consistent_covariance() -> None:
    normal = np.array([0.2, -0.1, 1.0])
    normal /= np.linalg.norm(normal)
    centre = np.array([0.4, 0.1, 0.1])
    P = _plane_points(6000, normal, centre, 20e-6)
    rng = np.random.default_rng(1)
    P[:1200] += rng.uniform(-0.01, 0.01, (1200, 3))  # 20 % gross outliers
    fit = fit_plane(P)
    tilt = math.acos(min(1.0, abs(float(fit.normal @ normal))))
    assert tilt < 4 * fit.sigma_normal_rad + 1e-7
    assert abs(fit.distance(centre)) < 4 * fit.sigma_offset_m + 1e-7
    assert fit.rms == pytest.approx(20e-6, rel=0.15)
    assert fit.scale == pytest.approx(20e-6, rel=0.15)
    assert 4700 < fit.n_inliers < 4900  # the 4800 good points (and a few outliers on the plane)
    assert not fit.inliers[:1200][np.abs(fit.residuals[:1200]) > 2e-4].any()
    # The noise-free plane: exact.
    exact = fit_plane(_plane_points(500, normal, centre, 0.0))
    assert abs(float(exact.normal @ normal)) == pytest.approx(1.0, abs=1e-14)


def test_plane_form_error_sees_a_bump_not_the_noise() -> None:
    normal = np.array([0.0, 0.0, 1.0])
    flat = fit_plane(_plane_points(20000, normal, np.zeros(3), 20e-6), form_bin_m=0.004)
    assert flat.peak_to_valley > 6 * 20e-6  # the noise's spread
    assert flat.form_error < 30e-6  # ... averages out of the form error
    P = _plane_points(20000, normal, np.zeros(3), 20e-6)
    P[:, 2] += 2e-4 * np.exp(-np.sum(P[:, :2] ** 2, axis=1) / (2 * 0.01**2))  # 0.2 mm bump
    bumpy = fit_plane(P, form_bin_m=0.004)
    assert bumpy.form_error > 150e-6


def test_plane_fit_rejects_degenerate_points() -> None:
    with pytest.raises(ValueError):
        fit_plane(np.zeros((10, 3)))
    with pytest.raises(ValueError):
        fit_plane(np.column_stack([np.linspace(0, 1, 10), np.zeros(10), np.zeros(10)]))
    with pytest.raises(ValueError):
        fit_plane(np.ones((2, 3)))
    with pytest.raises(ValueError):
        fit_plane(np.array([[0.0, 0.0, np.nan], [1, 0, 0], [0, 1, 0]]))


def test_line_fit_in_2d() -> None:
    y = np.linspace(-0.02, 0.02, 200)
    z = 0.1 + 0.3 * y
    z[::10] += 0.005  # spikes
    line = fit_hyperplane(np.column_stack([y, z]))
    expected = np.array([-0.3, 1.0]) / math.hypot(0.3, 1.0)
    assert abs(float(line.normal @ expected)) == pytest.approx(1.0, abs=1e-12)
    assert line.distance(np.array([0.0, 0.1])) == pytest.approx(0.0, abs=1e-12)
    assert line.n_inliers == 180


def test_plane_frame_axes() -> None:
    n = np.array([0.1, 0.2, 1.0])
    n /= np.linalg.norm(n)
    o = np.array([0.5, 0.1, 0.2])
    x_to = o + np.array([0.03, 0.01, 0.0])
    T = plane_frame(-n, o, x_to, o + 0.1 * n)  # the normal given the wrong way round
    R = T[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:, 2], n, atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], o)
    v = x_to - o
    expected_x = v - (v @ n) * n
    np.testing.assert_allclose(R[:, 0], expected_x / np.linalg.norm(expected_x), atol=1e-12)
    with pytest.raises(ValueError, match="normal"):
        plane_frame(n, o, o + 0.01 * n, o + n)
    with pytest.raises(ValueError, match="z_side"):
        plane_frame(n, o, x_to, o)


# --------------------------------------------------------------------------------------------
# Edges in synthetic profiles: parallel rays along +z from (0, y_i, 0)


def cast(
    segments: list[tuple[tuple[float, float], tuple[float, float]]],
    n: int = 512,
    noise: float = 20e-6,
    seed: int = 0,
    z_range: tuple[float, float] = (0.05, 0.15),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A profile of a 2D scene of segments ``((y0, z0), (y1, z1))`` (nearest hit per ray)."""
    y = np.linspace(-0.025, 0.025, n)
    S = np.asarray(segments, dtype=float)
    a, b = S[:, 0], S[:, 1]
    dy, dz = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (y[:, None] - a[None, :, 0]) / dy[None, :]
        t = a[None, :, 1] + u * dz[None, :]
    t = np.where((u >= 0) & (u <= 1) & (t > 0), t, np.inf).min(axis=1)
    t = t + np.random.default_rng(seed).normal(0.0, noise, n)
    valid = (t >= z_range[0]) & (t <= z_range[1])
    return y, np.where(valid, t, np.nan), valid


SPACING = 0.05 / 511


def test_step_with_the_wall_hidden_and_seen() -> None:
    model = EdgeModel("step", height_m=(0.005, 0.05))
    for k, corner in enumerate(np.linspace(-0.008, 0.008, 7)):
        # Hidden wall: the corner lies between two rays.
        y, z, v = cast([((-0.03, 0.1), (corner, 0.1)), ((corner, 0.12), (0.03, 0.12))], seed=k)
        d = detect_edge(y, z, v, model)
        assert d.found and d.confidence > 0.8
        assert abs(d.point[0] - corner) <= 0.5 * SPACING + 5e-6
        assert d.point[1] == pytest.approx(0.1, abs=10e-6)
        assert d.height_m == pytest.approx(0.02, abs=30e-6)
        assert d.side == "left"
        np.testing.assert_allclose(d.normal, [0.0, -1.0], atol=6e-3)  # 5 mm of face
    # A tilted upper face and a visible wall (the sensor looks at the step from the side).
    slope = math.tan(math.radians(10))
    segs = [((-0.03, 0.1 - 0.033 * slope), (0.003, 0.1)), ((0.003, 0.1), (0.006, 0.12))]
    segs.append(((0.006, 0.12), (0.03, 0.12)))
    d = detect_edge(*cast(segs), model)
    assert d.found
    np.testing.assert_allclose(d.point, [0.003, 0.1], atol=10e-6)
    n_true = np.array([slope, -1.0]) / math.hypot(slope, 1.0)
    np.testing.assert_allclose(d.normal, n_true, atol=2e-3)
    assert d.angle_deg == pytest.approx(180 - (math.degrees(math.atan2(0.02, 0.003)) - 10), abs=1)
    # Mirrored: the upper face on the right.
    d = detect_edge(*cast([((-0.03, 0.12), (-0.004, 0.12)), ((-0.004, 0.1), (0.03, 0.1))]), model)
    assert d.found and d.side == "right"
    assert abs(d.point[0] + 0.004) <= 0.5 * SPACING + 5e-6
    # The side of the model is enforced.
    right_only = EdgeModel("step", height_m=(0.005, 0.05), side="right")
    segs2 = [((-0.03, 0.1), (0.002, 0.1)), ((0.002, 0.12), (0.03, 0.12))]
    assert not detect_edge(*cast(segs2), right_only).found


def test_open_step_and_height_range() -> None:
    segs = [((-0.03, 0.1), (0.004, 0.1)), ((0.004, 0.2), (0.03, 0.2))]  # lower face out of range
    d = detect_edge(*cast(segs), EdgeModel("step"))
    assert d.found and math.isnan(d.height_m)
    assert abs(d.point[0] - 0.004) <= 0.5 * SPACING + 5e-6
    assert not detect_edge(*cast(segs), EdgeModel("step", allow_open=False)).found
    # A 2 mm step is not a 5-50 mm step: confidence falls.
    low = [((-0.03, 0.1), (0.0, 0.1)), ((0.0, 0.102), (0.03, 0.102))]
    d = detect_edge(*cast(low), EdgeModel("step", height_m=(0.005, 0.05)))
    assert not d.found and d.confidence < 0.5
    assert detect_edge(*cast(low), EdgeModel("step", height_m=(0.001, 0.005))).found


def test_lap_joint_root() -> None:
    model = EdgeModel("lap_joint", height_m=(0.002, 0.02))
    # Upper plate 3 mm thick ending at y = 1 mm on a lower plate; the wall hidden.
    d = detect_edge(*cast([((-0.03, 0.1), (0.001, 0.1)), ((0.001, 0.103), (0.03, 0.103))]), model)
    assert d.found
    assert abs(d.point[0] - 0.001) <= 0.5 * SPACING + 5e-6
    assert d.point[1] == pytest.approx(0.103, abs=10e-6)
    assert d.height_m == pytest.approx(0.003, abs=20e-6)
    # Seen from the side: the wall line meets the lower face at the root.
    segs = [((-0.03, 0.1), (0.001, 0.1)), ((0.001, 0.1), (0.0025, 0.103))]
    segs.append(((0.0025, 0.103), (0.03, 0.103)))
    d = detect_edge(*cast(segs, n=2048), model)
    assert d.found
    np.testing.assert_allclose(d.point, [0.0025, 0.103], atol=10e-6)


@pytest.mark.parametrize("angle_deg", [60.0, 90.0, 120.0])
def test_v_groove_and_outer_corner(angle_deg: float) -> None:
    half = math.radians(angle_deg / 2)
    k = 1 / math.tan(half)  # face slope dz/dy of a symmetric corner
    vy, vz = 0.002, 0.11
    groove = [((-0.03, vz - k * 0.032), (vy, vz)), ((vy, vz), (0.03, vz - k * 0.028))]
    d = detect_edge(*cast(groove), EdgeModel("v_groove"))
    assert d.found and d.confidence > 0.8
    np.testing.assert_allclose(d.point, [vy, vz], atol=25e-6)  # 20 um noise: ~6 um 1-sigma
    assert d.angle_deg == pytest.approx(angle_deg, abs=0.5)
    np.testing.assert_allclose(d.normal, [0.0, -1.0], atol=2e-3)
    assert not detect_edge(*cast(groove), EdgeModel("outer_corner")).found
    ridge = [((-0.03, vz + k * 0.032), (vy, vz)), ((vy, vz), (0.03, vz + k * 0.028))]
    d = detect_edge(*cast(ridge), EdgeModel("outer_corner"))
    assert d.found
    np.testing.assert_allclose(d.point, [vy, vz], atol=25e-6)
    assert d.angle_deg == pytest.approx(angle_deg, abs=0.5)
    assert not detect_edge(*cast(ridge), EdgeModel("v_groove")).found
    # Outside the taught angle range the confidence drops.
    narrow = EdgeModel("v_groove", angle_deg=(angle_deg + 40, 179))
    assert detect_edge(*cast(groove), narrow).confidence < 0.5


def test_spikes_and_ambiguity() -> None:
    segs = [((-0.03, 0.1), (0.002, 0.1)), ((0.002, 0.12), (0.03, 0.12))]
    y, z, v = cast(segs)
    rng = np.random.default_rng(3)
    spikes = rng.choice(512, 15, replace=False)
    z[spikes] -= rng.uniform(0.002, 0.02, 15)  # reflections in front of the surface
    d = detect_edge(y, z, v, EdgeModel("step", height_m=(0.005, 0.05)))
    assert d.found and abs(d.point[0] - 0.002) <= 0.5 * SPACING + 5e-6
    # Two equal steps in view: ambiguous without a prior, resolved with one.
    two = [((-0.03, 0.1), (-0.01, 0.1)), ((-0.01, 0.11), (0.01, 0.11))]
    two.append(((0.01, 0.12), (0.03, 0.12)))
    model = EdgeModel("step", height_m=(0.005, 0.05))
    plain = detect_edge(*cast(two), model)
    assert plain.confidence < 0.6
    tracked = detect_edge(*cast(two), model, prior_y=0.009)
    assert abs(tracked.point[0] - 0.01) < 1e-4
    assert tracked.confidence > plain.confidence
    # Nothing to see.
    nothing = detect_edge(*cast([((-0.03, 0.3), (0.03, 0.3))]), model)
    assert not nothing.found and nothing.reason


def test_edge_model_from_mapping() -> None:
    m = EdgeModel.from_mapping({"kind": "v_groove", "angle_deg": [70, 110], "min_confidence": 0.7})
    assert m.kind == "v_groove" and m.angle_deg == (70.0, 110.0)
    assert EdgeModel.from_mapping(m.to_dict()) == m
    with pytest.raises(ValueError, match="unknown"):
        EdgeModel.from_mapping({"kind": "step", "hieght_m": [0, 1]})
    with pytest.raises(ValueError, match="kind"):
        EdgeModel.from_mapping({"kind": "fillet"})
    with pytest.raises(ValueError, match="height_m"):
        EdgeModel.from_mapping({"kind": "step", "height_m": [0.01, 0.001]})


# --------------------------------------------------------------------------------------------
# Paths


def _curve(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A 3D curve on a tilted cylinder of radius 60 mm (points, unit normals of the top)."""
    r = 0.06
    phi = s / r
    p = np.stack([r * np.cos(phi), r * np.sin(phi), 0.02 + 0.01 * np.sin(phi)], axis=1)
    dp = np.stack([-np.sin(phi), np.cos(phi), 0.01 / r * np.cos(phi)], axis=1)
    n = np.cross(dp, -np.cross(dp, np.array([0.0, 0.0, 1.0])))  # up, perpendicular to dp
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    return p, n


def test_smooth_path_resamples_at_the_resolution_without_bias() -> None:
    rng = np.random.default_rng(0)
    s = np.sort(rng.uniform(0, 0.1, 3000))
    p_true, n_true = _curve(s)
    noisy = p_true + rng.normal(0, 30e-6, p_true.shape)
    # Normals as a sensor sees them: projected onto a laser plane whose X axis is off the
    # tangent by up to 10 degrees.
    t_true = np.gradient(p_true, axis=0)
    t_true /= np.linalg.norm(t_true, axis=1, keepdims=True)
    ang = np.radians(10) * np.sin(40 * s)
    x = t_true * np.cos(ang)[:, None] + np.cross(n_true, t_true) * np.sin(ang)[:, None]
    n_meas = n_true - np.einsum("ij,ij->i", n_true, x)[:, None] * x
    n_meas /= np.linalg.norm(n_meas, axis=1, keepdims=True)
    path = smooth_path(noisy, 0.001, normals=n_meas, view_x=x)
    spacing = np.linalg.norm(np.diff(path.points, axis=0), axis=1)
    np.testing.assert_allclose(spacing, 0.001, rtol=2e-3)
    assert path.length_m == pytest.approx(0.1, abs=0.002)
    dense, dense_n = _curve(np.linspace(-0.001, 0.101, 200001))
    from scipy.spatial import cKDTree

    d, j = cKDTree(dense).query(path.points)
    assert float(np.sqrt(np.mean(d**2))) < 10e-6  # well under the 30 um noise
    tang = dense[np.minimum(j + 1, len(dense) - 1)] - dense[np.maximum(j - 1, 0)]
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    cos_t = np.einsum("ij,ij->i", tang, path.tangents)
    assert float(np.min(cos_t[1:-1])) > math.cos(math.radians(1))
    assert float(np.min(cos_t)) > math.cos(math.radians(3))  # one-sided at the ends
    err = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", dense_n[j], path.normals), -1, 1)))
    assert float(err[1:-1].max()) < 0.5
    assert float(err.max()) < 2.0  # one-sided at the ends
    assert path.max_gap_m < 0.001
    assert path.residual_rms_m == pytest.approx(math.sqrt(2) * 30e-6, rel=0.25)  # 2 axes
    with pytest.raises(ValueError):
        smooth_path(noisy[:3], 0.001)


def test_smooth_path_reports_a_gap() -> None:
    s = np.concatenate([np.linspace(0, 0.02, 200), np.linspace(0.025, 0.04, 150)])
    p, _ = _curve(s)
    path = smooth_path(p, 0.001)
    assert path.max_gap_m == pytest.approx(0.005, rel=0.05)


def test_path_direction_follows_acquisition_order() -> None:
    s = np.linspace(0.0, 0.03, 300)[::-1]
    p, _ = _curve(s)
    path = smooth_path(p, 0.001)
    assert float(np.linalg.norm(path.points[0] - p[0])) < 1e-4  # starts where it started
    assert float(path.tangents[0] @ (p[1] - p[0])) > 0
