"""Cloud batches through zenoh's shared memory (``[zenoh] shared_memory``): real zenoh sessions
on loopback, a subscriber on this host with shared memory (the batch arrives by reference) and
one without (zenoh copies it out), and a pool that fills up (the batch goes as plain bytes)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import zenoh
from support import free_tcp_port, own_loopback_host

from wristscan.daemon.cloud import ros2msg, wsc1
from wristscan.daemon.cloud.ros2pub import Ros2Publisher
from wristscan.daemon.cloud.zenoh_io import DaemonZenoh, open_session
from wristscan.daemon.config.ros2 import Ros2Config

PREFIX = "wristscan/shmtest"
POINTS = 20_000
"""240 kB batches: zenoh would cut each into four network batches."""


@pytest.fixture(scope="module")
def endpoint() -> str:
    host = own_loopback_host()
    return f"tcp/{host}:{free_tcp_port(host)}"


@pytest.fixture(scope="module")
def daemon_session(endpoint: str) -> Iterator[zenoh.Session]:
    session = open_session(listen=[endpoint], shared_memory=True)
    yield session
    session.close()


class Recorder:
    """A subscriber that keeps every sample (so a shared buffer stays in use until
    :meth:`release`)."""

    def __init__(self, endpoint: str, shared_memory: bool) -> None:
        self.session = open_session(connect=[endpoint], shared_memory=shared_memory)
        self.samples: list[zenoh.Sample] = []
        self.sub = self.session.declare_subscriber(f"{PREFIX}/cloud", self.samples.append)

    def wait(self, n: int, timeout_s: float = 20.0) -> None:
        deadline = time.monotonic() + timeout_s
        while len(self.samples) < n and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(self.samples) == n, f"{len(self.samples)} of {n} batches received"

    def clouds(self) -> list[wsc1.Cloud]:
        return [wsc1.decode(s.payload.to_bytes()) for s in self.samples]

    def by_reference(self) -> list[bool]:
        return [s.payload.as_shm() is not None for s in self.samples]

    def release(self) -> None:
        self.samples.clear()

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def points(i: int) -> Any:
    rng = np.random.default_rng(i)
    return rng.uniform(-1.0, 1.0, (POINTS, 3)).astype(np.float32)


def publish(face: DaemonZenoh, subscriber: Recorder, n: int) -> list[Any]:
    """Publish ``n`` batches once the subscriber is matched; their points."""
    deadline = time.monotonic() + 10
    while not face._cloud.matching_status.matching and time.monotonic() < deadline:
        time.sleep(0.01)
    sent = [points(face.seq + i) for i in range(n)]
    for i, xyz in enumerate(sent):
        face.publish_cloud(xyz, 1000 + i, 2000 + i, 1, "base")
    return sent


def check_same(sent: list[Any], got: list[wsc1.Cloud]) -> None:
    assert [c.seq for c in got] == sorted(c.seq for c in got)
    for xyz, cloud in zip(sent, got, strict=True):
        np.testing.assert_array_equal(cloud.xyz, xyz)


def test_batches_reach_a_subscriber_on_this_host_by_reference(daemon_session: Any, endpoint: str):
    face = DaemonZenoh(daemon_session, PREFIX, congestion="block", shm_pool_bytes=8 << 20)
    near = Recorder(endpoint, shared_memory=True)
    plain = Recorder(endpoint, shared_memory=False)
    try:
        sent = publish(face, near, 5)
        near.wait(5)
        plain.wait(5)
        assert face.shm is not None and face.shm.counters() == {"shared": 5, "fallbacks": 0}
        assert near.by_reference() == [True] * 5
        assert plain.by_reference() == [False] * 5  # zenoh copied it out for this one
        check_same(sent, near.clouds())
        check_same(sent, plain.clouds())
    finally:
        near.close()
        plain.close()
        face.close()


def test_a_full_pool_sends_plain_bytes_and_is_reused_once_released(
    daemon_session: Any, endpoint: str
) -> None:
    """A 1 MiB pool holds four 240 kB batches: with the subscriber keeping every sample, the
    next ones go as plain bytes (counted), nothing is lost or mixed up; once the subscriber
    lets them go, batches are shared again."""
    face = DaemonZenoh(daemon_session, PREFIX, congestion="block", shm_pool_bytes=1 << 20)
    near = Recorder(endpoint, shared_memory=True)
    try:
        sent = publish(face, near, 8)
        near.wait(8)
        assert face.shm is not None
        assert face.shm.shared + face.shm.fallbacks == 8
        assert 1 <= face.shm.shared <= 4 and face.shm.fallbacks >= 4
        by_ref = near.by_reference()
        assert sum(by_ref) == face.shm.shared
        check_same(sent, near.clouds())
        near.release()
        shared = face.shm.shared
        time.sleep(0.2)  # zenoh's transport lets go of the buffers it sent
        again = publish(face, near, 2)
        near.wait(2)
        assert face.shm.shared == shared + 2
        check_same(again, near.clouds())
    finally:
        near.close()
        face.close()


def test_pointcloud2_goes_through_the_same_pool(daemon_session: Any, endpoint: str) -> None:
    """The ROS 2 publisher writes its PointCloud2 payloads into the WSC1 face's pool (the
    layout itself is checked against rosbags in test_ros2pub.py)."""
    face = DaemonZenoh(daemon_session, PREFIX, shm_pool_bytes=4 << 20)
    peer = open_session(connect=[endpoint], shared_memory=True)
    got: list[zenoh.Sample] = []
    sub = peer.declare_subscriber("shmtest/cloud2", got.append)
    try:
        cfg = Ros2Config(enabled=True, mode="bridge", topic="/shmtest/cloud2")
        ros = Ros2Publisher(daemon_session, cfg, "x", face.shm)
        xyz = points(99)
        deadline = time.monotonic() + 10
        while ros.publish_cloud(xyz, 42, 43, 1, "part") == -1 and time.monotonic() < deadline:
            time.sleep(0.01)
        while not got and time.monotonic() < deadline:
            time.sleep(0.01)
        assert got and got[0].payload.as_shm() is not None
        np.testing.assert_array_equal(ros2msg.cdr_to_cloud(got[0].payload.to_bytes()).xyz, xyz)
        assert face.shm is not None and face.shm.shared == 1
        ros.close()
    finally:
        sub.undeclare()
        peer.close()
        face.close()
