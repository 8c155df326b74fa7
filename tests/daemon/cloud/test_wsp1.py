"""The WSP1 robot-pose payload (``<prefix>/pose``): its documented layout byte for byte, the
round trip, malformed input, and its trip over a real zenoh session beside WSC1."""

from __future__ import annotations

import struct
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support import free_tcp_port, own_loopback_host

from wristscan.calib import se3
from wristscan.daemon.cloud import wsp1
from wristscan.daemon.cloud.client import CloudClient
from wristscan.daemon.cloud.poses import PoseSubscriber
from wristscan.daemon.cloud.zenoh_io import DaemonZenoh, open_session


def _poses(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    f2b = (
        np.stack(
            [
                se3.make(se3.rotvec_to_matrix(rng.normal(size=3)), rng.normal(size=3))
                for _ in range(n)
            ]
        )
        if n
        else np.zeros((0, 4, 4))
    )
    s2f = se3.make(se3.rot_x(0.4), np.array([0.01, 0.0, 0.1]))
    return f2b, f2b @ s2f


def test_layout_is_the_documented_one() -> None:
    f2b, s2p = _poses(2)
    payload = wsp1.encode(9, "part", np.array([100, 200]), f2b, s2p)
    assert len(payload) == 48 + 2 * (8 + 96 + 96)
    assert payload[:4] == b"WSP1"
    assert struct.unpack_from("<HHQII", payload, 4) == (1, 0, 9, 2, 0)
    assert payload[24:40] == b"part" + bytes(12) and payload[40:48] == bytes(8)
    assert struct.unpack_from("<qq", payload, 48) == (100, 200)
    rows = np.frombuffer(payload, "<f8", 48, 64).reshape(2, 2, 3, 4)
    np.testing.assert_array_equal(rows[0], f2b[:, :3, :])
    np.testing.assert_array_equal(rows[1], s2p[:, :3, :])
    back = wsp1.decode(payload)
    assert (back.seq, back.frame_id, back.n_poses) == (9, "part", 2)
    assert back.t_ns.tolist() == [100, 200]
    np.testing.assert_array_equal(back.flange2base, f2b)
    np.testing.assert_array_equal(back.sensor2frame, s2p)


def test_empty_batch_and_bad_arguments() -> None:
    empty = wsp1.decode(wsp1.encode(0, "base", np.zeros(0, np.int64), *_poses(0)))
    assert empty.n_poses == 0 and empty.flange2base.shape == (0, 4, 4)
    with pytest.raises(ValueError, match=r"\(2, 4, 4\)"):
        wsp1.encode(0, "base", np.zeros(2, np.int64), np.zeros((3, 4, 4)), np.zeros((2, 4, 4)))
    with pytest.raises(ValueError, match="longer than 16"):
        wsp1.encode(0, "x" * 17, np.zeros(1, np.int64), *_poses(1))


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300), st.integers(0, 500), st.binary(min_size=1, max_size=4))
def test_decode_never_raises_anything_but_wsp1error(junk: bytes, pos: int, patch: bytes) -> None:
    good = wsp1.encode(3, "base", np.array([1, 2]), *_poses(2))
    for candidate in (junk, good[: pos % len(good)], good[:pos] + patch + good[pos + len(patch) :]):
        try:
            b = wsp1.decode(candidate)
        except wsp1.Wsp1Error:
            continue
        assert b.flange2base.shape == b.sensor2frame.shape == (b.n_poses, 4, 4)
        assert np.isfinite(b.flange2base).all() and np.isfinite(b.sensor2frame).all()


def test_poses_follow_their_cloud_over_zenoh() -> None:
    host = own_loopback_host()
    endpoint = f"tcp/{host}:{free_tcp_port(host)}"
    daemon = open_session(listen=[endpoint])
    face = DaemonZenoh(daemon, "wristscan/posetest")
    try:
        with CloudClient("wristscan/posetest", connect=[endpoint], capacity=64) as client:
            poses = PoseSubscriber(client.session, client.prefix, capacity=4)
            f2b, s2p = _poses(3, seed=5)
            deadline = time.monotonic() + 30
            got: list[wsp1.PoseBatch] = []
            while len(got) < 6 and time.monotonic() < deadline:
                seq = face.publish_cloud(np.zeros((1, 3)), 10, 12, 3, "base")
                face.publish_pose(seq, "base", np.array([10, 11, 12]), f2b, s2p)
                time.sleep(0.02)
                got += poses.drain()
            assert len(got) >= 6, "poses never arrived"
            seqs = [g.seq for g in got]
            assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
            np.testing.assert_array_equal(got[-1].flange2base, f2b)
            np.testing.assert_array_equal(got[-1].sensor2frame, s2p)
            # the ring is bounded: a consumer that never drains loses the oldest, counted
            for k in range(10):
                face.publish_pose(1000 + k, "base", np.array([1]), *_poses(1))
            while poses.received < len(got) + 10 and time.monotonic() < deadline:
                time.sleep(0.02)
            tail = poses.drain()
            assert len(tail) == 4 and poses.dropped >= 6 and tail[-1].seq == 1009
            poses.close()
    finally:
        face.close()
        daemon.close()
