"""Fault campaign (issue 22): ``wristscan run`` on the simulated cell, one fault after another.

The simulated cell (UR5e still, the sensor 0.1 m above the table top, ``rate_hz`` x ``n_points``
LPF1 over UDP) runs in this process's children, ``wristscan run`` as a subprocess (a systemd
notify socket, a session of its own; as root at the unit's ``Nice=``), a WSC1 subscriber in this
process. Once batches flow, these faults are injected in turn, the daemon running throughout:
the sensor silent for 2 s (``SimulatedSensor.disconnect``), the same with a reboot (frame
counter and clock restart), the sensor's process stopped for 2 s (SIGSTOP/SIGCONT: it then sends
its backlog in a burst), 3 s of corrupt frames (2 % of the datagrams each corrupted, truncated,
duplicated, reordered), the controller dropping every RTDE connection, the RTDE output stalled
for 2 s, every process of the cell stopped for 1 s (SIGSTOP/SIGCONT), and SIGHUP reloads: the
file unchanged, a ``[sensor]`` change, a ``[robot]`` change (that device closed and reopened).

For each fault: the time from its end (the end of the silence, SIGCONT; for a reload the
daemon's ``READY=1`` after SIGHUP) until the first batch whose last exposure (the daemon's
estimate) is after that end arrives at the subscriber (target <= 2 s); the ``stats`` counters
add up (``received == published + sum(dropped) + pending``, also in the middle of the 2 s
outages) and stay cumulative; the daemon alive, no traceback in its log; the log says what it
should (the outages last 2 s, over the service's ``outage_after_s``, 1 s by default: each
logged at WARNING when it starts and when it ends; a reload logs what it changed). As
information: the longest pause between batches, the profiles dropped (by reason), batches
missing at the subscriber, whether systemd's STATUS said "degraded". At the end: no gap or
restart in the WSC1 sequence numbers at the subscriber, SIGTERM exits 0, the final counters
count as published exactly what the subscriber received. The campaign runs the daemon with
``[zenoh] congestion_control = "block"`` (``--congestion``), so that this last check is exact:
with the default ``drop`` a subscriber that falls behind for a moment loses batches by design.

``--soak SECONDS`` runs the cell at 2 kHz x 2048 for that long instead (no faults): the RSS of
the daemon and of its process tree (with the robot receiver), sampled every 2 s, grows less than
5 % from the end of the warm-up (``--warmup``, default a quarter of the run, at most 150 s) to
the end (medians of five samples at each end); no profile lost after start-up: the measured
window opens and closes with the sensor silent and the pipeline drained (as in
``benchmarks/pipeline.py``), so lost = sent by the sensor - profiles at the subscriber, exactly,
split into not received, dropped by the daemon, lost in zenoh.

Run: ``.venv/bin/python benchmarks/faults.py [--rate 1000] [--json out.json] [--workdir DIR]``
(under a minute of faults) or ``... --soak 3600``; exits 1 when a target is missed. Figures:
docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _cellrun import CellRun, own_nice, running, write_config
from _report import Figure, report
from pipeline import (
    _children,
    _drained_stats,
    _udp_drops,
    _unit_nice,
)

RECOVERY_TARGET_S = 2.0
RSS_GROWTH_TARGET = 0.05
FAULT_S = 2.0
"""How long the sensor and robot outages last: over the service's ``outage_after_s`` (1 s by
default), so that each must be logged when it starts and when it ends."""
CELL_STOP_S = 1.0
CORRUPT_S = 3.0
CORRUPT_P = 0.02
RECOVERY_WAIT_S = 20.0
"""How long to wait for batches after a fault before calling it not recovered."""
SETTLE_S = 1.5
"""After a recovery, before the counters are read and the next fault starts."""
PAUSE_S = 1.5
"""Sensor silence that opens and closes the soak's window (the pipeline drains meanwhile)."""


# ----------------------------------------------------------------------------------------------
# The faults: each injects one and returns (start, end) in host monotonic ns


def _stop_cont(pids: list[int], seconds: float) -> tuple[int, int]:
    t0 = time.monotonic_ns()
    try:
        for p in pids:
            os.kill(p, signal.SIGSTOP)
        time.sleep(seconds)
    finally:
        for p in pids:
            os.kill(p, signal.SIGCONT)
    return t0, time.monotonic_ns()


def _sensor_drop(run: CellRun, reboot: bool = False) -> tuple[int, int]:
    t0 = time.monotonic_ns()  # the silence ends at most the call's latency after t0 + FAULT_S
    run.cell.sensor.disconnect(FAULT_S, reboot=reboot)
    return t0, t0 + int(FAULT_S * 1e9)


def _corrupt(run: CellRun) -> tuple[int, int]:
    t0, p = time.monotonic_ns(), CORRUPT_P
    run.cell.sensor.set_faults(corrupt=p, truncate=p, duplicate=p, reorder=p)
    try:
        time.sleep(CORRUPT_S)
    finally:
        run.cell.sensor.set_faults()
    return t0, time.monotonic_ns()


def _rtde_drop(run: CellRun) -> tuple[int, int]:
    t0 = time.monotonic_ns()
    if run.cell.controller.drop_connections() < 1:
        raise RuntimeError("the controller had no RTDE connection to drop")
    return t0, time.monotonic_ns()


def _rtde_stall(run: CellRun) -> tuple[int, int]:
    t0 = time.monotonic_ns()
    run.cell.controller.stall_output(FAULT_S)
    return t0, t0 + int(FAULT_S * 1e9)


def _reload(run: CellRun, section: str | None, key: str, value: float) -> tuple[int, int]:
    """SIGHUP, after setting ``[section] key`` to ``value`` (None: the file unchanged). The
    reload ends when the daemon tells systemd ``READY=1`` again."""
    if section is not None:
        run.doc[section][key] = value
        write_config(run.doc, run.cfg_path)
    t0 = time.monotonic_ns()
    run.daemon.send_signal(signal.SIGHUP)
    t_ready = run.notes.first("READY=1", t0, RECOVERY_WAIT_S)
    if t_ready is None:
        raise RuntimeError(f"no READY=1 within {RECOVERY_WAIT_S:g} s of SIGHUP")
    return t0, t_ready


FAULTS: list[tuple[str, Callable[[CellRun], tuple[int, int]], str | None]] = [
    ("sensor link drop 2 s", _sensor_drop, "sensor"),
    ("sensor reboot (2 s off)", lambda r: _sensor_drop(r, reboot=True), "sensor"),
    ("sensor stall (SIGSTOP 2 s)", lambda r: _stop_cont(r.cell_pids(("sensor",)), FAULT_S),
     "sensor"),
    ("corrupt frames 3 s", _corrupt, None),
    ("RTDE link drop", _rtde_drop, None),
    ("RTDE stall 2 s", _rtde_stall, "robot"),
    ("whole cell SIGSTOP 1 s", lambda r: _stop_cont(r.cell_pids(), CELL_STOP_S), None),
    ("SIGHUP reload, unchanged", lambda r: _reload(r, None, "", 0.0), "reload"),
    ("SIGHUP reload, [sensor] changed", lambda r: _reload(r, "sensor", "latency_s", 0.0021),
     "reload"),
    ("SIGHUP reload, [robot] changed", lambda r: _reload(r, "robot", "max_speed_m_s", 0.24),
     "reload"),
]  # fmt: skip
"""Name, injection, what the log must say: ``sensor``/``robot`` (an outage of that device, when
it starts and when it ends, at WARNING), ``reload`` (what the reload changed), None (nothing)."""


def _dropped(st: dict[str, Any]) -> dict[str, int]:
    return {k: int(v) for k, v in dict(st.get("dropped") or {}).items()}


def _imbalance(st: dict[str, Any]) -> int:
    """``received - (published + sum(dropped) + pending)``: 0 when the counters add up."""
    return int(st["received"]) - (
        int(st["published"]) + sum(_dropped(st).values()) + int(st["pending"])
    )


_ROUTINE = re.compile(r"slow tick|garbage collection")
"""Warnings about the daemon's own timing, not about the fault."""


def _logged(text: str, expect: str | None) -> bool | None:
    """Whether the log says what ``expect`` asks for (None: nothing asked)."""
    if expect == "reload":
        return re.search(r"INFO .*reloaded: ", text) is not None
    if expect is not None:
        starts = re.findall(rf"WARNING .*{expect} outage: ", text)
        ends = re.findall(rf"WARNING .*{expect} outage over after ", text)
        return len(starts) == len(ends) >= 1
    return None


def _one_fault(
    run: CellRun, name: str, inject: Callable[[CellRun], tuple[int, int]], expect: str | None
) -> dict[str, Any]:
    run.wait_flowing()
    time.sleep(0.5)
    log_at = run.log_size()
    st_a = run.stats()
    t0, t_end = inject(run)
    mid = 0  # the counters also add up in the middle of an outage still going on
    if (left := t_end - time.monotonic_ns()) > 600_000_000:
        time.sleep(left / 2e9)
        mid = _imbalance(run.stats())
    fresh = run.batches.wait_fresh(t_end, RECOVERY_WAIT_S)
    time.sleep(SETTLE_S)
    alive = run.daemon.poll() is None
    st_b = run.stats() if alive else st_a
    arr = run.batches.rows()[:, 0]
    upto = fresh if fresh is not None else time.monotonic_ns()
    span = arr[(arr >= t0 - 1_000_000_000) & (arr <= upto)]
    drop_a, drop_b = _dropped(st_a), _dropped(st_b)
    text = run.log_text(log_at)
    lines = [ln.split(" ", 2)[-1] for ln in text.splitlines() if re.search(r"WARNING|ERROR", ln)]
    about = [ln for ln in lines if not _ROUTINE.search(ln)]
    return {
        "fault": name,
        "fault_s": (t_end - t0) / 1e9,
        "recovered_s": (fresh - t_end) / 1e9 if fresh is not None else float("inf"),
        "longest_pause_s": float(np.max(np.diff(span))) / 1e9 if span.size > 1 else float("nan"),
        "imbalance": abs(mid) + abs(_imbalance(st_b)) if alive else -1,
        "cumulative": all(int(st_b[k]) >= int(st_a[k]) for k in ("received", "published")),
        "alive": alive,
        "traceback": "Traceback" in text,
        "dropped": {k: v - drop_a.get(k, 0) for k, v in drop_b.items() if v != drop_a.get(k, 0)},
        "errors": sum(" ERROR " in f" {ln}" for ln in lines),
        "logged": about,
        "seen": _logged(text, expect),
        "span_ns": (t0, time.monotonic_ns()),
        "status_degraded": run.notes.any_between("degraded", t0, time.monotonic_ns()),
    }


def _failed(run: CellRun, name: str, exc: BaseException) -> dict[str, Any]:
    """The result of a fault whose injection or check failed with ``exc``."""
    now = time.monotonic_ns()
    alive = run.daemon.poll() is None
    return {
        "fault": name, "fault_s": float("nan"), "recovered_s": float("inf"),
        "longest_pause_s": float("nan"), "imbalance": -1, "cumulative": False, "alive": alive,
        "traceback": "Traceback" in run.log_text(), "dropped": {}, "errors": 0,
        "logged": [f"benchmark: {exc}"], "seen": False, "span_ns": (now, now),
        "status_degraded": False,
    }  # fmt: skip


def _fault_figures(r: dict[str, Any]) -> list[Figure]:
    k = r["fault"]
    ok = r["recovered_s"] <= RECOVERY_TARGET_S
    sound = r["alive"] and not r["traceback"]
    said = r["seen"] if r["seen"] is not None else bool(r["logged"])  # any warning about it
    return [
        Figure(f"{k}: recovered after", r["recovered_s"], "s", f"<= {RECOVERY_TARGET_S:g}", ok),
        Figure(f"{k}: longest pause in batches", r["longest_pause_s"], "s", "-", None),
        Figure(f"{k}: profiles dropped", sum(r["dropped"].values()), "", "-", None),
        Figure(f"{k}: batches missing at the subscriber", r["missing"], "", "-", None),
        Figure(f"{k}: logged it (outage start and end / reload)", int(said), "",
               "-" if r["seen"] is None else "1", r["seen"]),
        Figure(f"{k}: STATUS said degraded", int(r["status_degraded"]), "", "-", None),
        Figure(f"{k}: counters off by", r["imbalance"], "", "0, cumulative",
               r["imbalance"] == 0 and r["cumulative"]),
        Figure(f"{k}: alive, no traceback", int(sound), "", "1", sound),
    ]  # fmt: skip


def _seq_check(rows: np.ndarray) -> tuple[int, int]:
    """(batches missing between the sequence numbers received, sequence restarts)."""
    seq = rows[:, 1]
    if seq.size < 2:
        return 0, 0
    d = np.diff(seq)
    return int(np.sum(d[d > 1] - 1)), int(np.sum(d <= 0))


def _attribute_gaps(rows: np.ndarray, results: list[dict[str, Any]]) -> None:
    """Each fault's ``missing``: the batches missing before those that arrived from its start
    to the next fault's."""
    for r in results:
        r["missing"], r["missing_seqs"] = 0, []
    if rows.shape[0] < 2 or not results:
        return
    d = np.diff(rows[:, 1])
    starts = np.array([r["span_ns"][0] for r in results])
    for i in np.flatnonzero(d > 1):
        k = int(np.searchsorted(starts, rows[i + 1, 0], side="right")) - 1
        if k >= 0:
            results[k]["missing"] += int(d[i] - 1)
            t_rel = round((int(rows[i + 1, 0]) - results[k]["span_ns"][0]) / 1e9, 3)
            results[k]["missing_seqs"].append((int(rows[i, 1]) + 1, int(rows[i + 1, 1]) - 1, t_rel))


def campaign(
    tmp: Path, rate_hz: float, n_points: int, nice: int | None, congestion: str
) -> list[Figure]:
    t_start = time.monotonic()
    results = []
    with running(tmp, rate_hz, n_points, nice, congestion) as run:
        for name, inject, expect in FAULTS:
            try:
                r = _one_fault(run, name, inject, expect)
            except (RuntimeError, TimeoutError) as exc:  # the fault or a query failed: a miss
                r = _failed(run, name, exc)
            results.append(r)
            print(
                f"# {name}: lasted {r['fault_s']:.3f} s, recovered {r['recovered_s']:.3f} s after"
                f" its end, longest pause {r['longest_pause_s']:.3f} s, dropped {r['dropped']}, "
                f"counters off by {r['imbalance']}, STATUS degraded {r['status_degraded']}, "
                f"errors {r['errors']}, logged: {' | '.join(r['logged'][:4]) or '-'}",
                flush=True,
            )
            if not r["alive"]:
                break
        code = run.stop_daemon() if run.daemon.poll() is None else run.daemon.returncode
        rows = run.batches.rows()
        log = run.log_text()
    _attribute_gaps(rows, results)
    for r in results:
        if r["missing"]:
            print(f"# {r['fault']}: batches missing (first, last seq, s after the fault began "
                  f"that the next arrived): {r['missing_seqs']}")  # fmt: skip
    figures = [f for r in results for f in _fault_figures(r)]
    missing, restarts = _seq_check(rows)
    received = int(rows[:, 3].sum())
    m = re.search(r"final counters: received (\d+) = published (\d+)", log)
    published = int(m.group(2)) if m else -1  # no final counters: a miss
    figures += [
        Figure("batches missing at the subscriber (seq gaps)", missing, "", "0", missing == 0),
        Figure("sequence restarts at the subscriber", restarts, "", "0", restarts == 0),
        Figure("exit code at SIGTERM", code, "", "0", code == 0),
        Figure("published (final counters) - at the subscriber", published - received,
               "profiles", "0", published == received),
        Figure("traceback anywhere in the daemon log", int("Traceback" in log), "", "0",
               "Traceback" not in log),
        Figure("campaign wall time", time.monotonic() - t_start, "s", "-", None),
        Figure("sensor rate", rate_hz, "Hz", "-", None),
        Figure("load average (1 min)", os.getloadavg()[0], "", "-", None),
    ]  # fmt: skip
    return figures


# ----------------------------------------------------------------------------------------------
# Soak


def _rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def _tree_rss_kb(pid: int) -> int:
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        try:
            total += _rss_kb(p)
            todo += _children(p)
        except OSError:
            pass
    return total


def _sample_rss(run: CellRun, until: float, samples: list[tuple[float, int, int]]) -> None:
    """Append (time, daemon RSS kB, tree RSS kB) every 2 s until ``until`` (monotonic s)."""
    pid = run.daemon.pid
    while (now := time.monotonic()) < until:
        if run.daemon.poll() is not None:
            raise RuntimeError(f"the daemon exited with {run.daemon.returncode} during the soak")
        samples.append((now, _rss_kb(pid), _tree_rss_kb(pid)))
        time.sleep(min(2.0, max(until - now, 0.0)))


def _window_edge(run: CellRun) -> tuple[dict[str, Any], dict[str, int], int | None]:
    """Sensor silent, pipeline drained: the daemon's stats, the sensor's and the UDP drops."""
    run.cell.sensor.disconnect(PAUSE_S)
    t_back = time.monotonic() + PAUSE_S
    st = _drained_stats(run.client)
    sensor = run.cell.sensor.stats()
    udp = _udp_drops(run.port)
    if time.monotonic() > t_back:
        raise RuntimeError("the pipeline did not drain within the sensor's pause")
    time.sleep(max(t_back - time.monotonic(), 0.0))
    return st, sensor, udp


def soak(
    tmp: Path,
    seconds: float,
    warmup_s: float,
    rate_hz: float,
    n_points: int,
    nice: int | None,
    congestion: str,
) -> list[Figure]:
    samples: list[tuple[float, int, int]] = []
    with running(tmp, rate_hz, n_points, nice, congestion) as run:
        t0 = time.monotonic()
        _sample_rss(run, t0 + warmup_s, samples)
        st_a, s_a, udp_a = _window_edge(run)
        n_warm = len(samples)
        _sample_rss(run, t0 + seconds, samples)
        st_b, s_b, udp_b = _window_edge(run)
        rows = run.batches.rows()
        log = run.log_text()
        window_s = time.monotonic() - t0 - warmup_s
    seq0, seq1 = int(st_a["published_batches"]), int(st_b["published_batches"])
    win = rows[(rows[:, 1] >= seq0) & (rows[:, 1] < seq1)]
    win = win[np.unique(win[:, 1], return_index=True)[1]]
    at_sub = int(win[:, 3].sum())
    sent = s_b["profiles_sent"] - s_a["profiles_sent"]
    received = int(st_b["received"]) - int(st_a["received"])
    published = int(st_b["published"]) - int(st_a["published"])
    dropped = sum(_dropped(st_b).values()) - sum(_dropped(st_a).values())
    lost = sent - at_sub
    s = np.array(samples, dtype=np.float64)
    after = s[n_warm:]
    if after.shape[0] < 10:
        raise RuntimeError("the soak is too short after its warm-up for an RSS trend (>= 20 s)")
    growth = [
        (float(np.median(after[-5:, c])) - float(np.median(after[:5, c])))
        / float(np.median(after[:5, c]))
        for c in (1, 2)
    ]
    pick = np.linspace(0, s.shape[0] - 1, min(s.shape[0], 13)).astype(int)
    half = after[after.shape[0] // 2 :]
    slope = float(np.polyfit(half[:, 0] / 60, half[:, 1] / 1024, 1)[0])
    udp = None if udp_a is None or udp_b is None else udp_b - udp_a
    print(
        f"# soak: {rate_hz:g} Hz x {n_points}, {seconds:g} s (warm-up {warmup_s:g} s); window "
        f"{window_s:.0f} s: sent {sent}, received {received} (UDP socket drops {udp}), "
        f"published {published}, dropped {dropped} {_dropped(st_b)}, at the subscriber {at_sub} "
        f"in {win.shape[0]} batches of {seq1 - seq0}; RSS (MB) daemon "
        f"{after[0, 1] / 1024:.1f} -> {after[-1, 1] / 1024:.1f} (peak {s[:, 1].max() / 1024:.1f}),"
        f" tree {after[0, 2] / 1024:.1f} -> {after[-1, 2] / 1024:.1f}; daemon RSS (s: MB) "
        f"{[(round(t - s[0, 0]), round(v / 1024, 1)) for t, v in s[pick, :2].tolist()]}; traceback "
        f"{'Traceback' in log}",
        flush=True,
    )
    n_lost = (seq1 - seq0) - win.shape[0]
    rss_target = f"< {100 * RSS_GROWTH_TARGET:g}"
    return [
        Figure("soak duration", seconds, "s", "-", None),
        Figure("warm-up", warmup_s, "s", "-", None),
        Figure("profiles sent in the window", sent, "", "-", None),
        Figure("profiles lost after start-up", lost, "", "0", lost == 0),
        Figure("  of which not received by the daemon", sent - received, "", "-", None),
        Figure("  of which dropped by the daemon", dropped, "", "-", None),
        Figure("  of which lost in zenoh", published - at_sub, "", "-", None),
        Figure("batches lost (seq gaps)", n_lost, "", "0", n_lost == 0),
        Figure("daemon RSS growth after warm-up", 100 * growth[0], "%", rss_target,
               growth[0] < RSS_GROWTH_TARGET),
        Figure("daemon + robot receiver RSS growth after warm-up", 100 * growth[1], "%",
               rss_target, growth[1] < RSS_GROWTH_TARGET),
        Figure("daemon RSS slope, second half of the window", slope, "MB/min", "-", None),
        Figure("daemon RSS at end", after[-1, 1] / 1024, "MB", "-", None),
        Figure("traceback in the daemon log", int("Traceback" in log), "", "0",
               "Traceback" not in log),
        Figure("load average (1 min)", os.getloadavg()[0], "", "-", None),
    ]  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    root = os.geteuid() == 0
    add = ap.add_argument
    add("--soak", type=float, metavar="SECONDS", help="run the soak instead of the campaign")
    add("--warmup", type=float, help="soak warm-up, s (default: a quarter, at most 150 s)")
    add("--rate", type=float, help="sensor rate, Hz (default 1000; the soak 2000)")
    add("--points", type=int, default=2048)
    add("--json", help="write the figures here")
    add("--workdir", help="keep the configuration and the daemon log here")
    add("--nice", type=int, default=_unit_nice() if root else None,
        help="the daemon's nice value (default as root: the unit's Nice=)")  # fmt: skip
    add("--cell-nice", type=int, default=-10 if root else None,
        help="the simulated cell's nice value (default as root: -10)")  # fmt: skip
    add("--congestion", choices=("block", "drop"),
        help="the daemon's [zenoh] congestion_control (default: block for the campaign, so "
        "that all it counts as published must arrive; the soak: drop, the default)")  # fmt: skip
    ns = ap.parse_args(argv)
    if ns.soak is not None and (ns.soak < 30 or not np.isfinite(ns.soak)):
        ap.error("--soak must be at least 30 s")
    warm = ns.warmup if ns.warmup is not None else min(150.0, (ns.soak or 0.0) / 4)
    if ns.soak is not None and not 0 <= warm <= ns.soak - 20:
        ap.error("--warmup must be between 0 and the soak's length minus 20 s")
    ctx = tempfile.TemporaryDirectory(prefix="wristscan-faults-") if ns.workdir is None else None
    tmp = Path(ctx.name if ctx is not None else ns.workdir)
    tmp.mkdir(parents=True, exist_ok=True)
    try:
        with own_nice(ns.cell_nice):
            if ns.soak is None:
                figures = campaign(
                    tmp, ns.rate or 1000.0, ns.points, ns.nice, ns.congestion or "block"
                )
                title = "fault campaign (issue 22): wristscan run on the simulated cell"
            else:
                rate = ns.rate or 2000.0
                figures = soak(
                    tmp, ns.soak, warm, rate, ns.points, ns.nice, ns.congestion or "drop"
                )
                title = "soak (issue 22): wristscan run on the simulated cell"
    finally:
        if ctx is not None:
            ctx.cleanup()
    return report(title, figures, ns.json)


if __name__ == "__main__":
    sys.exit(main())
