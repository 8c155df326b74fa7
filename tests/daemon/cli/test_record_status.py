"""``wristscan record`` and ``wristscan status`` as subprocesses against a real zenoh publisher.

The publisher is the daemon's own zenoh face (DaemonZenoh) on loopback, publishing synthetic
batches whose coordinates encode their sequence number, and skipping every 5th sequence number
to stand for batches lost on the way.

Endpoints are on a loopback address of the run's own (two test runs on one machine never meet),
and no assert depends on how fast a loaded machine runs: waits are for events (a batch in the
file being written, a line) with generous timeouts.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from support import RefusingPort, loopback_publisher, own_loopback_host
from typer.testing import CliRunner

from wristscan.daemon.cli.app import app
from wristscan.daemon.cloud.zenoh_io import DaemonZenoh
from wristscan.daemon.io import ply as plyio

PREFIX = "wristscan/rectest"
B = 400  # points per batch
PROFILES = 8
SKIP_EVERY = 5  # every 5th sequence number is never published
STATS = {
    "received": 1000,
    "paired": 900,
    "pending": 0,
    "dropped": {"no_robot_state": 60, "late": 40},
    "batches": 90,
}


def batch_xyz(seq: int) -> np.ndarray:
    xyz = np.empty((B, 3), np.float32)
    xyz[:, 0] = seq * 1e-3
    xyz[:, 1] = np.arange(B) * 1e-4
    xyz[:, 2] = 0.25
    return xyz


def batch_intensity(seq: int) -> np.ndarray:
    return ((np.arange(B) + seq) % 256).astype(np.uint8)


@dataclass
class Daemon:
    endpoint: str
    zenoh: DaemonZenoh

    def args(self) -> list[str]:
        return ["--prefix", PREFIX, "--connect", self.endpoint]


def _publish(dz: DaemonZenoh, k: int) -> None:
    if dz.seq % SKIP_EVERY == SKIP_EVERY - 1:
        dz.seq += 1  # a batch lost before reaching any subscriber
    seq = dz.seq
    dz.publish_cloud(
        batch_xyz(seq),
        t_first_ns=1_700_000_000_000_000_000 + seq,
        t_last_ns=1_700_000_000_000_000_000 + seq + 1,
        n_profiles=PROFILES,
        frame_id="base",
        intensity=batch_intensity(seq),
        profile_index=np.arange(B, dtype=np.uint32) % PROFILES,
    )
    if k % 10 == 0:
        dz.publish_status({"state": "running", "sensor": {"rate_hz": 1000.0}})


@pytest.fixture
def daemon() -> Iterator[Daemon]:
    with loopback_publisher(PREFIX, _publish, stats=lambda: STATS) as (endpoint, dz):
        yield Daemon(endpoint, dz)


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "wristscan.daemon.cli", *args]


def _cli_interruptible(*args: str) -> list[str]:
    """:func:`_cli` with SIGINT handled as in a terminal, even when this test run ignores it (a
    background job of a shell, nohup, some CI runners): the commands keep an ignored SIGINT
    ignored on purpose, and the child would inherit it."""
    start = (
        "import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
        "sys.argv[0] = 'wristscan'; runpy.run_module('wristscan.daemon.cli', run_name='__main__')"
    )
    return [sys.executable, "-c", start, *args]


def _run(args: list[str], cwd: Path, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=timeout)


def _summary(stdout: str) -> dict[str, str]:
    rows = [line.split(None, 1) for line in stdout.splitlines() if line.strip()]
    return {r[0]: r[1] for r in rows if len(r) == 2}


def _seq_gaps(seqs: list[int]) -> int:
    return int(np.sum(np.diff(seqs) - 1)) if len(seqs) > 1 else 0


def _check_ply_batches(path: Path) -> list[int]:
    """Every run of B points is one published batch, in order; returns their seqs."""
    got = plyio.read_ply(path)
    xyz, intensity = got["xyz"], got["intensity"]
    n = xyz.shape[0]
    seqs = []
    for lo in range(0, n, B):
        seq = round(float(xyz[lo, 0]) / 1e-3)
        take = min(B, n - lo)
        np.testing.assert_array_equal(xyz[lo : lo + take], batch_xyz(seq)[:take])
        np.testing.assert_array_equal(intensity[lo : lo + take], batch_intensity(seq)[:take])
        assert seq % SKIP_EVERY != SKIP_EVERY - 1, "a never-published batch appeared"
        seqs.append(seq)
    assert seqs == sorted(seqs)
    return seqs


def test_record_ply_stops_at_point_limit(daemon: Daemon, tmp_path: Path) -> None:
    limit = 10 * B + 123  # ends inside a batch: the last one is cut
    res = _run(
        _cli("record", *daemon.args(), "--out", "scan.ply", "--points", str(limit)), tmp_path
    )
    assert res.returncode == 0, res.stderr
    path = tmp_path / "scan.ply"
    assert plyio.read_ply(path)["xyz"].shape == (limit, 3)
    seqs = _check_ply_batches(path)
    summary = _summary(res.stdout)
    assert summary["file"] == str(path)
    assert summary["points"] == str(limit)
    assert summary["batches"] == str(len(seqs)) == "11"
    # Every 5th seq is skipped by the publisher: the gaps seen are reported as lost batches.
    assert summary["lost"].split()[0] == str(_seq_gaps(seqs)) != "0"
    assert summary["stopped"] == "point limit reached"
    header = plyio.read_ply_header(path)
    assert "frame base" in header.comments
    assert os.listdir(tmp_path) == ["scan.ply"]


def test_record_npz_for_a_duration(daemon: Daemon, tmp_path: Path) -> None:
    res = _run(_cli("record", *daemon.args(), "-o", "scan.npz", "--duration", "1.0"), tmp_path)
    assert res.returncode == 0, res.stderr
    summary = _summary(res.stdout)
    # Stopped by the duration, not before it (a lower bound, which load cannot break); that it
    # stops at all is the run's own timeout, so no stopwatch bound above (a loaded machine
    # stretches the last receive and the file's writing).
    assert summary["stopped"] == "duration reached"
    assert float(summary["duration"].split()[0]) >= 1.0
    with np.load(tmp_path / "scan.npz") as d:
        seq = d["seq"].astype(np.int64)
        # ~80 batches/s are published; a lost batch shows once a sequence spans a 5th seq.
        assert seq.size >= 5
        assert d["xyz"].shape == (seq.size * B, 3)
        np.testing.assert_array_equal(d["n_points"], B)
        np.testing.assert_array_equal(d["n_profiles"], PROFILES)
        np.testing.assert_array_equal(d["frame_id"], "base")
        np.testing.assert_array_equal(d["t_first_ns"], 1_700_000_000_000_000_000 + seq)
        for i, s in enumerate(seq):
            sl = slice(i * B, (i + 1) * B)
            np.testing.assert_array_equal(d["xyz"][sl], batch_xyz(int(s)))
            np.testing.assert_array_equal(d["intensity"][sl], batch_intensity(int(s)))
            np.testing.assert_array_equal(d["profile_index"][sl], np.arange(B) % PROFILES)
        lost = _seq_gaps(seq.tolist())
    assert summary["points"] == str(seq.size * B)
    assert summary["lost"].split()[0] == str(lost) != "0"


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_finishes_the_file_cleanly(
    daemon: Daemon, tmp_path: Path, sig: signal.Signals
) -> None:
    proc = subprocess.Popen(
        _cli_interruptible("record", *daemon.args(), "-o", "scan.ply"),
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()
        assert line.startswith("recording wristscan/rectest/cloud"), line
        # Until 3 batches are in the file being written (its body, flushed as it fills), not for
        # a fixed 0.7 s, which a loaded machine could spend before the first batch.
        _wait_for_body(tmp_path, 3 * B * _BATCH_RECORD_BYTES)
        assert not (tmp_path / "scan.ply").exists()
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    summary = _summary(out)
    assert summary["stopped"] == "signal"
    seqs = _check_ply_batches(tmp_path / "scan.ply")
    assert len(seqs) >= 3
    assert summary["points"] == str(len(seqs) * B)
    assert os.listdir(tmp_path) == ["scan.ply"]


_BATCH_RECORD_BYTES = plyio._vertex_dtype(False, True, False).itemsize
"""Bytes per point of the binary body (x, y, z and intensity)."""


def _wait_for_body(folder: Path, n_bytes: int, timeout_s: float = 60.0) -> None:
    """Wait until the temporary body of the PLY file being recorded holds ``n_bytes``."""
    deadline = time.monotonic() + timeout_s
    while True:
        sizes = [p.stat().st_size for p in folder.glob(".scan.ply.*.body.tmp")]
        if sizes and max(sizes) >= n_bytes:
            return
        assert time.monotonic() < deadline, f"the recorder wrote {sizes} bytes, not {n_bytes}"
        time.sleep(0.02)


def test_status_shows_counters(daemon: Daemon, tmp_path: Path) -> None:
    res = _run(_cli("status", *daemon.args()), tmp_path)
    assert res.returncode == 0, res.stderr
    out = res.stdout
    assert "alive    yes" in out
    assert "state           running" in out
    assert "sensor.rate_hz  1000" in out
    assert "dropped.no_robot_state  60" in out
    assert (
        "received 1000 = paired 900 + pending 0 + dropped 100 (no_robot_state 60, late 40)" in out
    )

    res = _run(_cli("status", *daemon.args(), "--json"), tmp_path)
    assert res.returncode == 0, res.stderr
    snap = json.loads(res.stdout)
    assert snap["alive"] is True
    assert snap["stats"] == STATS
    assert snap["status"] == {"state": "running", "sensor": {"rate_hz": 1000.0}}


def test_status_watch_until_sigint(daemon: Daemon, tmp_path: Path) -> None:
    proc = subprocess.Popen(
        _cli_interruptible("status", *daemon.args(), "--json", "--watch"),
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        snaps = [json.loads(proc.stdout.readline()) for _ in range(3)]
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert all(s["alive"] and s["stats"] == STATS for s in snaps)


def test_no_daemon_is_a_clear_error(tmp_path: Path) -> None:
    # Nobody there: a port held bound and not listening (no other process can take it).
    refusing = RefusingPort(own_loopback_host())
    nobody = ["--prefix", PREFIX, "--connect", f"tcp/{refusing.host}:{refusing.port}"]
    nobody += ["--timeout", "1"]
    with refusing:
        _no_daemon(nobody, tmp_path)


def _no_daemon(nobody: list[str], tmp_path: Path) -> None:
    # The two commands at once (each waits out its --timeout): independent of each other.
    status = subprocess.Popen(
        _cli("status", *nobody), cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    try:
        res = _run(_cli("record", *nobody, "-o", "scan.ply"), tmp_path)
        out, err = status.communicate(timeout=60)
    finally:
        if status.poll() is None:
            status.kill()
            status.wait()
    assert res.returncode == 1
    assert res.stderr.startswith("error: no wristscan daemon answered on wristscan/rectest")
    assert len(res.stderr.strip().splitlines()) == 1 and "Traceback" not in res.stderr
    assert os.listdir(tmp_path) == []
    res = subprocess.CompletedProcess(status.args, status.returncode, out, err)
    assert res.returncode == 1
    assert res.stderr.startswith("error: no wristscan daemon answered on wristscan/rectest")
    assert len(res.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["-o", "scan.txt"], "--out must end in .ply or .npz"),
        (["-o", "scan.npz", "--ascii"], "--ascii applies to .ply output only"),
        (["-o", "missing/scan.ply"], "the folder of --out does not exist"),
        (["-o", "scan.ply", "--mode", "router"], "--mode must be 'peer' or 'client'"),
        (["-o", "scan.ply", "--prefix", "wristscan/*"], "--prefix must be a plain zenoh key"),
        (["-o", "scan.ply", "-d", "nan"], "--duration: must be a finite number > 0 (got nan)"),
        (["-o", "scan.ply", "-d", "inf"], "--duration: must be a finite number > 0 (got inf)"),
        (["-o", "scan.ply", "-d", "-1"], "--duration: must be a finite number > 0 (got -1)"),
    ],
)
def test_record_user_errors(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, args: list[str], message: str
) -> None:
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(app, ["record", "--connect", "tcp/127.0.0.1:9", *args])
    assert res.exit_code == 2
    assert message in res.output
    assert os.listdir(tmp_path) == []


def test_record_never_replaces_a_file_unless_forced(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "run.mcap").write_bytes(b"a long recording")
    args = ["record", "--connect", "tcp/127.0.0.1:9", "-o", "run.mcap", "--timeout", "0.2"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2
    assert "--out 'run.mcap' exists; use --force to replace it" in res.output
    # --force gets past the check; with no daemon to record, the old file stays as it was
    res = CliRunner().invoke(app, [*args, "--force"])
    assert res.exit_code == 1 and "no wristscan daemon answered" in res.output
    assert (tmp_path / "run.mcap").read_bytes() == b"a long recording"
    assert os.listdir(tmp_path) == ["run.mcap"]


def test_target_from_config_file(tmp_path: Path) -> None:
    from wristscan.daemon.cli._remote import resolve_target

    src = Path(__file__).resolve().parents[3] / "config" / "sim.toml"
    text = src.read_text().replace(
        'listen = ["tcp/127.0.0.1:7447"]', 'listen = ["tcp/0.0.0.0:7500"]'
    )
    assert "tcp/0.0.0.0:7500" in text
    cfg = tmp_path / "cell.toml"
    cfg.write_text(text)
    target = resolve_target(cfg, None, None, None)
    assert (target.prefix, target.connect, target.mode) == (
        "wristscan/sim",
        ("tcp/127.0.0.1:7500",),
        "peer",
    )
    target = resolve_target(cfg, "other/cell", ["tcp/10.0.0.1:7447"], "client")
    assert (target.prefix, target.connect, target.mode) == (
        "other/cell",
        ("tcp/10.0.0.1:7447",),
        "client",
    )


def test_breakdown_of_counters() -> None:
    from wristscan.daemon.cli._common import table
    from wristscan.daemon.cli.status import breakdown, flatten

    assert breakdown({"received": 10, "published": 7, "dropped": 3}) == (
        "received 10 = published 7 + dropped 3"
    )
    # The term that makes the sum add up is chosen ...
    assert breakdown(
        {"received": 10, "published": 2, "paired": 6, "pending": 1, "dropped": {"late": 3}}
    ) == ("received 10 = paired 6 + pending 1 + dropped 3 (late 3)")
    # ... and a shortfall is shown, not hidden.
    assert breakdown({"received": 10, "paired": 5, "dropped": {"late": 3}}) == (
        "received 10 = paired 5 + dropped 3 (late 3)  [does not add up: +2]"
    )
    assert breakdown({"received": 10}) is None
    assert breakdown({"paired": 10}) is None
    rows = flatten({"a": {"b": 1.5, "c": {}}, "ok": True, "ids": [1, 2], "inf": float("inf")})
    assert rows == [("a.b", "1.5"), ("a.c", "-"), ("ok", "yes"), ("ids", "[1,2]"), ("inf", "inf")]
    assert table([("a", "1"), ("long.key", "2")]) == ["  a         1", "  long.key  2"]
