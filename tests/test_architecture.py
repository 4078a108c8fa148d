"""The package's layers (docs/architecture.md), stated as import-linter contracts in
``pyproject.toml`` (``[tool.importlinter]``): every import points down, or sideways within a layer,
and no modules or packages import each other in a circle. The tests run the contracts on demon_lab
and show that they fail on a package that breaks them."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import tomllib

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "demon_lab"
CONFIG = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]


def _lint(config: Path, cache: Path, path: Path = ROOT) -> int:
    """lint-imports' exit status for ``config``, with ``path`` first on sys.path (in a process of its
    own: the linter configures logging, which would silence the loggers of the tests after it)."""
    code = ("import sys; from importlinter.cli import lint_imports; "
            f"sys.exit(lint_imports(config_filename={str(config)!r}, no_logo=True, cache_dir={str(cache)!r}))")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(path), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-c", code], cwd=path, env=env, capture_output=True).returncode


def _layered() -> set[str]:
    """Every module or package the layers contract names, relative to demon_lab."""
    (layers,) = [c["layers"] for c in CONFIG["contracts"] if c["type"] == "layers"]
    return {m.strip().removeprefix("demon_lab.") for layer in layers for m in layer.replace("|", ":").split(":")}


def test_every_part_of_the_package_has_a_layer():
    """A part of the package that no layer names would escape the contract; a module at the top is a
    command, which runs one main() of a lower layer."""
    tops = {p.stem if p.is_file() else p.name for p in PACKAGE.iterdir()
            if p.suffix == ".py" or (p.is_dir() and (p / "__init__.py").is_file())} - {"__init__"}
    assert tops - _layered() == set()
    for name in {t for t in tops if (PACKAGE / f"{t}.py").is_file()} - {"resources", "__main__"}:
        assert 'if __name__ == "__main__":' in (PACKAGE / f"{name}.py").read_text(), name


def test_the_package_keeps_its_import_contracts(tmp_path):
    """No import points up a layer, and nothing imports in a circle (lint-imports exits 0)."""
    assert _lint(ROOT / "pyproject.toml", tmp_path) == 0


@pytest.mark.parametrize("breach", [None, "upward", "circle"])
def test_the_contracts_fail_on_an_upward_import_and_on_a_circle(tmp_path, breach):
    """The same two contract types, on a toy package: high over low, kept (high imports low); then
    an import of high from low (upward), or two modules of one package importing each other (a circle)."""
    package = tmp_path / "toy"
    (package / "high").mkdir(parents=True)
    (package / "low").mkdir()
    for path in (package, package / "high", package / "low"):
        (path / "__init__.py").write_text("")
    (package / "high" / "a.py").write_text("from toy.low import b\n")
    (package / "low" / "b.py").write_text({None: "", "upward": "def f():\n    from toy.high import a  # lazy: counts\n",
                                           "circle": "from toy.low import c\n"}[breach])
    (package / "low" / "c.py").write_text("from toy.low import b\n" if breach == "circle" else "")
    config = tmp_path / "contracts.toml"
    config.write_text('[tool.importlinter]\nroot_package = "toy"\n'
                      '[[tool.importlinter.contracts]]\nname = "layers"\ntype = "layers"\n'
                      'layers = ["toy.high", "toy.low"]\n'
                      '[[tool.importlinter.contracts]]\nname = "circles"\ntype = "acyclic_siblings"\n'
                      'ancestors = ["toy"]\n')
    assert _lint(config, tmp_path / "cache", path=tmp_path) == (0 if breach is None else 1)
