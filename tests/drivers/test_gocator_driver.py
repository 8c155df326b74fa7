"""The Gocator driver against a Gocator played here on three loopback sockets: the handshake
(a refused Start, a sensor already running), what the data channel may carry (point clouds with
intensity, unknown message types, stamps without profiles, other sensors), and the health
channel's indicators."""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from wristscan.drivers import gocator
from wristscan.drivers.base import DriverInitError
from wristscan.drivers.gocator import Cmd, Status
from wristscan.drivers.sensor_gocator import GocatorSensor


class PlayedGocator:
    """Control, data and health listeners on 127.0.0.1; the control channel answers from
    ``status`` (and the sensor's state), the data and health channels send what a test gives."""

    def __init__(self, running: bool = False, start_status: int = Status.OK) -> None:
        self.listeners = []
        for _ in range(3):
            s = socket.socket()
            s.bind(("127.0.0.1", 0))
            s.listen(1)
            self.listeners.append(s)
        self.ports = tuple(s.getsockname()[1] for s in self.listeners)
        self.running = running
        self.start_status = start_status
        self.commands: list[int] = []
        self.conns: list[socket.socket] = []
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        self.conns = [s.accept()[0] for s in self.listeners]
        control = self.conns[0]
        while True:
            try:
                head = control.recv(6, socket.MSG_WAITALL)
            except OSError:
                return
            if len(head) < 6:
                return
            cmd = struct.unpack("<IH", head)[1]
            self.commands.append(cmd)
            control.sendall(self._answer(cmd))

    def _answer(self, cmd: int) -> bytes:
        if cmd == Cmd.PROTOCOL_VERSION:
            return gocator.encode_reply(cmd, Status.OK, bytes((3, 2)))
        if cmd == Cmd.GET_SYSTEM_INFO:
            info = gocator.SensorInfo(77, "127.0.0.1", "G2340", (5, 3, 1, 9), int(self.running),
                                      0, 0)  # fmt: skip
            return gocator.encode_reply(cmd, Status.OK, gocator.encode_system_info(info))
        if cmd == Cmd.START:
            self.running = self.start_status == Status.OK
            return gocator.encode_reply(cmd, self.start_status)
        if cmd == Cmd.GET_TIMESTAMP:
            return gocator.encode_reply(cmd, Status.OK, struct.pack("<Q", 123_456_789))
        if cmd == Cmd.STOP:
            self.running = False
            return gocator.encode_reply(cmd, Status.OK)
        return gocator.encode_reply(cmd, Status.INVALID_COMMAND)

    def send(self, channel: int, data: bytes) -> None:
        deadline = time.monotonic() + 10
        while len(self.conns) < 3:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        self.conns[channel].sendall(data)

    def close(self) -> None:
        for s in [*self.conns, *self.listeners]:
            s.close()
        self._thread.join(5)


@contextmanager
def played(**kw: object) -> Iterator[tuple[PlayedGocator, GocatorSensor]]:
    dev = PlayedGocator(**kw)  # type: ignore[arg-type]
    c, d, h = dev.ports
    drv = GocatorSensor("127.0.0.1", control_port=c, data_port=d, health_port=h)
    try:
        yield dev, drv
    finally:
        drv.close()
        dev.close()


def _drain(drv: GocatorSensor, timeout_s: float = 0.3) -> list:
    out = []
    while (p := drv.read(timeout=timeout_s)) is not None:
        out.append(p)
    return out


def test_handshake_starts_a_ready_sensor_and_stops_it_on_close() -> None:
    with played() as (dev, drv):
        drv.open()
        h = drv.health()
        assert dev.commands == [Cmd.PROTOCOL_VERSION, Cmd.GET_SYSTEM_INFO, Cmd.START,
                                Cmd.GET_TIMESTAMP]  # fmt: skip
        assert h.detail["model"] == "G2340" and h.detail["serial"] == 77
        assert h.detail["firmware"] == "5.3.1.9" and h.detail["protocol_version"] == (3, 2)
        assert h.detail["device_time_us_at_start"] == 123_456_789
        drv.close()
        deadline = time.monotonic() + 5
        while Cmd.STOP not in dev.commands and time.monotonic() < deadline:
            time.sleep(0.01)
        assert dev.commands[-1] == Cmd.STOP


def test_a_running_sensor_is_not_restarted_nor_stopped() -> None:
    with played(running=True) as (dev, drv):
        drv.open()
        drv.close()
        time.sleep(0.1)
        assert Cmd.START not in dev.commands and Cmd.STOP not in dev.commands


def test_a_refused_start_is_one_clear_error() -> None:
    with played(start_status=Status.FAILED) as (_, drv):
        with pytest.raises(DriverInitError, match=r"^gocator: Start refused with status 0$"):
            drv.open()
    with pytest.raises(DriverInitError, match=r"control_port 0 outside 1\.\.65535"):
        GocatorSensor("127.0.0.1", control_port=0)


def test_point_clouds_intensity_unknown_types_stamp_only_groups_and_other_sensors() -> None:
    n = 32
    x = np.linspace(-0.01, 0.01, n)
    z = np.full((4, n), 0.1)
    valid = np.ones((4, n), bool)
    valid[:, 3] = False
    enc = gocator.GocatorEncoder(77, n, uniform=False, intensity=True)
    groups = enc.encode([5, 6, 7, 8], [1000, 2000, 3000, 4000], x, z, valid,
                        np.full((4, n), 50), encoder=[-1, -2, -3, -4])  # fmt: skip
    other = gocator.GocatorEncoder(78, n, uniform=False, intensity=True)
    foreign = other.encode([9], [5000], x, z[:1], valid[:1], np.full((1, n), 50))[0]
    # A stamp alone (a sensor with profile output disabled for a frame), then an unknown type
    # inside group 7, then another sensor's group.
    stamp_only = bytearray(groups[1][:70])
    stamp_only[4:6] = struct.pack("<H", 1 | 0x8000)
    unknown = struct.pack("<IH", 12, 42) + b"skipme"
    g7 = groups[2][:70] + unknown + groups[2][70:]
    health = gocator.encode_health({(21000, 0): 4, (2002, 0): 4150, (99999, 2): 7})
    with played() as (dev, drv):
        drv.open()
        dev.send(2, health)
        dev.send(1, groups[0] + bytes(stamp_only) + g7 + foreign + groups[3] + groups[0][:16])
        got = _drain(drv)
        h = drv.health()
    assert [p.frame_counter for p in got] == [5, 7, 8]
    assert h.counters.lost == 1  # frame 6 had no profile
    # Any sensor accepted (no sensor_id), but the stream is locked on the first one's serial and
    # scaling: another sensor's lone group is rejected (two in a row would re-lock).
    assert h.counters.malformed == 1
    assert h.detail["stamp_only_groups"] == 1 and h.detail["skipped_messages"] == 1
    p = got[0]
    np.testing.assert_allclose(p.y[valid[0]], x[valid[0]], atol=0.5e-6)
    np.testing.assert_allclose(p.z[valid[0]], 0.1, atol=1e-6)
    assert not p.valid[3] and np.isnan(p.z[3])
    assert p.intensity is not None and p.intensity[0] == 50 and p.intensity[3] == 0
    assert (p.encoder, p.sensor_time_ns, p.sensor_id) == (-1, 1_000_000, 77)
    assert h.detail["device"] == {"processing_drops": 4, "internal_temperature_cdeg": 4150,
                                  "99999[2]": 7}  # fmt: skip
    assert h.detail["health_messages"] == 1


def test_another_sensors_profiles_are_filtered_by_serial() -> None:
    n = 16
    enc = gocator.GocatorEncoder(78, n)
    groups = enc.encode([1, 2], [10, 20], 0, np.full((2, n), 0.1), True)
    dev = PlayedGocator()
    c, d, h = dev.ports
    drv = GocatorSensor("127.0.0.1", sensor_id=77, control_port=c, data_port=d, health_port=h)
    try:
        drv.open()
        dev.send(1, b"".join(groups) + groups[0][:16])
        assert _drain(drv) == []
        assert drv.health().detail["foreign"] == 2
    finally:
        drv.close()
        dev.close()


def test_a_group_with_two_profiles_is_damage() -> None:
    """A message cut short by exactly the next group's Stamp realigns the stream on a message
    boundary: the group then holds two profiles, and is dropped."""
    enc = gocator.GocatorEncoder(5, 16)
    groups = enc.encode([1, 2, 3], [10, 20, 30], 0, np.full((3, 16), 0.1), True)
    prof = groups[1][70:]
    not_last = prof[:4] + struct.pack("<H", gocator.Msg.UNIFORM_PROFILE) + prof[6:]
    drv = GocatorSensor("127.0.0.1")
    drv._consume(groups[0] + groups[1][:70] + not_last + prof + groups[2] + groups[0][:16], 0)
    assert [p.frame_counter for p in drv._ready] == [1, 3]
    assert drv.health().counters.malformed == 1


def test_the_last_group_before_a_pause_is_delivered() -> None:
    enc = gocator.GocatorEncoder(77, 16)
    (group,) = enc.encode([3], [30], 0, np.full((1, 16), 0.1), True)
    with played() as (dev, drv):
        drv.open()
        dev.send(1, group)  # and nothing after it
        got = _drain(drv)
    assert [p.frame_counter for p in got] == [3]
