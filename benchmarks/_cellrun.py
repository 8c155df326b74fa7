"""The daemon on the simulated cell, for benchmarks: the cell in this process's children,
``wristscan run`` as a subprocess with a systemd notify socket (every message kept), and a WSC1
subscriber in this process that keeps each batch's arrival, sequence number, last exposure and
profile count (:func:`running`). Used by ``benchmarks/faults.py``."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from array import array
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from pipeline import _Notify, _set_session_nice

TARGET_XY = (0.45, 0.0)
"""Table-top point the sensor looks at from 0.1 m: clear of the ball and the platter, so that
every point of a profile is valid."""


class Batches:
    """The subscriber: per batch its arrival (host monotonic ns), sequence number, last exposure
    (the daemon's UTC estimate turned into host monotonic ns) and profile count."""

    def __init__(self) -> None:
        from wristscan.daemon.cloud import wsc1

        self._head = wsc1.HEADER
        self.lock = threading.Lock()
        self.cols = (array("q"), array("q"), array("q"), array("q"))

    def __call__(self, sample: Any) -> None:
        now = time.monotonic_ns()
        utc_offset = time.time_ns() - now
        head = self._head.unpack_from(sample.payload.to_bytes())
        with self.lock:
            for col, v in zip(
                self.cols, (now, head[3], head[5] - utc_offset, head[7]), strict=True
            ):
                col.append(int(v))

    def rows(self) -> np.ndarray:
        """``(K, 4)``: arrival, seq, last exposure, profiles."""
        with self.lock:
            return np.stack([np.frombuffer(c, dtype=np.int64).copy() for c in self.cols], axis=1)

    def last_arrival(self) -> int:
        with self.lock:
            return int(self.cols[0][-1]) if len(self.cols[0]) else 0

    def wait_fresh(self, t_ns: int, timeout_s: float) -> int | None:
        """Arrival of the first batch exposed after ``t_ns`` (waiting up to ``timeout_s``)."""
        deadline = time.monotonic() + timeout_s
        while True:
            r = self.rows()
            hit = np.flatnonzero((r[:, 0] >= t_ns) & (r[:, 2] >= t_ns))
            if hit.size:
                return int(r[hit[0], 0])
            if time.monotonic() > deadline:
                return None
            time.sleep(0.01)


class Notes(_Notify):
    """The systemd side of sd_notify, keeping every message after READY with its arrival."""

    def __init__(self, path: Path) -> None:
        super().__init__(path)
        self.messages: list[tuple[int, str]] = []

    def _drain(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096).decode(errors="replace")
            except TimeoutError:
                continue
            except OSError:
                return
            self.messages.append((time.monotonic_ns(), data))

    def first(self, needle: str, since_ns: int, timeout_s: float) -> int | None:
        """Arrival of the first message at or after ``since_ns`` holding ``needle``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for t, m in list(self.messages):
                if t >= since_ns and needle in m:
                    return t
            time.sleep(0.01)
        return None

    def any_between(self, needle: str, t0: int, t1: int) -> bool:
        return any(t0 <= t <= t1 and needle in m for t, m in list(self.messages))


@dataclass
class CellRun:
    """A running cell, daemon and subscriber."""

    cell: Any
    daemon: subprocess.Popen[bytes]
    client: Any
    batches: Batches
    doc: dict[str, Any]
    cfg_path: Path
    log_path: Path
    port: int
    notes: Notes
    sub: Any = None

    def stats(self) -> dict[str, Any]:
        result: dict[str, Any] = self.client.query("stats", timeout=10.0)
        return result

    def log_text(self, offset: int = 0) -> str:
        with open(self.log_path, "rb") as fh:
            fh.seek(offset)
            return fh.read().decode(errors="replace")

    def log_size(self) -> int:
        return self.log_path.stat().st_size

    def cell_pids(self, which: tuple[str, ...] = ("controller", "sensor")) -> list[int]:
        pids = []
        for name in which:
            proc = getattr(getattr(self.cell, name), "_proc", None)
            if proc is not None and proc.pid is not None:
                pids.append(int(proc.pid))
        return pids

    def wait_flowing(self, timeout_s: float = 30.0) -> None:
        """Until batches arrive steadily (the last one under 0.2 s ago)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic_ns() - self.batches.last_arrival() > 200_000_000:
            if self.daemon.poll() is not None:
                raise RuntimeError(f"the daemon exited with {self.daemon.returncode}")
            if time.monotonic() > deadline:
                raise RuntimeError("no batches flow")
            time.sleep(0.05)

    def stop_daemon(self) -> int:
        """SIGTERM; the exit code (the subscriber stays up to receive the drained batches)."""
        self.daemon.send_signal(signal.SIGTERM)
        code = self.daemon.wait(60)
        time.sleep(0.5)  # the last batches on their way
        return code


def write_config(run_doc: dict[str, Any], path: Path) -> None:
    from wristscan.daemon.simcell.cell import dump_toml

    path.write_text(dump_toml(run_doc))


def aim_at_table(cell: Any, cfg: Any) -> None:
    """The arm to where the sensor looks down at the table top from 0.1 m."""
    from wristscan.calib import kinematics, se3
    from wristscan.drivers.sim.scene import sensor_looking_down

    s2f = np.array(cell.truth()["sensor2flange"])
    flange = sensor_looking_down(np.array([*TARGET_XY, 0.0]), 0.10) @ se3.invert(s2f)
    q0 = np.array(cell.controller.state()["q"])
    q = kinematics.inverse_nearest(cfg.robot.model, flange, q0)
    if not cell.controller.set_joint_positions(q.tolist()):
        raise RuntimeError("the simulated robot refused the measuring pose")


@contextlib.contextmanager
def running(
    tmp: Path,
    rate_hz: float,
    n_points: int,
    nice: int | None,
    congestion: str | None = None,
    pipeline: dict[str, Any] | None = None,
    sim_sensor: dict[str, Any] | None = None,
    on_daemon: Callable[[int], None] | None = None,
) -> Iterator[CellRun]:
    """Start the cell, the daemon (until READY and batches flow) and the subscriber.
    ``congestion``: the daemon's ``[zenoh] congestion_control`` (None: the default, drop);
    ``pipeline``, ``sim_sensor``: more ``[pipeline]`` and ``[sim.sensor]`` settings;
    ``on_daemon``: called with the daemon's pid as soon as it is spawned."""
    from wristscan.daemon.cloud.client import CloudClient
    from wristscan.daemon.config import load_config
    from wristscan.daemon.simcell.cell import free_sim_config, start_cell, write_truth_calibrations

    doc = free_sim_config(
        {
            "calibration": {"file": "sensor2flange.json"},
            "sim.sensor": {
                "rate_hz": float(rate_hz),
                "n_points": int(n_points),
                **(sim_sensor or {}),
            },
            "sim.table": {"enabled": False},  # clouds in the base frame: no table needed
            **({"pipeline": pipeline} if pipeline else {}),
        }
    )
    doc.pop("table", None)
    if congestion is not None:
        doc["zenoh"]["congestion_control"] = congestion
    cfg_path = tmp / "cell.toml"
    write_config(doc, cfg_path)
    cfg = load_config(cfg_path)
    cell = start_cell(cfg)
    notify = Notes(tmp / "notify.sock")
    log_path = tmp / "daemon.log"
    daemon: subprocess.Popen[bytes] | None = None
    client = None
    try:
        write_truth_calibrations(cfg, cell.truth())
        aim_at_table(cell, cfg)
        env = dict(os.environ, NOTIFY_SOCKET=str(notify.path))
        for k in ("WATCHDOG_USEC", "WATCHDOG_PID"):
            env.pop(k, None)
        with open(log_path, "w") as log_fh:
            daemon = subprocess.Popen(
                [sys.executable, "-m", "wristscan.daemon.cli", "run", "--config", str(cfg_path)],
                env=env,
                stdin=subprocess.DEVNULL,
                stdout=log_fh,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # its own scheduling entity, as under systemd
            )
        if on_daemon is not None:
            on_daemon(daemon.pid)
        if nice is not None:
            _set_session_nice(daemon.pid, nice)
        try:
            notify.wait_ready(90.0, daemon)
        except RuntimeError as exc:
            tail = log_path.read_text(errors="replace").strip().splitlines()[-5:]
            raise RuntimeError(f"{exc}; daemon log ends: {' | '.join(tail)}") from None
        endpoint = cfg.zenoh.listen[0]
        client = CloudClient(cfg.zenoh.prefix, connect=[endpoint], subscribe=False)
        batches = Batches()
        sub = client.session.declare_subscriber(f"{cfg.zenoh.prefix}/cloud", batches)
        port = int(cfg.sensor.options.port)  # type: ignore[union-attr]  # the cell's UDP sensor
        run = CellRun(cell, daemon, client, batches, doc, cfg_path, log_path, port, notify, sub=sub)
        run.wait_flowing(60.0)
        yield run
    finally:
        if daemon is not None and daemon.poll() is None:
            daemon.send_signal(signal.SIGTERM)
            try:
                daemon.wait(30)
            except subprocess.TimeoutExpired:
                daemon.kill()
                daemon.wait()
        if client is not None:
            client.close()
        cell.stop()
        notify.close()


@contextlib.contextmanager
def own_nice(nice: int | None) -> Iterator[None]:
    """This process (the simulated cell, started after) at ``nice``, restored at the end."""
    if nice is None:
        yield
        return
    own = Path("/proc/self/autogroup")
    saved = int(own.read_text().split()[-1]) if own.exists() else None
    _set_session_nice(os.getpid(), nice)
    try:
        yield
    finally:
        os.setpriority(os.PRIO_PROCESS, 0, 0)
        if saved is not None:
            own.write_text(str(saved))
