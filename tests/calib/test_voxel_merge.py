"""Voxel means of a cloud held as batches (``voxel_mean_chunks``) against ``voxel_mean`` of
the whole cloud at once."""

from __future__ import annotations

import numpy as np

from wristscan.calib.merge import voxel_mean, voxel_mean_chunks


def _batches(seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    for k in range(12):
        n = int(rng.integers(0, 3000)) if k != 4 else 0  # an empty batch among them
        centre = rng.uniform(-0.2, 0.2, 3)
        out.append((centre + rng.normal(0.0, 0.004, (n, 3))).astype(np.float32))
    return out


def test_batches_give_the_voxels_of_the_whole_cloud() -> None:
    for seed in range(3):
        chunks = _batches(seed)
        whole = voxel_mean(np.concatenate(chunks).astype(np.float64), 0.0005, grid="origin")[0]
        merged = voxel_mean_chunks(chunks, 0.0005)
        assert merged.shape == whole.shape and merged.shape[0] > 1000
        # The same voxels in the same order; the means up to the order of the float64 sums.
        np.testing.assert_allclose(merged, whole, rtol=0, atol=1e-15)


def test_far_points_and_edge_cases_take_the_plain_way() -> None:
    far = [np.array([[0.0, 0.0, 0.0], [600.0, 0.0, 0.0]], np.float32)]  # 1.2 M voxels away
    np.testing.assert_array_equal(
        voxel_mean_chunks(far, 0.0005),
        voxel_mean(far[0].astype(np.float64), 0.0005, grid="origin")[0],
    )
    assert voxel_mean_chunks([], 0.0005).shape == (0, 3)
    pts = [np.ones((3, 3), np.float32)]
    np.testing.assert_array_equal(voxel_mean_chunks(pts, 0.0), pts[0])
