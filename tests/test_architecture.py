"""The package's layers (docs/architecture.md): every import points down or sideways within a layer,
and no modules or packages import each other in a circle."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "demon_lab"

LAYERS = {
    "resources": 0, "core": 0,
    "nets": 1, "data": 1, "baselines": 1,
    "pipeline": 2,
    "reporting": 3,
    "app": 4, "tools": 4, "commands": 4,
}
"""The layer of each top-level part of demon_lab, from the model library (0, 1) through the pipeline
(2) and reporting (3) to the commands (4): ``commands`` are the modules at the top of the package
(``__main__`` and the entry module of each ``python -m demon_lab.NAME``)."""


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


MODULES = _modules()


def _imports(name: str, path: Path) -> set[str]:
    """The demon_lab modules ``name`` imports anywhere in its body (lazy imports included)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "demon_lab":
            for alias in node.names:
                sub = f"{node.module}.{alias.name}"
                found.add(sub if sub in MODULES else node.module)
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.split(".")[0] == "demon_lab"}
    return {m for m in found if m in MODULES and m != name}


def _part(module: str) -> str:
    parts = module.split(".")
    if len(parts) == 1:
        return "commands"  # demon_lab itself (its __init__): a docstring and the version
    if parts[1] in LAYERS:
        return parts[1]
    return "commands"


GRAPH = {name: _imports(name, path) for name, path in MODULES.items()}


def test_every_part_of_the_package_has_a_layer():
    tops = {p.stem if p.is_file() else p.name for p in PACKAGE.iterdir()
            if (p.suffix == ".py" or (p.is_dir() and any(p.glob("*.py"))))} - {"__init__"}
    packages = {t for t in tops if (PACKAGE / t).is_dir()}
    assert packages <= set(LAYERS), packages - set(LAYERS)
    commands = {t for t in tops - packages if t != "resources"}
    for name in commands:  # a module at the top is a command: it runs one main() of a lower layer
        text = (PACKAGE / f"{name}.py").read_text()
        assert 'if __name__ == "__main__":' in text or name == "__main__", name


def test_no_import_points_up_a_layer():
    upward = [f"{a} -> {b}" for a, deps in GRAPH.items() for b in deps
              if LAYERS[_part(b)] > LAYERS[_part(a)]]
    assert upward == []


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


@pytest.mark.parametrize("level", ["module", "package"])
def test_nothing_imports_in_a_circle(level):
    if level == "module":
        graph = GRAPH
    else:  # the part of the package a module is in: demon_lab.pipeline for demon_lab.pipeline.stages.cache
        def folder(m):
            return ".".join(m.split(".")[:2])
        graph = {}
        for a, deps in GRAPH.items():
            graph.setdefault(folder(a), set()).update(folder(b) for b in deps if folder(b) != folder(a))
    assert _cycles(graph) == []


def test_the_checks_see_a_circle_and_an_upward_import():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _part("demon_lab.pipeline.stages.cache") == "pipeline" and _part("demon_lab.report") == "commands"
    assert "demon_lab.core.geometry" in GRAPH["demon_lab.data.sample"]  # lazy and top-level imports both seen
    assert "demon_lab.reporting.report" in GRAPH["demon_lab.app.callbacks"]
