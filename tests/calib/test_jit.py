"""calib.jit: the compiled kernels against the numpy paths, and the fallback where a JIT cannot
run (tests/calib/test_align_rows.py runs every alignment test on both paths)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from test_align_rows import poses_near_base

from wristscan.calib import align, jit, kinematics


def test_compiled_and_numpy_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    """The two paths give the same points to float32 rounding (FMA may round once less)."""
    rng = np.random.default_rng(5)
    p, n = 9, 300
    poses = poses_near_base(rng, p)
    y, z = np.linspace(-0.05, 0.05, n), rng.uniform(0.05, 0.4, (p, n))
    valid = rng.uniform(size=(p, n)) > 0.1
    monkeypatch.setattr(jit, "enabled", True)
    compiled = align.align_rows(y, z, valid, poses)
    monkeypatch.setattr(jit, "enabled", False)
    plain = align.align_rows(y, z, valid, poses)
    assert compiled.shape == plain.shape
    # one float32 ulp at 2 m is 0.24 um
    assert np.abs(compiled - plain).max() <= 2.5e-7


def test_compiled_forward_kinematics_agrees_and_is_batch_independent(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The pairer's per-tick forward kinematics compiled: numpy's products to rounding, NaN
    joints give NaN poses, and a pose's bits do not depend on its batch (blocks and records
    batch profiles differently and must pair them alike)."""
    rng = np.random.default_rng(8)
    q = rng.uniform(-np.pi, np.pi, (256, 6))
    q[5] = np.nan
    model = kinematics.get_model("ur5e")
    monkeypatch.setattr(jit, "enabled", True)
    assert jit.kernel("dh_forward") is not None
    compiled = kinematics.forward(model, q)
    alone = np.stack([kinematics.forward(model, q[k]) for k in (0, 7, 255)])
    shaped = kinematics.forward(model, q[:12].reshape(2, 6, 6))
    monkeypatch.setattr(jit, "enabled", False)
    plain = kinematics.forward(model, q)
    assert np.isnan(compiled[5, :3]).all() and np.isnan(plain[5, :3]).all()
    ok = np.arange(256) != 5
    assert np.abs(compiled[ok] - plain[ok]).max() <= 1e-15
    assert alone.tobytes() == compiled[[0, 7, 255]].tobytes()
    # The pairer's call: joints interpolated between samples in the same kernel, same bits.
    rows, frac = rng.integers(0, 255, 40), rng.uniform(0, 1, 40)
    rows[3] = 4  # between a sample and the NaN one
    between = kinematics.forward_between(model, q, rows, frac)  # numpy's path
    monkeypatch.setattr(jit, "enabled", True)
    q0 = q[rows]
    interpolated = kinematics.forward(model, q0 + (q[rows + 1] - q0) * frac[:, None])
    assert kinematics.forward_between(model, q, rows, frac).tobytes() == interpolated.tobytes()
    assert np.abs(between - interpolated)[np.arange(40) != 3].max() <= 1e-15
    assert shaped.tobytes() == compiled[:12].reshape(2, 6, 4, 4).tobytes()


def test_without_executable_memory_the_numpy_path_runs() -> None:
    """Under systemd's MemoryDenyWriteExecute (here the kernel's own switch for it, prctl
    PR_SET_MDWE, which a process cannot undo) numba cannot run: a warning, then numpy."""
    code = textwrap.dedent(
        """
        import ctypes, logging, numpy as np
        libc = ctypes.CDLL(None, use_errno=True)
        assert libc.prctl(65, 1, 0, 0, 0) == 0, ctypes.get_errno()  # PR_SET_MDWE, REFUSE_EXEC_GAIN
        logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")
        from wristscan.calib import align, jit, kinematics
        assert not jit.available()
        poses = np.tile(np.eye(4), (2, 1, 1))
        pts = align.align_rows(np.zeros(3), np.full((2, 3), 0.1), None, poses)
        assert pts.shape == (6, 3) and np.allclose(pts[:, 2], 0.1)
        print("numpy ok")
        """
    )
    env = {**os.environ, "WRISTSCAN_JIT": "1"}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         timeout=120)  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "numpy ok" in res.stdout
    assert "compiled hot-path kernels unavailable" in res.stderr and "Traceback" not in res.stderr
