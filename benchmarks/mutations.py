"""Deliberate faults that the default test run must catch (issue 16).

Each fault of ``tests/plugins/wristscan_faults.py`` (a wrong configured latency, a sensor
calibration off by 0.1 mm or 0.05 deg, the robot state at the nearest sample, the sensor clock's
drift ignored, a table encoder offset off by 0.05 deg) is applied from outside the code under
test: a ``sitecustomize.py`` in a temporary folder first on ``PYTHONPATH`` reaches every process
a test starts (pytest, the daemon, the CLI, the simulated devices) and patches one seam at import
time when ``WRISTSCAN_FAULT`` names the fault. See docs/mutations.md.

Run: ``.venv/bin/python benchmarks/mutations.py [--fast] [--fault NAME ...] [--keep DIR]``

1. A clean run of the selected tests (:data:`CELL_TESTS`, the cell-level tests of the default
   run, and :data:`SYNC_TESTS`, the synchroniser's tests against its simulated truth) with the
   same ``sitecustomize.py`` and no fault: every test must pass (a test that fails is run once
   more alone; passing then, it is reported as flaky).
2. For each fault, the same tests with ``WRISTSCAN_FAULT`` set (pytest in a subprocess,
   ``-p no:cacheprovider``, junit XML). A failed test *caught* the fault when the fault was used
   in its test file (each process logs the seams it patched and used, with the test running) and
   the test fails again when run once more with the fault (``--no-confirm`` skips this); a test
   that failed without using the fault, or passed on the second run, is listed apart.

``--fast``: only the smallest set of tests that catches every fault (a greedy cover of
:data:`CATCHERS`, the confirmed catches of the last full run), each fault run on its own
catchers from that set.

Exits 1 when the clean run fails or a fault is caught by no test, 2 when a listed test no longer
exists (the lists here and in docs/mutations.md need updating).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "plugins"))
import wristscan_faults as wf  # noqa: E402

_E2E = "tests/daemon/service/test_e2e_daemon.py::"
_SCAN = "tests/daemon/scan/test_scan.py::"
_SENSOR = "tests/daemon/calibrate/test_calib_sensor.py::"
_TABLE = "tests/daemon/calibrate/test_calib_table_latency.py::"
_TEACH = "tests/daemon/teach/test_teach.py::"
_PLUGIN = "tests/daemon/test_plugin_robot.py::"
_DEMO = "tests/daemon/simcell/test_demo.py::"
_PAIRING = "tests/daemon/sync/test_pairing.py::"

CELL_TESTS = [
    _E2E + "test_daemon_end_to_end",
    _SCAN + "test_an_unreachable_plan_is_refused_before_anything_moves",
    _SCAN + "test_recorded_profiles_match_the_scene_from_their_paired_poses",
    _SCAN + "test_scan_on_the_simulated_cell_writes_aligned_clouds",
    _SCAN + "test_icp_corrections_are_small_with_the_true_calibration_and_flag_a_wrong_one",
    _SENSOR + "test_automatic_calibration_on_the_simulated_cell",
    _SENSOR + "test_manual_mode_records_while_the_operator_moves",
    _TABLE + "test_table_procedure_on_the_simulated_cell",
    _TABLE + "test_latency_procedure_on_the_simulated_cell",
    _TEACH + "test_measure_and_teach_plane_on_the_simulated_cell",
    _TEACH + "test_teach_edge_and_replay_on_the_simulated_cell",
    _PLUGIN + "test_a_plugin_robot_runs_calibrate_latency_and_a_scan_pass",
    _DEMO + "test_demo_writes_a_merged_scan",
]
"""The cell-level tests of the default run: end to end on the simulated cell against its truth."""

SYNC_TESTS = [
    _PAIRING + "test_pairs_match_truth",
    _PAIRING + "test_table_angle_at_exposure",
]
"""The synchroniser against the truth of its own simulated streams, in-process (a few seconds):
the code faults (``nearest``, ``drift``) reach them; the configuration faults do not."""

CHEAPEST_FIRST = [
    *SYNC_TESTS,
    _E2E + "test_daemon_end_to_end",
    _TEACH + "test_measure_and_teach_plane_on_the_simulated_cell",
    _TABLE + "test_latency_procedure_on_the_simulated_cell",
    _TEACH + "test_teach_edge_and_replay_on_the_simulated_cell",
    *(t for t in CELL_TESTS if t.startswith(_SCAN)),
    _TABLE + "test_table_procedure_on_the_simulated_cell",
    _SENSOR + "test_manual_mode_records_while_the_operator_moves",
    _PLUGIN + "test_a_plugin_robot_runs_calibrate_latency_and_a_scan_pass",
    _SENSOR + "test_automatic_calibration_on_the_simulated_cell",
    _DEMO + "test_demo_writes_a_merged_scan",
]
"""The listed tests by their time in a clean run on the development machine (the sync tests
take a second, the e2e test 10-20 s, the scan tests share a 30 s fixture, the demo ~2 min):
``--fast`` prefers the first of equally good catchers."""

CATCHERS: dict[str, list[str]] = {
    "latency": [
        _E2E + "test_daemon_end_to_end",
        _SCAN + "test_icp_corrections_are_small_with_the_true_calibration_and_flag_a_wrong_one",
        _SENSOR + "test_automatic_calibration_on_the_simulated_cell",
        _SENSOR + "test_manual_mode_records_while_the_operator_moves",
        _TABLE + "test_table_procedure_on_the_simulated_cell",
        _TABLE + "test_latency_procedure_on_the_simulated_cell",
        _PLUGIN + "test_a_plugin_robot_runs_calibrate_latency_and_a_scan_pass",
    ],
    "s2f-shift": [
        _E2E + "test_daemon_end_to_end",
        _SCAN + "test_scan_on_the_simulated_cell_writes_aligned_clouds",
        _SCAN + "test_icp_corrections_are_small_with_the_true_calibration_and_flag_a_wrong_one",
        _TABLE + "test_table_procedure_on_the_simulated_cell",
        _TEACH + "test_measure_and_teach_plane_on_the_simulated_cell",
        _TEACH + "test_teach_edge_and_replay_on_the_simulated_cell",
        _PLUGIN + "test_a_plugin_robot_runs_calibrate_latency_and_a_scan_pass",
        _DEMO + "test_demo_writes_a_merged_scan",
    ],
    "s2f-rot": [
        _E2E + "test_daemon_end_to_end",
        _SCAN + "test_scan_on_the_simulated_cell_writes_aligned_clouds",
        _SCAN + "test_icp_corrections_are_small_with_the_true_calibration_and_flag_a_wrong_one",
        _TABLE + "test_table_procedure_on_the_simulated_cell",
        _TEACH + "test_measure_and_teach_plane_on_the_simulated_cell",
        _TEACH + "test_teach_edge_and_replay_on_the_simulated_cell",
        _PLUGIN + "test_a_plugin_robot_runs_calibrate_latency_and_a_scan_pass",
    ],
    "nearest": [
        _E2E + "test_daemon_end_to_end",
        _TABLE + "test_table_procedure_on_the_simulated_cell",
        _PLUGIN + "test_a_plugin_robot_runs_calibrate_latency_and_a_scan_pass",
        _PAIRING + "test_pairs_match_truth",
    ],
    "drift": [
        _E2E + "test_daemon_end_to_end",
        _SCAN + "test_icp_corrections_are_small_with_the_true_calibration_and_flag_a_wrong_one",
        _PAIRING + "test_pairs_match_truth",
        _PAIRING + "test_table_angle_at_exposure",
    ],
    "encoder": [_PLUGIN + "test_a_plugin_robot_runs_calibrate_latency_and_a_scan_pass"],
    "kinematics": [_E2E + "test_daemon_end_to_end"],
}
"""Per fault, the tests that caught it (confirmed): the full run of 2026-11-26, and for
``drift`` (since the e2e and scan cells' sensor clocks drift) and ``kinematics`` (since the e2e
cell's arm has kinematic errors) their runs on the tests concerned; docs/mutations.md has the
whole table. ``--fast`` picks from these."""

RUN_TIMEOUT_S = 3600.0


@dataclass
class Run:
    """One pytest run: per test node id, None (passed) or the first line of its failure."""

    label: str
    seconds: float
    exit_code: int
    outcome: dict[str, str | None] = field(default_factory=dict)
    patched: set[str] = field(default_factory=set)
    used: dict[str, set[str]] = field(default_factory=dict)
    """Seam used -> the test files it was used in."""
    problem: str = ""
    """Why the run says nothing (it crashed, timed out, lost a result); empty when sound."""

    @property
    def failed(self) -> list[str]:
        return [t for t, why in self.outcome.items() if why is not None]

    def exercised_in(self, node: str) -> bool:
        """Whether the fault was used in the test file of ``node`` (module fixtures run once per
        file, in the first test that needs them)."""
        path = node.partition("::")[0]
        return any(path in files for files in self.used.values())


@dataclass
class Verdict:
    """One fault's result."""

    run: Run
    caught: list[str] = field(default_factory=list)
    flaky: list[str] = field(default_factory=list)
    """Failed once with the fault, passed when run again with it."""
    unused: list[str] = field(default_factory=list)
    """Failed, but the fault was not used in its test file."""
    confirm_seconds: float = 0.0


def _node_key(node: str) -> tuple[str, str]:
    """(junit classname, name) of a pytest node id ``path.py::name`` (module-level tests)."""
    path, _, name = node.partition("::")
    return path.removesuffix(".py").replace("/", "."), name


def _first_line(text: str, limit: int = 150) -> str:
    line = next((x.strip() for x in text.splitlines() if x.strip()), "(no message)")
    return line if len(line) <= limit else line[: limit - 3] + "..."


def _read_junit(path: Path, tests: list[str]) -> dict[str, str | None]:
    keys = {_node_key(t): t for t in tests}
    out: dict[str, str | None] = {}
    for case in ET.parse(path).getroot().iter("testcase"):
        node = keys.get((case.get("classname", ""), case.get("name", "")))
        if node is None:
            continue
        bad = [c for c in case if c.tag in ("failure", "error")]
        if not bad:
            out[node] = None if case.find("skipped") is None else "skipped"
            continue
        kinds = "/".join(sorted({c.tag for c in bad}))
        out[node] = f"{kinds}: {_first_line(bad[0].get('message') or bad[0].text or '')}"
    return out


def _read_log(path: Path) -> tuple[set[str], dict[str, set[str]]]:
    patched: set[str] = set()
    used: dict[str, set[str]] = {}
    if path.exists():
        for line in path.read_text().splitlines():
            parts = line.split("\t")
            if len(parts) != 4:
                continue
            _, kind, what, test = parts
            if kind == "patched":
                patched.add(what)
            elif kind == "used":
                used.setdefault(what, set()).add(test.partition("::")[0])
    return patched, used


def run_tests(label: str, tests: list[str], work: Path, site: str, fault: str | None) -> Run:
    """pytest on ``tests`` in a subprocess, with ``fault`` (None: clean) in its environment."""
    stem = label.replace(" ", "_")
    xml, log, out = work / f"{stem}.xml", work / f"{stem}.faults.log", work / f"{stem}.out"
    log.unlink(missing_ok=True)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([site, *filter(None, [env.get("PYTHONPATH")])])
    env[wf.LOG_ENV] = str(log)
    env.pop(wf.ENV, None)
    if fault is not None:
        env[wf.ENV] = fault
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"]
    cmd += ["--junitxml", str(xml), "--durations", "0", *tests]
    t0 = time.monotonic()
    with out.open("w") as fh:
        try:
            code = subprocess.run(
                cmd, cwd=ROOT, env=env, stdout=fh, stderr=subprocess.STDOUT,
                timeout=RUN_TIMEOUT_S, check=False,
            ).returncode  # fmt: skip
        except subprocess.TimeoutExpired:
            code = -1
    run = Run(label, time.monotonic() - t0, code)
    run.patched, run.used = _read_log(log)
    if code == -1:
        run.problem = f"timed out after {RUN_TIMEOUT_S:.0f} s"
    elif code not in (0, 1) or not xml.exists():
        run.problem = f"pytest exited {code} (see {out})"
    else:
        run.outcome = _read_junit(xml, tests)
        missing = [t for t in tests if t not in run.outcome]
        if missing:
            run.problem = f"no result for {', '.join(missing)} (see {out})"
    return run


def check_collected(tests: list[str]) -> list[str]:
    """The node ids of ``tests`` that pytest cannot find."""
    res = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--collect-only", *tests],
        cwd=ROOT, capture_output=True, text=True, check=False,
    )  # fmt: skip
    found = {line.strip() for line in res.stdout.splitlines() if "::" in line}
    return [t for t in tests if t not in found]


def fast_selection(faults: list[str], order: list[str]) -> dict[str, list[str]]:
    """Per fault, the tests of the smallest set (greedy cover of :data:`CATCHERS`) that catch it."""
    left = {f for f in faults if CATCHERS.get(f)}
    rank = {t: -i for i, t in enumerate(order)}
    chosen: list[str] = []
    while left:
        counts: dict[str, int] = {}
        for f in left:
            for t in CATCHERS[f]:
                counts[t] = counts.get(t, 0) + 1
        # The test catching the most faults left; ties go to the cheapest.
        best = max(counts, key=lambda t: (counts[t], rank.get(t, -len(order))))
        chosen.append(best)
        left = {f for f in left if best not in CATCHERS[f]}
    return {f: [t for t in chosen if t in CATCHERS.get(f, [])] for f in faults}


def _short(node: str) -> str:
    return node.split("/")[-1]


def print_run(run: Run, fault: wf.Fault | None) -> None:
    print(f"-- {run.label}: {run.seconds:.0f} s, pytest exit {run.exit_code}")
    if run.problem:
        print(f"   RUN PROBLEM: {run.problem}")
    if fault is not None:
        print(f"   fault: {fault.what}")
        print(f"   patched: {', '.join(sorted(run.patched)) or 'NOTHING'}")
        for site, files in sorted(run.used.items()):
            print(f"   used: {site}, in {', '.join(sorted(_short(f) for f in files))}")
        if not run.used:
            print("   used: NEVER")
    for node, why in run.outcome.items():
        if why is None and fault is not None:
            continue
        if why is None:
            mark = "ok"
        elif fault is None:
            mark = "FAILED"
        else:
            mark = "failed" if run.exercised_in(node) else "failed, fault unused in its file"
        print(f"   {mark:<6} {_short(node)}")
        if why is not None:
            print(f"          {why}")


def judge(run: Run, confirm: bool, work: Path, site: str, fault: str) -> Verdict:
    """Which failures of ``run`` are catches (see the module docstring)."""
    v = Verdict(run)
    if run.problem:
        return v
    suspects = [t for t in run.failed if run.exercised_in(t)]
    v.unused = [t for t in run.failed if t not in suspects]
    if not confirm or not suspects:
        v.caught = suspects
        return v
    again = run_tests(f"{fault} confirm", suspects, work, site, fault)
    v.confirm_seconds = again.seconds
    for t in suspects:
        (v.caught if again.outcome.get(t) is not None else v.flaky).append(t)
    print(
        f"   run again with the fault ({again.seconds:.0f} s): failed again: {len(v.caught)}",
        end="",
    )
    print(f", passed (flaky): {', '.join(map(_short, v.flaky))}" if v.flaky else "")
    if again.problem:
        print(f"   confirmation run problem: {again.problem}")
    return v


def clean_run(tests: list[str], work: Path, site: str) -> tuple[Run, list[str], list[str]]:
    """The clean run; its failures run once more alone. Returns the run, the tests that failed
    twice and those that passed the second time (flaky)."""
    clean = run_tests("clean", tests, work, site, None)
    print_run(clean, None)
    failed, flaky = list(clean.failed), []
    if clean.problem:
        return clean, tests, []
    for t in list(failed):
        again = run_tests(f"clean again {_short(t).replace('::', '.')}", [t], work, site, None)
        if not again.problem and again.outcome.get(t) is None:
            failed.remove(t)
            flaky.append(t)
            print(f"   {_short(t)} passed when run again alone (flaky)")
    return clean, failed, flaky


def _summary(verdicts: dict[str, Verdict], pending: list[wf.Fault]) -> list[str]:
    bad = []
    for name, v in verdicts.items():
        cell = [t for t in v.caught if t in CELL_TESTS]
        if v.run.problem:
            verdict = "RUN PROBLEM"
        elif not v.run.used:
            verdict = "NOT USED"
        elif not v.caught:
            verdict = "NOT CAUGHT"
        else:
            verdict = "caught" if cell else "caught (unit)"
        if not v.caught:
            bad.append(name)
        secs = v.run.seconds + v.confirm_seconds
        who = ", ".join(_short(t) for t in v.caught) or "-"
        print(f"   {name:<10} {verdict:<13} {secs:5.0f} s  by {len(v.caught)}: {who}")
        for label, nodes in (("flaky", v.flaky), ("fault unused", v.unused)):
            if nodes:
                print(f"   {'':<10} {'':<13} {'':>7}  ({label}: {', '.join(map(_short, nodes))})")
    for f in pending:
        print(f"   {f.name:<10} pending: {f.pending}")
    return bad


def _write_json(path: Path, tests: list[str], clean: Run, verdicts: dict[str, Verdict]) -> None:
    doc = {
        "tests": tests,
        "clean": {"seconds": clean.seconds, "outcome": clean.outcome, "problem": clean.problem},
        "faults": {
            n: {
                "seconds": v.run.seconds + v.confirm_seconds,
                "caught_by": v.caught,
                "flaky": v.flaky,
                "failed_without_using_the_fault": v.unused,
                "outcome": v.run.outcome,
                "used": {k: sorted(s) for k, s in v.run.used.items()},
                "problem": v.run.problem,
            }
            for n, v in verdicts.items()
        },
    }
    path.write_text(json.dumps(doc, indent=2))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fast", action="store_true", help="only the smallest catching set")
    ap.add_argument("--fault", action="append", choices=sorted(wf.FAULTS), help="only these")
    ap.add_argument("--tests", nargs="+", help="node ids to run instead of the listed ones")
    ap.add_argument("--no-confirm", action="store_true", help="do not re-run catching tests")
    ap.add_argument("--keep", type=Path, help="keep junit XML, logs and output in this folder")
    ap.add_argument("--json", type=Path, help="write the results here")
    args = ap.parse_args()

    pending = [f for f in wf.FAULTS.values() if f.pending]
    faults = [n for n in (args.fault or wf.FAULTS) if not wf.FAULTS[n].pending]
    listed = CELL_TESTS + SYNC_TESTS
    if args.fast:
        per_fault = fast_selection(faults, CHEAPEST_FIRST)
        uncovered = [f for f in faults if not per_fault[f]]
        if uncovered:
            print(f"--fast: no known catcher for {', '.join(uncovered)}; run the full form")
            return 1
        tests = [t for t in listed if any(t in v for v in per_fault.values())]
    else:
        tests = list(args.tests or listed)
        per_fault = {f: tests for f in faults}
    missing = check_collected(tests)
    if missing:
        print("these tests no longer exist (update the lists in benchmarks/mutations.py and the")
        print("table in docs/mutations.md):\n  " + "\n  ".join(missing))
        return 2

    form = " (fast)" if args.fast else ""
    print(f"== mutations: {len(faults)} faults on {len(tests)} tests{form}")
    work = args.keep or Path(tempfile.mkdtemp(prefix="wristscan-mutations-"))
    work.mkdir(parents=True, exist_ok=True)
    verdicts: dict[str, Verdict] = {}
    with tempfile.TemporaryDirectory(prefix="wristscan-faults-") as site_dir:
        site = wf.write_sitecustomize(site_dir)
        clean, clean_failed, clean_flaky = clean_run(tests, work, site)
        for name in faults:
            run = run_tests(name, per_fault[name], work, site, name)
            print_run(run, wf.FAULTS[name])
            verdicts[name] = judge(run, not args.no_confirm, work, site, name)

    print("== summary")
    state = "FAIL" if clean_failed else "pass"
    flaky = f", flaky: {', '.join(map(_short, clean_flaky))}" if clean_flaky else ""
    print(f"   clean run  {state:<13} {clean.seconds:5.0f} s  {len(tests)} tests{flaky}")
    bad = _summary(verdicts, pending)
    total = clean.seconds + sum(v.run.seconds + v.confirm_seconds for v in verdicts.values())
    if args.keep or clean_failed or bad:  # what went wrong stays to be read
        print(f"   total {total / 60:.1f} min; junit XML, output and fault logs in {work}")
    else:
        print(f"   total {total / 60:.1f} min (--keep DIR keeps the junit XML, output and logs)")
        shutil.rmtree(work, ignore_errors=True)
    if args.json:
        _write_json(args.json, tests, clean, verdicts)
    if clean_failed:
        print("   the clean run failed: the catches above mean nothing until it passes")
    if bad:
        print(f"   not caught: {', '.join(bad)}")
    return 1 if clean_failed or bad else 0


if __name__ == "__main__":
    sys.exit(main())
