"""Shared printing for benchmark scripts: each figure beside its target, non-zero exit on a miss."""

from __future__ import annotations

import json
import sys
from dataclasses import asdict, dataclass


@dataclass
class Figure:
    name: str
    value: float
    unit: str
    target: str
    ok: bool | None
    """None: reported only, no target."""


def report(title: str, figures: list[Figure], json_out: str | None = None) -> int:
    """Print a table of figures; return 1 if any target was missed, else 0."""
    print(f"== {title}")
    width = max((len(f.name) for f in figures), default=10)
    for f in figures:
        verdict = "info" if f.ok is None else ("ok" if f.ok else "MISS")
        print(f"  {f.name:<{width}}  {f.value:>12.6g} {f.unit:<8} target {f.target:<18} {verdict}")
    if json_out:
        with open(json_out, "w") as fh:
            json.dump([asdict(f) for f in figures], fh, indent=2)
    missed = [f.name for f in figures if f.ok is False]
    if missed:
        print(f"  missed: {', '.join(missed)}")
        return 1
    return 0


def main_exit(code: int) -> None:
    sys.exit(code)
