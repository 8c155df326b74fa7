"""The wheel installs into a fresh virtual environment and every subpackage imports from it."""

from __future__ import annotations

import subprocess
import sys
import sysconfig
import tomllib
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SUBPACKAGES: list[str] = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
    "packages"
]


@pytest.mark.slow
def test_every_code_folder_is_listed() -> None:
    folders = {
        "wristscan." + ".".join(p.parent.relative_to(ROOT).parts)
        for top in ("calib", "drivers", "daemon")
        for p in (ROOT / top).rglob("__init__.py")
    }
    assert folders == set(SUBPACKAGES)


@pytest.mark.slow
def test_wheel_installs_and_imports(tmp_path: Path) -> None:
    dist = tmp_path / "dist"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "build",
            "--wheel",
            "--no-isolation",
            "--outdir",
            str(dist),
            str(ROOT),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    wheels = list(dist.glob("wristscan-*.whl"))
    assert len(wheels) == 1
    env_dir = tmp_path / "env"
    # A fresh environment without a pip of its own (ensurepip costs ~4.5 s): this interpreter's
    # pip installs into it (``--python``).
    venv.EnvBuilder(with_pip=False).create(env_dir)
    py = env_dir / "bin" / "python"
    subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(py), "install", "-q", "--no-deps",
         "--no-index", str(wheels[0])],
        check=True,
        timeout=300,
    )  # fmt: skip
    # Dependencies come from this interpreter's site-packages (a plain path entry, so the
    # editable install's finder there is not activated); wristscan itself must come from the wheel.
    env_site = subprocess.run(
        [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    (Path(env_site) / "outer_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    code = (
        "import importlib, pathlib\n"
        f"for name in {SUBPACKAGES!r}:\n"
        "    m = importlib.import_module(name)\n"
        f"    assert pathlib.Path(m.__file__).is_relative_to({str(env_dir)!r}), m.__file__\n"
        "import wristscan.calib.se3, wristscan.drivers.records\n"
        "print('ok')\n"
    )
    out = subprocess.run(
        [str(py), "-c", code], check=True, capture_output=True, text=True, cwd=tmp_path, timeout=120
    )
    assert out.stdout.strip() == "ok"
    script = env_dir / "bin" / "wristscan"
    assert script.exists()
    ver = subprocess.run([str(script), "--version"], capture_output=True, text=True, timeout=120)
    assert ver.returncode == 0 and ver.stdout.startswith("wristscan "), ver.stderr
