"""README's fresh-machine commands stay true: CI runs the test command README gives."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _blocks() -> list[str]:
    return re.findall(r"```sh\n(.*?)\n```", (ROOT / "README.md").read_text(), flags=re.S)


def test_ci_runs_the_readme_test_command() -> None:
    test_cmd = next(b for b in _blocks() if "pytest" in b)
    ci_lines = (ROOT / ".ci" / "run").read_text().splitlines()
    assert test_cmd.strip() in [line.strip() for line in ci_lines]


def test_main_job_command_uses_the_embedded_default() -> None:
    main_cmd = _blocks()[0]
    assert "wristscan demo" in main_cmd
    # The demo runs the embedded default, which is config/sim.toml shipped inside the package.
    shipped = ROOT / "daemon" / "default_sim.toml"
    assert shipped.read_text() == (ROOT / "config" / "sim.toml").read_text()
