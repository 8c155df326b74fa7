"""Every calib/ accuracy and speed target of issue 2 in one run.

Runs the topic benchmarks (sphere, TCP, hand-eye, kinematics, alignment/ICP), prints each figure
beside its target and exits non-zero when any target is missed. ``--json FILE`` also writes the
figures (docs/benchmarks.md keeps the current ones).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from _report import Figure, report

TOPICS = ["calib_sphere", "calib_tcp", "calib_handeye", "calib_kinematics", "calib_align"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", help="write all figures to this file")
    parser.add_argument("--only", nargs="*", choices=TOPICS, help="run these topics only")
    args = parser.parse_args(argv)
    figures: list[Figure] = []
    for topic in args.only or TOPICS:
        module = importlib.import_module(topic)
        got = module.run()
        figures.extend(Figure(f"{topic}: {f.name}", f.value, f.unit, f.target, f.ok) for f in got)
    return report("calib accuracy and speed", figures, json_out=args.json)


if __name__ == "__main__":
    sys.exit(main())
