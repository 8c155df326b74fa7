"""The simulated UR controller against the real ur_rtde clients (and raw sockets for the wire).

Every test starts its own controller process on a random free 127.a.b.c address and stops it,
with every client disconnected, before it ends.

No assert depends on how fast a loaded machine runs: waits are for events (a state, a timestamp,
a position) with generous timeouts, and host times are compared only where causality orders
them (the controller sends cycle k at ``start_time_ns + k * period``, never before).
"""

from __future__ import annotations

import math
import socket
import struct
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import dashboard_client
import numpy as np
import pytest
import rtde_control
import rtde_receive

from wristscan.calib import kinematics, se3
from wristscan.drivers.sim.truth import TruthRing
from wristscan.drivers.sim.ur.controller import ControllerConfig, SimulatedController
from wristscan.drivers.sim.ur.fastkin import fast_kinematics, rotvec_of, tcp_jacobian
from wristscan.drivers.sim.ur.motion import (
    CartesianPath,
    Decel,
    JointPath,
    PathMotion,
    RepeatabilityNoise,
    Trapezoid,
)
from wristscan.drivers.ur import rtde_wire

pytestmark = pytest.mark.timeout(180)

UR5E = kinematics.get_model("UR5e")
HOME = np.array([0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0])
# A comfortable working pose (elbow up, tool down, well away from singularities).
WORK_Q = np.array([0.3, -1.9, 1.9, -1.57, -1.57, 0.2])


@contextmanager
def controller(**overrides: Any) -> Iterator[SimulatedController]:
    ring = overrides.pop("ring", None)
    with SimulatedController.on_free_loopback(ControllerConfig(**overrides), ring) as sim:
        yield sim


@contextmanager
def receiver(host: str, variables: list[str] | None = None) -> Iterator[Any]:
    r = rtde_receive.RTDEReceiveInterface(host, -1.0, variables or [])
    try:
        yield r
    finally:
        r.disconnect()


@contextmanager
def controlled(host: str) -> Iterator[Any]:
    c = rtde_control.RTDEControlInterface(host)
    try:
        yield c
    finally:
        if c.isConnected() and c.isProgramRunning():
            c.stopScript()
        c.disconnect()


def settle(r: Any, sim: SimulatedController, timeout_s: float = 30.0) -> None:
    """Wait until the receive client holds data from after everything the controller did so far
    (its getters may otherwise return a packet from a few cycles back on a loaded machine)."""
    now = sim.state()["timestamp"]
    deadline = time.monotonic() + timeout_s
    while r.getTimestamp() <= now:
        assert time.monotonic() < deadline, "receive client saw no new data"
        time.sleep(0.002)


def wait_for(predicate: Any, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.005)


class Seen:
    """Timestamps seen by polling a receive client, each with the host time it was seen at."""

    def __init__(self, r: Any, sim: SimulatedController, seconds: float) -> None:
        ts, seen_ns = [], []
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            ts.append(r.getTimestamp())
            seen_ns.append(time.monotonic_ns())
            time.sleep(0.0003)
        self.ts = np.array(ts)
        self.sent_ns = np.array([sim.host_time_ns(t) for t in ts])
        """When the controller sent each (cycle k at ``start_time_ns + k * period``)."""
        self.seen_ns = np.array(seen_ns)


def assert_cycle_grid(seen: Seen, period_s: float) -> None:
    ts = np.unique(seen.ts)
    steps = ts / period_s
    assert np.all(np.abs(steps - np.round(steps)) < 1e-6), "timestamps off the cycle grid"
    d = np.diff(ts)
    assert d.min() == pytest.approx(period_s, abs=1e-9), "no two consecutive cycles observed"
    assert np.all(np.abs(d / period_s - np.round(d / period_s)) < 1e-6)
    # The controller clock follows host time: no sample is seen before the host time it stands
    # for (a clock running fast or skipping ahead fails; exact whatever the load), nor seconds
    # after it (a clock running slow or stuck; the bound is generous enough for any load,
    # where the old 25 % rate window over 0.4 s was not).
    lag_s = (seen.seen_ns - seen.sent_ns) * 1e-9
    assert lag_s.min() >= -1e-4  # (the sleep to a cycle's due time rounds to the microsecond)
    assert lag_s.max() < 2.0


def tcp_matrix(pose: list[float]) -> np.ndarray:
    return np.asarray(se3.pose_to_matrix(np.asarray(pose)))


def pose_error(a: list[float], b: np.ndarray) -> tuple[float, float]:
    """Position (m) and rotation (rad) difference between two UR poses / a pose and a matrix."""
    Ta = tcp_matrix(a)
    Tb = b if np.shape(b) == (4, 4) else tcp_matrix(list(b))
    dp = float(np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]))
    dr = float(se3.rotation_angle(Ta[:3, :3].T @ Tb[:3, :3]))
    return dp, dr


# ------------------------------------------------------------------------------ motion maths


def test_trapezoid_and_decel_profiles() -> None:
    p = Trapezoid(1.0, 0.5, 1.0)  # cruise phase: 0.5 s up, 1.5 s flat, 0.5 s down
    assert p.duration == pytest.approx(2.5)
    assert p.at(0.25) == pytest.approx((0.03125, 0.25))
    assert p.at(1.0) == pytest.approx((0.125 + 0.25, 0.5))
    assert p.at(2.5) == (1.0, 0.0)
    taus = np.linspace(0, p.duration, 2001)
    s = np.array([p.at(t)[0] for t in taus])
    v = np.array([p.at(t)[1] for t in taus])
    assert np.all(np.diff(s) >= 0) and v.max() == pytest.approx(0.5)
    # Finite-difference speed matches the reported one (continuous profile).
    assert np.allclose(np.gradient(s, taus), v, atol=2e-3)
    tri = Trapezoid(0.01, 1.0, 1.0)  # too short to reach 1 m/s
    assert tri.v_peak == pytest.approx(0.1) and tri.duration == pytest.approx(0.2)
    d = Decel(0.2, 0.4, 2.0, s_max=1.0)
    assert d.duration == pytest.approx(0.2)
    assert d.at(1.0) == pytest.approx((0.2 + 0.04, 0.0))
    assert Decel(0.9, 1.0, 1.0, s_max=1.0).at(5.0) == (1.0, 0.0)


def test_cartesian_path_is_straight_and_exact_at_the_end() -> None:
    tcp = se3.pose_to_matrix(np.array([0.0, 0.0, 0.12, 0.0, 0.0, 0.3]))
    T0 = kinematics.forward(UR5E, WORK_Q) @ tcp
    T1 = T0 @ se3.make(se3.rot_y(0.4), [0.05, -0.12, 0.08])
    path = CartesianPath(UR5E, tcp, WORK_Q, T1)
    assert path.unit == "m" and path.length == pytest.approx(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
    s = np.linspace(0.0, path.length, 997)
    q = np.array([path.q_at(x) for x in s])
    T = kinematics.forward(UR5E, q) @ tcp
    ref = se3.interpolate(T0, T1, s / path.length)
    assert np.max(np.linalg.norm(T[:, :3, 3] - ref[:, :3, 3], axis=1)) < 1e-7  # on the line
    rot = se3.rotation_angle(np.swapaxes(T[:, :3, :3], -1, -2) @ ref[:, :3, :3])
    assert rot.max() < 1e-6  # orientation slerped
    end = kinematics.forward(UR5E, path.q_at(path.length)) @ tcp
    assert np.abs(end - T1).max() < 1e-12
    # Joint motion is smooth: no jumps between consecutive samples.
    assert np.abs(np.diff(q, axis=0)).max() < 5e-3


def test_fast_kinematics_matches_the_vectorised_kinematics() -> None:
    model = kinematics.with_deltas(
        "UR10e",
        [1e-3, -2e-3, 3e-3, 0.0, 1e-3, 2e-3],
        [1e-4, 2e-3, -1e-3, 0.0, 0.0, 3e-4],
        [1e-3, 0.0, 0.0, 2e-3, -1e-3, 5e-4],
        [1e-3, -2e-3, 0.0, 1e-3, 0.0, 2e-3],
    )
    fast = fast_kinematics(model)
    tcp = se3.pose_to_matrix(np.array([0.01, 0.02, 0.15, 0.1, 0.2, 0.3]))
    rng = np.random.default_rng(7)
    for q in rng.uniform(-2 * np.pi, 2 * np.pi, (20, 6)):
        J, T = fast.tcp_jacobian(q, tcp)
        assert np.abs(fast.forward(q) - kinematics.forward(model, q)).max() < 1e-14
        assert np.abs(T - kinematics.forward(model, q) @ tcp).max() < 1e-14
        assert np.abs(J - tcp_jacobian(model, q, tcp)).max() < 1e-14
        R = T[:3, :3]
        assert np.abs(se3.rotvec_to_matrix(np.array(rotvec_of(R))) - R).max() < 1e-14
    # The TCP Jacobian predicts the TCP velocity (finite differences).
    q, dq = WORK_Q, rng.normal(0.0, 1.0, 6)
    h = 1e-7
    _, Tp = fast.tcp_jacobian(q + h * dq, tcp)
    _, Tm = fast.tcp_jacobian(q - h * dq, tcp)
    v_fd = (Tp[:3, 3] - Tm[:3, 3]) / (2 * h)
    J, _ = fast.tcp_jacobian(q, tcp)
    assert np.abs(J[:3] @ dq - v_fd).max() < 1e-6


def test_repeatability_noise_rms_and_stillness() -> None:
    tcp = se3.identity()
    noise = RepeatabilityNoise(UR5E, tcp, sigma_m=5e-5, corr_rad=0.05, seed=3)
    rng = np.random.default_rng(4)
    walk = WORK_Q + np.cumsum(rng.normal(0.0, 0.004, (20000, 6)), axis=0) * 0.1
    dq = noise.joint_offsets(walk)
    F_rep = kinematics.forward(UR5E, walk)
    F_true = kinematics.forward(UR5E, walk + dq)
    d = np.linalg.norm(F_true[:, :3, 3] - F_rep[:, :3, 3], axis=1)
    assert float(np.sqrt(np.mean(d**2))) == pytest.approx(5e-5, rel=0.25)
    # Standing still: the true arm does not wander.
    still = noise.joint_offsets(np.repeat(walk[-1:], 50, axis=0))
    assert np.ptp(still, axis=0).max() == 0.0
    assert np.array_equal(still[0], dq[-1])
    assert not np.any(RepeatabilityNoise(UR5E, tcp, 0.0).joint_offsets(walk[:10]))


def test_path_motion_stop_decelerates_on_the_path() -> None:
    m = PathMotion(JointPath(HOME, HOME + 1.0), 1.0, 2.0)
    for _ in range(500):  # 0.5 s: still accelerating, at 1 rad/s
        q = m.step(0.001)
    m.request_stop(4.0)
    qs = [m.step(0.001) for _ in range(400)]
    assert m.finished
    travelled = qs[-1][0] - q[0]
    assert travelled == pytest.approx(1.0**2 / (2 * 4.0), abs=2e-3)  # v^2 / 2a
    assert np.allclose(qs[-1] - HOME, qs[-1][0] - HOME[0])  # still on the joint-space line


# ------------------------------------------------------------------------------ raw wire


def _recv_exact(s: socket.socket, n: int) -> bytes:
    out = b""
    while len(out) < n:
        chunk = s.recv(n - len(out))
        if not chunk:
            raise ConnectionError("closed")
        out += chunk
    return out


def _packet(s: socket.socket) -> tuple[int, bytes]:
    size, ptype = rtde_wire.HEADER.unpack(_recv_exact(s, 3))
    return ptype, _recv_exact(s, size - 3)


def _ask(s: socket.socket, ptype: int, payload: bytes = b"") -> bytes:
    s.sendall(rtde_wire.encode(ptype, payload))
    rtype, body = _packet(s)
    assert rtype == ptype
    return body


def test_rtde_wire_recipes_and_dashboard() -> None:
    with controller(primary_interface=True) as sim:
        with (
            socket.create_connection((sim.host, 30004), timeout=10) as a,
            socket.create_connection((sim.host, 30004), timeout=10) as b,
        ):
            assert _ask(a, ord("V"), struct.pack(">H", 2)) == b"\x01"
            assert struct.unpack(">IIII", _ask(a, ord("v"))) == (5, 15, 0, 0)
            bad = _ask(a, ord("O"), struct.pack(">d", 10.0) + b"timestamp,actual_q,bogus,")
            assert bad == b"\x00DOUBLE,VECTOR6D,NOT_FOUND"
            names = "timestamp,input_int_register_0,input_double_register_0,joint_mode,"
            ok = _ask(a, ord("O"), struct.pack(">d", 100.0) + names.encode())
            assert ok == b"\x01DOUBLE,INT32,DOUBLE,VECTOR6INT32"
            assert _ask(a, ord("I"), b"input_int_register_0,input_double_register_0,") == (
                b"\x01INT32,DOUBLE"
            )
            assert _ask(a, ord("I"), b"input_int_register_1,") == b"\x02INT32"
            assert _ask(b, ord("I"), b"input_int_register_0,") == b"\x00IN_USE"
            assert _ask(b, ord("I"), b"speed_slider_fraction,") == b"\x01DOUBLE"
            assert _ask(a, ord("I"), b"actual_q,") == b"\x00NOT_FOUND"  # not an input
            a.sendall(rtde_wire.encode(ord("U"), b"\x01" + struct.pack(">id", 7, 2.5)))
            assert _ask(a, ord("S")) == b"\x01"
            rec = struct.Struct(">Bdid6i")
            ts: list[float] = []
            echoed: list[tuple[int, float]] = []
            while len(ts) < 30:
                ptype, body = _packet(a)
                assert ptype == ord("U")
                rid, t, i0, d0, *modes = rec.unpack(body)
                assert rid == 1 and modes == [253] * 6
                ts.append(t)
                echoed.append((i0, d0))
            # 100 Hz requested from a 500 Hz controller: every 5th cycle.
            steps = np.diff(ts) / 0.01
            assert np.allclose(steps, np.round(steps), atol=1e-6) and np.all(np.round(steps) >= 1)
            assert np.mean(np.round(steps) == 1) > 0.5
            assert echoed[-1] == (7, 2.5)  # input registers read back as outputs
            a.sendall(rtde_wire.encode(ord("P")))
            while _packet(a)[0] == ord("U"):  # data already on its way, then the reply
                pass
        with socket.create_connection((sim.host, 29999), timeout=10) as d:
            f = d.makefile("rwb")

            def ask(line: str) -> str:
                f.write(line.encode() + b"\n")
                f.flush()
                return f.readline().decode().strip()

            assert f.readline().decode().startswith("Connected: Universal Robots Dashboard")
            assert ask("PolyscopeVersion").startswith("URSoftware 5.15.0.0")
            assert ask("get serial number") == "20235500001"
            assert ask("is in remote control") == "true"
            assert ask("robotmode") == "Robotmode: RUNNING"
            assert ask("safetystatus") == "Safetystatus: NORMAL"
            assert ask("programState") == "STOPPED <unnamed>"
            assert ask("fly to the moon").startswith("could not understand")
            assert ask("quit") == "Disconnected"
            assert f.readline() == b""
            f.close()
        with socket.create_connection((sim.host, 30001), timeout=10) as p:
            size, kind = struct.unpack(">iB", _recv_exact(p, 5))
            assert kind == 20 and size > 5  # the primary interface's version message


# ------------------------------------------------------------------------------ receive client


def test_receive_default_recipe_500hz() -> None:
    with controller() as sim, receiver(sim.host) as r:
        assert r.isConnected()
        # timestamp = seconds since the controller started, on the host's monotonic clock.
        assert_cycle_grid(Seen(r, sim, 0.8), 0.002)
        assert r.getActualQ() == pytest.approx(HOME.tolist(), abs=1e-15)
        T = kinematics.forward(UR5E, HOME)
        assert pose_error(r.getActualTCPPose(), T) < (1e-12, 1e-12)
        assert r.getRobotMode() == 7 and r.getSafetyMode() == 1
        assert r.getRuntimeState() == 1 and not r.isProtectiveStopped()
        assert r.getSafetyStatusBits() == 1 and r.getRobotStatus() == 1
        assert r.getJointMode() == [253] * 6 and r.getSpeedScaling() == 1.0


def test_receive_custom_recipes_cb3_and_eseries_side_by_side() -> None:
    variables = ["timestamp", "actual_q", "actual_TCP_pose", "safety_status_bits"]
    tcp = (0.01, -0.02, 0.15, 0.0, 0.2, 0.0)
    with (
        controller(version=(3, 15, 8, 106339), model="UR5", tcp_offset=tcp) as cb3,
        controller(initial_q=tuple(WORK_Q)) as eseries,
    ):
        assert cb3.host != eseries.host and cb3.frequency_hz == 125.0
        with receiver(cb3.host, variables) as r3, receiver(eseries.host, variables) as r5:
            assert_cycle_grid(Seen(r3, cb3, 0.8), 0.008)
            assert_cycle_grid(Seen(r5, eseries, 0.4), 0.002)
            T = kinematics.forward("UR5", HOME) @ se3.pose_to_matrix(np.array(tcp))
            assert pose_error(r3.getActualTCPPose(), T) < (1e-12, 1e-12)
            assert r5.getActualQ() == pytest.approx(WORK_Q.tolist(), abs=1e-15)
            assert r3.getSafetyStatusBits() == 1


# ------------------------------------------------------------------------------ control client


def test_control_movej_movel_reach_targets_along_their_paths() -> None:
    ring = TruthRing.create(6, capacity=1 << 14)
    try:
        with (
            controller(initial_q=tuple(WORK_Q), ring=ring.name) as sim,
            receiver(sim.host) as r,
            controlled(sim.host) as c,
        ):
            assert c.isProgramRunning()
            wait_for(lambda: r.getRuntimeState() == 2)
            assert "def rtde_control():" in sim.program_text()
            # moveJ: all joints along one straight line in joint space, leading axis trapezoid.
            q0 = np.array(r.getActualQ())
            q1 = q0 + np.array([0.25, -0.1, 0.15, 0.05, -0.2, 0.4])
            # The truth from the controller's own clock at the command: a controller running
            # late on a loaded machine starts the move at its (earlier) cycle time, not at the
            # host time the command was sent.
            t_before = sim.host_time_ns(sim.state()["timestamp"])
            assert c.moveJ(q1.tolist(), 1.0, 2.0)
            settle(r, sim)
            assert np.abs(np.array(r.getActualQ()) - q1).max() < 1e-6
            assert np.abs(np.array(r.getTargetQ()) - q1).max() < 1e-6
            grid = sim.start_time_ns + 1_000_000 * np.arange(
                (t_before - sim.start_time_ns) // 1_000_000 + 1,
                (time.monotonic_ns() - sim.start_time_ns) // 1_000_000,
            )
            qs = ring.sample(grid)
            qs = qs[~np.isnan(qs[:, 0])]
            frac = (qs - q0) / (q1 - q0)
            assert np.ptp(frac, axis=1).max() < 1e-9  # synchronised joints
            moving = (frac[:, 0] > 1e-12) & (frac[:, 0] < 1 - 1e-12)
            assert moving.sum() * 1e-3 == pytest.approx(Trapezoid(0.4, 1.0, 2.0).duration, abs=3e-3)

            # moveL: TCP on a straight line with the orientation slerped, via the UR IK.
            p0 = r.getActualTCPPose()
            T0 = tcp_matrix(p0)
            T1 = T0 @ se3.make(se3.rot_x(0.2), [0.04, 0.03, -0.06])
            p1 = se3.matrix_to_pose(T1).tolist()
            t_before = sim.host_time_ns(sim.state()["timestamp"])
            assert c.moveL(p1, 0.1, 0.5)
            settle(r, sim)
            dp, dr = pose_error(r.getActualTCPPose(), T1)
            assert dp < 1e-5 and dr < 1e-6  # within 0.01 mm
            grid = sim.start_time_ns + 1_000_000 * np.arange(
                (t_before - sim.start_time_ns) // 1_000_000 + 1,
                (time.monotonic_ns() - sim.start_time_ns) // 1_000_000,
            )
            qs = ring.sample(grid)
            qs = qs[~np.isnan(qs[:, 0])]
            T = kinematics.forward(UR5E, qs)
            L = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
            u = np.linalg.norm(T[:, :3, 3] - T0[:3, 3], axis=1) / L
            ref = se3.interpolate(T0, T1, np.clip(u, 0, 1))
            assert np.linalg.norm(T[:, :3, 3] - ref[:, :3, 3], axis=1).max() < 1e-6
            assert (
                se3.rotation_angle(np.swapaxes(T[:, :3, :3], -1, -2) @ ref[:, :3, :3]).max() < 1e-5
            )
            speed = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1) / 1e-3
            assert speed.max() == pytest.approx(0.1, abs=1e-3)  # cruise at the requested speed
            moving = (u > 1e-9) & (u < 1 - 1e-9)
            assert moving.sum() * 1e-3 == pytest.approx(Trapezoid(L, 0.1, 0.5).duration, abs=3e-3)
            # With no repeatability error the truth is the reported state.
            _, q_last = ring.latest()  # type: ignore[misc]
            assert np.abs(q_last - np.array(r.getActualQ())).max() < 1e-12
    finally:
        ring.close()
        ring.unlink()


def test_async_moves_stops_speedl_and_repeatability() -> None:
    ring = TruthRing.create(6, capacity=1 << 14)
    try:
        with (
            controller(
                initial_q=tuple(WORK_Q), ring=ring.name, repeatability_m=1e-4, noise_seed=5
            ) as sim,
            receiver(sim.host) as r,
            controlled(sim.host) as c,
        ):
            assert c.getAsyncOperationProgress() < 0  # nothing running
            p0 = r.getActualTCPPose()
            p1 = list(p0)
            p1[2] += 0.05
            assert c.moveL(p1, 0.1, 0.5, True)  # returns at once
            running = []
            while True:
                prog = c.getAsyncOperationProgress()
                running.append(prog >= 0)
                if prog < 0:
                    break
                time.sleep(0.01)
            # Returned while the 0.7 s move runs: the first poll sees it running. (Counted, not
            # timed: how many polls fit in 0.7 s depends on the machine's load.)
            assert running[0] and not running[-1]
            assert not c.getAsyncOperationProgressEx().isAsyncOperationRunning()
            settle(r, sim)
            assert pose_error(r.getActualTCPPose(), tcp_matrix(p1))[0] < 1e-5
            # The true arm is off by about the repeatability; the reported one is exact.
            T_true = kinematics.forward(UR5E, ring.latest()[1])  # type: ignore[index]
            off = pose_error(r.getActualTCPPose(), T_true)[0]
            assert 0 < off < 6e-4

            # An async moveJ interrupted by a synchronous stopJ halts short of its target.
            # Stopped once it has moved 0.05 rad (of 0.6 rad, 1.7 s), watched rather than a
            # fixed 0.3 s, which a loaded machine stretches.
            q0 = np.array(r.getActualQ())
            assert c.moveJ((q0 + 0.6).tolist(), 0.5, 1.0, True)
            wait_for(lambda: r.getActualQ()[0] - q0[0] > 0.05)
            assert c.getAsyncOperationProgress() >= 0  # still running when stopped
            c.stopJ(2.0)
            assert c.getAsyncOperationProgress() < 0
            settle(r, sim)
            q = np.array(r.getActualQ())
            assert np.abs(np.array(r.getActualQd())).max() == 0.0
            assert 0.05 < q[0] - q0[0] < 0.59  # stopped part way
            assert np.allclose(q - q0, q[0] - q0[0], atol=1e-9)  # on the joint-space line

            # speedL drives the TCP along +x; stopL brings it to rest on that line.
            p0 = r.getActualTCPPose()
            assert c.speedL([0.05, 0.0, 0.0, 0.0, 0.0, 0.0], 0.5)
            # Cruising once 12 mm along (accelerating takes 0.1 s and 2.5 mm).
            wait_for(lambda: r.getActualTCPPose()[0] - p0[0] > 0.012)
            assert r.getActualTCPSpeed()[0] == pytest.approx(0.05, abs=1e-3)
            c.stopL(1.0)
            settle(r, sim)
            p = r.getActualTCPPose()
            assert p[0] - p0[0] > 0.01
            assert abs(p[1] - p0[1]) < 1e-5 and abs(p[2] - p0[2]) < 1e-5
            assert pose_error(p0[:3] + p[3:], tcp_matrix(p0))[1] < 1e-5  # orientation kept
            assert np.abs(np.array(r.getActualQd())).max() == 0.0
            assert c.isProgramRunning()
    finally:
        ring.close()
        ring.unlink()


def test_protective_stop_aborts_a_move() -> None:
    with (
        controller(initial_q=tuple(WORK_Q), pstop_unlock_delay_s=0.0) as sim,
        receiver(sim.host) as r,
        controlled(sim.host) as c,
    ):
        q0 = np.array(r.getActualQ())
        target = q0 + np.array([1.0, 0, 0, 0, 0, 0])

        def stop_when_moving() -> None:
            # Once the arm has moved 0.03 rad (watched, not a fixed delay a loaded machine
            # stretches); it would take 2.5 s to the target.
            deadline = time.monotonic() + 30.0
            while sim.state()["q"][0] - q0[0] < 0.03 and time.monotonic() < deadline:
                time.sleep(0.005)
            sim.protective_stop()

        watcher = threading.Thread(target=stop_when_moving, name="test-pstop")
        watcher.start()
        try:
            ok = c.moveJ(target.tolist(), 0.5, 1.0)
        finally:
            watcher.join()
        # The blocking move returned, failed: the stop was noticed (an arm stopped short never
        # reaches the target, so a client that missed it would not return at all).
        assert not ok
        wait_for(lambda: not sim.state()["moving"])
        settle(r, sim)
        q = np.array(r.getActualQ())
        assert 0.03 < q[0] - q0[0] < 0.9 and np.abs(np.array(r.getActualQd())).max() == 0.0
        assert r.isProtectiveStopped() and r.getSafetyMode() == 3
        assert r.getSafetyStatusBits() & 4 and not c.isProgramRunning()
        assert not c.moveJ(q0.tolist(), 0.5, 1.0)  # refused while stopped

        db = dashboard_client.DashboardClient(sim.host)
        db.connect()
        try:
            assert "PROTECTIVE_STOP" in db.safetystatus()
            db.unlockProtectiveStop()  # raises unless the reply is "Protective stop releasing"
            db.closeSafetyPopup()
            assert "NORMAL" in db.safetystatus()
        finally:
            db.disconnect()
        assert c.reuploadScript()
        wait_for(c.isProgramRunning)
        assert c.moveJ(q0.tolist(), 1.0, 2.0)
        settle(r, sim)
        assert np.abs(np.array(r.getActualQ()) - q0).max() < 1e-6


@pytest.mark.slow
def test_dropped_and_stalled_connections() -> None:
    with controller() as sim, receiver(sim.host) as r:
        assert sim.drop_connections() == 1
        deadline = time.monotonic() + 30
        while r.isConnected() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not r.isConnected()
        assert r.reconnect() and r.isConnected()
        assert sim.state()["rtde_clients"] == 1

        # A short stall: the client keeps its connection; the clock jumps on resumption (the
        # controller's clock runs on while it sends nothing, no backlog is replayed). Followed
        # as it happens, polling until the timestamp jumps (a fixed schedule of sleeps could
        # land after the stall on a loaded machine); the jump is the stall less what a late
        # controller was still catching up, so half of it is asserted.
        settle(r, sim)
        sim.stall_output(1.0)
        frozen = after = r.getTimestamp()
        deadline = time.monotonic() + 30
        while after - frozen < 0.25:
            assert time.monotonic() < deadline, "no stall seen"
            frozen = after
            time.sleep(0.001)
            after = r.getTimestamp()
        assert r.isConnected() and after - frozen > 0.5
        assert_cycle_grid(Seen(r, sim, 0.3), 0.002)

        # A stall longer than the client's 2.5 s receive timeout: it gives up.
        sim.stall_output(4.0)
        deadline = time.monotonic() + 30
        while r.isConnected() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not r.isConnected()
        time.sleep(1.6)
        assert r.reconnect()
        assert r.getTimestamp() > after
