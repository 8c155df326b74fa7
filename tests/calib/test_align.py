"""calib.align: Eq. (1) on batches against a hand example, a per-profile loop and the part frame."""

from __future__ import annotations

import numpy as np
import pytest

from wristscan.calib import align, se3, table


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(11)


def random_poses(rng: np.random.Generator, p: int) -> np.ndarray:
    return se3.make(se3.rotvec_to_matrix(rng.normal(size=(p, 3))), rng.normal(size=(p, 3)))


def loop_reference(y: np.ndarray, z: np.ndarray, idx: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """One profile at a time, through se3.apply (the obvious slow way)."""
    out = np.empty((y.shape[0], 3))
    for i in range(poses.shape[0]):
        sel = np.flatnonzero(idx == i)
        out[sel] = se3.apply(poses[i], align.profile_points(y[sel], z[sel]))
    return out


def test_profile_points() -> None:
    p = align.profile_points([0.1, 0.2], [0.3, 0.4])
    np.testing.assert_array_equal(p, [[0.0, 0.1, 0.3], [0.0, 0.2, 0.4]])
    with pytest.raises(ValueError, match="equal length"):
        align.profile_points([0.1], [0.3, 0.4])


def test_hand_computed_example() -> None:
    # Flange at (1, 2, 3) turned 90 deg about base Z; sensor 0.1 m ahead of the flange on its Z.
    flange2base = se3.make(se3.rot_z(np.pi / 2), [1.0, 2.0, 3.0])[None]
    sensor2flange = se3.make(t=[0.0, 0.0, 0.1])
    # Sensor (0, 0.01, 0.2) -> flange (0, 0.01, 0.3) -> Rz90 (-0.01, 0, 0.3) -> base + (1, 2, 3).
    xyz = align.align([0.01], [0.2], [0], flange2base, sensor2flange)
    np.testing.assert_allclose(xyz, [[0.99, 2.0, 3.3]], atol=1e-15)
    # Table frame: the table origin at (1, 2, 0), no rotation.
    b2t = se3.make(t=[-1.0, -2.0, 0.0])
    xyz_t = align.align([0.01], [0.2], [0], flange2base, sensor2flange, b2t, frame="table")
    np.testing.assert_allclose(xyz_t, [[-0.01, 0.0, 3.3]], atol=1e-15)
    # Part frame: the table has turned by 90 deg (offset 0.1 + angle pi/2 - 0.1), so undo it.
    xyz_p = align.align(
        [0.01], [0.2], [0], flange2base, sensor2flange, b2t, [np.pi / 2 - 0.1], 0.1, "part"
    )
    np.testing.assert_allclose(xyz_p, [[0.0, 0.01, 3.3]], atol=1e-15)


@pytest.mark.parametrize("shuffle", [False, True])
def test_matches_per_profile_loop(rng: np.random.Generator, shuffle: bool) -> None:
    p, n = 37, 101
    poses_f = random_poses(rng, p)
    s2f = random_poses(rng, 1)[0]
    y = rng.normal(size=p * n)
    z = rng.normal(size=p * n)
    idx = np.repeat(np.arange(p), n).astype(np.uint32)
    if shuffle:  # exercises the general (gather) path
        perm = rng.permutation(p * n)
        y, z, idx = y[perm], z[perm], idx[perm]
    got = align.align(y, z, idx, poses_f, s2f)
    want = loop_reference(y, z, idx, poses_f @ s2f)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-13)
    assert got.dtype == np.float64 and got.flags.c_contiguous


def test_uneven_profiles_and_unused_poses(rng: np.random.Generator) -> None:
    poses = random_poses(rng, 6)
    counts = [3, 0, 5, 1, 0, 4]  # sorted but uneven, two poses without points
    idx = np.repeat(np.arange(6), counts)
    y, z = rng.normal(size=idx.size), rng.normal(size=idx.size)
    got = align.align_with_poses(y, z, idx, poses)
    np.testing.assert_allclose(got, loop_reference(y, z, idx, poses), atol=1e-13)
    # Equal runs that skip poses (regular path), and a layout that only looks regular at first.
    for idx2 in (np.repeat([0, 2, 5], 4), np.array([0, 0, 1, 1, 1, 2])):
        y2, z2 = rng.normal(size=idx2.size), rng.normal(size=idx2.size)
        np.testing.assert_allclose(
            align.align_with_poses(y2, z2, idx2, poses),
            loop_reference(y2, z2, idx2, poses),
            atol=1e-13,
        )


def test_mask_drops_invalid_points(rng: np.random.Generator) -> None:
    p, n = 5, 8
    poses_f = random_poses(rng, p)
    y = rng.normal(size=p * n)
    z = rng.normal(size=p * n)
    idx = np.repeat(np.arange(p), n)
    mask = rng.uniform(size=p * n) > 0.3
    y[~mask] = np.nan  # invalid points may hold anything
    got = align.align(y, z, idx, poses_f, np.eye(4), mask=mask)
    want = loop_reference(y[mask], z[mask], idx[mask], poses_f)
    assert got.shape == (int(mask.sum()), 3)
    np.testing.assert_allclose(got, want, atol=1e-13)
    with pytest.raises(ValueError, match="non-finite"):
        align.align(y, z, idx, poses_f, np.eye(4))
    # Same on the general path (points not grouped by profile).
    perm = rng.permutation(p * n)
    got_sh = align.align(y[perm], z[perm], idx[perm], poses_f, np.eye(4), mask=mask[perm])
    np.testing.assert_allclose(got_sh, loop_reference(y, z, idx, poses_f)[perm][mask[perm]])
    with pytest.raises(ValueError, match="non-finite"):
        align.align(y[perm], z[perm], idx[perm], poses_f, np.eye(4))


def test_align_and_poses_returns_the_poses_the_points_went_through(
    rng: np.random.Generator,
) -> None:
    p, n = 4, 6
    f2b = random_poses(rng, p)
    s2f = se3.make(se3.rotvec_to_matrix([0.1, -0.2, 0.05]), [0.01, 0.0, 0.12])
    b2t = se3.make(se3.rotvec_to_matrix([0.02, 0.01, 0.3]), [0.7, 0.1, 0.02])
    theta = rng.uniform(0.0, 6.0, size=p)
    y, z = rng.normal(size=p * n), rng.normal(size=p * n)
    idx = np.repeat(np.arange(p), n)
    mask = rng.uniform(size=p * n) > 0.2
    args = (y, z, idx, f2b, s2f, b2t, theta, 0.25, "part", mask)
    xyz, poses = align.align_and_poses(*args)
    want = align.sensor_poses(f2b, s2f, b2t, theta, 0.25, "part")
    np.testing.assert_allclose(poses, want, atol=1e-15)
    np.testing.assert_array_equal(xyz, align.align(*args))
    np.testing.assert_allclose(xyz, loop_reference(y, z, idx, want)[mask], atol=1e-13)


def test_part_frame_point_on_turning_part_is_constant(rng: np.random.Generator) -> None:
    # A tilted table axis, a fixed part point, and a sensor that sees it from a new robot pose
    # at each of P table angles.
    axis_dir = se3.rotvec_to_matrix([0.03, 0.01, 0.0]) @ np.array([0.0, 0.0, 1.0])
    b2t = table.base2table_from(axis_dir, [0.7, 0.1, 0.02])
    offset = 0.25
    s2f = se3.make(se3.rotvec_to_matrix([0.1, -0.2, 0.05]), [0.01, 0.0, 0.12])
    p_part = np.array([0.05, -0.03, 0.04])
    P = 9
    theta = np.linspace(0.0, 5.0, P)
    part2base = se3.invert(b2t) @ table.table_rotation(theta, offset)
    p_base = part2base[:, :3, :3] @ p_part + part2base[:, :3, 3]
    # Pick each sensor pose so that the point lies in the laser plane at (0, y_k, z_k).
    R_s = se3.rotvec_to_matrix(rng.normal(size=(P, 3)))
    yz = rng.uniform(-0.02, 0.02, size=(P, 2)) + np.array([0.0, 0.15])
    s_pt = np.column_stack([np.zeros(P), yz])
    sensor2base = se3.make(R_s, p_base - np.einsum("kij,kj->ki", R_s, s_pt))
    f2b = sensor2base @ se3.invert(s2f)
    idx = np.arange(P)
    got_part = align.align(yz[:, 0], yz[:, 1], idx, f2b, s2f, b2t, theta, offset, "part")
    np.testing.assert_allclose(got_part, np.tile(p_part, (P, 1)), atol=1e-12)
    got_base = align.align(yz[:, 0], yz[:, 1], idx, f2b, s2f, frame="base")
    np.testing.assert_allclose(got_base, p_base, atol=1e-12)
    got_table = align.align(yz[:, 0], yz[:, 1], idx, f2b, s2f, b2t, frame="table")
    np.testing.assert_allclose(got_table, se3.apply(b2t, p_base), atol=1e-12)
    # sensor_poses is the composed chain of Eq. (1).
    poses = align.sensor_poses(f2b, s2f, b2t, theta, offset, "part")
    np.testing.assert_allclose(poses, table.table2part(theta, offset) @ b2t @ f2b @ s2f, atol=1e-14)


def test_empty_batch() -> None:
    out = align.align(np.zeros(0), np.zeros(0), np.zeros(0, dtype=int), np.eye(4)[None], np.eye(4))
    assert out.shape == (0, 3)


def test_bad_input_is_refused(rng: np.random.Generator) -> None:
    poses = random_poses(rng, 3)
    y = z = np.zeros(4)
    idx = np.array([0, 1, 2, 2])
    with pytest.raises(ValueError, match="out of range"):
        align.align(y, z, np.array([0, 1, 3, 2]), poses, np.eye(4))
    with pytest.raises(ValueError, match="out of range"):
        align.align(y, z, np.array([0, -1, 2, 2]), poses, np.eye(4))
    with pytest.raises(ValueError, match="integer"):
        align.align(y, z, idx.astype(float), poses, np.eye(4))
    with pytest.raises(ValueError, match="equal length"):
        align.align(y, z[:3], idx, poses, np.eye(4))
    with pytest.raises(ValueError, match=r"flange2base: expected \(P, 4, 4\)"):
        align.align(y, z, idx, poses[0], np.eye(4))
    bad = poses.copy()
    bad[1, 0, 0] = 2.0
    with pytest.raises(ValueError, match="flange2base: rotation part is not orthonormal"):
        align.align(y, z, idx, bad, np.eye(4))
    with pytest.raises(ValueError, match="sensor2flange"):
        align.align(y, z, idx, poses, np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match="needs base2table"):
        align.align(y, z, idx, poses, np.eye(4), frame="table")
    with pytest.raises(ValueError, match="needs table_angle_rad"):
        align.align(y, z, idx, poses, np.eye(4), np.eye(4), frame="part")
    with pytest.raises(ValueError, match="table_angle_rad"):
        align.align(y, z, idx, poses, np.eye(4), np.eye(4), np.zeros(2), frame="part")
    with pytest.raises(ValueError, match="frame must be"):
        align.align(y, z, idx, poses, np.eye(4), frame="world")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="sensor2frame: contains NaN"):
        align.align_with_poses(y, z, idx, np.full((3, 4, 4), np.nan))
    with pytest.raises(ValueError, match=r"sensor2frame: expected \(P, 4, 4\)"):
        align.align_with_poses(y, z, idx, np.eye(4))
    with pytest.raises(ValueError, match="mask"):
        align.align(y, z, idx, poses, np.eye(4), mask=np.ones(4, dtype=int))
