"""The format by the extension: clear errors, and ``wristscan record`` writing MCAP and E57 from
a real zenoh publisher (the daemon's own zenoh face on loopback, publishing batches whose
coordinates encode their sequence number)."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pye57
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from support import loopback_publisher
from typer.testing import CliRunner

from wristscan.calib import se3
from wristscan.daemon.cli.app import app
from wristscan.daemon.cloud.zenoh_io import DaemonZenoh
from wristscan.daemon.io import cloudfile
from wristscan.daemon.io.cloudfile import CloudFormatError, cloud_format

PREFIX = "wristscan/cloudfiletest"
B = 300
T0 = 1_700_000_000_000_000_000
DT_NS = 1_000_000  # batch to batch
SPAN_NS = 300_000  # first to last profile of a batch
PROFILES = 4


def batch_xyz(seq: int) -> np.ndarray:
    xyz = np.empty((B, 3), np.float32)
    xyz[:, 0] = seq * 1e-3
    xyz[:, 1] = np.arange(B) * 1e-4
    xyz[:, 2] = 0.25
    return xyz


def batch_intensity(seq: int) -> np.ndarray:
    return ((np.arange(B) + seq) % 256).astype(np.uint8)


SENSOR2FLANGE = se3.make(se3.rot_x(0.3), np.array([0.01, -0.02, 0.1]))


def batch_flange(seq: int) -> np.ndarray:
    """The flange of each of the batch's profiles (P, 4, 4): moves and turns with ``seq``."""
    k = seq * PROFILES + np.arange(PROFILES)
    return se3.make(se3.rot_z(k * 0.01), np.stack([k * 1e-4, 0.2 + 0 * k, 0.3 + 0 * k], 1))


@pytest.mark.parametrize(
    ("name", "fmt"), [("a.ply", "ply"), ("b.NPZ", "npz"), ("c.mcap", "mcap"), ("d.e57", "e57")]
)
def test_format_by_extension(name: str, fmt: str) -> None:
    assert cloud_format(name) == fmt


def test_unknown_extension_names_the_ones_there_are() -> None:
    with pytest.raises(CloudFormatError, match=r"'\.las'.*\.ply, \.npz, \.mcap, \.e57"):
        cloud_format("scan.las")
    with pytest.raises(CloudFormatError, match=r"use one of \.ply, \.e57"):
        cloud_format("scan.npz", allowed=("ply", "e57"))


def test_missing_extra_names_the_pip_line(monkeypatch: pytest.MonkeyPatch) -> None:
    real = importlib.util.find_spec

    def without_pye57(name: str, *args: object) -> object:
        return None if name == "pye57" else real(name, *args)  # type: ignore[arg-type]

    monkeypatch.setattr(cloudfile.importlib.util, "find_spec", without_pye57)
    with pytest.raises(CloudFormatError, match=r"pip install 'wristscan\[e57\]'"):
        cloud_format("x.e57")
    assert cloud_format("x.mcap") == "mcap"


def test_record_refuses_an_unknown_extension(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(app, ["record", "--connect", "tcp/127.0.0.1:9", "-o", "x.las"])
    assert res.exit_code == 2
    assert ".mcap, .e57" in res.output
    assert os.listdir(tmp_path) == []


def _publish(dz: DaemonZenoh, k: int) -> None:
    seq = dz.seq
    dz.publish_cloud(
        batch_xyz(seq),
        t_first_ns=T0 + seq * DT_NS,
        t_last_ns=T0 + seq * DT_NS + SPAN_NS,
        n_profiles=PROFILES,
        frame_id="base",
        intensity=batch_intensity(seq),
        profile_index=np.arange(B, dtype=np.uint32) % PROFILES,
    )
    f2b = batch_flange(seq)
    t_ns = T0 + seq * DT_NS + np.linspace(0, SPAN_NS, PROFILES).astype(np.int64)
    dz.publish_pose(seq, "base", t_ns, f2b, f2b @ SENSOR2FLANGE)


@pytest.fixture(scope="module")
def endpoint() -> Iterator[str]:
    with loopback_publisher(PREFIX, _publish) as (ep, _):
        yield ep


def _record(endpoint: str, out: str, cwd: Path, points: int, *more: str) -> None:
    args = ["record", "--prefix", PREFIX, "--connect", endpoint, "-o", out, "-n", str(points)]
    args += more
    res = subprocess.run(
        [sys.executable, "-m", "wristscan.daemon.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 0, res.stderr
    assert os.listdir(cwd) == [out]


def test_record_mcap_plays_back_the_published_batches(endpoint: str, tmp_path: Path) -> None:
    _record(endpoint, "rec.mcap", tmp_path, 6 * B)
    seqs = []
    with open(tmp_path / "rec.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, msg in reader.iter_decoded_messages(topics=["/wristscan/cloud"]):
            assert channel.topic == "/wristscan/cloud"
            raw = np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.width, msg.point_step)
            pts = raw.copy().view("<f4")
            seq = round(float(pts[0, 0]) / 1e-3)
            np.testing.assert_array_equal(pts[:, :3], batch_xyz(seq))
            np.testing.assert_array_equal(pts[:, 3], batch_intensity(seq))
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            assert stamp == message.log_time == T0 + seq * DT_NS
            assert msg.header.frame_id == "base"
            seqs.append(seq)
    assert len(seqs) == 6 and seqs == sorted(seqs)
    # each batch's robot pose: the flange in the base frame and the sensor in the cloud's frame,
    # at the batch's first exposure, where the tools draw them with the clouds
    poses: dict[str, dict[int, np.ndarray]] = {}
    with open(tmp_path / "rec.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, msg in reader.iter_decoded_messages(
            topics=["/wristscan/flange_pose", "/wristscan/sensor_pose"]
        ):
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            assert stamp == message.log_time and msg.header.frame_id == "base"
            p, q = msg.pose.position, msg.pose.orientation
            m = se3.make(se3.quat_xyzw_to_matrix([q.x, q.y, q.z, q.w]), [p.x, p.y, p.z])
            poses.setdefault(channel.topic, {})[(stamp - T0) // DT_NS] = m
    # (the very first batch may have come in before the pose subscription did)
    assert sorted(poses["/wristscan/flange_pose"]) in (seqs, seqs[1:])
    assert sorted(poses["/wristscan/sensor_pose"]) == sorted(poses["/wristscan/flange_pose"])
    for seq in poses["/wristscan/flange_pose"]:
        want = batch_flange(seq)[0]
        np.testing.assert_allclose(poses["/wristscan/flange_pose"][seq], want, atol=1e-12)
        np.testing.assert_allclose(
            poses["/wristscan/sensor_pose"][seq], want @ SENSOR2FLANGE, atol=1e-12
        )


def test_record_e57_is_one_scan_of_the_published_batches(endpoint: str, tmp_path: Path) -> None:
    _record(endpoint, "rec.e57", tmp_path, 5 * B)
    e57 = pye57.E57(str(tmp_path / "rec.e57"))
    assert e57.scan_count == 1
    raw = e57.read_scan_raw(0)
    xyz = np.stack([raw[c] for c in ("cartesianX", "cartesianY", "cartesianZ")], axis=1)
    assert xyz.shape == (5 * B, 3)
    for lo in range(0, 5 * B, B):
        seq = round(float(xyz[lo, 0]) / 1e-3)
        np.testing.assert_array_equal(xyz[lo : lo + B], batch_xyz(seq))
        np.testing.assert_array_equal(raw["intensity"][lo : lo + B], batch_intensity(seq))


def test_record_ply_time_is_each_points_exposure(endpoint: str, tmp_path: Path) -> None:
    """``--time``: ``scalar_time`` is the point's profile time, from the published batch times
    and profile indices, in seconds since the first batch."""
    from wristscan.daemon.io import ply as plyio

    _record(endpoint, "rec.ply", tmp_path, 4 * B, "--time")
    got = plyio.read_ply(tmp_path / "rec.ply")
    seqs = [round(float(got["xyz"][lo, 0]) / 1e-3) for lo in range(0, 4 * B, B)]
    pidx = np.arange(B) % PROFILES
    expect = np.concatenate(
        [(s - seqs[0]) * DT_NS * 1e-9 + SPAN_NS * 1e-9 * pidx / (PROFILES - 1) for s in seqs]
    )
    np.testing.assert_allclose(got["scalar_time"], expect, rtol=0, atol=1e-12)
    comments = plyio.read_ply_header(tmp_path / "rec.ply").comments
    assert f"scalar_time seconds since t0_ns {T0 + seqs[0] * DT_NS}" in comments


def _scan_passes() -> tuple[list, list, Any]:
    """Two synthetic passes: clouds in the part frame, their recorded sweeps (flange poses and
    exposure times at 1 kHz), and an ICP result that moves the second pass."""
    from scipy.spatial.transform import Rotation

    from wristscan.calib.merge import MergeOptions, MergeResult, PassCloud, PassCorrection
    from wristscan.daemon.procedure.acquisition import Sweep
    from wristscan.daemon.scan.record import RecordedPass

    rng = np.random.default_rng(2)
    clouds, recorded, corrections = [], [], []
    for k in range(2):
        xyz = rng.normal(size=(400 + k, 3)) * 0.02
        clouds.append(PassCloud(k, f"strip {k}", xyz, xyz + np.array([0.0, 0.0, 0.1])))
        p = 50  # profiles, 1 ms apart
        f2b = np.tile(np.eye(4), (p, 1, 1))
        f2b[:, 0, 3] = np.linspace(0.3, 0.35, p) + k
        t = T0 + k * 10**9 + np.arange(p, dtype=np.int64) * 1_000_000
        sweep = Sweep(
            np.zeros(p), np.zeros(p), np.ones(p, bool), np.arange(p), f2b, t, table_angle=None
        )
        recorded.append(RecordedPass(k, f"strip {k}", "linear", sweep, None, 0.05))
        m = np.eye(4)
        if k == 1:
            m[:3, :3] = Rotation.from_rotvec([0.0, 0.0, 1e-3]).as_matrix()
            m[:3, 3] = [2e-5, -1e-5, 3e-5]
        corrections.append(PassCorrection(k, f"strip {k}", m, 0.0, 0.0, 0.0, 0.0, 0, 0, 0, 0, "ok"))
    return clouds, recorded, MergeResult(corrections, 1, MergeOptions())


def test_scan_e57_has_one_scan_per_pass_with_its_icp_pose(tmp_path: Path) -> None:
    from wristscan.daemon.io.e57_out import utc_ns_to_gps_s
    from wristscan.daemon.scan.output import write_scan_file

    clouds, recorded, merge = _scan_passes()
    path = write_scan_file(tmp_path / "part.e57", clouds, merge, recorded, "part")
    e57 = pye57.E57(str(path))
    assert e57.scan_count == 2
    for k, c in enumerate(clouds):
        head = e57.get_header(k)
        assert head["name"].value() == f"pass {k + 1}: strip {k}"
        np.testing.assert_allclose(head.rotation_matrix, merge.transform(k)[:3, :3], atol=1e-12)
        np.testing.assert_allclose(head.translation, merge.transform(k)[:3, 3], atol=1e-12)
        t = recorded[k].sweep.exposure_ns
        start = head["acquisitionStart"]["dateTimeValue"].value()
        end = head["acquisitionEnd"]["dateTimeValue"].value()
        assert (start, end) == pytest.approx(
            (utc_ns_to_gps_s(int(t[0])), utc_ns_to_gps_s(int(t[-1]))), abs=1e-6
        )
        world = e57.read_scan(k, transform=True, ignore_missing_fields=True)
        moved = c.xyz.astype(np.float32).astype(np.float64) @ merge.transform(k)[:3, :3].T
        moved += merge.transform(k)[:3, 3]
        np.testing.assert_allclose(world["cartesianY"], moved[:, 1], atol=1e-12)


def test_scan_mcap_has_a_cloud_per_pass_and_the_flange_trail(tmp_path: Path) -> None:
    """One cloud per pass; the flange every 10 ms in the base frame; the sensor (flange @
    sensor2flange, moved by the pass's ICP correction) in the frame of the clouds."""
    from scipy.spatial.transform import Rotation

    from wristscan.calib.merge import corrected_clouds
    from wristscan.daemon.scan.job import ScanCalibration
    from wristscan.daemon.scan.output import write_scan_file

    clouds, recorded, merge = _scan_passes()
    s2f = np.eye(4)
    s2f[:3, :3] = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    s2f[:3, 3] = [0.01, 0.02, 0.15]
    cal = ScanCalibration(s2f)
    path = write_scan_file(tmp_path / "part.mcap", clouds, merge, recorded, "base", cal)
    got: dict[str, list] = {
        "/wristscan/cloud": [],
        "/wristscan/flange_pose": [],
        "/wristscan/sensor_pose": [],
    }
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, _, msg in reader.iter_decoded_messages():
            got[channel.topic].append(msg)
    fixed = corrected_clouds(clouds, merge)
    assert len(got["/wristscan/cloud"]) == 2
    for c, r, msg in zip(fixed, recorded, got["/wristscan/cloud"], strict=True):
        pts = np.frombuffer(bytes(msg.data), "<f4").reshape(-1, 3)
        np.testing.assert_array_equal(pts, c.xyz.astype(np.float32))
        assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == r.sweep.exposure_ns[0]
        assert msg.header.frame_id == "base"
    poses = got["/wristscan/flange_pose"]
    # 50 profiles 1 ms apart per pass: a pose every 10 ms is 5 per pass
    assert len(poses) == 10
    xs = [p.pose.position.x for p in poses]
    expect = np.concatenate([r.sweep.flange2base[::10, 0, 3] for r in recorded])
    np.testing.assert_allclose(xs, expect, atol=1e-12)
    assert all(p.header.frame_id == "base" for p in poses)
    sensor = got["/wristscan/sensor_pose"]
    assert len(sensor) == 10
    for j, msg in enumerate(sensor):
        r = recorded[j // 5]
        expect = merge.transform(r.index) @ r.sweep.flange2base[(j % 5) * 10] @ s2f
        p, q = msg.pose.position, msg.pose.orientation
        np.testing.assert_allclose([p.x, p.y, p.z], expect[:3, 3], atol=1e-12)
        rot = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
        np.testing.assert_allclose(rot, expect[:3, :3], atol=1e-12)
        assert msg.header.frame_id == "base"
        assert (
            msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            == (r.sweep.exposure_ns[(j % 5) * 10])
        )


def test_scan_out_names_the_file_and_its_folder(capsys: pytest.CaptureFixture[str]) -> None:
    import typer

    from wristscan.daemon.cli.scan import _split_out

    assert _split_out(Path("a/part.e57")) == (Path("a/part"), Path("a/part.e57"))
    assert _split_out(Path("a/part.MCAP")) == (Path("a/part"), Path("a/part.MCAP"))
    assert _split_out(Path("run-1.2")) == (Path("run-1.2"), None)
    with pytest.raises(typer.Exit):
        _split_out(Path("part.npz"))
    assert "use one of .mcap, .e57 (or a folder name) (nothing moved)" in capsys.readouterr().err


def test_scan_pass_files_carry_their_pass_number(tmp_path: Path) -> None:
    from wristscan.calib.merge import MergeOptions
    from wristscan.daemon.io.ply import read_ply, read_ply_header
    from wristscan.daemon.scan.output import write_outputs

    clouds, _, _ = _scan_passes()
    write_outputs(tmp_path, clouds, None, MergeOptions(voxel_m=0.0), {"frame": "part"})
    for k in (1, 2):
        got = read_ply(tmp_path / f"pass_{k:02d}.ply")
        assert got["xyz"].shape[0] == clouds[k - 1].n_points
        np.testing.assert_array_equal(got["scalar_pass"], k)
        vertex = read_ply_header(tmp_path / f"pass_{k:02d}.ply").element("vertex")
        assert vertex is not None and ("scalar_pass", "u2") in vertex.properties
    assert "scalar_pass" not in read_ply(tmp_path / "merged.ply")
