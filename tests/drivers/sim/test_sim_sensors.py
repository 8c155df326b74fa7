"""Simulated sensors over their real transports, against the ground truth they were given.

No assert depends on how fast a loaded machine runs: waits are for events with generous
timeouts, and host times are compared only where causality orders them."""

from __future__ import annotations

import contextlib
import math
import socket
import time
from collections.abc import Callable
from typing import TypeVar

import numpy as np
import pytest
import serial
from hokuyolx import HokuyoLX

from wristscan.calib import kinematics, se3
from wristscan.drivers import lpf1, lpf1_reader, rf627, scip
from wristscan.drivers.records import Profile
from wristscan.drivers.sim.clock import DeviceClock
from wristscan.drivers.sim.scene import demo_scene, sensor_looking_down
from wristscan.drivers.sim.sensors import (
    DEFAULT_SENSOR2FLANGE_POSE,
    FaultConfig,
    SensorSimConfig,
    SimulatedSensor,
)
from wristscan.drivers.sim.truth import TruthRing

BALL = demo_scene().find("ball")
BALL_C = BALL.pose[:3, 3]
BALL_R = 0.0127
T = TypeVar("T")


def _udp_receiver() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    s.bind(("127.0.0.1", 0))
    s.settimeout(30.0)  # generous: a datagram is due every few ms, however loaded the machine
    return s


def _collect_udp(sock: socket.socket, decode: Callable[[bytes], T | None], n: int) -> list[T]:
    out: list[T] = []
    deadline = time.monotonic() + 60
    while len(out) < n and time.monotonic() < deadline:
        item = decode(sock.recv(70000))
        if item is not None:
            out.append(item)
    assert len(out) == n, f"only {len(out)} of {n} items"
    return out


def _points_base(p: Profile, sensor2base: np.ndarray) -> np.ndarray:
    v = p.valid
    return se3.apply(sensor2base, np.column_stack([np.zeros(v.sum()), p.y[v], p.z[v]]))


# ----------------------------------------------------------------------------------------------
# Clock


def test_device_clock_offset_drift_reset() -> None:
    clk = DeviceClock(offset_ns=5_000, drift_ppm=100.0, epoch_host_ns=1_000_000)
    h = np.array([1_000_000, 1_000_000 + 10**9, 1_000_000 + 10**12])
    np.testing.assert_array_equal(
        clk.ideal_ns(h), [5_000, 5_000 + 10**9 + 100_000, 5_000 + 10**12 + 10**8]
    )
    np.testing.assert_array_equal(clk.host_ns(clk.ideal_ns(h)), h)
    noisy = DeviceClock(jitter_ns=1000.0, rng=1, epoch_host_ns=0)
    d = noisy.device_ns(np.full(20000, 10**9)) - 10**9
    assert abs(d.mean()) < 30 and d.std() == pytest.approx(1000, rel=0.05)
    clk.reset(host_ns=2 * 10**9, offset_ns=0)
    assert clk.ideal_ns(2 * 10**9 + 10**6) == 10**6 + 100


# ----------------------------------------------------------------------------------------------
# Each kind over its transport


def test_lpf1_udp_profiles_land_on_the_ball_with_true_timing() -> None:
    rx = _udp_receiver()
    cfg = SensorSimConfig(
        kind="lpf1-udp",
        rate_hz=500,
        target=rx.getsockname(),
        latency_s=0.004,
        stamp_delay_s=0.001,
        clock_offset_ns=123_456_789,
        clock_drift_ppm=50.0,
        noise_std_m=20e-6,
        max_datagram=1472,
        encoder="time",
        encoder_counts_per_s=10_000,
    )
    with rx, SimulatedSensor(cfg) as sim:
        info = sim.info()
        reasm = lpf1_reader.Reassembler()

        def decode(d: bytes) -> Profile | None:
            m = reasm.push(lpf1.parse_message(d))
            if m is None or m.header.msg_type != lpf1.MsgType.PROFILE:
                return None
            return lpf1.decode_profile(m, time.monotonic_ns())

        profiles = _collect_udp(rx, decode, 60)
        st = sim.stats()
    # Sends are timed: the late ones are counted (a stalled simulator sends in a burst). How
    # late depends on the machine's load; that the two counters agree does not.
    assert 0 <= st["sent_late_5ms"] <= st["profiles_sent"]
    assert (st["sent_late_5ms"] > 0) == (st["max_send_late_us"] > 5000)
    counters = np.array([p.frame_counter for p in profiles])
    assert counters[0] < 5 and np.all(np.diff(counters) == 1)
    prof = profiles[-1]
    s2f = se3.pose_to_matrix(DEFAULT_SENSOR2FLANGE_POSE)
    np.testing.assert_allclose(np.asarray(info["sensor2flange"]), s2f, atol=1e-15)
    s2b = np.asarray(info["standalone_flange2base"]) @ s2f
    r = np.linalg.norm(_points_base(prof, s2b) - BALL_C, axis=1)
    assert prof.valid.sum() > 900  # the chord across the ball
    assert np.max(np.abs(r - BALL_R)) < 5 * 20e-6 + 1e-6  # noise plus 2 µm quantisation
    # Timing truth: exposure k at t0 + k * period; stamped on the drifting clock.
    clk = DeviceClock(info["clock_offset_ns"], info["clock_drift_ppm"],
                      epoch_host_ns=info["clock_epoch_host_ns"])  # fmt: skip
    for p in profiles:
        k = p.frame_counter + info["counter_base"]
        t_exp = info["t0_ns"] + int(k * info["period_ns"])
        assert abs(p.sensor_time_ns - clk.ideal_ns(t_exp + info["stamp_delay_ns"])) <= 1
        assert p.host_time_ns - t_exp >= info["latency_ns"]
        assert p.encoder == round((t_exp - info["t0_ns"]) * 1e-9 * 10_000)
    stamps = np.array([p.sensor_time_ns for p in profiles])
    # The device exposes every 1/rate of its own clock.
    np.testing.assert_allclose(np.diff(stamps), 2_000_000, atol=2)


def test_lpf1_tcp_hello_then_profiles_and_disconnect() -> None:
    cfg = SensorSimConfig(kind="lpf1-tcp", rate_hz=1000, n_points=512, heartbeat_s=0.05)
    with SimulatedSensor(cfg) as sim:
        addr = (sim.endpoint["host"], sim.endpoint["port"])

        def read(sock: socket.socket, n_profiles: int) -> tuple[list[lpf1.Message], int]:
            dec = lpf1_reader.StreamDecoder()
            msgs: list[lpf1.Message] = []
            while sum(m.header.msg_type == lpf1.MsgType.PROFILE for m in msgs) < n_profiles:
                data = sock.recv(65536)
                if not data:
                    break
                msgs += dec.feed(data)
            return msgs, dec.bad_messages

        with socket.create_connection(addr, timeout=3) as sock:
            msgs, bad = read(sock, 200)
        assert msgs[0].header.msg_type == lpf1.MsgType.HELLO
        assert msgs[0].json()["n_points"] == 512 and bad == 0
        assert any(m.header.msg_type == lpf1.MsgType.HEARTBEAT for m in msgs)
        counters = [lpf1.decode_profile(m).frame_counter for m in msgs
                    if m.header.msg_type == lpf1.MsgType.PROFILE]  # fmt: skip
        assert np.all(np.diff(counters) == 1), sim.stats()
        # Disconnect: the port refuses, then comes back; rebooted: counters restart. Away for
        # 1.5 s, so that the refusal is seen however late a loaded machine runs the next line.
        with socket.create_connection(addr, timeout=3) as sock:
            sim.disconnect(1.5, reboot=True)
            sock.settimeout(30)
            while sock.recv(65536):
                pass  # drained until the device closes the connection
        with pytest.raises(ConnectionRefusedError):
            socket.create_connection(addr, timeout=1).close()
        deadline = time.monotonic() + 30
        while True:
            try:
                sock = socket.create_connection(addr, timeout=1)
                break
            except ConnectionRefusedError:
                assert time.monotonic() < deadline, "the sensor did not come back"
                time.sleep(0.05)
        with sock:
            msgs, _ = read(sock, 5)
        first = lpf1.decode_profile(
            next(m for m in msgs if m.header.msg_type == lpf1.MsgType.PROFILE)
        )
        assert msgs[0].header.msg_type == lpf1.MsgType.HELLO
        # Rebooted: counters restarted (counter_base > 0) and the clock restarted at the return.
        info = sim.info()
        assert info["counter_base"] > counters[-1]
        clk = DeviceClock(info["clock_offset_ns"], epoch_host_ns=info["clock_epoch_host_ns"])
        t_exp = info["t0_ns"] + int((first.frame_counter + info["counter_base"]) * 1e6)
        assert first.sensor_time_ns == clk.ideal_ns(t_exp + info["stamp_delay_ns"])
        assert first.sensor_time_ns < (first.frame_counter + 10) * 1e6
        assert sim.stats()["clients"] == 3


def test_lpf1_serial_over_a_pty_opened_by_path() -> None:
    cfg = SensorSimConfig(kind="lpf1-serial", rate_hz=200, n_points=256, intensity=True)
    with SimulatedSensor(cfg) as sim:
        port = serial.Serial(sim.endpoint["port_path"], 921600, timeout=0.5)
        try:
            dec = lpf1_reader.SerialDecoder()
            profiles: list[Profile] = []
            deadline = time.monotonic() + 60
            while len(profiles) < 20 and time.monotonic() < deadline:
                for m in dec.feed(port.read(4096)):
                    if m.header.msg_type == lpf1.MsgType.PROFILE:
                        profiles.append(lpf1.decode_profile(m))
        finally:
            port.close()
    assert len(profiles) >= 20
    counters = np.array([p.frame_counter for p in profiles])
    assert np.all(np.diff(counters) == 1)
    p = profiles[-1]
    assert p.intensity is not None and np.all(p.intensity[p.valid] > 0)
    assert np.all(p.intensity[~p.valid] == 0)


def test_rf627_udp() -> None:
    rx = _udp_receiver()
    cfg = SensorSimConfig.for_kind("rf627-udp", rate_hz=1000, target=rx.getsockname(), sensor_id=77)
    with rx, SimulatedSensor(cfg) as sim:
        frames = _collect_udp(rx, rf627.decode, 50)
        info = sim.info()
    hdr = [f.header for f in frames]
    assert all(h.serial == 77 and h.device_type == 627 for h in hdr)
    assert np.all(np.diff([h.measure_count for h in hdr]) == 1)
    assert np.all(np.diff([h.packet_count for h in hdr]) == 1)
    prof = frames[-1].profile
    assert prof.n_points == 648
    s2b = np.asarray(info["standalone_flange2base"]) @ np.asarray(info["sensor2flange"])
    r = np.linalg.norm(_points_base(prof, s2b) - BALL_C, axis=1)
    assert np.max(np.abs(r - BALL_R)) < 5 * 20e-6 + 4e-6


def test_hokuyolx_reads_the_simulated_scip_sensor_over_tcp() -> None:
    cfg = SensorSimConfig.for_kind("scip-tcp", rate_hz=40, noise_std_m=0.0)
    with SimulatedSensor(cfg) as sim:
        laser = HokuyoLX(addr=(sim.endpoint["host"], sim.endpoint["port"]), tsync=True)
        try:
            assert (laser.amin, laser.amax, laser.aforw, laser.ares) == (0, 1080, 540, 1440)
            assert laser.scan_freq == 40 and laser.model == cfg.scip_model
            t_ask_ms = time.time() * 1000
            ts, scan = laser.get_dist()
            t_read_ms = time.time() * 1000
            # hokuyolx reads until a blank line, so two replies that share one recv() become
            # one garbled message (its own limitation: it loses a scan or raises a checksum
            # error). skips=9: one scan in ten, 0.25 s apart, so that only a reader or simulator
            # stalled that long on a loaded machine would see two at once (at 40 Hz, 25 ms did).
            scans = list(laser.iter_dist(scans=3, skips=9))
            state = laser.sensor_state()
            info = sim.info()
        finally:
            laser.close()
    assert scan.shape == (1081,)
    # hokuyolx counts down the scans it still expects; it can lose the first when the command's
    # answer and the first scan share a recv() (above), so require a count-down that ends at 0.
    pendings = [pending for _, _, pending in scans]
    assert len(pendings) >= 2 and pendings[-1] == 0 and pendings == sorted(pendings, reverse=True)
    # hokuyolx maps the 24-bit stamps to UNIX ms: the scan asked for lies between the ask and
    # the answer, within the mapping's own error (its tsync round trips; generous, a wrong
    # mapping is off by the 24-bit wrap, hours, or the epoch).
    assert t_ask_ms - 1000 < ts < t_read_ms + 1000
    assert state["LASR"] == "ON"
    # The front step looks straight down at the top of the ball, 0.1 m below the sensor origin.
    s2b = np.asarray(info["standalone_flange2base"]) @ np.asarray(info["sensor2flange"])
    ang = laser.get_angles()
    rng_m = scan * 1e-3
    ok = scan >= 20
    pts = se3.apply(s2b, np.column_stack([np.zeros(ok.sum()), rng_m[ok] * np.sin(ang[ok]),
                                          rng_m[ok] * np.cos(ang[ok])]))  # fmt: skip
    on_ball = np.abs(np.linalg.norm(pts - BALL_C, axis=1) - BALL_R) < 0.001
    # From 0.1 m the ball spans 2 asin(R / 0.1) of the fan; ranges are whole millimetres.
    span_steps = 2 * math.asin(BALL_R / 0.1) / (2 * math.pi / 1440)
    assert abs(on_ball.sum() - span_steps) <= 3
    assert scan[540] == round((0.1 - BALL_R) * 1000)


def test_scip_serial_with_the_wristscan_decoder() -> None:
    cfg = SensorSimConfig.for_kind("scip-serial", rate_hz=100, n_points=681, scip_ares=1024)
    with SimulatedSensor(cfg) as sim:
        port = serial.Serial(sim.endpoint["port_path"], 115200, timeout=0.5)
        dec = scip.ReplyDecoder()
        replies: list[scip.Reply] = []

        def until(pred: Callable[[], bool]) -> None:
            deadline = time.monotonic() + 30
            while not pred() and time.monotonic() < deadline:
                replies.extend(dec.feed(port.read(max(1, port.in_waiting))))
            assert pred()

        try:
            port.write(b"PP\n")
            until(lambda: len(replies) >= 1)
            pp = scip.decode_info(replies[0])
            assert pp["AMAX"] == "680" and pp["ARES"] == "1024" and pp["AFRT"] == "340"
            port.write(b"MS0100050002005;hello\n")  # 2-char encoding, clusters of 2, 5 scans
            until(lambda: len(replies) >= 7)
            port.write(b"QT\n")
            until(lambda: any(r.echo == b"QT" for r in replies))
        finally:
            port.close()
    ack = replies[1]
    assert ack.echo == b"MS0100050002005;hello" and ack.status == b"00"
    scans = [scip.decode_scan(r, n_chars=2) for r in replies[2:7]]
    assert [s.remaining for s in scans] == [4, 3, 2, 1, 0]
    assert all(s.ranges_mm.shape == (201,) for s in scans)  # steps 100..500 in pairs
    dt = np.diff([s.timestamp_ms for s in scans])
    assert np.all((dt >= 9) & (dt <= 11))  # 100 Hz on the device's ms clock


# ----------------------------------------------------------------------------------------------
# Truth rings: the pose at the exposure instant


def test_profiles_use_the_robot_pose_at_the_exposure_instant() -> None:
    model = kinematics.get_model("UR5e")
    s2f = se3.pose_to_matrix(DEFAULT_SENSOR2FLANGE_POSE)
    flange0 = sensor_looking_down(BALL_C, 0.1) @ se3.invert(s2f)
    q0 = kinematics.inverse_nearest(model, flange0, np.radians([0, -90, 90, -90, -90, 0]))

    def q_at(t_ns: np.ndarray) -> np.ndarray:
        # Joint 1 swings +-0.01 rad at 2 Hz: the laser line sweeps ~ +-4.5 mm across the ball.
        s = np.asarray(t_ns, dtype=np.float64) * 1e-9
        q = np.tile(q0, (s.size, 1))
        q[:, 0] += 0.01 * np.sin(2 * np.pi * 2.0 * s)
        return q

    with TruthRing.create(width=6, capacity=16384) as ring, TruthRing.create(width=1) as tring:
        # The truth is known ahead: fill the ring for the next 16 s at 1 kHz (the simulator
        # starts and sends its 120 profiles within it, however slowly a loaded machine starts
        # a process).
        t_now = time.monotonic_ns()
        ts = t_now + np.arange(16000, dtype=np.int64) * 1_000_000
        for t, q in zip(ts, q_at(ts), strict=True):
            ring.append(int(t), q)
        for t in ts[::10]:
            tring.append(int(t), [0.5 * (t - t_now) * 1e-9])
        rx = _udp_receiver()
        cfg = SensorSimConfig(
            kind="lpf1-udp", rate_hz=400, target=rx.getsockname(), latency_s=0.02,
            encoder="table", encoder_counts_per_rev=360_000,
        )  # fmt: skip
        with rx, SimulatedSensor(cfg, robot_ring=ring.name, table_ring=tring.name) as sim:
            info = sim.info()

            def decode(d: bytes) -> Profile | None:
                m = lpf1.parse_message(d)
                return lpf1.decode_profile(m) if m.header.msg_type == lpf1.MsgType.PROFILE else None

            profiles = _collect_udp(rx, decode, 120)
            assert sim.stats()["truth_clamped"] == 0
    worst_exposure, worst_send = 0.0, 0.0
    for p in profiles:
        t_exp = info["t0_ns"] + int((p.frame_counter + info["counter_base"]) * info["period_ns"])
        for t, which in ((t_exp, "exp"), (t_exp + info["latency_ns"], "send")):
            s2b = kinematics.forward(model, q_at(np.array([t]))[0]) @ s2f
            err = np.abs(np.linalg.norm(_points_base(p, s2b) - BALL_C, axis=1) - BALL_R).max()
            if which == "exp":
                worst_exposure = max(worst_exposure, err)
            else:
                worst_send = max(worst_send, err)
        expected_count = round(0.5 * (t_exp - t_now) * 1e-9 / (2 * math.pi) * 360_000)
        assert p.encoder is not None and abs(p.encoder - expected_count) <= 1
    assert worst_exposure < 5 * 20e-6 + 1e-6
    assert worst_send > 5 * worst_exposure  # the send instant would be visibly wrong


# ----------------------------------------------------------------------------------------------
# Faults


def test_fault_injection_is_visible_in_the_decoded_stream() -> None:
    rx = _udp_receiver()
    faults = FaultConfig(drop=0.1, duplicate=0.1, reorder=0.1, truncate=0.05, corrupt=0.05)
    cfg = SensorSimConfig(kind="lpf1-udp", rate_hz=1000, n_points=256, target=rx.getsockname(),
                          faults=faults, seed=11, heartbeat_s=0)  # fmt: skip
    counters: list[int] = []
    errors = {"trunc": 0, "crc": 0}
    with rx, SimulatedSensor(cfg) as sim:
        deadline = time.monotonic() + 60
        while len(counters) < 600 and time.monotonic() < deadline:
            d = rx.recv(70000)
            try:
                m = lpf1.parse_message(d)
            except lpf1.TruncatedError:
                errors["trunc"] += 1
                continue
            except lpf1.FrameError:
                errors["crc"] += 1
                continue
            if m.header.msg_type == lpf1.MsgType.PROFILE:
                counters.append(lpf1.decode_profile(m).frame_counter)
        sim.set_faults()  # back to a clean stream
        # Everything sent before the switch is in the socket already (loopback delivers within
        # the send): drop it, however far behind a loaded machine left this reader.
        rx.setblocking(False)
        with contextlib.suppress(BlockingIOError):
            while True:
                rx.recv(70000)
        rx.settimeout(30.0)
        clean: list[int] = []
        while len(clean) < 100:
            m = lpf1.parse_message(rx.recv(70000))
            if m.header.msg_type == lpf1.MsgType.PROFILE:
                clean.append(lpf1.decode_profile(m).frame_counter)
        stats = sim.stats()
    c = np.array(counters)
    steps = np.diff(c)
    assert np.sum(steps == 0) > 20  # duplicates
    assert np.sum(steps < 0) > 20  # reordering
    assert np.sum(steps > 1) > 40  # losses (drops, damaged frames, reordering)
    assert errors["trunc"] > 10 and errors["crc"] > 10
    assert stats["dropped"] > 30 and stats["corrupted"] > 10 and stats["truncated"] > 10
    assert np.all(np.diff(clean[5:]) == 1)


def test_tcp_stream_survives_corruption_by_resynchronising() -> None:
    cfg = SensorSimConfig(kind="lpf1-tcp", rate_hz=1000, n_points=256, seed=5,
                          faults=FaultConfig(truncate=0.05, corrupt=0.05))  # fmt: skip
    with (
        SimulatedSensor(cfg) as sim,
        socket.create_connection((sim.endpoint["host"], sim.endpoint["port"]), timeout=3) as sock,
    ):
        dec = lpf1_reader.StreamDecoder()
        counters: list[int] = []
        while len(counters) < 400:
            for m in dec.feed(sock.recv(65536)):
                if m.header.msg_type == lpf1.MsgType.PROFILE:
                    counters.append(lpf1.decode_profile(m).frame_counter)
    assert dec.bad_messages > 5
    steps = np.diff(counters)
    assert np.all(steps >= 1) and np.sum(steps > 1) > 10  # damaged frames skipped, order kept
    assert 0.8 < len(counters) / (counters[-1] - counters[0] + 1) < 0.95
