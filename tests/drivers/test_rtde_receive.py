"""The native RTDE receive client (drivers/rtde_receive.py) against the simulated UR controller,
and URRobot's native receive backend.

Every test starts its own simulated controller process on a random free 127.a.b.c address and
stops it before it ends. Ground truth: the controller's timestamps are exact multiples of its
period (2 ms e-Series, 8 ms CB3), and ``SimulatedController.state()`` (``skipped_cycles``: cycles
the controller itself never sent because it ran late, which no client can receive).

No assert depends on how fast a loaded machine runs: reads go on until the samples span a
controller time (not for a wall time, then counted), waits are for events with generous
timeouts, and host times are compared only where causality orders them.
"""

from __future__ import annotations

import logging
import os
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import pytest

from wristscan.drivers.base import DriverInitError, LinkState
from wristscan.drivers.records import RobotState
from wristscan.drivers.sim.ur.controller import (
    ControllerConfig,
    SimulatedController,
    pick_free_loopback_host,
)
from wristscan.drivers.ur import rtde_wire
from wristscan.drivers.ur.receive import (
    RtdeConnectError,
    RtdeHandshakeError,
    RtdeLinkLost,
    RtdeNotFound,
    RtdeReceiver,
    Samples,
)
from wristscan.drivers.ur.robot import URRobot

pytestmark = pytest.mark.timeout(120)

WORK_Q = (0.3, -1.9, 1.9, -1.57, -1.57, 0.2)
VARS = ("timestamp", "actual_q", "actual_qd", "actual_TCP_pose", "runtime_state")


@contextmanager
def controller(host: str | None = None, **overrides: Any) -> Iterator[SimulatedController]:
    cfg = ControllerConfig(host=host or pick_free_loopback_host(), initial_q=WORK_Q, **overrides)
    with SimulatedController(cfg) as sim:
        yield sim


def _joined(got: list[Samples]) -> Samples:
    return Samples(
        np.concatenate([g.host_ns for g in got]), np.concatenate([g.values for g in got])
    )


def read_for(client: RtdeReceiver, seconds: float) -> Samples:
    got: list[Samples] = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        got.append(client.read(timeout=0.1))
    return _joined(got)


def read_span(client: RtdeReceiver, span_s: float, timeout_s: float = 30.0) -> Samples:
    """Read until the controller timestamps received span ``span_s`` (a controller that runs late
    skips cycles, the clock goes on: the span is reached whatever the load)."""
    got: list[Samples] = []
    first: float | None = None
    deadline = time.monotonic() + timeout_s
    while True:
        g = client.read(timeout=0.1)
        got.append(g)
        if len(g):
            first = float(g["timestamp"][0]) if first is None else first
            if g["timestamp"][-1] - first >= span_s:
                return _joined(got)
        assert time.monotonic() < deadline, f"the samples did not span {span_s} s in time"


def assert_every_sample(t: np.ndarray, period_s: float, skipped: int) -> None:
    """Strictly increasing timestamps on the period grid; any gap is a cycle the controller
    itself skipped (none on an idle machine)."""
    steps = np.round(np.diff(t) / period_s)
    assert np.allclose(np.diff(t), steps * period_s, atol=1e-9)
    assert np.all(steps >= 1), "a sample repeated or out of order"
    assert int(np.sum(steps - 1)) <= skipped


# ------------------------------------------------------------------------ wire helpers


def test_recipe_dtype_matches_struct_for_every_type() -> None:
    names = [
        "output_bit_register_64",  # BOOL
        "tool_output_mode",  # UINT8
        "runtime_state",  # UINT32
        "actual_digital_input_bits",  # UINT64
        "robot_mode",  # INT32
        "timestamp",  # DOUBLE
        "elbow_position",  # VECTOR3D
        "actual_q",  # VECTOR6D
        "joint_mode",  # VECTOR6INT32
    ]
    types = [rtde_wire.VARIABLE_TYPES[n] for n in names]
    assert set(types) == set(rtde_wire.TYPE_DTYPE) - {"VECTOR6UINT32"}
    recipe = rtde_wire.Recipe(3, names, types)
    values = {
        "output_bit_register_64": True,
        "tool_output_mode": 200,
        "runtime_state": 4_000_000_000,
        "actual_digital_input_bits": 2**60 + 5,
        "robot_mode": -7,
        "timestamp": 1234.5678,
        "elbow_position": (0.1, -0.2, 0.3),
        "actual_q": (1.0, -2.0, 3.0, -4.0, 5.0, -6.0),
        "joint_mode": (253, -1, 2**31 - 1, -(2**31), 0, 9),
    }
    payload = recipe.pack(values, {})
    assert recipe.dtype.itemsize == recipe.struct.size == len(payload) - 1
    decoded = np.frombuffer(payload[1:], recipe.dtype).astype(recipe.numpy_dtype())[0]
    for name, expected in values.items():
        assert np.array_equal(decoded[name], np.asarray(expected)), name
    assert recipe.unpack(payload[1:]) == values

    msg = rtde_wire.encode_text_message("protective stop", "RTDE", 2)
    assert rtde_wire.parse_text_message(msg) == ("protective stop", "RTDE", 2)
    assert rtde_wire.parse_text_message(b"\x09abc") == ("\tabc", "", 3)  # malformed: kept as text


# ------------------------------------------------------------------------ the client


def test_handshake_and_every_sample_in_order() -> None:
    extra = ("control_step", "robot_mode", "target_gravity", "joint_mode")
    with controller() as sim:
        fast = RtdeReceiver(sim.host, VARS + extra, connect_timeout_s=5.0)
        slow = RtdeReceiver(sim.host, ("timestamp",), frequency_hz=125.0)
        with fast, slow:
            assert fast.controller_version == (5, 15, 0, 0)
            assert fast.frequency_hz == 500.0 and slow.frequency_hz == 125.0
            assert fast.recipe is not None and fast.recipe.types[1] == "VECTOR6D"
            got = read_span(fast, 2.0)
            got_slow = slow.read(timeout=10.0)
            truth = sim.state()
        assert not fast.is_open
        t = got["timestamp"]
        # 2 s of controller time: 1001 samples, less the cycles the controller itself skipped.
        assert len(got) + truth["skipped_cycles"] >= 1001
        assert_every_sample(t, 0.002, truth["skipped_cycles"])
        assert len(got_slow) > 0
        assert_every_sample(got_slow["timestamp"], 0.008, truth["skipped_cycles"])
        # Decoded values against the controller's own: UINT64 cycle counter, INT32 mode,
        # VECTOR3D gravity, VECTOR6D joints (at rest), VECTOR6INT32 joint modes (253: running).
        assert np.array_equal(got["control_step"], np.round(t / 0.002).astype(np.uint64))
        assert np.all(got["robot_mode"] == truth["robot_mode"])
        assert np.allclose(got["target_gravity"], [0.0, 0.0, -9.82])
        assert got["actual_q"].shape == (len(got), 6)
        assert np.allclose(got["actual_q"], truth["q"], atol=1e-12)
        assert np.all(got["joint_mode"] == 253)
        # Host stamps: in order, after the controller produced each sample (causality, whatever
        # the load), and on the host's monotonic clock: a stamp on another clock or taken long
        # after receipt would be seconds off (a bound generous enough for any load).
        assert np.all(np.diff(got.host_ns) >= 0)
        lag_ms = (got.host_ns - np.array([sim.host_time_ns(x) for x in t])) * 1e-6
        assert lag_ms.min() > 0.0 and np.median(lag_ms) < 1000.0
        assert fast.counters["packets"] == len(got)


def test_starved_reader_loses_nothing() -> None:
    with controller() as sim, RtdeReceiver(sim.host, VARS) as client:
        first = client.read(timeout=10.0)
        time.sleep(0.6)  # not reading: the kernel holds the packets
        t_wake = time.monotonic_ns()
        burst = client.read(timeout=0)
        rest = read_for(client, 0.2)
        skipped = sim.state()["skipped_cycles"]
    t = np.concatenate([first["timestamp"], burst["timestamp"], rest["timestamp"]])
    # The 0.6 s not read came out at once: the burst spans most of it on the controller's clock
    # (a span, not a count: a controller running late skips cycles, its clock goes on).
    assert np.ptp(burst["timestamp"]) >= 0.3
    assert np.all(burst.host_ns >= t_wake)  # stamped when taken in, not invented earlier
    assert_every_sample(t, 0.002, skipped)


def test_text_message_mid_stream_is_logged_and_kept(caplog: pytest.LogCaptureFixture) -> None:
    with controller() as sim, RtdeReceiver(sim.host, VARS) as client:
        before = read_for(client, 0.3)
        with caplog.at_level(logging.INFO, logger="wristscan.drivers.ur.receive"):
            assert sim.send_text_message("safety: reduced mode", "Controller", 2) == 1
            sim.send_text_message("hello", "", 3)
            after = read_for(client, 0.3)
        skipped = sim.state()["skipped_cycles"]
    assert [(m.text, m.source, m.level) for m in client.messages] == [
        ("safety: reduced mode", "Controller", 2),
        ("hello", "", 3),
    ]
    assert client.counters["text_messages"] == 2
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "safety: reduced mode" in warnings[0].getMessage()
    assert_every_sample(np.concatenate([before["timestamp"], after["timestamp"]]), 0.002, skipped)


def test_link_loss_is_reported_and_reopen_continues() -> None:
    with controller() as sim:
        client = RtdeReceiver(sim.host, VARS, data_timeout_s=0.4)
        try:
            client.open()
            before = read_for(client, 0.2)
            assert sim.drop_connections() == 1
            with pytest.raises(RtdeLinkLost, match=r"closed|lost"):
                read_for(client, 2.0)
            assert not client.is_open
            client.open()  # the same receiver connects again
            after = read_for(client, 0.2)
            assert after["timestamp"][0] > before["timestamp"][-1]
            # The controller goes silent: no data for data_timeout_s counts as a lost link. The
            # stall outlasts any wait (the controller keeps the connection open): raising at all
            # is the timeout firing; and not before data_timeout_s after the last data taken in
            # (a bound that causality orders, whatever the load; a fixed window after the
            # request would not be).
            last_ns = int(after.host_ns[-1])
            sim.stall_output(30.0)
            deadline = time.monotonic() + 25.0
            with pytest.raises(RtdeLinkLost, match="no data for"):
                while time.monotonic() < deadline:
                    g = client.read(timeout=0.1)
                    last_ns = int(g.host_ns[-1]) if len(g) else last_ns
            assert time.monotonic_ns() - last_ns >= 0.4e9
        finally:
            client.close()


def test_refusals_are_clear() -> None:
    free = pick_free_loopback_host()
    with pytest.raises(RtdeConnectError, match="refused"):
        RtdeReceiver(free, VARS).open()
    with pytest.raises(ValueError):
        RtdeReceiver(free, ("timestamp", "timestamp"))
    with controller(version=(3, 15, 7, 0)) as sim:  # CB3: 125 Hz at most
        with pytest.raises(RtdeNotFound, match="no_such_output, actual_qq") as info:
            RtdeReceiver(sim.host, ("timestamp", "no_such_output", "actual_qq")).open()
        assert info.value.names == ("no_such_output", "actual_qq")
        with pytest.raises(RtdeHandshakeError, match="rejected at 500 Hz"):
            RtdeReceiver(sim.host, VARS, frequency_hz=500.0).open()
        with RtdeReceiver(sim.host, VARS) as client:  # the default adapts to CB3
            assert client.frequency_hz == 125.0
            assert len(client.read(timeout=10.0)) > 0
        # Every connection, failed handshakes included, was closed (the controller notices
        # each end of stream a moment later).
        deadline = time.monotonic() + 30.0
        while sim.state()["rtde_clients"] and time.monotonic() < deadline:
            time.sleep(0.02)
        assert sim.state()["rtde_clients"] == 0


def test_framing_split_packets_and_stray_packets() -> None:
    """Byte-level framing against a scripted server: packets split at every awkward boundary,
    a text message and a foreign recipe's package between data packages."""
    recipe = rtde_wire.Recipe(1, ["timestamp", "actual_q"], ["DOUBLE", "VECTOR6D"])
    packets = [
        rtde_wire.encode(
            rtde_wire.DATA_PACKAGE, recipe.pack({"timestamp": k * 0.002, "actual_q": (k,) * 6}, {})
        )
        for k in range(40)
    ]
    text = rtde_wire.encode(rtde_wire.TEXT_MESSAGE, rtde_wire.encode_text_message("hi", "x", 3))
    foreign = rtde_wire.encode(rtde_wire.DATA_PACKAGE, b"\x02" + struct.pack(">i", 5))
    stream = b"".join(packets[:10]) + text + b"".join(packets[10:20]) + foreign
    stream += b"".join(packets[20:])
    cut = 7 * 29  # the first 203 bytes in 7-byte pieces, then the rest at once
    pieces = [stream[i : i + 7] for i in range(0, cut, 7)] + [stream[cut:]]
    host = pick_free_loopback_host()
    with socket.socket() as srv:
        srv.bind((host, 0))
        srv.listen(1)
        srv.settimeout(10.0)
        port = srv.getsockname()[1]
        seen: list[int] = []

        def serve() -> None:
            conn, _ = srv.accept()
            conn.settimeout(10.0)
            with conn:
                reader = rtde_wire.PacketReader()
                replies = {
                    ord("V"): b"\x01",
                    ord("v"): struct.pack(">IIII", 5, 9, 0, 0),
                    ord("O"): b"\x01DOUBLE,VECTOR6D",
                    ord("S"): b"\x01",
                }
                while ord("S") not in seen:
                    data = conn.recv(4096)
                    if not data:
                        return
                    for ptype, _payload in reader.feed(data):
                        seen.append(ptype)
                        if ptype == ord("O"):  # a message during the handshake is fine too
                            conn.sendall(text)
                        conn.sendall(rtde_wire.encode(ptype, replies[ptype]))
                for piece in pieces:
                    conn.sendall(piece)
                    time.sleep(0.002)
                while data := conn.recv(4096):  # until the client closes
                    seen.extend(p for p, _ in reader.feed(data))

        th = threading.Thread(target=serve)
        th.start()
        try:
            with RtdeReceiver(host, ["timestamp", "actual_q"], port=port) as client:
                assert client.frequency_hz == 500.0
                got = read_span(client, 38.5 * 0.002)  # all 40 packages, however late they come
        finally:
            th.join(timeout=10.0)
    assert np.allclose(got["timestamp"], np.arange(40) * 0.002)
    assert np.array_equal(got["actual_q"][:, 3], np.arange(40.0))
    assert client.counters["text_messages"] == 2 and client.counters["ignored"] == 1
    assert seen == [ord("V"), ord("v"), ord("O"), ord("S"), ord("P")]


# ------------------------------------------------------------------------ URRobot, native


def test_robot_native_loses_nothing_under_cpu_hog() -> None:
    with controller() as sim, URRobot(sim.host, receive_backend="native") as r:
        r.read_for(0.2)
        # The driver's lost count from a point of the stream no earlier than the controller's
        # skipped count: a cycle the controller skips between the two snapshots would otherwise
        # count as lost but not as skipped (seen when the machine was loaded).
        snap = sim.state()
        skipped0 = snap["skipped_cycles"]
        deadline = time.monotonic() + 30.0
        while (s := r.read(timeout=0.1)) is None or s.controller_time_s < snap["timestamp"]:
            assert time.monotonic() < deadline, "the stream did not reach the snapshot"
        lost0 = r.counters.lost
        hogs = [
            subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range(os.cpu_count() or 2)
        ]
        try:
            sim.send_text_message("mid-stream notice", "test", 3)
            states = r.read_for(2.0)  # while the hogs run: what is read is counted below
        finally:
            for hog in hogs:
                hog.kill()
            for hog in hogs:
                hog.wait()
        states += r.read_for(0.1)
        h = r.health()
        skipped = sim.state()["skipped_cycles"] - skipped0
    t = np.array([s.controller_time_s for s in states])
    # Over a second of controller time under the hogs (a span: how many samples the 2 s of
    # reading held depends on the load; that none was lost is asserted next).
    assert t[-1] - t[0] > 1.0
    assert r.counters.lost - lost0 <= skipped  # 0 unless the controller itself ran late
    assert_every_sample(t, 0.002, skipped)
    assert h.state is LinkState.OPEN and h.counters.duplicates == 0
    assert h.detail["receive_backend"] == "native" and h.detail["text_messages"] == 1
    assert h.detail["child_overflow"] == 0


def test_robot_native_survives_controller_restart() -> None:
    host = pick_free_loopback_host()
    r = URRobot(host, receive_backend="native", backoff_max_s=0.2)
    try:
        with controller(host):
            r.open()
            # Over a second of history, so that the new controller's clock (from 0) is seen
            # as a restart rather than as reordered samples.
            before = r.read_for(1.5)
            assert before and r.counters.reconnects == 0
        t_down = time.monotonic()
        while r.health().state is not LinkState.RECONNECTING:
            assert time.monotonic() - t_down < 30.0, "the loss was not noticed"
            r.read(timeout=0.05)
        with controller(host) as sim2:
            after: list[RobotState] = []
            end = time.monotonic() + 30.0
            while time.monotonic() < end and len(after) < 200:
                s = r.read(timeout=0.1)
                if s is not None and s.host_time_ns > sim2.start_time_ns:
                    after.append(s)
            h = r.health()
            skipped = sim2.state()["skipped_cycles"]
        assert len(after) >= 200, f"no data after the restart: {h}"
        assert h.counters.reconnects == 1 and h.state is LinkState.OPEN
        assert h.last_error is not None
        assert_every_sample(np.array([s.controller_time_s for s in after]), 0.002, skipped)
    finally:
        r.close()


def test_robot_native_unknown_variable_fails_clearly() -> None:
    with controller() as sim:
        r = URRobot(sim.host, receive_backend="native", variables=["no_such_output"])
        with pytest.raises(DriverInitError, match=r"no output variable.*no_such_output"):
            r.open()
        # Failed for good at the first answer: no retry, no restarted child (counted, not timed).
        h = r.health()
        assert h.state is LinkState.FAILED
        assert h.counters.reconnects == 0 and h.detail["receive_restarts"] == 0
    with pytest.raises(DriverInitError, match="receive_backend"):
        URRobot("127.0.0.1", receive_backend="rtde")
