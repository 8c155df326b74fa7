"""A cell's scan archive over real zenoh sessions on loopback: ``<prefix>/scans`` lists, a job's
manifest and files come back byte for byte (also through ``wristscan scans fetch``), a plant-wide
wildcard query gets each cell's list on its own key, a job finished while the daemon runs is put
once for storages, and bad requests get errors, not silence."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from wristscan.daemon.cli.app import app
from wristscan.daemon.cloud.scans import ScanServer, fetch_file, fetch_jobs, fetch_manifest
from wristscan.daemon.cloud.zenoh_io import open_session
from wristscan.daemon.io.archive import ScanArchive


def _archive(root: Path, *jobs: str) -> ScanArchive:
    arch = ScanArchive(root)
    for job in jobs:
        src = root.parent / f"src-{job}"
        src.mkdir(parents=True)
        (src / "merged.ply").write_bytes(b"ply\n" + job.encode() * 1000)
        (src / "report.json").write_text(json.dumps({"job": job}))
        arch.add(job, {"merged.ply": src / "merged.ply", "report.json": src / "report.json"})
    return arch


def test_archive_served_listed_fetched_and_announced(endpoint: str, tmp_path: Path) -> None:
    arch1 = _archive(tmp_path / "c1" / "scans", "20261126T080000Z-bracket")
    arch2 = _archive(tmp_path / "c2" / "scans", "20261126T090000Z-lid")
    daemon = open_session(listen=[endpoint])
    servers = [
        ScanServer(daemon, "wristscan/c1", arch1, poll_s=0.1),
        ScanServer(daemon, "wristscan/c2", arch2, poll_s=0.1),
    ]
    peer = open_session(connect=[endpoint])
    stored: dict[str, bytes] = {}
    storage = peer.declare_subscriber(
        "wristscan/*/scans/**", lambda s: stored.__setitem__(str(s.key_expr), s.payload.to_bytes())
    )
    try:
        deadline = time.monotonic() + 20
        while True:  # the session may still be connecting
            try:
                jobs = fetch_jobs(peer, "wristscan/c1", timeout_s=1.0)
                break
            except TimeoutError:
                assert time.monotonic() < deadline, "no archive answered"
        assert [j["job"] for j in jobs] == ["20261126T080000Z-bracket"]
        man = fetch_manifest(peer, "wristscan/c1", "20261126T080000Z-bracket")
        assert man["files"]["merged.ply"] == 4 + 24 * 1000
        data = fetch_file(peer, "wristscan/c1", "20261126T080000Z-bracket", "merged.ply")
        assert (
            data
            == (tmp_path / "c1" / "scans" / "20261126T080000Z-bracket" / "merged.ply").read_bytes()
        )
        # plant-wide: each cell answers its list on its own key
        lists = {
            str(r.ok.key_expr): json.loads(r.ok.payload.to_string())
            for r in peer.get("wristscan/*/scans", timeout=5.0)
            if r.ok is not None
        }
        assert sorted(lists) == ["wristscan/c1/scans", "wristscan/c2/scans"]
        assert lists["wristscan/c2/scans"][0]["job"] == "20261126T090000Z-lid"
        # errors reach the asker
        with pytest.raises(LookupError, match="no scan 'nope'"):
            fetch_manifest(peer, "wristscan/c1", "nope")
        with pytest.raises(LookupError, match=r"has no file 'secret\.txt'"):
            fetch_file(peer, "wristscan/c1", "20261126T080000Z-bracket", "secret.txt")
        # a scan finished while the daemon runs is put once, for a storage to keep
        assert not stored
        _archive(tmp_path / "c1" / "scans", "20261126T100000Z-cover")
        key = "wristscan/c1/scans/20261126T100000Z-cover"
        while f"{key}/merged.ply" not in stored or key not in stored:
            assert time.monotonic() < deadline + 20, f"not announced: {sorted(stored)}"
            time.sleep(0.05)
        assert stored[f"{key}/merged.ply"].startswith(b"ply\n20261126T100000Z-cover")
        assert json.loads(stored[key])["job"] == "20261126T100000Z-cover"
        # the CLI: list, fetch into a folder
        runner = CliRunner()
        res = runner.invoke(
            app, ["scans", "list", "--prefix", "wristscan/c1", "--connect", endpoint, "--json"]
        )
        assert res.exit_code == 0, res.output
        assert [j["job"] for j in json.loads(res.stdout)] == [
            "20261126T080000Z-bracket",
            "20261126T100000Z-cover",
        ]
        out = tmp_path / "fetched"
        out.mkdir()
        args = ["scans", "fetch", "20261126T100000Z-cover", "--out", str(out)]
        res = runner.invoke(app, [*args, "--prefix", "wristscan/c1", "--connect", endpoint])
        assert res.exit_code == 0, res.output
        assert sorted(p.name for p in out.iterdir()) == [
            "manifest.json",
            "merged.ply",
            "report.json",
        ]
        assert (out / "merged.ply").read_bytes() == stored[f"{key}/merged.ply"]
        res = runner.invoke(
            app,
            [
                "scans",
                "fetch",
                "nope",
                "--out",
                str(out),
                "--prefix",
                "wristscan/c1",
                "--connect",
                endpoint,
            ],
        )
        assert res.exit_code == 1 and "no scan 'nope'" in res.output
        res = runner.invoke(
            app, ["scans", "fetch", "../x", "--prefix", "wristscan/c1", "--connect", endpoint]
        )
        assert res.exit_code == 2 and "not a scan archive name" in res.output
    finally:
        storage.undeclare()
        peer.close()
        for s in servers:
            s.close()
        daemon.close()


def test_no_archive_is_exit_1(endpoint: str) -> None:
    res = CliRunner().invoke(
        app,
        ["scans", "list", "--prefix", "wristscan/none", "--connect", endpoint, "--timeout", "0.5"],
    )
    assert res.exit_code == 1 and "no scan archive answered on wristscan/none/scans" in res.output
