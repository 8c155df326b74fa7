"""wsc1.Wsc1Frame: the WSC1 payload written in place by the hot path (points aligned straight
into it), byte-identical to ``encode``, published through ``DaemonZenoh`` and the ROS 2 tee over
real zenoh sessions on loopback, the PointCloud2 read back with rosbags."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore
from support import publish_until

from wristscan.calib import align, se3
from wristscan.daemon.cloud import ros2msg, wsc1
from wristscan.daemon.cloud.ros2pub import Ros2Publisher
from wristscan.daemon.cloud.zenoh_io import DaemonZenoh, open_session
from wristscan.daemon.config.ros2 import Ros2Config

GOLDEN = bytes.fromhex(
    "57534331010003000201000000000000fbffffffffffffff15cd853dfe9c9717020000000200000074616"
    "26c65000000000000000000000000000000000000000000003f000080be0000803f6f12833a0000004000"
    "0060c007ff0000000001000000"
)
"""Two points with intensity and profile index, as the encoder before Wsc1Frame wrote them
(seq 258, t_first -5, t_last 1.7e18 + 123456789, 2 profiles, frame "table")."""


def test_golden_message() -> None:
    xyz = np.array([[0.5, -0.25, 1.0], [1e-3, 2.0, -3.5]])
    kw: dict[str, Any] = dict(
        seq=258, t_first_ns=-5, t_last_ns=1_700_000_000_123_456_789, n_profiles=2
    )
    assert GOLDEN[:4] == b"WSC1" and len(GOLDEN) == 64 + 24 + 2 + 8
    inten, pidx = np.array([7, 255], np.uint8), np.array([0, 1])
    assert wsc1.encode(xyz, frame_id="table", intensity=inten, profile_index=pidx, **kw) == GOLDEN
    frame = wsc1.Wsc1Frame(2, intensity=True, profile_index=True)
    frame.xyz[...] = xyz
    assert frame.intensity is not None and frame.profile_index is not None
    frame.intensity[...] = inten
    frame.profile_index[...] = pidx
    payload = frame.finish(frame_id="table", **kw)
    assert payload is frame.buffer and payload == GOLDEN
    cloud = wsc1.decode(payload)
    assert (cloud.seq, cloud.t_first_ns, cloud.frame_id, cloud.n_profiles) == (258, -5, "table", 2)


@pytest.mark.parametrize("blocks", [(False, False), (True, False), (False, True), (True, True)])
def test_frame_is_byte_identical_to_encode(blocks: tuple[bool, bool]) -> None:
    rng = np.random.default_rng(4)
    n = 3001
    xyz = rng.normal(size=(n, 3))
    inten = rng.integers(0, 256, n).astype(np.uint8) if blocks[0] else None
    pidx = np.sort(rng.integers(0, 40, n)) if blocks[1] else None
    want = wsc1.encode(
        xyz, seq=9, t_first_ns=1, t_last_ns=2, n_profiles=40, intensity=inten, profile_index=pidx
    )
    frame = wsc1.Wsc1Frame(n, intensity=blocks[0], profile_index=blocks[1])
    assert frame.xyz.flags.writeable and frame.xyz.flags.c_contiguous
    assert frame.xyz.shape == (n, 3) and frame.xyz.dtype == np.float32
    frame.xyz[...] = xyz
    if inten is not None:
        assert frame.intensity is not None
        frame.intensity[...] = inten
    else:
        assert frame.intensity is None
    if pidx is not None:
        assert frame.profile_index is not None
        frame.profile_index[...] = pidx
    # finish may be called again (a new seq): only the header changes
    frame.finish(seq=1, t_first_ns=0, t_last_ns=0, n_profiles=1, frame_id="part")
    assert frame.finish(seq=9, t_first_ns=1, t_last_ns=2, n_profiles=40) == want
    assert (
        wsc1.frame_of(xyz, inten, pidx).finish(seq=9, t_first_ns=1, t_last_ns=2, n_profiles=40)
        == want
    )
    back = wsc1.decode(bytes(frame.buffer))
    np.testing.assert_array_equal(back.xyz, xyz.astype(np.float32))


def test_frame_refuses_bad_arguments() -> None:
    with pytest.raises(ValueError, match="n_points must be >= 0"):
        wsc1.Wsc1Frame(-1)
    with pytest.raises(ValueError, match="longer than 16"):
        wsc1.Wsc1Frame(1).finish(seq=0, t_first_ns=0, t_last_ns=0, n_profiles=1, frame_id="x" * 17)
    with pytest.raises(ValueError, match=r"intensity must be \(2,\)"):
        wsc1.frame_of(np.zeros((2, 3)), np.zeros(3, np.uint8))
    empty = wsc1.Wsc1Frame(0, intensity=True).finish(seq=0, t_first_ns=0, t_last_ns=0, n_profiles=0)
    assert wsc1.decode(empty).n_points == 0


def _aligned_frame(
    rng: np.random.Generator,
) -> tuple[wsc1.Wsc1Frame, np.ndarray, np.ndarray, np.ndarray]:
    """A tick's profiles (30 % invalid) aligned into a frame with its intensities and profile
    indices, as the pipeline builds it; also the points, intensities and indices on their own."""
    p, n = 6, 300
    poses = se3.make(se3.rotvec_to_matrix(rng.normal(size=(p, 3))), rng.normal(size=(p, 3)))
    y = np.linspace(-0.02, 0.02, n)
    z = rng.uniform(0.1, 0.2, (p, n))
    valid = rng.uniform(size=(p, n)) > 0.3
    inten = rng.integers(0, 256, (p, n)).astype(np.uint8)
    counts = valid.sum(axis=1)
    frame = wsc1.Wsc1Frame(int(counts.sum()), intensity=True, profile_index=True)
    assert frame.intensity is not None and frame.profile_index is not None
    align.align_rows(y, z, valid, poses, out=frame.xyz)
    np.compress(valid.ravel(), inten.ravel(), out=frame.intensity)
    frame.profile_index[...] = np.repeat(np.arange(p), counts)
    pidx = np.nonzero(valid)[0]
    return frame, align.align_rows(y, z, valid, poses), inten[valid], pidx


def test_frame_through_zenoh_and_the_ros2_tee(endpoint: str) -> None:
    daemon_session = open_session(listen=[endpoint])
    peer = open_session(connect=[endpoint])
    try:
        face = DaemonZenoh(daemon_session, "wristscan/f")
        ros = Ros2Publisher(daemon_session, Ros2Config(enabled=True, domain_id=3), "f")
        wsc: list[zenoh.Sample] = []
        pc2: list[zenoh.Sample] = []
        subs = [
            peer.declare_subscriber("wristscan/f/cloud", wsc.append),
            peer.declare_subscriber(ros.key_for(ros2msg.POINTCLOUD2, ros.topic), pc2.append),
        ]
        frame, xyz, inten, pidx = _aligned_frame(np.random.default_rng(8))
        with pytest.raises(ValueError, match="intensity and profile_index are its own"):
            face.publish_cloud(frame, 1, 2, 6, "base", inten, None)
        publish = ros.tee(face.publish_cloud)
        t0 = 1_700_000_000_000_000_007

        publish_until(
            lambda: publish(frame, t0, t0 + 5_000_000, 6, "base", None, None),
            lambda: bool(wsc and pc2),
            "the frame never arrived as WSC1 and PointCloud2",
        )
        payload = wsc[-1].payload.to_bytes()
        cloud = wsc1.decode(payload)
        assert (cloud.t_first_ns, cloud.n_profiles, cloud.frame_id) == (t0, 6, "base")
        # what the old path (arrays through encode) would have sent, byte for byte
        assert payload == wsc1.encode(
            xyz,
            seq=cloud.seq,
            t_first_ns=t0,
            t_last_ns=t0 + 5_000_000,
            n_profiles=6,
            intensity=inten,
            profile_index=pidx,
        )
        seqs = [wsc1.decode(s.payload.to_bytes()).seq for s in wsc]
        assert seqs == sorted(set(seqs))  # one frame, its header written again for each put
        msg = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(
            pc2[-1].payload.to_bytes(), ros2msg.POINTCLOUD2
        )
        assert (msg.width, msg.point_step) == (xyz.shape[0], 16)
        table = np.frombuffer(bytes(msg.data), "<f4").reshape(-1, 4)
        np.testing.assert_array_equal(table[:, :3], xyz)
        np.testing.assert_array_equal(table[:, 3], inten.astype(np.float32))
        assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_000, 7)
        for s in subs:
            s.undeclare()
        ros.close()
        face.close()
    finally:
        peer.close()
        daemon_session.close()


@pytest.mark.parametrize("invalid", ["none", "scattered", "runs"])
def test_aligned_frame_holds_the_valid_points_with_their_blocks(invalid: str) -> None:
    rng = np.random.default_rng(12)
    p, n = 5, 400
    poses = se3.make(se3.rotvec_to_matrix(rng.normal(size=(p, 3))), rng.normal(size=(p, 3)))
    y = np.linspace(-0.02, 0.02, n)
    z = rng.uniform(0.1, 0.2, (p, n))
    valid = rng.uniform(size=(p, n)) >= (0.3 if invalid == "scattered" else 0.0)
    if invalid == "runs":  # the edges out of range, an occlusion
        valid[:, :40] = valid[:, 350:] = valid[:, 200:230] = False
    inten = rng.integers(0, 256, (p, n)).astype(np.uint8)
    frame = wsc1.aligned_frame(y, z, valid, poses, intensity=inten, profile_index=True)
    cloud = wsc1.decode(frame.finish(seq=3, t_first_ns=1, t_last_ns=2, n_profiles=p))
    rows, cols = np.nonzero(valid)
    want = align.align_with_poses(y[cols], z[rows, cols], rows, poses)
    np.testing.assert_allclose(cloud.xyz, want, rtol=0, atol=1e-6)
    assert cloud.intensity is not None and cloud.profile_index is not None
    np.testing.assert_array_equal(cloud.intensity, inten[rows, cols])
    np.testing.assert_array_equal(cloud.profile_index, rows)
    bare = wsc1.aligned_frame(y, z, valid, poses)
    assert bare.intensity is None and bare.profile_index is None
    np.testing.assert_array_equal(bare.xyz, cloud.xyz)
    with pytest.raises(ValueError, match=r"intensity must be \(5, 400\)"):
        wsc1.aligned_frame(y, z, valid, poses, intensity=inten[:, :10])
    with pytest.raises(ValueError, match=r"must be \(P, N\) alike"):
        wsc1.aligned_frame(y, z, valid[:, :10], poses)


def test_a_frame_reuses_a_free_payload_and_never_one_in_use() -> None:
    first = wsc1.Wsc1Frame(1000)
    first.xyz[...] = 1.0
    buf = first.finish(seq=1, t_first_ns=0, t_last_ns=0, n_profiles=1)
    kept = bytes(buf)
    # While the first frame's views are alive its buffer cannot change size: a new one is made.
    second = wsc1.Wsc1Frame(900, reuse=buf)
    assert second.buffer is not buf and bytes(buf) == kept
    del first, second
    # Free now: written over in place, at the new size, and a valid message once finished.
    third = wsc1.Wsc1Frame(900, reuse=buf)
    assert third.buffer is buf and len(buf) == 64 + 12 * 900
    third.xyz[...] = 2.0
    cloud = wsc1.decode(third.finish(seq=2, t_first_ns=5, t_last_ns=6, n_profiles=3))
    assert cloud.seq == 2 and cloud.n_points == 900 and np.all(cloud.xyz == 2.0)
    del third, cloud
    fourth = wsc1.Wsc1Frame(1200, reuse=buf, intensity=True)  # grows
    assert fourth.buffer is buf and len(buf) == 64 + 13 * 1200
