"""WSC1 codec and the daemon's zenoh face, over real zenoh sessions on loopback (an address of
the run's own: two test runs on one machine never meet). Waits are for events, with generous
timeouts; nothing asserts how fast a loaded machine delivers."""

from __future__ import annotations

import struct
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from wristscan.daemon.cloud import wsc1
from wristscan.daemon.cloud.client import CloudClient
from wristscan.daemon.cloud.zenoh_io import DaemonZenoh, open_session


def test_header_layout_matches_design() -> None:
    xyz = np.arange(6, dtype=np.float32).reshape(2, 3)
    payload = wsc1.encode(
        xyz,
        seq=7,
        t_first_ns=11,
        t_last_ns=12,
        n_profiles=1,
        frame_id="part",
        intensity=np.array([3, 4], np.uint8),
        profile_index=np.array([0, 0]),
    )
    assert len(payload) == 64 + 24 + 2 + 8
    assert payload[:4] == b"WSC1"
    assert struct.unpack_from("<HHQqqII", payload, 4) == (1, 3, 7, 11, 12, 2, 1)
    assert payload[40:56] == b"part" + bytes(12)
    assert payload[56:64] == bytes(8)
    np.testing.assert_array_equal(np.frombuffer(payload, "<f4", 6, 64).reshape(2, 3), xyz)
    assert payload[88:90] == b"\x03\x04"
    cloud = wsc1.decode(payload)
    assert (cloud.seq, cloud.frame_id, cloud.n_points, cloud.n_profiles) == (7, "part", 2, 1)
    assert cloud.intensity is not None and cloud.intensity.tolist() == [3, 4]


def test_minimal_payload_without_blocks() -> None:
    cloud = wsc1.decode(
        wsc1.encode(np.zeros((0, 3)), seq=0, t_first_ns=0, t_last_ns=0, n_profiles=0)
    )
    assert cloud.n_points == 0 and cloud.intensity is None and cloud.profile_index is None


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200), st.integers(0, 150), st.binary(min_size=1, max_size=4))
def test_decode_never_raises_anything_but_wsc1error(junk: bytes, pos: int, patch: bytes) -> None:
    good = wsc1.encode(
        np.ones((3, 3)),
        seq=1,
        t_first_ns=1,
        t_last_ns=2,
        n_profiles=1,
        profile_index=np.zeros(3, np.uint32),
    )
    for candidate in (junk, good[: pos % len(good)], good[:pos] + patch + good[pos + len(patch) :]):
        try:
            cloud = wsc1.decode(candidate)
        except wsc1.Wsc1Error:
            continue
        assert cloud.xyz.shape == (cloud.n_points, 3)


def test_encode_rejects_bad_shapes() -> None:
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        wsc1.encode(np.zeros((4, 2)), seq=0, t_first_ns=0, t_last_ns=0, n_profiles=0)
    with pytest.raises(ValueError, match="longer than 16"):
        wsc1.encode(
            np.zeros((1, 3)), seq=0, t_first_ns=0, t_last_ns=0, n_profiles=1, frame_id="x" * 17
        )


def test_publish_subscribe_query_and_liveliness(endpoint: str) -> None:
    daemon_session = open_session(listen=[endpoint])
    try:
        daemon = DaemonZenoh(
            daemon_session,
            "wristscan/test",
            calibration=lambda: {"kind": "sensor2flange"},
            stats=lambda: {"received": 5},
        )
        with CloudClient("wristscan/test", connect=[endpoint], capacity=4) as client:
            deadline = time.monotonic() + 30
            while not client.alive(timeout=0.5):
                assert time.monotonic() < deadline, "daemon liveliness never seen"
            assert client.query("stats") == {"received": 5}
            assert client.query("calibration")["kind"] == "sensor2flange"
            xyz = np.random.default_rng(0).normal(size=(1000, 3)).astype(np.float32)
            got = None
            deadline = time.monotonic() + 30
            while got is None and time.monotonic() < deadline:
                daemon.publish_cloud(xyz, 1, 2, 10, "base")
                got = client.recv(timeout=0.2)
            assert got is not None
            np.testing.assert_array_equal(got.xyz, xyz)
            # A consumer that does not keep up loses the oldest batches, memory stays bounded.
            # zenoh may itself drop some of a burst (congestion control DROP), the more on a
            # loaded machine: bursts of 20 until over 5 arrived (nothing read meanwhile).
            before = client.received
            deadline = time.monotonic() + 30
            while client.received - before < 6:
                assert time.monotonic() < deadline, f"{client.received - before} arrived"
                for _ in range(20):
                    daemon.publish_cloud(xyz, 1, 2, 10, "base")
                settle_until = time.monotonic() + 1.0
                while client.received - before < 6 and time.monotonic() < settle_until:
                    time.sleep(0.05)
            # Of what arrived, the ring kept at most its 4 slots and counted the rest as dropped.
            arrived = client.received - before
            assert client.dropped >= arrived - 4 - 1
            # Drained: in order, ending with the newest batch published (the burst's own tail
            # may be one zenoh dropped, so a newest one is published whenever nothing is left),
            # and at most the ring's 4 slots plus what arrived while draining (on a loaded
            # machine the burst's last batches can still be arriving).
            received0 = client.received
            seqs: list[int] = []
            deadline = time.monotonic() + 30
            while not seqs or seqs[-1] != daemon.seq - 1:
                assert time.monotonic() < deadline, "no batch arrives any more"
                if (c := client.recv(timeout=0.5)) is not None:
                    seqs.append(c.seq)
                else:
                    daemon.publish_cloud(xyz, 1, 2, 10, "base")
            assert seqs == sorted(seqs)
            assert len(seqs) <= 4 + (client.received - received0)
        daemon.close()
        daemon.close()
    finally:
        daemon_session.close()


def test_query_without_daemon_times_out(endpoint: str) -> None:
    with CloudClient("wristscan/nobody", listen=[endpoint]) as client:
        with pytest.raises(TimeoutError, match="no wristscan daemon"):
            client.query("stats", timeout=0.3)
        assert client.recv(timeout=0.05) is None
