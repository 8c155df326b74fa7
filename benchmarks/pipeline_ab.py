"""Side-by-side pipeline benchmark: the package at a commit (A) against the working tree (B).

The machine is shared and its speed drifts, so a change to a hot path is judged by runs of A
and B alternated in one session (A B A B ...), compared by their medians. A is a ``git
worktree`` of the commit whose ``calib``/``drivers``/``daemon`` are put first on
``PYTHONPATH`` (as ``wristscan.*``); both run the working tree's ``benchmarks/pipeline.py``, so
only the package differs (daemon, drivers and the simulator). With ``--own-script``, A runs the
commit's own ``benchmarks/pipeline.py`` (for a commit from before modules moved, whose package the
working tree's script cannot import). Prints each run and the medians; exits 1 when B's median
p99 latency is worse than A's by more than ``--tolerance``.

    .venv/bin/python benchmarks/pipeline_ab.py fdd6f34 --pairs 3 --duration 15
    .venv/bin/python benchmarks/pipeline_ab.py 26130b0 --pairs 5 --hot-path --rate 10000

``--hot-path`` compares the in-process hot path instead (CPU per profile of each step; A as its
own script measured it: until issue 21 a replica of the steps in ``benchmarks/pipeline.py``,
since then ``benchmarks/hot_path.py`` driving the pipeline's own tick).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
FIGURES = (
    "latency_p50_ms",
    "latency_p99_ms",
    "lost_profiles",
    "daemon_cpu_pct",
    "cpu_us_per_profile",
    "sim_sensor_cpu_pct",
    "runqueue_wait_ms_s",
)


def _package_view(commit: str, work: Path) -> Path:
    """A directory holding ``wristscan/{calib,drivers,daemon}`` of ``commit``."""
    tree = work / "tree"
    subprocess.run(
        ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), commit],
        check=True,
        capture_output=True,
    )
    view = work / "view" / "wristscan"
    view.mkdir(parents=True)
    for name in ("calib", "drivers", "daemon"):
        (view / name).symlink_to(tree / name)
    return view.parent


def _one_run(
    env: dict[str, str], out: Path, rate: str, duration: str, root: Path = ROOT
) -> dict[str, Any]:
    cmd = [
        sys.executable,
        str(root / "benchmarks" / "pipeline.py"),
        "--rates",
        rate,
        "--duration",
        duration,
        "--json",
        str(out),
    ]
    if root != ROOT:  # a commit's own script from before issue 21 still measured raw zenoh
        cmd += ["--raw-runs", "1"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=root)
    details = out.with_suffix(".details.json")
    if not details.exists():
        raise RuntimeError(f"benchmark run failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    d = json.loads(details.read_text())[0]
    row = {k: d[k] for k in FIGURES}
    process = d.get("daemon_latency_ms", {}).get("process", {})
    row["process_p50_ms"] = process.get("p50")
    row["process_p99_ms"] = process.get("p99")
    return row


_HOT_PATH = """
import json, sys
sys.path.insert(0, {bench!r})
try:
    from hot_path import measure_hot_path
except ImportError:  # a commit from before issue 21: the in-process figure lived in pipeline.py
    from pipeline import measure_hot_path
print(json.dumps(measure_hot_path({rate}, 2048)))
"""


def _hot_path_run(env: dict[str, str], rate: str, root: Path) -> dict[str, Any]:
    """One in-process hot-path measurement (``benchmarks/hot_path.py``, or the ``pipeline.py``
    of a commit from before it) in a fresh interpreter."""
    code = _HOT_PATH.format(bench=str(root / "benchmarks"), rate=float(rate))
    proc = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, cwd=root
    )
    if proc.returncode != 0:
        raise RuntimeError(f"hot path run failed:\n{proc.stderr[-2000:]}")
    row: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    return {"total_us": row["total_us"], **{k: v for k, v in row.items() if k.endswith("_us")}}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("commit", help="the A side: a commit of this repository")
    ap.add_argument("--pairs", type=int, default=3, help="A/B pairs of runs")
    ap.add_argument("--duration", default="15", help="measured window of each run, s")
    ap.add_argument("--rate", default="5000", help="sensor rate, Hz")
    ap.add_argument(
        "--tolerance", type=float, default=1.25, help="B's p99 may be this many times A's"
    )
    ap.add_argument(
        "--own-script",
        action="store_true",
        help="A runs the commit's own benchmarks/pipeline.py (a commit from before a move)",
    )
    ap.add_argument(
        "--hot-path",
        action="store_true",
        help="compare the in-process hot path (CPU per profile) instead of the whole chain; A "
        "runs the commit's own script (its measurement as it was then)",
    )
    ns = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="wristscan-ab-") as tmp:
        work = Path(tmp)
        try:
            view = _package_view(ns.commit, work)
        except subprocess.CalledProcessError as exc:
            print(f"cannot check out {ns.commit!r}: {exc.stderr.strip()}", file=sys.stderr)
            return 2
        try:
            rows: dict[str, list[dict[str, Any]]] = {"A": [], "B": []}
            for i in range(ns.pairs):
                for side in ("A", "B"):
                    env = dict(os.environ)
                    env.pop("PYTHONPATH", None)
                    root = ROOT
                    if side == "A":
                        env["PYTHONPATH"] = str(view)
                        root = work / "tree" if ns.own_script else ROOT
                    if ns.hot_path:
                        root = work / "tree" if side == "A" else ROOT
                        row = _hot_path_run(env, ns.rate, root)
                    else:
                        row = _one_run(env, work / f"{side}{i}.json", ns.rate, ns.duration, root)
                    rows[side].append(row)
                    shown = {k: round(v, 2) if isinstance(v, float) else v for k, v in row.items()}
                    print(f"{side} run {i + 1}: {shown}", flush=True)
        finally:
            subprocess.run(
                ["git", "-C", str(ROOT), "worktree", "remove", "--force", str(work / "tree")],
                capture_output=True,
            )
    med = {
        side: {
            k: statistics.median(r[k] for r in runs if r[k] is not None)
            for k in runs[0]
            if runs[0][k] is not None
        }
        for side, runs in rows.items()
    }
    for side in ("A", "B"):
        print(f"{side} ({ns.commit if side == 'A' else 'working tree'}) medians:")
        for k, v in med[side].items():
            print(f"  {k:24s} {v:12.2f}")
    if ns.hot_path:
        print(f"hot path total B / A: {med['B']['total_us'] / med['A']['total_us']:.2f}")
        return 0
    ratio = med["B"]["latency_p99_ms"] / med["A"]["latency_p99_ms"]
    print(f"p99 latency B / A: {ratio:.2f} (tolerance {ns.tolerance})")
    return 0 if ratio <= ns.tolerance else 1


if __name__ == "__main__":
    sys.exit(main())
