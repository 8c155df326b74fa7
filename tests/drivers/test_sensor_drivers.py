"""Sensor drivers against the simulated sensors: one conformance class re-run for each backend.

The simulated sensors run standalone (no robot ring): the sensor looks down at the tooling ball
from 0.1 m, noise-free, so every profile must equal the ray-cast truth computed here to within
the wire format's quantisation. Faults injected by the simulator must show in the driver's
counters and never as a wrong profile.

No assert depends on how fast a loaded machine runs: waits are for events (a profile, a state,
a counter) with generous timeouts, and times are compared only where causality orders them.
"""

from __future__ import annotations

import contextlib
import inspect
import logging
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
from support import RefusingPort

from wristscan.drivers import lpf1, registry, rf627
from wristscan.drivers.base import DriverInitError, DriverIOError, LinkState
from wristscan.drivers.records import Profile
from wristscan.drivers.sensor_gocator import GocatorSensor
from wristscan.drivers.sensor_lpf1 import Lpf1SerialSensor, Lpf1TcpSensor, Lpf1UdpSensor
from wristscan.drivers.sensor_rf627 import Rf627Sensor
from wristscan.drivers.sensor_scip import ScipSensor
from wristscan.drivers.sim.scene import demo_scene
from wristscan.drivers.sim.sensors import FaultConfig, SensorSimConfig, SimulatedSensor

Driver = Lpf1UdpSensor | Lpf1TcpSensor | Lpf1SerialSensor | Rf627Sensor | ScipSensor | GocatorSensor


@dataclass(frozen=True)
class Backend:
    name: str
    """Simulator kind."""
    driver: str
    """Registry name."""
    cls: type[Any]
    make: Callable[[dict[str, Any]], Driver]
    """Driver from the simulator's endpoint (UDP: the driver is made first, endpoint empty)."""
    sim: dict[str, Any] = field(default_factory=dict)
    y_tol: float = 2e-6
    z_tol: float = 2e-6
    stamp_tol_ns: float = 2
    """Quantisation of the device timestamps."""
    checksum: bool = True
    """Damage among the points is detected (not by RF627 and Gocator: no checksum)."""

    @property
    def udp(self) -> bool:
        return self.name.endswith("udp")

    @property
    def scip(self) -> bool:
        return self.name.startswith("scip")

    def __str__(self) -> str:
        return self.name


def _tcp_url(ep: dict[str, Any]) -> str:
    return f"socket://{ep['host']}:{ep['port']}"


SCIP_SIM = {"rate_hz": 200.0, "n_points": 361, "scip_ares": 1440}
BACKENDS = [
    Backend(
        "lpf1-udp",
        "lpf1-udp",
        Lpf1UdpSensor,
        lambda ep: Lpf1UdpSensor(bind_host="127.0.0.1", port=0),
        {"rate_hz": 500.0, "n_points": 256},
    ),
    Backend(
        "lpf1-tcp",
        "lpf1-tcp",
        Lpf1TcpSensor,
        lambda ep: Lpf1TcpSensor(ep["host"], ep["port"]),
        {"rate_hz": 500.0, "n_points": 256},
    ),
    Backend(
        "lpf1-serial",
        "lpf1-serial",
        Lpf1SerialSensor,
        lambda ep: Lpf1SerialSensor(ep["port_path"]),
        {"rate_hz": 500.0, "n_points": 256, "intensity": True},
    ),
    Backend(
        "rf627-udp",
        "rf627-udp",
        Rf627Sensor,
        lambda ep: Rf627Sensor(bind_host="127.0.0.1", port=0),
        {"rate_hz": 500.0},
        y_tol=1.6e-6,  # half of 50 mm / 16384
        z_tol=3.1e-6,  # half of 100 mm / 16384
        checksum=False,
    ),
    Backend(
        "scip-tcp",
        "scip",
        ScipSensor,
        lambda ep: ScipSensor(_tcp_url(ep)),
        SCIP_SIM,
        y_tol=0.5e-3,  # whole millimetres
        z_tol=0.5e-3,
    ),
    Backend(
        "scip-serial",
        "scip",
        ScipSensor,
        lambda ep: ScipSensor(ep["port_path"], intensity=True, start_step=20, cluster=3),
        SCIP_SIM,
        y_tol=0.5e-3,
        z_tol=0.5e-3,
    ),
    Backend(
        "gocator",
        "gocator",
        GocatorSensor,
        lambda ep: GocatorSensor(
            ep["host"],
            control_port=ep["port"],
            data_port=ep.get("data_port", ep["port"]),
            health_port=ep.get("health_port", ep["port"]),
        ),
        {"rate_hz": 500.0, "n_points": 256, "intensity": True, "port": 0},
        y_tol=1e-6,  # the uniform grid: xScale whole nm, xOffset whole µm
        z_tol=1e-6,  # half of 100 mm / 65000 in whole nm
        stamp_tol_ns=1000,  # timestamps in µs
        checksum=False,
    ),
]

CONTRACT: dict[type, list[str]] = {
    Lpf1UdpSensor: ["sensor_id", "bind_host", "port", "source_host", "recv_buffer_bytes"],
    Lpf1TcpSensor: ["host", "port", "sensor_id", "connect_timeout_s"],
    Lpf1SerialSensor: ["url", "sensor_id", "baudrate"],
    Rf627Sensor: ["sensor_id", "bind_host", "port", "sensor_host", "recv_buffer_bytes"],
    GocatorSensor: [
        "host",
        "sensor_id",
        "control_port",
        "data_port",
        "health_port",
        "connect_timeout_s",
    ],
    ScipSensor: [
        "url",
        "sensor_id",
        "baudrate",
        "intensity",
        "start_step",
        "end_step",
        "cluster",
    ],
}


@dataclass
class Truth:
    """The noise-free profile the standalone sensor must deliver."""

    y: np.ndarray
    z: np.ndarray
    valid: np.ndarray
    intensity: np.ndarray | None


def _truth(cfg: SensorSimConfig, info: dict[str, Any], drv: Driver) -> Truth:
    s2b = np.asarray(info["standalone_flange2base"]) @ np.asarray(info["sensor2flange"])
    meas = cfg.laser_model(0).measure(s2b[None], demo_scene(), cfg.standalone_table_angle_rad)
    y, z, valid = meas.y[0].copy(), meas.z[0].copy(), meas.valid[0].copy()
    if isinstance(drv, ScipSensor):
        # What the sensor answers to the driver's command: steps start..end in clusters, each
        # the nearest return of its steps in whole mm, seen along the cluster's middle step.
        start = 0 if drv.start_step is None else drv.start_step
        end = cfg.n_points - 1 if drv.end_step is None else drv.end_step
        c = drv.cluster
        t = np.where(valid, meas.t[0], np.inf)[start : end + 1]
        t = np.concatenate([t, np.full((-t.size) % c, np.inf)]).reshape(-1, c)
        r = np.rint(t.min(axis=1) * 1000) * 1e-3
        valid = np.isfinite(r)
        lo = start + c * np.arange(r.size)
        mid = (lo + np.minimum(lo + c - 1, end)) / 2
        ang = 2 * np.pi * (mid - (cfg.n_points - 1) // 2) / cfg.scip_ares
        y, z = r * np.sin(ang), r * np.cos(ang)
    return Truth(y, z, valid, None)


def _check_profile(p: Profile, truth: Truth, backend: Backend) -> bool:
    """True when ``p`` is the true profile within quantisation."""
    if p.y.shape != truth.y.shape or not np.array_equal(p.valid, truth.valid):
        return False
    v = p.valid
    return bool(
        np.all(np.abs(p.y[v] - truth.y[v]) <= backend.y_tol)
        and np.all(np.abs(p.z[v] - truth.z[v]) <= backend.z_tol)
        and np.all(np.isnan(p.z[~v]))
    )


@contextlib.contextmanager
def running(
    backend: Backend, faults: FaultConfig | None = None, **overrides: Any
) -> Iterator[tuple[Driver, SimulatedSensor, SensorSimConfig]]:
    """A simulated sensor and an open driver reading it; both stopped afterwards."""
    opts = {"noise_std_m": 0.0, "seed": 3, **backend.sim, **overrides}
    if faults is not None:
        opts["faults"] = faults
    with contextlib.ExitStack() as stack:
        if backend.udp:
            drv = backend.make({})
            stack.enter_context(drv)
            assert drv.local_address is not None  # type: ignore[union-attr]
            cfg = SensorSimConfig.for_kind(
                backend.name,  # type: ignore[arg-type]
                target=drv.local_address,  # type: ignore[union-attr]
                **opts,
            )
            sim = stack.enter_context(SimulatedSensor(cfg))
        else:
            cfg = SensorSimConfig.for_kind(backend.name, **opts)  # type: ignore[arg-type]
            sim = stack.enter_context(SimulatedSensor(cfg))
            drv = backend.make(sim.endpoint)
            stack.enter_context(drv)
        yield drv, sim, cfg


def _read(drv: Driver, n: int, timeout_s: float = 60.0) -> list[Profile]:
    out: list[Profile] = []
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        p = drv.read(timeout=0.2)
        if p is not None:
            out.append(p)
    assert len(out) == n, f"only {len(out)} of {n} profiles: {drv.health()}"
    return out


@pytest.fixture(params=BACKENDS, ids=str)
def backend(request: pytest.FixtureRequest) -> Backend:
    b: Backend = request.param
    return b


class TestProfileSensorConformance:
    """What every sensor driver does, whatever its wire format and transport."""

    def test_registry_loads_the_class_and_the_constructor_keeps_its_contract(
        self, backend: Backend
    ) -> None:
        assert registry.load("sensors", backend.driver) is backend.cls
        params = list(inspect.signature(backend.cls).parameters)
        assert params == CONTRACT[backend.cls]
        with pytest.raises(TypeError):
            backend.cls(no_such_option=1)  # type: ignore[call-arg]

    def test_open_close_idempotent_and_quiet_reads(self, backend: Backend) -> None:
        if backend.udp:
            drv = backend.make({})
            with drv:
                assert drv.open() is drv and drv.is_open
                # A quiet read waits its timeout, then returns None: not sooner (a lower bound,
                # which load cannot break); returning at all is the upper one (blocking for
                # good would end in the test's timeout), so no stopwatch bound on top.
                t0 = time.monotonic()
                assert drv.read(timeout=0.15) is None
                assert time.monotonic() - t0 >= 0.14
                h = drv.health()
                assert h.state is LinkState.OPEN and h.detail["stale"] is True
                assert h.detail["rcvbuf_bytes"] >= 65536
            drv.close()
            assert drv.health().state is LinkState.CLOSED
            with pytest.raises(DriverIOError):
                drv.read(timeout=0.01)
            return
        # Nothing listening: a stream driver refuses to open with a clear error. The port is
        # held (bound, not listening) so that no other process can listen there meanwhile.
        with RefusingPort() as refusing:
            ep = {
                "host": refusing.host,
                "port": refusing.port,
                "port_path": "/dev/wristscan-no-such-port",
            }
            drv = backend.make(ep)
            with pytest.raises(DriverInitError):
                drv.open()
        assert drv.health().state is LinkState.FAILED and not drv.is_open
        drv.close()  # closing a device that never opened is harmless

    def test_profiles_faults_reconnection_and_reboot(self, backend: Backend) -> None:
        # One simulator session for all (each start costs a second). latency_s: the simulator
        # stamps the first exposure after a reboot up to one loop period before its clock
        # restarts; a stamp before the restart would be negative.
        with running(backend, latency_s=0.25) as (drv, sim, cfg):
            assert drv.open() is drv  # already open: idempotent
            self._profiles_match_the_truth_and_faults_are_counted(backend, drv, sim, cfg)
            self._reconnects_after_the_link_drops_and_survives_a_reboot(backend, drv, sim, cfg)

    def _profiles_match_the_truth_and_faults_are_counted(
        self, backend: Backend, drv: Driver, sim: SimulatedSensor, cfg: SensorSimConfig
    ) -> None:
        truth = _truth(cfg, sim.info(), drv)
        clean = _read(drv, 30)
        counters = np.array([p.frame_counter for p in clean])
        assert np.all(np.diff(counters) == 1)
        for p in clean:
            assert p.sensor_id == cfg.sensor_id
            assert _check_profile(p, truth, backend), p.frame_counter
            assert 0 < p.host_time_ns <= time.monotonic_ns()
        v = clean[0].valid
        assert v.sum() > 0.3 * v.size
        if backend.scip:
            r = np.hypot(clean[0].y[v], clean[0].z[v])
            assert np.all((r >= cfg.scip_range_min_m) & (r <= cfg.scip_range_max_m))
            step_ms = np.diff([p.sensor_time_ns for p in clean]) / 1e6
            assert np.all(np.abs(step_ms - 1000 / cfg.rate_hz) <= 1)
            if drv.intensity:  # type: ignore[union-attr]
                assert clean[0].intensity is not None
                assert clean[0].intensity.shape == v.shape
        else:
            assert np.all(np.abs(clean[0].y) <= cfg.half_width_m + 1e-6)
            assert np.all((clean[0].z[v] >= cfg.z_min_m) & (clean[0].z[v] <= cfg.z_max_m))
            stamps = np.array([p.sensor_time_ns for p in clean])
            np.testing.assert_allclose(
                np.diff(stamps), 1e9 / cfg.rate_hz, atol=backend.stamp_tol_ns
            )
        if cfg.intensity and not backend.scip:
            assert clean[0].intensity is not None
            assert np.all(clean[0].intensity[v] > 0)
        h0 = drv.health()
        assert h0.state is LinkState.OPEN
        assert h0.counters.malformed == 0 and h0.counters.lost == 0
        assert h0.counters.received == 30

        sim.set_faults(drop=0.08, duplicate=0.08, reorder=0.05, truncate=0.05, corrupt=0.05)
        # Read until every kind of fault has shown (at least 150 profiles, 120 for SCIP): on a
        # loaded machine the reader can be far behind, and what it reads first is the backlog
        # sent before the faults were switched on.
        faulty: list[Profile] = []
        deadline = time.monotonic() + 60.0
        while True:
            faulty += _read(drv, 30)
            c = drv.health().counters
            enough = len(faulty) >= (150 if not backend.scip else 120)
            if enough and c.lost > 0 and c.duplicates > 0 and c.malformed > 0:
                break
            assert time.monotonic() < deadline, (c, sim.stats())
        sim.set_faults()
        stats = sim.stats()
        h = drv.health()
        c = h.counters
        got = np.array([p.frame_counter for p in faulty])
        assert np.all(np.diff(got) >= 1), "a duplicate or a late frame was delivered"
        assert c.received == 30 + len(faulty)
        bad = [p.frame_counter for p in faulty if not _check_profile(p, truth, backend)]
        if not backend.checksum:
            # No checksum: a flipped bit among the points cannot be seen (PROTOCOLS.md), but
            # never more profiles are off than bits were flipped, and the rest is sound.
            assert len(bad) <= stats["corrupted"]
            for p in faulty:
                assert p.y.shape == (cfg.n_points,) and p.valid.shape == p.y.shape
                assert np.all(np.isfinite(p.z[p.valid])) and np.all(np.isfinite(p.y))
        else:
            assert bad == [], "a damaged frame became a profile"

    def _reconnects_after_the_link_drops_and_survives_a_reboot(
        self, backend: Backend, drv: Driver, sim: SimulatedSensor, cfg: SensorSimConfig
    ) -> None:
        if backend.udp:
            drv.stale_after_s = 0.3  # type: ignore[union-attr]
        if backend.name.endswith("serial"):
            # A pty does not hang up when the device goes silent: silence is the drop.
            drv.silence_timeout_s = 0.5  # type: ignore[union-attr]
        prev = _read(drv, 10)[-1]
        lost0 = drv.health().counters.lost
        sim.disconnect(1.0)
        states = set()
        stale = False
        resumed: Profile | None = None
        # Until the first profile measured after the outage: the sensor's own clock jumps over
        # it (profiles queued from before come first, one period apart). Told by the device's
        # clock, not by when the test expects the sensor back, so a late test thread on a loaded
        # machine cannot mistake one for the other; how soon it comes is not asserted.
        deadline = time.monotonic() + 60.0
        while resumed is None:
            assert time.monotonic() < deadline, f"no profile after the outage: {drv.health()}"
            p = drv.read(timeout=0.05)  # never raises while the link is down
            h = drv.health()
            states.add(h.state)
            stale |= bool(h.detail.get("stale"))
            if p is not None:
                if p.sensor_time_ns - prev.sensor_time_ns > 0.5e9:
                    resumed = p
                prev = p
        h = drv.health()
        assert h.state is LinkState.OPEN
        # What the sensor measured while away shows as lost frames.
        assert h.counters.lost - lost0 >= 0.7 * cfg.rate_hz, h
        if backend.udp:
            assert stale and h.counters.reconnects == 0
        else:
            assert LinkState.RECONNECTING in states
            assert h.counters.reconnects == 1
        # A reboot restarts the device's counters and clock: the driver follows.
        restarts0 = h.detail.get("restarts", 0)
        sim.disconnect(0.6, reboot=True)
        t_reboot = time.monotonic()
        after: list[Profile] = []
        while len(after) < 10 and time.monotonic() < t_reboot + 60.0:
            p = drv.read(timeout=0.05)
            if p is None:
                continue
            if drv.health().detail.get("restarts", 0) > restarts0:
                after.append(p)  # profiles from before the reboot may still be queued
        h = drv.health()
        assert len(after) == 10, h
        assert h.detail["restarts"] == restarts0 + 1, h
        if not backend.scip:  # SCIP's counters are the driver's: they go on
            assert after[-1].frame_counter < resumed.frame_counter  # the device's restarted
        assert np.all(np.diff([p.frame_counter for p in after]) == 1)


# ----------------------------------------------------------------------------------------------
# Specific behaviour, with datagrams and streams made here (no simulator process)


def _lpf1_messages(n_prof: int, sensor_id: int = 7, start: int = 0, **kw: Any) -> list[bytes]:
    enc = lpf1.ProfileEncoder(sensor_id, x_uniform=(-0.02, 0.02 / 63), **kw)
    z = np.linspace(0.08, 0.12, 128)
    msgs = enc.encode(np.arange(start, start + n_prof), np.arange(n_prof) * 10**6,
                      np.tile(z, (n_prof, 1)), np.ones((n_prof, 128), bool))  # fmt: skip
    return [m for frags in msgs for m in frags]


def _drain(drv: Driver, timeout_s: float = 0.3) -> list[Profile]:
    out = []
    while (p := drv.read(timeout=timeout_s)) is not None:
        out.append(p)
    return out


def test_lpf1_udp_reassembles_fragments_and_filters_ids_and_sources(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.DEBUG, logger="wristscan.drivers.sensor_lpf1")
    drv = Lpf1UdpSensor(sensor_id=7, bind_host="127.0.0.1", port=0)
    with drv, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        assert drv.local_address is not None
        frags = _lpf1_messages(5, max_message_bytes=176)  # 256 payload bytes in 3 fragments
        assert len(frags) == 15
        order = [frags[i] for i in (2, 0, 1, 3, 4, 5, 8, 6, 7, 9, 10, 11, 12, 13, 14)]
        for m in order:
            tx.sendto(m, drv.local_address)
        for m in _lpf1_messages(3, sensor_id=8):  # another sensor on the same port
            tx.sendto(m, drv.local_address)
        tx.sendto(lpf1.encode_control(lpf1.MsgType.HEARTBEAT, 7, 4, 10), drv.local_address)
        tx.sendto(b"LPF1 garbage", drv.local_address)
        got = _drain(drv)
        h = drv.health()
    assert [p.frame_counter for p in got] == [0, 1, 2, 3, 4]
    assert all(p.n_points == 128 and p.sensor_id == 7 for p in got)
    np.testing.assert_allclose(got[0].z, np.linspace(0.08, 0.12, 128), atol=1e-6)
    assert h.detail["foreign"] == 3 and h.detail["heartbeats"] == 1
    assert h.counters.malformed == 1 and h.counters.lost == 0
    # The rejection is logged with the raw frames that came before it.
    (rec,) = [r for r in caplog.records if "frame rejected" in r.getMessage()]
    assert b"LPF1 garbage".hex() in rec.getMessage() and frags[-1][:256].hex() in rec.getMessage()

    drv = Lpf1UdpSensor(bind_host="127.0.0.1", port=0, source_host="127.0.0.2")
    with drv, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        assert drv.local_address is not None
        for m in _lpf1_messages(2):
            tx.sendto(m, drv.local_address)
        assert drv.read(timeout=0.2) is None
        assert drv.health().detail["foreign_source"] == 2


def test_udp_receipt_stamps_come_from_the_kernel_not_the_late_reader() -> None:
    """A reader that gets to the socket 80 ms after the datagram arrived still stamps the
    arrival (the sensor clock fit would otherwise see the delay as link jitter)."""
    drv = Lpf1UdpSensor(bind_host="127.0.0.1", port=0)
    with drv, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        assert drv.local_address is not None
        assert drv.health().detail["kernel_stamps"] is True
        sent_ns = []
        for m in _lpf1_messages(3):
            sent_ns.append(time.monotonic_ns())
            tx.sendto(m, drv.local_address)
        time.sleep(0.08)
        read_ns = time.monotonic_ns()
        got = _drain(drv)
    assert len(got) == 3
    stamps = np.array([p.host_time_ns for p in got])
    # Each stamp lies between its send and the next send (loopback delivers within the call).
    assert np.all(stamps >= np.array(sent_ns)) and np.all(stamps < read_ns - 70_000_000)
    assert np.all(np.diff(stamps) >= 0)


def test_lpf1_tcp_resynchronises_after_garbage_and_a_hello_announces_a_reboot() -> None:
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(1)
        drv = Lpf1TcpSensor("127.0.0.1", server.getsockname()[1])
        with drv:
            conn, _ = server.accept()
            with conn:
                msgs = _lpf1_messages(6, start=100)
                hello = lpf1.encode_control(lpf1.MsgType.HELLO, 7, 0, 0, {"model": "x"})
                # Garbage (with a false magic) between messages, a message cut short.
                stream = (msgs[0] + b"\x00LPF1\x01junk" + msgs[1] + msgs[2][:50] + msgs[3]
                          + hello + b"".join(_lpf1_messages(2, start=0)))  # fmt: skip
                conn.sendall(stream)
                got = _drain(drv)
                h = drv.health()
    assert [p.frame_counter for p in got] == [100, 101, 103, 0, 1]
    assert h.counters.malformed >= 2 and h.counters.lost == 1
    assert h.detail["restarts"] == 1 and h.detail["hello"] == {"model": "x"}


def test_rf627_rejects_header_damage_and_follows_a_counter_restart() -> None:
    enc = rf627.RF627Encoder(serial=42)
    n = 64
    x = np.linspace(-0.02, 0.02, n)
    z = np.full((30, n), 0.05)
    counts = np.r_[np.arange(1000, 1020), np.arange(0, 10)]
    times = np.r_[np.arange(20), np.arange(10)] * 1_000_000 + 5_000_000_000
    grams = enc.encode(counts, times, x, z, np.ones((30, n), bool))
    damaged = bytearray(grams[5])
    damaged[28] ^= 0x04  # zmr: the scaling of this packet changes
    late = bytearray(grams[8])
    late[24:28] = (1019 + 7000).to_bytes(4, "little")  # a wild counter
    drv = Rf627Sensor(sensor_id=42, bind_host="127.0.0.1", port=0)
    with drv, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        assert drv.local_address is not None
        for i, g in enumerate(grams):
            tx.sendto(bytes(damaged if i == 5 else late if i == 8 else g), drv.local_address)
        tx.sendto(grams[3][:-10], drv.local_address)  # truncated
        got = _drain(drv)
        h = drv.health()
    counters = [p.frame_counter for p in got]
    assert 5 + 1000 not in counters and 1019 + 7000 not in counters
    assert counters[:5] == [1000, 1001, 1002, 1003, 1004]
    # After the restart (one packet held back to confirm it) the new counters flow.
    assert counters[-9:] == list(range(1, 10))
    assert h.counters.malformed == 4  # header, counter, truncated, the restart's first packet
    assert h.detail["restarts"] == 1
    assert all(np.allclose(p.z, 0.05, atol=4e-6) for p in got)


def test_scip_driver_rejects_bad_steps_before_connecting() -> None:
    with pytest.raises(DriverInitError):
        ScipSensor("socket://127.0.0.1:1", start_step=10, end_step=5)
    with pytest.raises(DriverInitError):
        ScipSensor("socket://127.0.0.1:1", cluster=0)


def _wait_until_in(thread: threading.Thread, function: str, timeout_s: float = 30.0) -> None:
    """Wait until ``thread`` runs ``function`` (somewhere down its stack)."""
    deadline = time.monotonic() + timeout_s
    while True:
        frame = sys._current_frames().get(thread.ident or -1)
        while frame is not None:
            if frame.f_code.co_name == function:
                return
            frame = frame.f_back
        assert time.monotonic() < deadline, f"{thread.name} never reached {function}"
        time.sleep(0.01)


def test_close_from_another_thread_ends_a_blocking_read() -> None:
    """The daemon's reader thread blocks in read(); closing the driver must release it."""
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(1)
        drivers: list[Driver] = [
            Lpf1UdpSensor(bind_host="127.0.0.1", port=0),
            Lpf1TcpSensor("127.0.0.1", server.getsockname()[1]),
        ]
        for drv in drivers:
            drv.open()
            results: list[object] = []
            t = threading.Thread(target=lambda d=drv, r=results: r.append(d.read(timeout=None)))
            t.start()
            _wait_until_in(t, "_read_internal")  # in the driver's read (a sleep could be short)
            drv.close()
            t.join(30.0)  # generous: released at once, but the thread may wait for a CPU
            assert not t.is_alive() and results == [None]
            assert drv.health().state is LinkState.CLOSED
