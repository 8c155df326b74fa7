"""Interpolating buffers: exact on linear truth, never beyond the samples, bounded memory."""

from __future__ import annotations

import math

import numpy as np
import pytest

from wristscan.calib import kinematics, se3
from wristscan.daemon.sync.buffers import Reason, RobotStateBuffer, SampleBuffer, ScalarBuffer

MS = 1_000_000
Q0 = np.array([0.3, -1.2, 1.4, -1.8, -1.57, 0.2])
W = np.array([0.2, -0.1, 0.15, 0.3, -0.25, 0.5])  # rad/s


def q_at(t_ns: np.ndarray) -> np.ndarray:
    return Q0 + np.asarray(t_ns, dtype=np.float64)[..., None] * 1e-9 * W


def test_linear_interpolation_and_reasons() -> None:
    buf = SampleBuffer(width=2, capacity=64, max_gap_ns=5 * MS)
    for k in range(10):
        t = k * 2 * MS
        buf.append(t, (t * 1e-9, -3.0 * t * 1e-9))
    t = np.array([0, 3 * MS, 18 * MS, -1, 18 * MS + 1, 7 * MS + 500_000])
    v, reason = buf.interpolate(t)
    assert reason.tolist() == [
        Reason.OK,
        Reason.OK,
        Reason.OK,
        Reason.BEFORE_BUFFER,
        Reason.NOT_YET,
        Reason.OK,
    ]
    ok = reason == Reason.OK
    np.testing.assert_allclose(v[ok, 0], t[ok] * 1e-9, atol=1e-15)
    np.testing.assert_allclose(v[ok, 1], -3e-9 * t[ok], atol=1e-15)
    assert np.all(np.isnan(v[~ok]))


def test_gap_is_never_bridged() -> None:
    buf = SampleBuffer(width=1, capacity=64, max_gap_ns=5 * MS)
    for t in (0, 2 * MS, 4 * MS, 20 * MS, 22 * MS):
        buf.append(t, (float(t),))
    _, reason = buf.interpolate(np.array([3 * MS, 4 * MS + 1, 10 * MS, 19 * MS, 21 * MS]))
    assert reason.tolist() == [Reason.OK, Reason.GAP, Reason.GAP, Reason.GAP, Reason.OK]


def test_single_sample_and_empty() -> None:
    buf = SampleBuffer(width=1)
    _, reason = buf.interpolate(np.array([5]))
    assert reason.tolist() == [Reason.NOT_YET]
    buf.append(10, (1.0,))
    _, reason = buf.interpolate(np.array([5, 10, 15]))
    assert reason.tolist() == [Reason.BEFORE_BUFFER, Reason.NOT_YET, Reason.NOT_YET]


def test_non_increasing_times_are_rejected() -> None:
    buf = SampleBuffer(width=1)
    assert buf.append(10, (1.0,))
    assert not buf.append(10, (2.0,))
    assert not buf.append(5, (2.0,))
    assert len(buf) == 1 and buf.n_rejected == 2


def test_bounded_memory_keeps_newest() -> None:
    buf = SampleBuffer(width=3, capacity=100, max_gap_ns=10)
    storage = (buf._t.shape, buf._v.shape)
    for k in range(1000):
        buf.append(k, (k, 2 * k, 3 * k))
        assert len(buf) <= 100
    assert (buf._t.shape, buf._v.shape) == storage
    assert buf.first_ns == 900 and buf.last_ns == 999
    np.testing.assert_array_equal(buf.values[:, 1], 2 * np.arange(900, 1000))
    v, reason = buf.interpolate(np.array([899, 950]))
    assert reason.tolist() == [Reason.BEFORE_BUFFER, Reason.OK]
    assert v[1, 2] == 3 * 950


def test_joint_mode_matches_forward_kinematics() -> None:
    buf = RobotStateBuffer("UR5e", mode="joint", max_gap_ns=3 * MS)
    times = np.arange(0, 200 * MS, 2 * MS)
    for t in times:
        buf.append(int(t), q_at(t), np.zeros(6))
    t = np.sort(np.random.default_rng(0).integers(0, 198 * MS, 500))
    F, ok, reason = buf.interpolate(t)
    assert np.all(ok) and np.all(reason == Reason.OK)
    np.testing.assert_allclose(F, kinematics.forward("UR5e", q_at(t)), atol=1e-12)
    F, ok, reason = buf.interpolate(np.array([199 * MS, -1]))
    assert not np.any(ok) and np.all(np.isnan(F))
    assert reason.tolist() == [Reason.NOT_YET, Reason.BEFORE_BUFFER]


def test_tcp_mode_interpolates_on_se3_and_removes_tcp_offset() -> None:
    tcp_offset = np.array([0.01, -0.02, 0.15, 0.1, 0.0, -0.2])
    tcp2flange = se3.pose_to_matrix(tcp_offset)
    # Truth: rotation about a fixed axis at a constant rate plus a linear drift of the frame.
    start = se3.pose_to_matrix([0.4, -0.1, 0.3, 2.9, -0.5, 0.1])
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])

    def flange2base(t_ns: np.ndarray) -> np.ndarray:
        s = np.asarray(t_ns, dtype=np.float64) * 1e-9
        R = se3.rotvec_to_matrix(np.outer(s * 0.8, axis))
        trans = np.outer(s, [0.25, 0.05, -0.1])
        return se3.make(R, trans) @ start

    buf = RobotStateBuffer("UR5e", mode="tcp", tcp_offset=tcp_offset)
    times = np.arange(0, 100 * MS, 2 * MS)
    tcp2base = flange2base(times) @ tcp2flange
    for t, T in zip(times, tcp2base, strict=True):
        buf.append(int(t), np.zeros(6), se3.matrix_to_pose(T))
    t = np.array([1 * MS, 37 * MS + 123_456, 98 * MS])
    F, ok, _ = buf.interpolate(t)
    assert np.all(ok)
    # Only the rotation of the TCP frame interpolates exactly; its origin moves along the
    # screw, so allow the chord error of 2 ms of motion (sub-micrometre).
    np.testing.assert_allclose(F[:, :3, :3], flange2base(t)[:, :3, :3], atol=1e-9)
    np.testing.assert_allclose(F[:, :3, 3], flange2base(t)[:, :3, 3], atol=1e-6)


def test_scalar_buffer_unwraps_periodic_angle() -> None:
    buf = ScalarBuffer(max_gap_ns=50 * MS, period=2 * math.pi)
    angles = (6.0 + 0.1 * np.arange(10)) % (2 * math.pi)  # crosses 2 pi between samples 2 and 3
    for k, a in enumerate(angles):
        buf.append(k * 10 * MS, float(a))
    v, ok, _ = buf.interpolate(np.array([25 * MS]))
    assert ok[0]
    assert math.isclose(float(v[0]) % (2 * math.pi), (6.25) % (2 * math.pi), abs_tol=1e-12)


def test_bad_mode_rejected() -> None:
    with pytest.raises(ValueError, match="mode"):
        RobotStateBuffer(mode="cartesian")
