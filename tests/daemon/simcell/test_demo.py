"""The README's main job: ``wristscan demo`` on a fresh install, end to end."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from wristscan.daemon.io.ply import read_ply


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_demo_writes_a_merged_scan(tmp_path: Path) -> None:
    out = tmp_path / "scan.ply"
    res = subprocess.run(
        [sys.executable, "-m", "wristscan.daemon.cli", "demo", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stdout + res.stderr
    assert "6 passes at 2 table angles" in res.stdout
    cloud = read_ply(out)
    assert cloud["xyz"].shape[0] > 20000
    # The demo's own check: the part's top face lands where the scene puts it.
    line = next(x for x in res.stdout.splitlines() if "top face" in x)
    height_mm = float(line.split("cloud:")[1].split("mm")[0])
    assert height_mm == pytest.approx(70.0, abs=0.05)


def test_demo_refuses_a_bad_output_name(tmp_path: Path) -> None:
    res = subprocess.run(
        [sys.executable, "-m", "wristscan.daemon.cli", "demo", "--out", str(tmp_path / "x.txt")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 2 and ".ply" in res.stderr and "Traceback" not in res.stderr
