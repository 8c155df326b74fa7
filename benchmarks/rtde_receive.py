"""UR robot receive path: the native RTDE client against ur_rtde, idle and with the CPU busy.

For each receive backend of :class:`~wristscan.drivers.ur.robot.URRobot` (``native``,
``ur_rtde``) and each load (``idle``; ``hog``: one busy-loop process per core, at this
process's priority, for the whole window) a ``--duration`` window (default 10 s) of the 500 Hz
stream of a simulated UR5e controller (its own process, fresh per run) is read through the
driver, and measured:

* samples lost: the driver's ``lost`` counter (gaps in the controller's timestamps) over the
  window, minus the cycles the simulated controller itself skipped because it ran late
  (``skipped_cycles``: no client can receive those; reported beside);
* CPU of the receive child (``/proc/<pid>/stat`` utime + stime over the window), % of one core;
* host-stamp delay: the sample's ``host_time_ns`` minus the host time at which the controller
  produced it (the simulated controller's clock maps to the host clock exactly), p50 and p99.

Run: ``.venv/bin/python benchmarks/rtde_receive.py [--duration 10] [--json out.json]``.
Target: the native backend loses no sample, idle or not; exits 1 otherwise. Figures and their
discussion: docs/drivers.md, "UR robot receive path".
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from wristscan.drivers.sim.ur.controller import ControllerConfig, SimulatedController
from wristscan.drivers.ur.robot import URRobot

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _report import Figure, report  # noqa: E402

# This file's name shadows ur_rtde's top-level ``rtde_receive`` module, which the receive child
# imports: take this directory off the path again (spawned children inherit the path).
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != HERE]

WARMUP_S = 1.0
CLK_TCK = os.sysconf("SC_CLK_TCK")


def _cpu_s(pid: int) -> float:
    """utime + stime of one process, in seconds."""
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def run_one(backend: str, hog: bool, duration_s: float) -> dict[str, float]:
    with (
        SimulatedController.on_free_loopback(ControllerConfig()) as sim,
        URRobot(sim.host, receive_backend=backend) as r,
    ):
        r.read_for(WARMUP_S)
        rx = r._rx  # the receive child: a benchmark may look inside
        assert rx is not None
        pid = rx.proc.pid
        assert pid is not None
        lost0, skipped0 = r.counters.lost, sim.state()["skipped_cycles"]
        cpu0, t0 = _cpu_s(pid), time.monotonic()
        hogs = []
        if hog:
            hogs = [
                subprocess.Popen([sys.executable, "-c", "while True: pass"])
                for _ in range(os.cpu_count() or 2)
            ]
        try:
            states = r.read_for(duration_s)
        finally:
            for h in hogs:
                h.kill()
            for h in hogs:
                h.wait()
        cpu1, t1 = _cpu_s(pid), time.monotonic()
        lost, skipped = r.counters.lost - lost0, sim.state()["skipped_cycles"] - skipped0
        assert r._rx is not None and r._rx.proc.pid == pid, "the receive child was restarted"
        delay_ms = np.array(
            [(s.host_time_ns - sim.host_time_ns(s.controller_time_s)) * 1e-6 for s in states]
        )
    return {
        "received": float(len(states)),
        "lost": float(max(0, lost - skipped)),
        "skipped": float(skipped),
        "cpu_pct": 100.0 * (cpu1 - cpu0) / (t1 - t0),
        "delay_p50_ms": float(np.percentile(delay_ms, 50)),
        "delay_p99_ms": float(np.percentile(delay_ms, 99)),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    ap.add_argument("--duration", type=float, default=10.0, help="seconds per run")
    ap.add_argument("--backends", default="native,ur_rtde")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    figures: list[Figure] = []
    for backend in args.backends.split(","):
        for hog in (False, True):
            load = "hog" if hog else "idle"
            m = run_one(backend, hog, args.duration)
            tag = f"{backend}/{load}"
            print(f"{tag}: {m}", flush=True)
            native = backend == "native"
            lost_pct = 100.0 * m["lost"] / max(1.0, m["lost"] + m["received"])
            figures += [
                Figure(
                    f"{tag} samples lost",
                    m["lost"],
                    "",
                    "0" if native else "-",
                    m["lost"] == 0 if native else None,
                ),
                Figure(f"{tag} lost share", lost_pct, "%", "-", None),
                Figure(f"{tag} skipped by controller", m["skipped"], "", "-", None),
                Figure(f"{tag} receive child CPU", m["cpu_pct"], "% core", "-", None),
                Figure(f"{tag} host-stamp delay p50", m["delay_p50_ms"], "ms", "-", None),
                Figure(f"{tag} host-stamp delay p99", m["delay_p99_ms"], "ms", "-", None),
            ]
    return report(
        f"UR receive path, 500 Hz, {args.duration:g} s per run", figures, json_out=args.json
    )


if __name__ == "__main__":
    sys.exit(main())
