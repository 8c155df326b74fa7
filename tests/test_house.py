"""The house rules of docs/architecture.md, checked over the source tree: rooms of a readable size,
imports only downwards, no import cycle, the simulator only where it belongs."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {
    "calib": "wristscan.calib",
    "drivers": "wristscan.drivers",
    "daemon": "wristscan.daemon",
}
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80
LAYER = {"wristscan.calib": 0, "wristscan.drivers": 1, "wristscan.daemon": 2}
SIM = "wristscan.drivers.sim"
MAY_IMPORT_SIM = ("wristscan.drivers.sim", "wristscan.daemon.simcell", "wristscan.daemon.cli")


def _modules() -> dict[str, tuple[Path, ast.Module]]:
    out = {}
    for folder, package in PACKAGES.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = path.relative_to(ROOT / folder).with_suffix("").parts
            name = ".".join((package, *parts)).removesuffix(".__init__")
            out[name] = (path, ast.parse(path.read_text(encoding="utf-8"), str(path)))
    return out


MODULES = _modules()


def _rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING"
    )


def _imports(name: str, tree: ast.Module) -> set[str]:
    """The project modules ``name`` imports when it runs (at import time or inside functions;
    not under ``if TYPE_CHECKING``), resolved to module names."""
    found: set[str] = set()
    is_package = MODULES[name][0].name == "__init__.py"

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".")
                anchor = anchor[: len(anchor) - node.level + (1 if is_package else 0)]
                base = ".".join([*anchor, *([base] if base else [])])
            found.add(base)
            found.update(f"{base}.{a.name}" for a in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return {m for m in found if m in MODULES}


GRAPH = {name: _imports(name, tree) for name, (_, tree) in MODULES.items()}


def test_modules_and_functions_stay_readable() -> None:
    too_long = []
    for _, (path, tree) in MODULES.items():
        lines = path.read_text(encoding="utf-8").count("\n")
        if lines > MAX_MODULE_LINES:
            too_long.append(f"{_rel(path)}: {lines} lines (at most {MAX_MODULE_LINES})")
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = (node.end_lineno or node.lineno) - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    too_long.append(f"{_rel(path)}:{node.lineno} {node.name}(): {n} lines")
    assert not too_long, "split these (docs/architecture.md):\n" + "\n".join(too_long)


def _layer(module: str) -> int:
    return next(v for k, v in LAYER.items() if module == k or module.startswith(k + "."))


def test_imports_only_go_downwards() -> None:
    upward = [
        f"{m} imports {i}"
        for m, targets in GRAPH.items()
        for i in sorted(targets)
        if _layer(i) > _layer(m)
    ]
    assert not upward, "\n".join(upward)


def test_only_the_simulated_cell_and_the_cli_import_the_simulator() -> None:
    def inside(module: str, prefixes: tuple[str, ...]) -> bool:
        return any(module == p or module.startswith(p + ".") for p in prefixes)

    wrong = [
        f"{m} imports {i}"
        for m, targets in GRAPH.items()
        if not inside(m, MAY_IMPORT_SIM)
        for i in sorted(targets)
        if inside(i, (SIM,))
    ]
    assert not wrong, "production code must not import the simulator:\n" + "\n".join(wrong)


def _cycle() -> list[str] | None:
    """One import cycle among the project's modules, or None (depth-first search). A package's
    ``__init__`` importing its own submodules is how re-exports work, not a cycle."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def edges(m: str) -> list[str]:
        return sorted(t for t in GRAPH[m] if not t.startswith(m + ".") and t != m)

    def dfs(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for t in edges(m):
            if state.get(t) == 1 and not m.startswith(t + "."):
                return [*stack[stack.index(t) :], t]
            if t not in state and (found := dfs(t)) is not None:
                return found
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(GRAPH):
        if m not in state and (found := dfs(m)) is not None:
            return found
    return None


def test_no_import_cycle() -> None:
    cycle = _cycle()
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


@pytest.mark.parametrize(
    ("source", "expected"),
    [
        ("from wristscan.daemon.simcell import cell\n", {"wristscan.daemon.simcell.cell"}),
        ("if TYPE_CHECKING:\n    import wristscan.drivers.sim.cell\n", set()),
        ("def f():\n    from wristscan.calib.se3 import make\n", {"wristscan.calib.se3"}),
    ],
)
def test_the_import_reader_sees_lazy_imports_and_skips_type_checking(
    source: str, expected: set[str]
) -> None:
    assert _imports("wristscan.daemon.config", ast.parse(source)) & set(MODULES) >= expected
    if not expected:
        assert _imports("wristscan.daemon.config", ast.parse(source)) == set()
