"""Overload (issue 21): the daemon at twice its capacity sheds whole profiles and keeps publishing.

The simulated cell (UR5e still, the sensor 0.1 m above the table top, ``--rate`` x ``--points``
LPF1 over UDP) runs on the last CPU, ``wristscan run`` on the others (``benchmarks/_cellrun.py``).
A machine cannot be made slower on demand, so the daemon's capacity is brought down instead: its
worker thread (``pipeline-worker``: reading, decoding, pairing, aligning; not zenoh's threads nor
the publishing thread, whose cost a slower CPU would not make the bottleneck) is put into a CPU
cgroup (v1 ``cpu.cfs_quota_us``, per thread through ``tasks``; periods of 10 ms, longer when
needed to keep the quota at 2 ms or more) with a quota of ``c * rate / 2`` cores, where ``c`` is
the worker's CPU time per published profile measured first, without a quota, at the same rate:
its capacity is then ``rate / 2``, and the sensor sends at twice that. "Published" is what
reached the subscriber.

Phases (each a fresh cell and daemon, a ``--window`` of steady state):

1. **reference**: no quota: the worker's CPU per profile ``c`` keeping up at the rate, published
   rate (= the sensor's). With ``--capacity behind``, then **behind**: a quota from that cost, no
   shedding: the worker falls behind and works in big batches, at about half the cost per
   profile, and ``c`` is that cost instead (a harder overload: reading and decoding what
   arrives, paid for every profile, then takes most of the quota).
2. **overload**: the quota, shedding on (the default): published profiles/s >= 90 % of the
   capacity, the drops counted by reason (``overload``), the sensor clock locked throughout (no
   new epoch, locked at the end), the daemon's RSS bounded (end of the window within 10 % of
   its start), the latency of the published batches bounded (p99 of arrival minus the batch's
   last exposure <= 1 s). Then the quota is lifted: the time until nothing more is shed
   (recovery, target <= 1 s).
3. **overload, a late sender**: the same with the simulated sensor sending every datagram
   5-50 ms late with spikes (``late``): the same targets.
4. **without shedding** (information, ``[pipeline] shed_overload = false``): what the same
   overload does to a daemon that takes everything.

Needs root (the cgroup); exits 1 when a target is missed. Run:
``.venv/bin/python benchmarks/overload.py [--rate 5000] [--window 10] [--json out.json]``.
Figures: docs/pipeline.md ("Overload").
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _cellrun import CellRun, running
from _report import Figure, report

CGROUP_ROOT = Path("/sys/fs/cgroup/cpu")
PERIOD_US = 10_000
MIN_QUOTA_US = 2_000
PUBLISHED_TARGET = 0.9
RECOVERY_TARGET_S = 1.0
LATENCY_P99_TARGET_S = 1.0
RSS_GROWTH_TARGET = 0.10
LATE_SENDER: dict[str, Any] = {"send_late_s": [0.005, 0.05], "send_late_spike_prob": 0.01}
"""The simulated sensor's late-sender settings (``[sim.sensor]``)."""


class CpuQuota:
    """A cgroup-v1 CPU group for the daemon's process (its threads), quota settable."""

    def __init__(self) -> None:
        if not (CGROUP_ROOT / "cpu.cfs_quota_us").exists():
            raise SystemExit(f"overload benchmark: no cgroup-v1 cpu controller at {CGROUP_ROOT}")
        self.path = CGROUP_ROOT / f"wristscan-bench-{os.getpid()}"
        self.path.mkdir(exist_ok=True)
        (self.path / "cpu.cfs_period_us").write_text(str(PERIOD_US))

    def add_thread(self, tid: int) -> None:
        (self.path / "tasks").write_text(str(tid))

    def release(self, tid: int) -> None:
        (CGROUP_ROOT / "tasks").write_text(str(tid))

    def set(self, cores: float | None) -> None:
        """``cores`` of CPU (None: no limit). The kernel's smallest quota is 1 ms: below
        ``MIN_QUOTA_US`` per 10 ms the period grows instead (a worker at 20 us per profile needs
        only 0.05 cores at 2.5 kHz; a 1 ms floor would have given it twice that)."""
        if cores is None:
            (self.path / "cpu.cfs_quota_us").write_text("-1")
            return
        period = max(PERIOD_US, int(MIN_QUOTA_US / cores))
        (self.path / "cpu.cfs_quota_us").write_text("-1")  # the period may not go below a quota
        (self.path / "cpu.cfs_period_us").write_text(str(period))
        (self.path / "cpu.cfs_quota_us").write_text(str(max(MIN_QUOTA_US, int(cores * period))))

    def close(self) -> None:
        for tid in (self.path / "tasks").read_text().split():
            with contextlib.suppress(OSError):
                self.release(int(tid))
        with contextlib.suppress(OSError):
            self.path.rmdir()


def _proc_cpu_s(pid: int, tid: int | None = None) -> float:
    """The process's own CPU time (all its threads, not its children), or thread ``tid``'s, s."""
    path = f"/proc/{pid}/stat" if tid is None else f"/proc/{pid}/task/{tid}/stat"
    f = Path(path).read_text().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def _worker_tid(pid: int) -> int:
    for task in Path(f"/proc/{pid}/task").iterdir():
        if (task / "comm").read_text().strip() == "pipeline-worker":
            return int(task.name)
    raise RuntimeError("the daemon has no pipeline-worker thread")


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def _sensor_epochs(st: dict[str, Any]) -> tuple[int, bool]:
    clocks = st["pairing"]["sensor_clocks"]
    epochs = sum(int(c.get("epoch", 0)) for c in clocks.values())
    locked = all(bool(c.get("locked")) for c in clocks.values()) and bool(clocks)
    return epochs, locked


@contextlib.contextmanager
def _cell(
    tmp: Path,
    rate: float,
    points: int,
    quota: CpuQuota | None,
    shed: bool,
    late: bool,
    lag_s: float = 0.1,
) -> Iterator[CellRun]:
    cell_cpus = {os.cpu_count() - 1} if (os.cpu_count() or 1) > 1 else None  # type: ignore[operator]
    saved = os.sched_getaffinity(0)
    if cell_cpus:
        os.sched_setaffinity(0, cell_cpus)  # the cell's processes (and the subscriber) inherit

    def place(pid: int) -> None:
        if cell_cpus:
            os.sched_setaffinity(pid, saved - cell_cpus or saved)

    try:
        with running(
            tmp,
            rate,
            points,
            None,
            pipeline={"shed_overload": shed, "overload_lag_s": lag_s},
            sim_sensor=LATE_SENDER if late else None,
            on_daemon=place,
        ) as run:
            if quota is not None:
                quota.add_thread(_worker_tid(run.daemon.pid))
            yield run
    finally:
        os.sched_setaffinity(0, saved)


def _window(run: CellRun, window_s: float) -> dict[str, Any]:
    pid = run.daemon.pid
    tid = _worker_tid(pid)
    s0, c0, r0, t0 = run.stats(), _proc_cpu_s(pid), _rss_mb(pid), time.monotonic()
    w0 = _proc_cpu_s(pid, tid)
    n0 = len(run.batches.rows())
    time.sleep(window_s)
    s1, c1, r1, t1 = run.stats(), _proc_cpu_s(pid), _rss_mb(pid), time.monotonic()
    w1 = _proc_cpu_s(pid, tid)
    dt = t1 - t0
    rows = run.batches.rows()[n0:]
    lat = (rows[:, 0] - rows[:, 2]) * 1e-9 if rows.shape[0] else np.zeros(1)
    e0, _ = _sensor_epochs(s0)
    e1, locked = _sensor_epochs(s1)
    published = s1["published"] - s0["published"]
    at_sub = int(rows[:, 3].sum()) if rows.shape[0] else 0
    received = s1["received"] - s0["received"]
    dropped = {
        k: v - s0["dropped"].get(k, 0)
        for k, v in s1["dropped"].items()
        if v - s0["dropped"].get(k, 0)
    }
    return {
        "received_s": received / dt,
        "published_s": published / dt,
        "at_subscriber_s": at_sub / dt,
        "dropped": dropped,
        "cpu_us_per_profile": 1e6 * (c1 - c0) / max(published, 1),
        "worker_cpu_us_per_profile": 1e6 * (w1 - w0) / max(published, 1),
        "worker_cpu_pct": 100 * (w1 - w0) / dt,
        "cpu_pct": 100 * (c1 - c0) / dt,
        "rss_start_mb": r0,
        "rss_end_mb": r1,
        "latency_p99_s": float(np.percentile(lat, 99)),
        "new_sensor_epochs": e1 - e0,
        "sensor_locked_at_end": locked,
        "overload": s1.get("overload", {}),
    }


def _recovery(run: CellRun, quota: CpuQuota, timeout_s: float = 10.0) -> float:
    """Lift the quota; seconds until the ``overload`` count stops growing for 0.5 s."""
    quota.set(None)
    t0 = time.monotonic()
    last = run.stats()["dropped"].get("overload", 0)
    t_last = t0
    while time.monotonic() - t0 < timeout_s:
        time.sleep(0.05)
        n = run.stats()["dropped"].get("overload", 0)
        now = time.monotonic()
        if n != last:
            last, t_last = n, now
        elif now - t_last >= 0.5:
            return t_last - t0
    return float("inf")


def _overload_figures(tag: str, r: dict[str, Any], capacity: float) -> list[Figure]:
    pub = r["at_subscriber_s"]
    return [
        Figure(f"{tag}: received profiles/s", r["received_s"], "1/s", "-", None),
        Figure(
            f"{tag}: published / capacity",
            pub / capacity,
            "",
            f">= {PUBLISHED_TARGET}",
            pub >= PUBLISHED_TARGET * capacity,
        ),
        Figure(
            f"{tag}: shed (overload)", r["dropped_per_s"].get("overload", 0.0), "1/s", "-", None
        ),
        Figure(
            f"{tag}: new sensor clock epochs",
            r["new_sensor_epochs"],
            "",
            "0",
            r["new_sensor_epochs"] == 0,
        ),
        Figure(
            f"{tag}: sensor clock locked at the end",
            int(r["sensor_locked_at_end"]),
            "",
            "1",
            bool(r["sensor_locked_at_end"]),
        ),
        Figure(
            f"{tag}: latency p99 (arrival - last exposure)",
            r["latency_p99_s"],
            "s",
            f"<= {LATENCY_P99_TARGET_S:g}",
            r["latency_p99_s"] <= LATENCY_P99_TARGET_S,
        ),
        Figure(
            f"{tag}: RSS growth over the window",
            r["rss_end_mb"] / r["rss_start_mb"] - 1.0,
            "",
            f"<= {RSS_GROWTH_TARGET:g}",
            r["rss_end_mb"] <= (1 + RSS_GROWTH_TARGET) * r["rss_start_mb"],
        ),
        Figure(f"{tag}: daemon CPU", r["cpu_pct"], "% core", "-", None),
        Figure(f"{tag}: worker CPU (under its quota)", r["worker_cpu_pct"], "% core", "-", None),
    ]


def _phase(
    tmp: Path, args: argparse.Namespace, quota: CpuQuota, cores: float, shed: bool, late: bool
) -> dict[str, Any]:
    """One cell and daemon with the worker under ``cores`` of quota: the window's figures (and
    the recovery once the quota is lifted, when shedding)."""
    tmp.mkdir()
    with _cell(tmp, args.rate, args.points, quota, shed, late, args.lag) as run:
        quota.set(cores)
        time.sleep(4.0)  # the shedder finds the rate; buffers settle
        r = _window(run, args.window)
        r["dropped_per_s"] = {k: v / args.window for k, v in r["dropped"].items()}
        if shed:
            r["recovery_s"] = _recovery(run, quota)
        quota.set(None)
    return r


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=float, default=5000.0, help="sensor rate, Hz")
    ap.add_argument("--points", type=int, default=2048)
    ap.add_argument("--window", type=float, default=10.0, help="measured window per phase, s")
    ap.add_argument(
        "--capacity",
        choices=("reference", "behind"),
        default="reference",
        help="the cost per profile the capacity is sized with: keeping up at the rate "
        "(reference, default) or behind, in big batches (about half: a harder overload)",
    )
    ap.add_argument(
        "--lag",
        type=float,
        default=0.1,
        help="[pipeline] overload_lag_s, s: the lag bound (ticks while shedding: half of it)",
    )
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    if os.geteuid() != 0:
        raise SystemExit("overload benchmark: needs root (a CPU cgroup for the daemon)")
    figures: list[Figure] = []
    details: dict[str, Any] = {}
    quota = CpuQuota()
    capacity = args.rate / 2
    try:
        with tempfile.TemporaryDirectory(prefix="wristscan-overload-") as d:
            tmp = Path(d)
            (tmp / "ref").mkdir()
            with _cell(tmp / "ref", args.rate, args.points, None, True, False) as run:
                ref = _window(run, args.window)
            print(f"# reference {ref}", flush=True)
            # A worker behind works in big batches, at a lower cost per profile than one keeping
            # up: measure that cost behind (a first quota from the reference cost, no shedding:
            # it falls behind), and size the quota with it, so that rate = 2 x capacity.
            c_ref = ref["worker_cpu_us_per_profile"] * 1e-6
            c = c_ref
            details["reference"] = ref
            if args.capacity == "behind":
                behind = _phase(tmp / "behind", args, quota, c_ref * capacity, False, False)
                print(f"# behind {behind}", flush=True)
                c = behind["worker_cpu_us_per_profile"] * 1e-6
                details["behind"] = behind
            cores = c * capacity
            figures += [
                Figure("reference: published profiles/s", ref["published_s"], "1/s", "-", None),
                Figure("reference: worker CPU per profile", c_ref * 1e6, "us", "-", None),
                Figure(
                    "reference: daemon CPU per profile", ref["cpu_us_per_profile"], "us", "-", None
                ),
                Figure(f"worker CPU per profile ({args.capacity})", c * 1e6, "us", "-", None),
                Figure("quota (capacity = rate / 2)", cores, "cores", "-", None),
            ]
            for tag, shed, late in (
                ("overload", True, False),
                ("overload, late sender", True, True),
                ("no shedding", False, False),
            ):
                r = _phase(tmp / tag, args, quota, cores, shed, late)
                details[tag] = r
                print(f"# {tag} {r}", flush=True)
                figures += _phase_figures(tag, r, capacity, shed)
                figures.append(
                    Figure(  # else the phase measured no overload at all
                        f"{tag}: worker CPU / its quota",
                        r["worker_cpu_pct"] / (100 * cores),
                        "",
                        "<= 1.1",
                        r["worker_cpu_pct"] <= 110 * cores,
                    )
                )
    finally:
        quota.close()
    if args.json:
        Path(args.json).with_suffix(".details.json").write_text(json.dumps(details, indent=2))
    return report("overload (issue 21): the daemon at twice its capacity", figures, args.json)


def _phase_figures(tag: str, r: dict[str, Any], capacity: float, shed: bool) -> list[Figure]:
    if shed:
        return [
            *_overload_figures(tag, r, capacity),
            Figure(
                f"{tag}: recovery once the capacity is back",
                r["recovery_s"],
                "s",
                f"<= {RECOVERY_TARGET_S:g}",
                r["recovery_s"] <= RECOVERY_TARGET_S,
            ),
        ]
    return [
        Figure(f"{tag}: published / capacity", r["at_subscriber_s"] / capacity, "", "-", None),
        Figure(f"{tag}: latency p99", r["latency_p99_s"], "s", "-", None),
        Figure(f"{tag}: kernel + pipeline drops", sum(r["dropped"].values()), "", "-", None),
        Figure(f"{tag}: new sensor clock epochs", r["new_sensor_epochs"], "", "-", None),
    ]


if __name__ == "__main__":
    sys.exit(main())
