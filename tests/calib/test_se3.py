"""se3: conversions round-trip, composition follows the a2b naming, interpolation is geodesic."""

from __future__ import annotations

import numpy as np
import pytest

from wristscan.calib import se3


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1)


def test_rotvec_matrix_roundtrip_batched(rng: np.random.Generator) -> None:
    rv = rng.normal(size=(4, 5, 3))
    rv *= (np.pi * 0.99 / np.linalg.norm(rv, axis=-1))[..., None] * rng.uniform(size=(4, 5, 1))
    R = se3.rotvec_to_matrix(rv)
    assert R.shape == (4, 5, 3, 3)
    np.testing.assert_allclose(se3.matrix_to_rotvec(R), rv, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)


def test_rotvec_matches_rodrigues(rng: np.random.Generator) -> None:
    rv = rng.normal(size=3)
    th = np.linalg.norm(rv)
    k = rv / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    R = np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
    np.testing.assert_allclose(se3.rotvec_to_matrix(rv), R, atol=1e-14)


def test_quaternion_orders(rng: np.random.Generator) -> None:
    # 90 degrees about Z: w = cos 45, z = sin 45.
    R = se3.rot_z(np.pi / 2)
    h = np.sqrt(0.5)
    np.testing.assert_allclose(se3.matrix_to_quat_wxyz(R), [h, 0, 0, h], atol=1e-12)
    np.testing.assert_allclose(se3.matrix_to_quat_xyzw(R), [0, 0, h, h], atol=1e-12)
    Rs = se3.rotvec_to_matrix(rng.normal(size=(10, 3)))
    np.testing.assert_allclose(se3.quat_wxyz_to_matrix(se3.matrix_to_quat_wxyz(Rs)), Rs, atol=1e-12)
    np.testing.assert_allclose(se3.quat_xyzw_to_matrix(se3.matrix_to_quat_xyzw(Rs)), Rs, atol=1e-12)


def test_pose_roundtrip_and_ur_example() -> None:
    # UR pose p[0.1, 0.2, 0.3, 0, 0, pi/2]: a quarter turn about base Z.
    T = se3.pose_to_matrix([0.1, 0.2, 0.3, 0.0, 0.0, np.pi / 2])
    np.testing.assert_allclose(T[:3, 3], [0.1, 0.2, 0.3])
    np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(se3.matrix_to_pose(T), [0.1, 0.2, 0.3, 0, 0, np.pi / 2], atol=1e-12)


def test_pose_rejects_wrong_length() -> None:
    with pytest.raises(ValueError, match="6 values"):
        se3.pose_to_matrix([1, 2, 3])


def test_invert_compose_apply(rng: np.random.Generator) -> None:
    a2b = se3.pose_to_matrix(rng.normal(size=(3, 6)))
    b2c = se3.pose_to_matrix(rng.normal(size=(3, 6)))
    a2c = se3.compose(b2c, a2b)
    pts = rng.normal(size=(3, 7, 3))
    np.testing.assert_allclose(se3.apply(a2c, pts), se3.apply(b2c, se3.apply(a2b, pts)), atol=1e-12)
    np.testing.assert_allclose(
        se3.invert(a2b) @ a2b, np.broadcast_to(np.eye(4), (3, 4, 4)), atol=1e-12
    )
    np.testing.assert_allclose(se3.invert(a2b), np.linalg.inv(a2b), atol=1e-12)


def test_interpolate_endpoints_and_midpoint() -> None:
    T0 = se3.make(se3.rot_z(0.0), [0, 0, 0])
    T1 = se3.make(se3.rot_z(1.0), [1, 2, 3])
    s = np.array([0.0, 0.5, 1.0])
    Ti = se3.interpolate(T0, T1, s)
    np.testing.assert_allclose(Ti[0], T0, atol=1e-12)
    np.testing.assert_allclose(Ti[2], T1, atol=1e-12)
    np.testing.assert_allclose(Ti[1], se3.make(se3.rot_z(0.5), [0.5, 1, 1.5]), atol=1e-12)


def test_interpolate_takes_shortest_arc() -> None:
    T0 = se3.make(se3.rot_z(3.0))
    T1 = se3.make(se3.rot_z(-3.0))  # 0.283 rad apart through pi
    mid = se3.interpolate(T0, T1, 0.5)
    assert se3.rotation_angle(mid[:3, :3]) == pytest.approx(np.pi, abs=1e-9)


def test_check_transform_names_the_problem() -> None:
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValueError, match="sensor2flange: rotation part is not orthonormal"):
        se3.check_transform(bad, "sensor2flange")
    refl = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="reflection"):
        se3.check_transform(refl)
    assert se3.check_transform(np.eye(4)).shape == (4, 4)
