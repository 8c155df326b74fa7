"""Every file path and every ``wristscan.*`` import path the documentation names exists: the docs
are a map of the rooms, and a map that names rooms that moved sends readers nowhere."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted([ROOT / "README.md", *(ROOT / "docs").glob("*.md")])
ROOTS = "calib|drivers|daemon|benchmarks|tests|config|systemd|docs"
PATH = re.compile(rf"(?<![\w/.-])((?:{ROOTS})/[\w/.-]*)")
DOTTED = re.compile(r"\bwristscan\.(?:calib|drivers|daemon)(?:\.\w+)+")


def _resolves(dotted: str) -> bool:
    """``dotted`` is a module, or an attribute chain of one."""
    parts = dotted.split(".")
    for cut in range(len(parts), 1, -1):
        try:
            obj: object = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError:
            continue
        for attr in parts[cut:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_paths_named_in_the_docs_exist(doc: Path) -> None:
    text = doc.read_text(encoding="utf-8")
    missing = []
    for m in PATH.finditer(text):
        path = m.group(1).rstrip(".")
        if "*" in path or "<" in path:
            continue
        if not (ROOT / path).exists():
            missing.append(path)
    for m in DOTTED.finditer(text):
        if not _resolves(m.group(0).rstrip(".")):
            missing.append(m.group(0))
    assert not missing, f"{doc.name} names what does not exist: {sorted(set(missing))}"
