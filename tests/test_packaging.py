"""demon_lab stands on its own: nothing reads outside the package or the repository, and a
non-editable install runs from an unrelated directory with its configs, study specs and bundled
data found through the package."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# The names of the documents beside the project's checkout, and the path tricks that reach them,
# written in pieces so that this file does not itself cite them.
_BESIDE = ("../" + "sha" + "red", "sha" + "red/data", "DEMON_" + "REFERENCE", "DES" + "IGN.md", "STA" + "CK.md",
           "STY" + "LE.md", "parents" + "[2]", ".parent" + ".parent", "sp" + "ec section", "sp" + "ec §")
OUTSIDE = re.compile("|".join(re.escape(word) for word in _BESIDE))


def _tracked(*patterns: str) -> list[Path]:
    listed = subprocess.run(["git", "ls-files", *patterns], cwd=ROOT, capture_output=True, text=True, check=True)
    return [ROOT / line for line in listed.stdout.splitlines()]


def test_no_file_reads_or_cites_anything_beside_the_repository():
    files = _tracked("*.py", "*.yaml", "*.toml", "*.md", "*.csv", ".ci/*")
    assert len(files) > 50
    hits = [f"{f.relative_to(ROOT)}:{n}: {line.strip()}" for f in files
            for n, line in enumerate(f.read_text(errors="replace").splitlines(), 1) if OUTSIDE.search(line)]
    assert hits == []


def test_the_package_finds_its_files_through_itself():
    import demon_lab
    from demon_lab import resources

    if Path(demon_lab.__file__).resolve().parent == ROOT / "demon_lab":  # installed from this checkout
        # conf/ and ablations/ at the top of the repository, found through the package they install as
        assert resources.CONF.resolve() == ROOT / "conf" and resources.STUDIES.resolve() == ROOT / "ablations"
    assert (resources.CONF / "config.yaml").is_file() and (resources.CONF / "experiment").is_dir()
    assert {p.stem for p in resources.STUDIES.glob("*.yaml")} >= {"iterations", "gt_flow_oracle", "baselines"}
    assert (resources.DATA / "sun3d_train_0.1m_to_0.2m_00000" / "poses.txt").is_file()
    assert (resources.DATA / "README.md").read_text().count("Licence") == 1


def test_every_package_and_its_files_are_declared_for_the_wheel():
    """pyproject.toml lists the packages explicitly (two of them are folders beside the code): every
    folder of Python modules is listed, and each listed one exists where the mapping says; nothing is
    installed outside demon_lab (the sweeps run on Hydra's own sweeper: no plugin of demon_lab's)."""
    tomllib = pytest.importorskip("tomllib")
    setup = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    mapped = setup["package-dir"]
    found = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "demon_lab").rglob("*.py")
             if "__pycache__" not in p.parts}
    assert set(setup["packages"]) == found | set(mapped)
    assert all(p == "demon_lab" or p.startswith("demon_lab.") for p in setup["packages"])
    assert mapped == {"demon_lab.conf": "conf", "demon_lab.ablations": "ablations"}
    for package, folder in mapped.items():
        assert (ROOT / folder / "__init__.py").is_file(), package
    assert any((ROOT / "conf").rglob("*.yaml")) and any((ROOT / "ablations").glob("*.yaml"))


@pytest.mark.slow
def test_a_wheel_installed_elsewhere_runs_the_smoke_job_the_report_and_tests(tmp_path):
    """``pip install .`` (here: the wheel unpacked into a folder on PYTHONPATH, the environment's
    other packages reused), then commands run from a directory that is not the checkout."""
    wheels, site, work = tmp_path / "wheels", tmp_path / "site", tmp_path / "elsewhere"
    work.mkdir()
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run([*pip, "wheel", "--no-deps", "--no-build-isolation", "-w", str(wheels), str(ROOT)], check=True,
                   cwd=tmp_path, capture_output=True)
    (wheel,) = wheels.glob("demon_lab-*.whl")
    subprocess.run([*pip, "install", "--no-deps", "--target", str(site), str(wheel)], check=True, capture_output=True)
    env = {**os.environ, "PYTHONPATH": str(site), "DEMON_LAB_CACHE": str(tmp_path / "cache")}

    def run(*args: str, timeout: int = 600) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, *args], cwd=work, env=env, capture_output=True, text=True,
                              timeout=timeout)

    where = run("-c", "import demon_lab, demon_lab.resources as r; print(demon_lab.__file__); print(r.CONF); "
                      "print(r.STUDIES); print(r.DATA)")
    assert where.returncode == 0, where.stderr
    assert len(where.stdout.split()) == 4 and all(line.startswith(str(site)) for line in where.stdout.split()), \
        where.stdout
    assert (site / "demon_lab" / "conf" / "config.yaml").is_file()
    assert (site / "demon_lab" / "ablations" / "iterations.yaml").is_file()
    job = run("-m", "demon_lab", "scale=smoke", "eval.max_samples=1")
    assert job.returncode == 0, job.stderr[-3000:]
    assert "[demon_lab] results" in job.stdout and "sun3d_train_0.1m_to_0.2m_00000" in job.stdout
    assert (work / "mlflow.db").is_file()
    assert run("-m", "demon_lab.report", "--help").returncode == 0
    study = run("-m", "demon_lab.report", "iterations", "--out", str(work / "reports"))
    assert study.returncode == 0, study.stderr[-2000:]  # no runs of that study here: a report that lists them
    assert "missing" in (work / "reports" / "iterations.md").read_text()
    tests = run("-m", "pytest", "-q", "-p", "no:cacheprovider", "--import-mode=append", f"--rootdir={work}",
                str(ROOT / "tests" / "test_identity.py"), *(str(ROOT / "tests" / f"test_{name}.py") for name in
                                                             ("readers", "mixture", "data_stats")), "-k",
                "sun3d_pair or pair_folder or data_config or data_stats", timeout=900)
    assert tests.returncode == 0 and " passed" in tests.stdout, tests.stdout[-3000:]


def _code_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, stripped text) of a module's code: no blank lines, comments or docstrings."""
    import ast

    text = path.read_text()
    docstrings = set()
    for node in ast.walk(ast.parse(text)):
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and isinstance(body[0], ast.Expr) and \
                isinstance(getattr(body[0], "value", None), ast.Constant) and isinstance(body[0].value.value, str):
            docstrings |= set(range(body[0].lineno, body[0].end_lineno + 1))
    return [(n, line.strip()) for n, line in enumerate(text.splitlines(), 1)
            if line.strip() and not line.strip().startswith("#") and n not in docstrings]


def test_no_module_repeats_a_block_of_another(window: int = 8):
    """No run of ``window`` identical code lines appears in two places of the package: one function
    with a parameter instead of a copy."""
    seen: dict[tuple[str, ...], str] = {}
    copies = []
    for path in sorted((ROOT / "demon_lab").rglob("*.py")):
        lines = _code_lines(path)
        for i in range(len(lines) - window + 1):
            block = tuple(text for _, text in lines[i:i + window])
            if sum(len(t) > 12 for t in block) < window // 2:
                continue  # closing brackets, `else:`, `return out`: not logic
            where = f"{path.relative_to(ROOT)}:{lines[i][0]}"
            if block in seen and not seen[block].startswith(f"{path.relative_to(ROOT)}:"):
                copies.append(f"{where} repeats {seen[block]}")
            seen.setdefault(block, where)
    assert copies == []
