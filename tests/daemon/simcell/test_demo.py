"""The README's main job: ``wristscan demo`` on a fresh install, end to end; ``wristscan view
--record`` watches the demo's daemon meanwhile (the one simulated cell serves both)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from support import part_signed_distance, png_size

from wristscan.daemon.io.ply import read_ply
from wristscan.drivers.sim.scene import demo_scene


def _view_during_the_demo(
    out: Path, rrd: Path
) -> tuple[subprocess.CompletedProcess[str], subprocess.CompletedProcess[str]]:
    """Run ``wristscan demo`` and, once it names its daemon's config, ``wristscan view --record``
    against that daemon (the one cell run serves both); the two runs (the demo's stderr is in
    its stdout)."""
    demo = subprocess.Popen(
        [sys.executable, "-m", "wristscan.daemon.cli", "demo", "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=out.parent,
    )
    assert demo.stdout is not None
    lines: list[str] = []
    view: subprocess.Popen[str] | None = None
    for line in demo.stdout:
        lines.append(line)
        if view is None and "wristscan run --config " in line:
            cfg = line.split("--config ", 1)[1].strip()
            args = [
                "view",
                "--config",
                cfg,
                "--record",
                str(rrd),
                "--seconds",
                "15",
                "--stride",
                "8",
            ]
            view = subprocess.Popen(
                [sys.executable, "-m", "wristscan.daemon.cli", *args, "--timeout", "120"],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
    demo.wait(timeout=60)
    ran = subprocess.CompletedProcess(demo.args, demo.returncode, "".join(lines), "")
    assert view is not None, ran.stdout
    v_out, v_err = view.communicate(timeout=120)
    return ran, subprocess.CompletedProcess(view.args, view.returncode, v_out, v_err)


def _rrd_points(path: Path) -> np.ndarray:
    from rerun.chunk import RrdReader

    parts = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == "/world/cloud":
            batch = chunk.to_record_batch()
            name = next(n for n in batch.schema.names if n.endswith("Points3D:positions"))
            flat = batch.column(name).flatten().flatten().to_numpy(zero_copy_only=False)
            parts.append(np.asarray(flat, np.float64).reshape(-1, 3))
    return np.concatenate(parts) if parts else np.empty((0, 3))


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_demo_writes_a_merged_scan(tmp_path: Path) -> None:
    out = tmp_path / "scan.ply"
    rrd = tmp_path / "live.rrd"
    res, view = _view_during_the_demo(out, rrd)
    assert res.returncode == 0, res.stdout
    assert "6 passes at 2 table angles" in res.stdout
    cloud = read_ply(out)
    assert cloud["xyz"].shape[0] > 20000
    # The demo's own check: the part's top face lands where the scene puts it.
    line = next(x for x in res.stdout.splitlines() if "top face" in x)
    height_mm = float(line.split("cloud:")[1].split("mm")[0])
    assert height_mm == pytest.approx(70.0, abs=0.05)
    # The PNG preview next to the PLY, announced: the default size, with a picture in it.
    preview = out.with_suffix(".png")
    assert f"preview: {preview}" in res.stdout
    assert png_size(preview.read_bytes()) == (1200, 520)
    import matplotlib.image as mpimg

    assert float(mpimg.imread(preview)[:, :, :3].std()) > 0.05
    # wristscan view recorded the live cloud of the demo's daemon: points on the part and the
    # platter of the simulator's scene (the demo publishes in the part frame).
    assert view.returncode == 0, view.stdout + view.stderr
    pts = _rrd_points(rrd)
    assert pts.shape[0] > 1000
    dist = np.abs(part_signed_distance(demo_scene(), pts))
    assert float(np.median(dist)) < 0.5e-3


def test_demo_refuses_a_bad_output_name(tmp_path: Path) -> None:
    res = subprocess.run(
        [sys.executable, "-m", "wristscan.daemon.cli", "demo", "--out", str(tmp_path / "x.txt")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 2 and ".ply" in res.stderr and "Traceback" not in res.stderr
