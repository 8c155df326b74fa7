"""calib.table: axis fit against ground truth, the frames of Eq. (1), degenerate input."""

from __future__ import annotations

import numpy as np
import pytest

from wristscan.calib import se3, table

# Ground truth: an axis tilted ~1.3 deg from base Z, a point on it, a ball off the axis.
AXIS = se3.rotvec_to_matrix([0.02, -0.01, 0.0]) @ np.array([0.0, 0.0, 1.0])
ON_AXIS = np.array([0.6, -0.2, 0.05])
BALL0 = np.array([0.7, -0.1, 0.12])  # ball centre at encoder angle 0 (base frame, m)


def centres_at(theta: np.ndarray, axis: np.ndarray = AXIS) -> np.ndarray:
    """Ball centres after the table turned by theta (right-handed about ``axis``)."""
    R = se3.rotvec_to_matrix(theta[:, None] * axis)
    return ON_AXIS + np.einsum("kij,j->ki", R, BALL0 - ON_AXIS)


def foot_and_radius() -> tuple[np.ndarray, float]:
    d = BALL0 - ON_AXIS
    foot = ON_AXIS + (d @ AXIS) * AXIS
    return foot, float(np.linalg.norm(BALL0 - foot))


def expected_offset() -> float:
    """Azimuth of the ball at encoder zero from the table X axis (independent construction)."""
    foot, _ = foot_and_radius()
    x = np.array([1.0, 0.0, 0.0]) - AXIS[0] * AXIS
    x /= np.linalg.norm(x)
    y = np.cross(AXIS, x)
    d = BALL0 - foot
    return float(np.arctan2(d @ y, d @ x))


def test_noise_free_recovers_axis_point_offset() -> None:
    theta = np.linspace(0.0, 2 * np.pi, 8, endpoint=False) + 0.1
    ax = table.fit_table_axis(centres_at(theta), theta)
    foot, radius = foot_and_radius()
    np.testing.assert_allclose(ax.direction, AXIS, atol=1e-10)
    np.testing.assert_allclose(ax.point, foot, atol=1e-10)
    assert ax.radius_m == pytest.approx(radius, abs=1e-10)
    assert ax.encoder_offset_rad == pytest.approx(expected_offset(), abs=1e-9)
    assert ax.tilt_deg == pytest.approx(np.degrees(np.arccos(AXIS[2])), abs=1e-8)
    assert ax.rms_m < 1e-12
    np.testing.assert_allclose(ax.ball_in_part, [radius, 0.0, 0.0], atol=1e-10)
    assert ax.cov.shape == (7, 7)
    assert ax.n_angles == 8


def test_direction_sign_follows_increasing_angle() -> None:
    theta = np.array([0.0, 0.5, 1.0, 1.6])
    # The same centres reported with negated encoder angles: the table turns the other way.
    ax = table.fit_table_axis(centres_at(theta), -theta)
    np.testing.assert_allclose(ax.direction, -AXIS, atol=1e-10)
    assert ax.tilt_deg == pytest.approx(np.degrees(np.arccos(AXIS[2])), abs=1e-8)


def test_three_angles_small_arc_noise_free() -> None:
    theta = np.deg2rad([10.0, 25.0, 40.0])
    ax = table.fit_table_axis(centres_at(theta), theta)
    np.testing.assert_allclose(ax.direction, AXIS, atol=1e-9)
    assert ax.encoder_offset_rad == pytest.approx(expected_offset(), abs=1e-8)


def test_offset_not_estimated_puts_azimuth_in_ball_position() -> None:
    theta = np.linspace(-1.0, 2.0, 5)
    ax = table.fit_table_axis(centres_at(theta), theta, estimate_offset=False)
    _, radius = foot_and_radius()
    phi = expected_offset()
    assert ax.encoder_offset_rad == 0.0
    np.testing.assert_allclose(
        ax.ball_in_part, [radius * np.cos(phi), radius * np.sin(phi), 0.0], atol=1e-10
    )


def test_noisy_fit_within_its_covariance() -> None:
    rng = np.random.default_rng(7)
    theta = np.linspace(0.0, 2 * np.pi, 12, endpoint=False)
    sigma = 20e-6
    clean = centres_at(theta)
    foot, _ = foot_and_radius()
    tilt_err, off_err, pt_err, pred = [], [], [], []
    for _ in range(60):
        ax = table.fit_table_axis(clean + rng.normal(scale=sigma, size=clean.shape), theta)
        tilt_err.append(np.arccos(np.clip(ax.direction @ AXIS, -1.0, 1.0)))
        off_err.append(ax.encoder_offset_rad - expected_offset())
        pt_err.append(ax.point - foot)
        pred.append(np.sqrt(np.diag(ax.cov)))
        assert ax.rms_m < 5 * sigma
    tilt = np.asarray(tilt_err)
    p = np.asarray(pred).mean(axis=0)
    # Tilt recovered to a few thousandths of a degree with 20 um noise.
    assert np.degrees(tilt.mean()) < 0.006
    assert tilt.max() < 5 * p[0]
    assert abs(np.degrees(np.mean(off_err))) < 0.005
    # Empirical scatter agrees with the reported covariance (within a factor 1.5).
    emp_tilt = np.sqrt(np.mean(tilt**2) / 2.0)  # two tilt components share the angle
    assert 1 / 1.5 < emp_tilt / p[0] < 1.5
    assert 1 / 1.5 < np.std(off_err) / p[6] < 1.5
    assert 1 / 1.5 < np.std(np.asarray(pt_err)[:, 0]) / p[2] < 1.5
    # With the a-priori sigma the covariance does not depend on the residuals.
    ax = table.fit_table_axis(clean, theta, centre_sigma_m=sigma)
    assert np.sqrt(ax.cov[0, 0]) == pytest.approx(p[0], rel=0.3)


def test_part_frame_constant_for_point_on_turning_table() -> None:
    theta = np.linspace(0.0, 2 * np.pi, 6, endpoint=False)
    ax = table.fit_table_axis(centres_at(theta), theta)
    # Any point fixed on the table top (not the ball) turns with it: same part coordinates.
    other0 = np.array([0.55, -0.32, 0.08])
    th = np.linspace(-3.0, 7.0, 23)
    R = se3.rotvec_to_matrix(th[:, None] * AXIS)
    other = ON_AXIS + np.einsum("kij,j->ki", R, other0 - ON_AXIS)
    B2P = table.base2part(ax, th)
    assert B2P.shape == (23, 4, 4)
    in_part = np.einsum("kij,kj->ki", B2P[:, :3, :3], other) + B2P[:, :3, 3]
    np.testing.assert_allclose(in_part, np.broadcast_to(in_part[0], in_part.shape), atol=1e-12)
    # Hand check at theta = -offset: the part frame coincides with the table frame.
    T = table.table2part(-ax.encoder_offset_rad, ax.encoder_offset_rad)
    np.testing.assert_allclose(T, np.eye(4), atol=1e-15)


def test_table_rotation_and_inverse_vectorised() -> None:
    th = np.array([[0.0, np.pi / 2], [np.pi, -0.3]])
    P2T = table.table_rotation(th, 0.1)
    T2P = table.table2part(th, 0.1)
    assert P2T.shape == T2P.shape == (2, 2, 4, 4)
    np.testing.assert_allclose(P2T @ T2P, se3.identity((2, 2)), atol=1e-15)
    # Right-handed: rotating part X by +90 deg (offset 0) gives table Y.
    np.testing.assert_allclose(table.table_rotation(np.pi / 2)[:3, 0], [0, 1, 0], atol=1e-15)


def test_base2table_frame() -> None:
    T = table.base2table_from(AXIS, ON_AXIS, origin_along_axis_m=-0.02)
    se3.check_transform(T)
    table2base = se3.invert(T)
    np.testing.assert_allclose(table2base[:3, 2], AXIS, atol=1e-15)
    # X lies in the plane of base X and the axis, on the side of base X.
    assert table2base[:3, 0] @ np.cross([1.0, 0.0, 0.0], AXIS) == pytest.approx(0.0, abs=1e-15)
    assert table2base[0, 0] > 0.99
    np.testing.assert_allclose(table2base[:3, 3], ON_AXIS - 0.02 * AXIS, atol=1e-15)
    # An axis along base X falls back to projecting base Y.
    x = table.table_x_axis([1.0, 0.0, 0.0])
    np.testing.assert_allclose(x, [0.0, 1.0, 0.0], atol=1e-15)


@pytest.mark.parametrize(
    ("theta", "message"),
    [
        (np.array([0.0, 1.0]), ">= 3 table angles"),
        (np.array([0.0, 1.0, 1.0 + 1e-6, 1.0]), "distinct"),
        (np.deg2rad([0.0, 5.0, 10.0]), "span only"),
    ],
)
def test_degenerate_angles(theta: np.ndarray, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        table.fit_table_axis(centres_at(theta), theta)


def test_degenerate_centres() -> None:
    theta = np.array([0.0, 1.0, 2.0, 3.0])
    line = np.array([0.5, 0.0, 0.1]) + np.outer(theta, [0.01, 0.02, 0.0])
    with pytest.raises(ValueError, match="collinear"):
        table.fit_table_axis(line, theta)
    same = np.tile([0.5, 0.0, 0.1], (4, 1))
    with pytest.raises(ValueError, match="coincide"):
        table.fit_table_axis(same, theta)
    with pytest.raises(ValueError, match=r"\(k, 3\)"):
        table.fit_table_axis(np.zeros((4, 2)), theta)
    with pytest.raises(ValueError, match="angles_rad"):
        table.fit_table_axis(centres_at(theta), theta[:3])
    bad = centres_at(theta)
    bad[1, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        table.fit_table_axis(bad, theta)
