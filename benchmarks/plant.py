"""Plant benchmark (issue 22): three simulated cells through one zenoh router to one consumer.

Each cell is the simulated cell on a loopback address of its own (UR5e still, the sensor 0.1 m
above the table top so every point is valid, ``rate_hz`` x ``n_points``) with ``wristscan run``
as a subprocess in zenoh client mode towards the router, prefix ``wristscan/cell<k>``. The
router is a Python zenoh session in router mode in a process of its own (zenohd's stand-in);
the consumer, in this process, is a client session on the router subscribed to
``wristscan/*/cloud``. After every cell publishes and ``warmup_s`` more, a window of
``duration_s`` is measured:

* lost = batches missing between the sequence numbers the consumer received, per cell (lost on
  the way through the router), plus profiles the daemons dropped in the window (their ``stats``);
* latency per batch: the consumer's receipt (UTC) minus the daemon's estimate of the batch's last
  exposure (``t_last_ns``, UTC): exposure to the plant consumer through the router; p50, p99;
* CPU: the router process and each daemon (``/proc/<pid>/stat``, utime + stime), % of one core.

``wristscan cells`` through the router must list the three cells. Targets: 0 lost, p99 <= 20 ms,
three cells listed. Run: ``.venv/bin/python benchmarks/plant.py [--duration 20] [--rate 1000]
[--json out.json]``; exits 1 on a miss. Figures: docs/plant.md.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import Figure, report

CELLS = 3
P99_TARGET_MS = 20.0
TARGET_XY = (0.45, 0.0)
ROUTER_CODE = (
    "import sys, zenoh\n"
    "from wristscan.daemon.cloud.zenoh_io import open_session\n"
    "s = open_session('router', listen=[sys.argv[1]])\n"
    "print('ready', flush=True)\n"
    "sys.stdin.read()\n"
    "s.close()\n"
)


def _cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class _Consumer:
    """Counts each cell's batches, profiles, sequence gaps and latencies."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.recording = False
        self.seqs: dict[str, list[int]] = {}
        self.latency_ns: list[int] = []
        self.profiles: dict[str, int] = {}

    def __call__(self, sample: Any) -> None:
        from wristscan.daemon.cloud import wsc1

        now = time.time_ns()
        head = wsc1.HEADER.unpack_from(sample.payload.to_bytes())
        prefix = str(sample.key_expr).rsplit("/", 1)[0]
        seq, t_last, n_prof = int(head[3]), int(head[5]), int(head[7])
        with self.lock:
            self.seqs.setdefault(prefix, []).append(seq)
            if self.recording:
                self.latency_ns.append(now - t_last)
                self.profiles[prefix] = self.profiles.get(prefix, 0) + n_prof


def _start_cell(k: int, router: str, rate_hz: float, n_points: int, tmp: Path) -> Any:
    from wristscan.calib import kinematics, se3
    from wristscan.daemon.config import load_config
    from wristscan.daemon.simcell.cell import (
        dump_toml,
        free_sim_config,
        start_cell,
        write_truth_calibrations,
    )
    from wristscan.drivers.sim.scene import sensor_looking_down

    doc = free_sim_config(
        {
            "cell": {"name": f"cell{k}"},
            "calibration": {"file": f"s2f{k}.json"},
            "zenoh": {
                "mode": "client",
                "connect": [router],
                "listen": [],
                "prefix": f"wristscan/cell{k}",
            },
            "sim.sensor": {"rate_hz": float(rate_hz), "n_points": int(n_points)},
            "sim.table": {"enabled": False},
        }
    )
    doc.pop("table", None)
    path = tmp / f"cell{k}.toml"
    path.write_text(dump_toml(doc))
    cfg = load_config(path)
    cell = start_cell(cfg)
    truth = cell.truth()
    write_truth_calibrations(cfg, truth)
    s2f = np.array(truth["sensor2flange"])
    assert cell.controller is not None
    flange = sensor_looking_down(np.array([*TARGET_XY, 0.0]), 0.10) @ se3.invert(s2f)
    q0 = np.array(cell.controller.state()["q"])
    if not cell.controller.set_joint_positions(
        kinematics.inverse_nearest(cfg.robot.model, flange, q0).tolist()
    ):
        raise RuntimeError(f"cell {k}: the simulated robot refused the measuring pose")
    log = open(tmp / f"daemon{k}.log", "w")
    daemon = subprocess.Popen(
        [sys.executable, "-m", "wristscan.daemon.cli", "run", "--config", str(path)],
        stdin=subprocess.DEVNULL,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    return cell, daemon, log


def _stats(session: Any) -> dict[str, dict[str, Any]]:
    out = {}
    for reply in session.get("wristscan/**/stats", timeout=5.0):
        if reply.ok is not None:
            out[str(reply.ok.key_expr).rsplit("/", 1)[0]] = json.loads(reply.ok.payload.to_string())
    return out


def _dropped(st: dict[str, Any]) -> int:
    return sum(int(n) for n in dict(st.get("dropped", {})).values())


def measure(rate_hz: float, n_points: int, duration_s: float, warmup_s: float) -> dict[str, Any]:
    from support import free_tcp_port, own_loopback_host

    from wristscan.daemon.cloud.cells import list_cells
    from wristscan.daemon.cloud.zenoh_io import open_session

    host = own_loopback_host()
    router_ep = f"tcp/{host}:{free_tcp_port(host)}"
    router = subprocess.Popen(
        [sys.executable, "-c", ROUTER_CODE, router_ep],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    cells: list[tuple[Any, subprocess.Popen[bytes], Any]] = []
    consumer = None
    with tempfile.TemporaryDirectory(prefix="wristscan-plant-") as tmp_s:
        tmp = Path(tmp_s)
        try:
            assert router.stdout is not None
            if router.stdout.readline().strip() != "ready":
                raise RuntimeError("the router did not start")
            for k in range(1, CELLS + 1):
                cells.append(_start_cell(k, router_ep, rate_hz, n_points, tmp))
            consumer = open_session("client", connect=[router_ep])
            counts = _Consumer()
            sub = consumer.declare_subscriber("wristscan/*/cloud", counts)
            deadline = time.monotonic() + 90
            while True:
                st = _stats(consumer)
                if len(st) == CELLS and all(s["published"] > 0 for s in st.values()):
                    break
                if time.monotonic() > deadline or any(d.poll() is not None for _, d, _ in cells):
                    logs = [(tmp / f"daemon{k}.log").read_text()[-300:] for k in (1, 2, 3)]
                    raise RuntimeError(f"the cells did not all publish: {st}; logs: {logs}")
                time.sleep(0.5)
            time.sleep(warmup_s)
            listed = [c.prefix for c in list_cells(consumer, "wristscan")]
            st_a = _stats(consumer)
            cpu_a = [_cpu_s(router.pid)] + [_cpu_s(d.pid) for _, d, _ in cells]
            with counts.lock:
                counts.seqs.clear()
                counts.recording = True
            t_a = time.monotonic()
            time.sleep(duration_s)
            with counts.lock:
                counts.recording = False
            wall = time.monotonic() - t_a
            cpu_b = [_cpu_s(router.pid)] + [_cpu_s(d.pid) for _, d, _ in cells]
            st_b = _stats(consumer)
            sub.undeclare()
        finally:
            if consumer is not None:
                consumer.close()
            for cell, daemon, log in cells:
                daemon.terminate()
                try:
                    daemon.wait(20)
                except subprocess.TimeoutExpired:
                    daemon.kill()
                    daemon.wait()
                log.close()
                cell.stop()
            if router.stdin is not None:
                router.stdin.close()
            router.wait(20)
    gaps = {p: int(np.sum(np.diff(np.array(s)) - 1)) for p, s in counts.seqs.items() if s}
    dropped = {p: _dropped(st_b[p]) - _dropped(st_a[p]) for p in st_b if p in st_a}
    lat_ms = np.array(counts.latency_ns, float) / 1e6
    cpu = [(b - a) / wall * 100 for a, b in zip(cpu_a, cpu_b, strict=True)]
    return {
        "listed": listed,
        "gaps": gaps,
        "dropped": dropped,
        "profiles": dict(counts.profiles),
        "latency_p50_ms": float(np.percentile(lat_ms, 50)) if lat_ms.size else float("nan"),
        "latency_p99_ms": float(np.percentile(lat_ms, 99)) if lat_ms.size else float("nan"),
        "router_cpu_pct": cpu[0],
        "daemon_cpu_pct": cpu[1:],
        "wall_s": wall,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--warmup", type=float, default=3.0)
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--points", type=int, default=2048)
    ap.add_argument("--json")
    ns = ap.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
    r = measure(ns.rate, ns.points, ns.duration, ns.warmup)
    lost = sum(r["gaps"].values()) + sum(r["dropped"].values())
    rate = sum(r["profiles"].values()) / r["wall_s"]
    figs = [
        Figure(
            "cells listed by `wristscan cells`",
            len(r["listed"]),
            "",
            f"== {CELLS}",
            len(r["listed"]) == CELLS,
        ),
        Figure("profiles/s at the consumer (all cells)", rate, "1/s", "info", None),
        Figure("lost (seq gaps + daemon drops)", lost, "", "== 0", lost == 0),
        Figure("latency p50 (exposure -> consumer)", r["latency_p50_ms"], "ms", "info", None),
        Figure(
            "latency p99 (exposure -> consumer)",
            r["latency_p99_ms"],
            "ms",
            f"<= {P99_TARGET_MS:g}",
            r["latency_p99_ms"] <= P99_TARGET_MS,
        ),
        Figure("router CPU", r["router_cpu_pct"], "% core", "info", None),
    ]
    for k, c in enumerate(r["daemon_cpu_pct"], 1):
        figs.append(Figure(f"daemon cell{k} CPU", c, "% core", "info", None))
    title = f"plant: {CELLS} cells x {ns.rate:g} Hz x {ns.points} points through one router"
    return report(title, figs, ns.json)


if __name__ == "__main__":
    sys.exit(main())
