"""E57 files read back by pye57: one scan per pass, its pose, intensity, times."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pye57
import pytest
from scipy.spatial.transform import Rotation

from wristscan.daemon.io.e57_out import E57Writer, SpooledScan, utc_ns_to_gps_s

T0 = 1_700_000_000_000_000_000


def _pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    m[:3, 3] = rng.normal(size=3) * 0.2
    return m


def test_scans_with_poses_and_intensity(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    scans = [
        (rng.normal(size=(500 + 10 * k, 3)).astype(np.float32) * 0.05, _pose(k)) for k in range(3)
    ]
    inten = rng.integers(0, 256, 500).astype(np.uint8)
    path = tmp_path / "scan.e57"
    with E57Writer(path) as w:
        for k, (xyz, pose) in enumerate(scans):
            w.add_scan(
                xyz,
                f"pass {k + 1}",
                pose,
                intensity=inten if k == 0 else None,
                t_start_ns=T0 + k * 10**9,
                t_end_ns=T0 + k * 10**9 + 5 * 10**8,
            )
        w.add_scan(np.zeros((0, 3)), "empty")  # not written
    assert os.listdir(tmp_path) == ["scan.e57"]
    e57 = pye57.E57(str(path))
    assert e57.scan_count == 3
    for k, (xyz, pose) in enumerate(scans):
        head = e57.get_header(k)
        assert head["name"].value() == f"pass {k + 1}"
        np.testing.assert_allclose(head.rotation_matrix, pose[:3, :3], atol=1e-12)
        np.testing.assert_allclose(head.translation, pose[:3, 3], atol=1e-12)
        start = head["acquisitionStart"]["dateTimeValue"].value()
        assert start == pytest.approx(utc_ns_to_gps_s(T0 + k * 10**9), abs=1e-6)
        # 2023-11-14 22:13:20 UTC is GPS second 1384035218 (18 leap seconds)
        assert utc_ns_to_gps_s(T0) == pytest.approx(1_384_035_218.0)
        local = e57.read_scan_raw(k)
        got = np.stack([local[c] for c in ("cartesianX", "cartesianY", "cartesianZ")], axis=1)
        np.testing.assert_array_equal(got, xyz.astype(np.float64))
        world = e57.read_scan(k, transform=True, ignore_missing_fields=True)
        expect = xyz.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
        np.testing.assert_allclose(world["cartesianX"], expect[:, 0], atol=1e-9)
        np.testing.assert_allclose(world["cartesianZ"], expect[:, 2], atol=1e-9)
        if k == 0:
            np.testing.assert_array_equal(local["intensity"], inten)
            assert (head.intensityMinimum, head.intensityMaximum) == (0.0, 255.0)
        else:
            assert "intensity" not in head.point_fields


def test_spooled_scan_is_one_scan_and_leaves_no_files(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    parts = [rng.normal(size=(300, 3)).astype(np.float32) for _ in range(4)]
    ints = [rng.integers(0, 256, 300).astype(np.uint8) for _ in range(4)]
    path = tmp_path / "rec.e57"
    with E57Writer(path) as w:
        spool = SpooledScan(path, has_intensity=True)
        for p, i in zip(parts, ints, strict=True):
            spool.add(p, i)
        spool.write_into(w, "recording", T0, T0 + 10**9)
    assert os.listdir(tmp_path) == ["rec.e57"]
    e57 = pye57.E57(str(path))
    assert e57.scan_count == 1
    raw = e57.read_scan_raw(0)
    np.testing.assert_array_equal(raw["cartesianY"], np.concatenate(parts)[:, 1])
    np.testing.assert_array_equal(raw["intensity"], np.concatenate(ints))


def test_abort_leaves_nothing(tmp_path: Path) -> None:
    path = tmp_path / "x.e57"
    with pytest.raises(RuntimeError), E57Writer(path) as w:
        w.add_scan(np.ones((5, 3)), "a")
        raise RuntimeError("stopped")
    assert os.listdir(tmp_path) == []
