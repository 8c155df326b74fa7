"""calib.align.align_rows: the hot path's float32 alignment of whole profiles against the float64
``align`` (itself checked against a per-profile loop in test_align.py), compiled and in numpy."""

from __future__ import annotations

import numpy as np
import pytest

from wristscan.calib import align, jit, se3


@pytest.fixture(autouse=True, params=["compiled", "numpy"])
def backend(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Every test on both paths: the compiled kernel (numba, in the test install) and numpy."""
    monkeypatch.setattr(jit, "enabled", request.param == "compiled")
    if request.param == "compiled":
        assert jit.available(), "numba (extra 'fast') belongs to the test install"
    return str(request.param)


def poses_near_base(rng: np.random.Generator, p: int) -> np.ndarray:
    """Sensor poses within 1.5 m of the origin, looking anywhere: the points lie within 2 m."""
    return se3.make(se3.rotvec_to_matrix(rng.normal(size=(p, 3))), rng.uniform(-0.85, 0.85, (p, 3)))


def reference(y: np.ndarray, z: np.ndarray, valid: np.ndarray | None, poses: np.ndarray):
    """The float64 path: every point of every profile through ``align``, the invalid masked."""
    p, n = z.shape
    yy = np.broadcast_to(y, (p, n)).ravel()
    idx = np.repeat(np.arange(p), n)
    mask = None if valid is None else valid.ravel()
    return align.align_with_poses(yy, z.ravel(), idx, poses, mask=mask)


@pytest.mark.parametrize("grid", ["shared", "per-profile"])
@pytest.mark.parametrize("invalid", [0.0, 0.3])
def test_matches_the_float64_path(grid: str, invalid: float) -> None:
    rng = np.random.default_rng(21)
    p, n = 23, 700  # several blocks, the last one short
    poses = poses_near_base(rng, p)
    y = np.linspace(-0.05, 0.05, n) if grid == "shared" else rng.uniform(-0.05, 0.05, (p, n))
    z = rng.uniform(0.05, 0.4, (p, n))
    valid = rng.uniform(size=(p, n)) >= invalid
    valid[3] = False  # a profile without a valid point
    z[~valid] = np.nan  # invalid points may hold anything
    want = reference(y, z, valid, poses)
    got = align.align_rows(y, z, valid, poses)
    assert got.dtype == np.float32 and got.flags.c_contiguous and got.shape == want.shape
    assert np.abs(want).max() < 2.0
    # float32: half an ulp at 2 m is 0.12 um; three roundings stay far below 1 um
    err = np.abs(got.astype(np.float64) - want).max()
    assert err < 0.5e-6, err
    # into a caller's buffer (a WSC1 payload's view), returned as it is
    buf = np.full((want.shape[0], 3), np.nan, np.float32)
    assert align.align_rows(y, z, valid, poses, out=buf) is buf
    np.testing.assert_array_equal(buf, got)
    # valid=None and an all-true mask mean the same
    z_ok = np.where(valid, z, 0.2)
    np.testing.assert_array_equal(
        align.align_rows(y, z_ok, None, poses),
        align.align_rows(y, z_ok, np.ones_like(valid), poses),
    )


def test_hand_computed_point() -> None:
    # Sensor turned 90 deg about Z at (1, 2, 3): sensor (0, 0.01, 0.2) -> (-0.01, 0, 0.2) + t.
    pose = se3.make(se3.rot_z(np.pi / 2), [1.0, 2.0, 3.0])[None]
    got = align.align_rows(
        np.array([0.01, 0.02]), np.array([[0.2, np.nan]]), None, pose, check_finite=False
    )
    np.testing.assert_allclose(got[0], [0.99, 2.0, 3.2], atol=1e-7)


def test_empty_batches() -> None:
    assert align.align_rows(np.zeros(5), np.zeros((0, 5)), None, np.zeros((0, 4, 4))).shape == (
        0,
        3,
    )
    none_valid = align.align_rows(
        np.zeros(4), np.full((2, 4), np.nan), np.zeros((2, 4), bool), np.tile(np.eye(4), (2, 1, 1))
    )
    assert none_valid.shape == (0, 3) and none_valid.dtype == np.float32


def test_bad_input_is_refused() -> None:
    poses = np.tile(np.eye(4), (2, 1, 1))
    y, z = np.zeros(3), np.zeros((2, 3))
    with pytest.raises(ValueError, match=r"z: expected \(P, N\)"):
        align.align_rows(y, z.ravel(), None, poses)
    with pytest.raises(ValueError, match=r"y: expected \(3,\) or \(2, 3\)"):
        align.align_rows(np.zeros(4), z, None, poses)
    with pytest.raises(ValueError, match=r"valid: expected bool \(2, 3\)"):
        align.align_rows(y, z, np.ones((2, 3), int), poses)
    with pytest.raises(ValueError, match=r"sensor2frame: expected \(2, 4, 4\)"):
        align.align_rows(y, z, None, poses[:1])
    with pytest.raises(ValueError, match=r"out: expected a writable C-contiguous float32 \(6, 3\)"):
        align.align_rows(y, z, None, poses, out=np.empty((6, 3)))
    with pytest.raises(ValueError, match="out: expected"):
        align.align_rows(y, z, None, poses, out=np.empty((5, 3), np.float32))
    with pytest.raises(ValueError, match="out: expected"):
        align.align_rows(y, z, None, poses, out=np.empty((3, 6), np.float32).T)
    valid = np.array([[True, False, True], [True, True, True]])
    bad = np.array([[0.1, np.nan, 0.2], [0.3, np.inf, 0.4]])
    with pytest.raises(ValueError, match=r"non-finite coordinates \(first at output row 3\)"):
        align.align_rows(y, bad, valid, poses)
    assert align.align_rows(y, bad, valid, poses, check_finite=False).shape == (5, 3)
    # without a mask every point is valid: the inputs are checked
    with pytest.raises(ValueError, match="non-finite z in profile 1"):
        align.align_rows(y, np.array([[0.1, 0.2, 0.3], [0.1, np.nan, 0.2]]), None, poses)
    with pytest.raises(ValueError, match="non-finite y in profile 0"):
        align.align_rows(np.array([[0.1, np.inf, 0.2], [0.0, 0.1, 0.2]]), z, None, poses)
    with pytest.raises(ValueError, match="non-finite y in the lateral grid"):
        align.align_rows(np.array([0.0, np.nan, 0.2]), z, None, poses)


def test_a_sensors_codes_align_as_their_decoded_z(backend: str) -> None:
    """Integer codes with their scale (the LPF1 hot path keeps them undecoded) give the points
    the decoded float64 z gives: bit for bit compiled (the kernel decodes as numpy does)."""
    rng = np.random.default_rng(11)
    p, n = 6, 500
    poses = poses_near_base(rng, p)
    y = np.linspace(-0.03, 0.03, n)
    codes = rng.integers(-30000, 30000, (p, n)).astype(np.int16)
    codes[[0, 1, 3], :40] = -32768  # invalid (the sentinel); 4 and 5 all valid
    codes[2] = -32768  # a profile with no valid point
    valid = codes != -32768
    scale, offset = 2e-6, 0.15
    z = codes.astype(np.float64) * scale + offset
    z[~valid] = np.nan
    coded = align.align_rows(y, codes, valid, poses, z_scale=(scale, offset))
    decoded = align.align_rows(y, z, valid, poses)
    assert coded.shape == (int(valid.sum()), 3)
    if backend == "compiled":
        assert coded.tobytes() == decoded.tobytes()
    else:
        assert np.abs(coded - decoded).max() <= 2.5e-7
