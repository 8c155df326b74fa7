"""``wristscan run`` as an operator meets it, on the simulated cell: started before the controller
is up (it waits, says so, pings the watchdog, comes up once the cell does), a reload whose zenoh
endpoint is taken (refused in one line, the old configuration keeps publishing), a reload that
moves the sensor to another port (the WSC1 sequence and the counters go on: a real subscriber
sees every batch), a sensor outage (logged once when it starts and once when it ends, shown in
STATUS) and the final counters at exit, which must match what the subscriber received."""

from __future__ import annotations

import dataclasses
import itertools
import json
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

from wristscan.daemon.cloud.scans import fetch_jobs
from wristscan.daemon.cloud.zenoh_io import open_session
from wristscan.daemon.config import load_config
from wristscan.daemon.io.archive import ScanArchive
from wristscan.daemon.simcell.cell import (
    dump_toml,
    free_sim_config,
    start_cell,
    write_truth_calibrations,
)
from wristscan.drivers.sim.sensors import SimulatedSensor

RETRY_MAX_S = 1.0
"""The longest delay between two attempts to open a missing device in these tests."""


class Notifications:
    """The systemd side of sd_notify: a real AF_UNIX datagram socket, read by a thread (so that
    the daemon's notifications never wait for the test), every message kept with its time."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.1)
        self.messages: list[tuple[float, str]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65536).decode()
            except TimeoutError:
                continue
            with self._lock:
                self.messages.append((time.monotonic(), data))

    def since(self, t0: float) -> list[str]:
        with self._lock:
            return [m for t, m in self.messages if t >= t0]

    def wait_for(self, needle: str, timeout: float, since: float = 0.0) -> float:
        """The arrival time of the first message at or after ``since`` containing ``needle``."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                for t, m in self.messages:
                    if t >= since and needle in m:
                        return t
            time.sleep(0.02)
        raise AssertionError(f"no {needle!r} from the daemon; got {self.since(since)[-20:]}")

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.sock.close()


class Batches:
    """A real zenoh subscriber of ``<prefix>/cloud`` and ``<prefix>/status``: the sequence
    number and profile count of every WSC1 batch (read from the documented 64-byte header)."""

    def __init__(self, endpoint: str, prefix: str) -> None:
        self.session = open_session(connect=[endpoint])
        self.seqs: list[int] = []
        self.profiles: dict[int, int] = {}
        self.arrivals: list[float] = []
        self.statuses: list[dict[str, Any]] = []
        self._subs = [
            self.session.declare_subscriber(f"{prefix}/cloud", self._on_cloud),
            self.session.declare_subscriber(f"{prefix}/status", self._on_status),
        ]

    def _on_cloud(self, sample: zenoh.Sample) -> None:
        magic, _version, _flags, seq, _t0, _t1, _n, n_profiles = struct.unpack_from(
            "<4sHHQqqII", sample.payload.to_bytes(), 0
        )
        assert magic == b"WSC1"
        self.seqs.append(seq)
        self.profiles[seq] = n_profiles
        self.arrivals.append(time.monotonic())

    def _on_status(self, sample: zenoh.Sample) -> None:
        self.statuses.append(json.loads(sample.payload.to_string()))

    def wait(self, what: Callable[[], bool], timeout: float, message: str) -> None:
        deadline = time.monotonic() + timeout
        while not what():
            assert time.monotonic() < deadline, message
            time.sleep(0.05)

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self.session.close()


def _write(path: Path, doc: dict[str, Any], **changes: dict[str, Any]) -> None:
    doc = json.loads(json.dumps(doc))
    for section, values in changes.items():
        node = doc
        for part in section.split("."):
            node = node[part]
        node.update(values)
    path.write_text(dump_toml(doc))


def _run(cfg_path: Path, env: dict[str, str] | None = None, **kw: Any) -> Any:
    cmd = [sys.executable, "-m", "wristscan.daemon.cli", "run", "--config", str(cfg_path)]
    return subprocess.Popen(cmd, env=env, text=True, **kw)


def _taken_endpoint(host: str) -> tuple[socket.socket, str]:
    """A TCP port on ``host`` that something else holds: zenoh cannot listen there."""
    holder = socket.socket()
    holder.bind((host, 0))
    holder.listen()
    return holder, f"tcp/{host}:{holder.getsockname()[1]}"


def _free_udp_port(host: str) -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _no_gap(seqs: list[int]) -> None:
    assert seqs, "no batch received"
    s = sorted(seqs)
    assert len(set(s)) == len(s), "a batch arrived twice"
    missing = sorted(set(range(s[0], s[-1] + 1)) - set(s))
    assert not missing, f"{len(missing)} batches never arrived, first {missing[:5]}"


def test_run_waits_for_the_cell_reloads_and_reports(tmp_path: Path) -> None:
    doc = free_sim_config(
        {
            "calibration": {"file": "s2f.json"},
            "service": {
                "wait_for_devices_s": 120.0,
                "retry_initial_s": 0.1,
                "retry_max_s": RETRY_MAX_S,
                "outage_after_s": 1.0,
            },
            # Every batch must arrive: "drop" sheds batches by design under load.
            "zenoh": {"status_period_s": 0.5, "congestion_control": "block"},
            # Light enough for two simulated sensors at once on a 2-core machine.
            "sim.sensor": {"rate_hz": 500.0, "n_points": 256},
            "archive": {"enabled": True, "dir": str(tmp_path / "scans")},
        }
    )
    report = tmp_path / "report.json"
    report.write_text('{"passes": 6}')
    ScanArchive(tmp_path / "scans").add("20260101T000000Z-part", {"report.json": report})
    cfg_path = tmp_path / "cell.toml"
    cfg_path.write_text(dump_toml(doc))
    cfg = load_config(cfg_path)
    write_truth_calibrations(cfg)
    host = cfg.robot.host
    endpoint = cfg.zenoh.listen[0]
    log_path = tmp_path / "daemon.log"
    notes = Notifications(tmp_path / "notify.sock")
    env = dict(os.environ, NOTIFY_SOCKET=str(notes.path), WATCHDOG_USEC="3000000")
    env.pop("WATCHDOG_PID", None)
    holder, taken = _taken_endpoint(host)
    daemon = cell = sensor2 = batches = None
    try:
        with log_path.open("w") as log_file:
            daemon = _run(cfg_path, env, stdout=log_file, stderr=subprocess.STDOUT)

        # 1. No controller yet: it waits, says what for, pings the watchdog, is not READY.
        t_wait = notes.wait_for("STATUS=waiting for robot", timeout=60)
        batches = Batches(endpoint, cfg.zenoh.prefix)  # zenoh is up before the devices
        # the scan archive is served from the start too
        jobs = fetch_jobs(batches.session, cfg.zenoh.prefix)
        assert [j["job"] for j in jobs] == ["20260101T000000Z-part"]
        notes.wait_for("WATCHDOG=1", timeout=10, since=t_wait)
        batches.wait(
            lambda: any(s.get("state") == "waiting" for s in batches.statuses),
            20,
            "no 'waiting' status message on zenoh",
        )
        waiting = next(s for s in batches.statuses if s.get("state") == "waiting")
        assert waiting["waiting_for"] == "robot" and "connection refused" in waiting["error"]
        shown = subprocess.run(
            [sys.executable, "-m", "wristscan.daemon.cli", "status", "--config", str(cfg_path)],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert shown.returncode == 0, shown.stdout + shown.stderr
        assert re.search(r"state +waiting: waiting for robot for \d+ s", shown.stdout), shown.stdout
        assert not any("READY=1" in m for m in notes.since(0)) and daemon.poll() is None

        # 2. The cell comes up: the daemon is READY within the backoff.
        t_start = time.monotonic()
        cell = start_cell(cfg)  # the controller first, then the table and the sensor
        t_cell = time.monotonic()
        t_ready = notes.wait_for("READY=1", timeout=30)
        print(
            f"READY {t_ready - t_start:.2f} s after the cell began to start, "
            f"{t_ready - t_cell:+.2f} s after it was all up (retry_max_s {RETRY_MAX_S})"
        )
        assert t_ready - t_cell < RETRY_MAX_S + 5.0, t_ready - t_cell
        batches.wait(lambda: len(batches.seqs) > 50, 30, "no batches after READY")

        # 3. A reload whose zenoh endpoint is taken: refused in one line, the old one publishes.
        _write(cfg_path, doc, zenoh={"listen": [taken]})
        daemon.send_signal(signal.SIGHUP)
        t_bad = notes.wait_for("STATUS=reload ", timeout=30)  # failed (or refused by a check)
        n = len(batches.seqs)
        batches.wait(lambda: len(batches.seqs) > n + 50, 20, "publishing stopped")
        assert not any("READY=1\nSTATUS=running (reloaded)" in m for m in notes.since(t_bad))

        # 3b. One whose sensor port is taken: the old devices are opened again and publish.
        udp_holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        udp_holder.bind((host, 0))
        udp_taken = udp_holder.getsockname()[1]
        try:
            _write(cfg_path, doc, **{"sensor.options": {"port": udp_taken}})
            t_bad2 = time.monotonic()
            daemon.send_signal(signal.SIGHUP)
            notes.wait_for("reload failed", timeout=30, since=t_bad2)
        finally:
            udp_holder.close()
        n = len(batches.seqs)
        batches.wait(lambda: len(batches.seqs) > n + 50, 30, "publishing stopped")

        # 4. A reload that moves the sensor to another port (a second simulated sensor sends
        #    there): the sequence and the counters go on.
        assert cell.sensor is not None and cell.robot_ring is not None
        port2 = _free_udp_port(host)
        sensor2 = SimulatedSensor(
            dataclasses.replace(cell.sensor.config, target=(host, port2)),
            cell.scene,
            robot_ring=cell.robot_ring.name,
            table_ring=cell.table_ring.name if cell.table_ring is not None else None,
        ).start()
        _write(cfg_path, doc, **{"sensor.options": {"port": port2}})
        t_hup = time.monotonic()
        daemon.send_signal(signal.SIGHUP)
        notes.wait_for("running (reloaded)", timeout=30, since=t_hup)
        n = len(batches.seqs)
        batches.wait(lambda: len(batches.seqs) > n + 100, 20, "nothing after the reload")
        t = list(batches.arrivals)
        pause = max(b - a for a, b in itertools.pairwise(t) if b > t_hup)
        print(f"longest pause in publication around the sensor reload: {pause:.2f} s")
        sent_before = sensor2.stats()["profiles_sent"]
        batches.wait(lambda: len(batches.seqs) > n + 150, 20, "nothing after the reload")
        assert sensor2.stats()["profiles_sent"] > sent_before  # what flows comes from port2

        # 5. A sensor outage: seen in STATUS while it lasts.
        t_out = time.monotonic()
        sensor2.disconnect(2.5)
        notes.wait_for("STATUS=degraded: no profiles for", timeout=10, since=t_out)
        batches.wait(
            lambda: any(
                s.get("state") == "degraded" and "no profiles for" in s["degraded"][0]
                for s in batches.statuses[-3:]
            ),
            5,
            "no 'degraded' status message on zenoh",
        )
        t_back = notes.wait_for("STATUS=running:", timeout=15, since=t_out + 2.0)
        assert t_back - t_out > 2.0

        # 6. SIGTERM: drained, final counters logged; everything counted as published arrived.
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(timeout=30) == 0
        time.sleep(0.3)
    finally:
        for proc in (daemon,):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
        for part in (batches, sensor2, cell):
            if part is not None:
                part.close() if isinstance(part, Batches) else part.stop()
        holder.close()
        notes.close()
    log = log_path.read_text()
    print(log[-3000:])
    assert "Traceback" not in log
    assert "pipeline not progressing" not in log
    # the refused reloads: one error line each, naming the endpoint, the port
    refused = [ln for ln in log.splitlines() if re.search(r"reload (failed|refused)", ln)]
    assert len(refused) == 2, refused
    assert taken.split("/")[1] in refused[0] and f":{udp_taken}" in refused[1], refused
    assert re.search(r"reloaded: sensor\.options\.port \d+ -> " + str(port2), log)
    # each outage logged once as it starts and once as it ends, the disconnection among them
    starts = re.findall(r"WARNING .*sensor outage: no profiles for", log)
    ends = [float(x) for x in re.findall(r"WARNING .*sensor outage over after (\d+\.\d) s", log)]
    assert len(starts) == len(ends) >= 1 and max(ends) >= 1.5, (starts, ends)
    _no_gap(batches.seqs)
    assert min(batches.seqs) == 0
    m = re.search(r"final counters: received (\d+) = published (\d+) .*?; (\d+) batches", log)
    assert m is not None, "no final counters at exit"
    published, n_batches = int(m.group(2)), int(m.group(3))
    assert n_batches == len(batches.seqs) == max(batches.seqs) + 1
    assert published == sum(batches.profiles.values())
    assert re.search(rf"1 reloads \(2 failed\); outages: sensor {len(ends)} \(\d", log)


def test_run_gives_up_waiting_and_refuses_a_taken_endpoint(tmp_path: Path) -> None:
    """With a limit and no cell, one clear line and exit 1; a zenoh endpoint that something
    else holds, one clear line and exit 1 before any device is tried."""
    doc = free_sim_config(
        {"calibration": {"file": "s2f.json"}, "service": {"wait_for_devices_s": 1.0}}
    )
    cfg_path = tmp_path / "cell.toml"
    cfg_path.write_text(dump_toml(doc))
    write_truth_calibrations(load_config(cfg_path))
    t0 = time.monotonic()
    out = _run(cfg_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    text, _ = out.communicate(timeout=60)
    print(f"gave up after {time.monotonic() - t0:.1f} s (Python start included)")
    assert out.returncode == 1, text
    assert "Traceback" not in text
    assert re.search(r"cannot start: robot not available for \d s: .*connection refused", text)

    holder, taken = _taken_endpoint(load_config(cfg_path).robot.host)
    try:
        _write(cfg_path, doc, zenoh={"listen": [taken]})
        out = _run(cfg_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        text, _ = out.communicate(timeout=60)
    finally:
        holder.close()
    assert out.returncode == 1, text
    assert "Traceback" not in text
    errors = [ln for ln in text.splitlines() if "cannot start" in ln]
    assert len(errors) == 1 and taken.split("/")[1] in errors[0], text
    assert "waiting for" not in text  # zenoh first: no device was tried
