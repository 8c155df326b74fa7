"""``wristscan view --record FILE.rrd`` (in this process) against a real zenoh publisher: the
daemon's own zenoh face (DaemonZenoh) on loopback, as in test_record_status.py, publishing
batches whose coordinates encode their sequence number and answering the calibration query.

The recording is read back with rerun's own reader (``rerun.chunk.RrdReader``): every batch in
it holds exactly the points published under its sequence number, and the sensor frame is the
published calibration.
"""

from __future__ import annotations

import builtins
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from support import free_tcp_port, loopback_publisher, own_loopback_host
from typer.testing import CliRunner

from wristscan.calib import se3
from wristscan.daemon.cli.app import app
from wristscan.daemon.cloud.zenoh_io import DaemonZenoh

PREFIX = "wristscan/viewtest"
B = 300
SENSOR2FLANGE = se3.make(se3.rot_x(0.3) @ se3.rot_z(-1.1), np.array([0.01, -0.02, 0.095]))
CALIBRATION = {
    "kind": "sensor2flange",
    "transform": {"name": "sensor2flange", "matrix_rows": SENSOR2FLANGE.tolist()},
}


def batch_xyz(seq: int) -> np.ndarray:
    xyz = np.empty((B, 3), np.float32)
    xyz[:, 0] = seq * 1e-3
    xyz[:, 1] = np.arange(B) * 1e-4
    xyz[:, 2] = 0.02 * np.sin(np.arange(B) * 0.05 + seq)
    return xyz


def batch_flange(seq: int) -> np.ndarray:
    """The flange of the batch's 4 profiles (4, 4, 4): a line along y, one step per profile."""
    k = 4 * seq + np.arange(4)
    return se3.make(se3.rot_z(0.001 * k), np.stack([0.3 + 0 * k, k * 1e-4, 0.4 + 0 * k], 1))


def _publish(dz: DaemonZenoh, k: int) -> None:
    seq = dz.seq
    dz.publish_cloud(
        batch_xyz(seq),
        t_first_ns=1_700_000_000_000_000_000 + seq * 10_000_000,
        t_last_ns=1_700_000_000_000_000_000 + seq * 10_000_000 + 9_000_000,
        n_profiles=4,
        frame_id="base",
    )
    f2b = batch_flange(seq)
    t = 1_700_000_000_000_000_000 + seq * 10_000_000 + np.arange(4) * 3_000_000
    dz.publish_pose(seq, "base", t, f2b, f2b @ SENSOR2FLANGE)


@pytest.fixture
def daemon() -> Iterator[str]:
    with loopback_publisher(
        PREFIX, _publish, calibration=lambda: CALIBRATION, stats=lambda: {}
    ) as (endpoint, _):
        yield endpoint


def _entities(path: Path) -> dict[str, list[Any]]:
    """Record batches of every entity in the .rrd, read with rerun's own reader."""
    from rerun.chunk import RrdReader

    out: dict[str, list[Any]] = {}
    for chunk in RrdReader(path).stream():
        out.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return out


def _column(batch: Any, suffix: str) -> Any:
    name = next(n for n in batch.schema.names if n.endswith(suffix))
    return batch.column(name)


def test_view_records_the_live_cloud_and_the_calibration(daemon: str, tmp_path: Path) -> None:
    rrd = tmp_path / "live.rrd"
    args = ["view", "--prefix", PREFIX, "--connect", daemon, "--record", str(rrd)]
    res = CliRunner().invoke(app, [*args, "--seconds", "2"])
    assert res.exit_code == 0, res.output
    ent = _entities(rrd)
    seqs: list[int] = []
    for batch in ent["/world/cloud"]:
        positions = _column(batch, "Points3D:positions")
        for row in range(batch.num_rows):
            seq = int(batch.column("seq")[row].as_py())
            xyz = np.asarray(positions[row].values.flatten().to_numpy()).reshape(-1, 3)
            np.testing.assert_array_equal(xyz, batch_xyz(seq))
            seqs.append(seq)
    assert len(seqs) >= 20, "two seconds at 100 batches/s gave fewer than 20 batches"
    assert len(set(seqs)) == len(seqs)
    summary = dict(line.split(None, 1) for line in res.stdout.splitlines() if line.strip())
    assert summary["points"] == str(B * len(seqs))
    # The sensor frame under the flange is the calibration the daemon answered.
    tf = ent["/calibration/flange/sensor"][0]
    translation = np.asarray(_column(tf, "Transform3D:translation")[0].as_py(), float).reshape(3)
    mat = np.asarray(_column(tf, "Transform3D:mat3x3")[0].as_py(), float).reshape(3, 3)
    np.testing.assert_allclose(translation, SENSOR2FLANGE[:3, 3], atol=1e-6)
    np.testing.assert_allclose(mat.T, SENSOR2FLANGE[:3, :3], atol=1e-6)  # rerun: column-major
    assert "/world/laser_trail" in ent
    # the robot's pose stream: the flange trail holds each batch's last flange position, in
    # order; the sensor sits where flange and calibration put it
    strips = _column(ent["/world/flange_trail"][-1], "LineStrips3D:strips")[0].as_py()
    trail = np.asarray(strips[0], float).reshape(-1, 3)
    steps = np.round(trail[:, 1] / 4e-4 - 0.75).astype(int)  # the batch each point came from
    assert len(trail) >= 10 and np.all(np.diff(steps) > 0)
    want = np.stack([batch_flange(int(k))[-1, :3, 3] for k in steps])
    np.testing.assert_allclose(trail, want, atol=1e-9)
    sensor = ent["/world/sensor"][-1]
    seq = int(sensor.column("seq")[sensor.num_rows - 1].as_py())
    translation = np.asarray(
        _column(sensor, "Transform3D:translation")[sensor.num_rows - 1].as_py(), float
    ).reshape(3)
    want_s = batch_flange(seq)[-1] @ SENSOR2FLANGE
    np.testing.assert_allclose(translation, want_s[:3, 3], atol=1e-6)
    assert int(summary["poses"].split()[0]) >= 20


def test_view_refuses_a_record_file_that_is_not_rrd(tmp_path: Path) -> None:
    args = ["view", "--prefix", PREFIX, "--connect", "tcp/127.0.0.1:9"]
    res = CliRunner().invoke(app, [*args, "--record", str(tmp_path / "x.ply")])
    assert res.exit_code == 2 and ".rrd" in res.output
    assert not (tmp_path / "x.ply").exists()


def test_view_without_a_daemon_fails_and_leaves_no_file(tmp_path: Path) -> None:
    host = own_loopback_host()
    endpoint = f"tcp/{host}:{free_tcp_port(host)}"  # nobody listens there
    rrd = tmp_path / "x.rrd"
    args = ["view", "--prefix", PREFIX, "--connect", endpoint, "--timeout", "0.5"]
    res = CliRunner().invoke(app, [*args, "--record", str(rrd)])
    assert res.exit_code == 1 and "no wristscan daemon answered" in res.output
    assert not rrd.exists()


def test_view_without_rerun_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    real_import = builtins.__import__

    def no_rerun(name: str, *args: Any, **kwargs: Any) -> Any:
        if name == "rerun" or name.startswith("rerun."):
            raise ImportError(f"No module named {name!r}")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_rerun)
    res = CliRunner().invoke(app, ["view", "--prefix", PREFIX, "--connect", "tcp/127.0.0.1:9"])
    assert res.exit_code == 2 and "pip install 'wristscan[view]'" in res.output
