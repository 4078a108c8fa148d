"""The how-to guides (docs/guides/) that work on the user's own files hold commands that work as
written once those files exist.

docs/guides/your_own_study.md: its files (the blocks a line ``File `PATH`:`` names) written into a
folder and its commands run from there: each demon_lab command starts as written (the check of
tests/test_doc_commands.py), the specs load, and the
worked example runs at the smoke scale into a temporary store and ends in a report with the spec's
rows (slow). docs/guides/released_weights.md: its ``text`` commands, shown with the placeholders
``DIR`` and ``demon_original.pt``, compose on files of DeMoN's layout and weights of the released
shapes (slow). The guides' other commands: tests/test_doc_commands.py."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
from pathlib import Path

import pytest
import yaml
from conftest import table_rows

ROOT = Path(__file__).resolve().parents[1]
OWN_STUDY = ROOT / "docs" / "guides" / "your_own_study.md"
RELEASED = ROOT / "docs" / "guides" / "released_weights.md"
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.M | re.S)
FILE_LINE = re.compile(r"`([^`\s]+\.(?:yaml|csv|py))`:\s*$")
"""The line before a block that the reader saves as a file: ``File `my_conf/experiment/NAME.yaml`:``."""
EXAMPLE = "## A worked example"
COMMANDS = ("bash", "text")
"""The blocks that hold commands: ``text`` for those that read the user's files (they do not compose
where those files are missing, so tests/test_doc_commands.py leaves them out)."""


def blocks(text: str) -> list[tuple[str, str, str]]:
    """The fenced blocks of a page: (language, body, the last non-blank line before the fence)."""
    found = []
    for m in FENCE.finditer(text):
        before = [line for line in text[:m.start()].splitlines() if line.strip()]
        found.append((m.group(1), m.group(2), before[-1] if before else ""))
    return found


def commands(text: str, languages: tuple[str, ...] = COMMANDS) -> list[str]:
    """The commands of a page's blocks in ``languages``, one per line (``\\`` continuations joined)."""
    return [line.strip() for lang, body, _ in blocks(text) if lang in languages
            for line in body.replace("\\\n", " ").splitlines() if line.strip() and not line.strip().startswith("#")]


def files(text: str) -> dict[str, str]:
    """The files a page asks the reader to write: each block that a line naming the file precedes."""
    return {m.group(1): body for _, body, before in blocks(text) if (m := FILE_LINE.search(before))}


def write(written: dict[str, str], folder: Path) -> None:
    for name, body in written.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text(body)


def section(text: str, heading: str) -> str:
    """A page's section from its ``## `` heading to the next one."""
    start = text.index(heading + "\n")
    end = text.find("\n## ", start + len(heading))
    return text[start:] if end < 0 else text[start:end]


def words(command: str, folder: Path) -> list[str]:
    """A command as the shell hands it on, run from ``folder`` (``$PWD``: that folder)."""
    return shlex.split(command.replace("$PWD", str(folder)), comments=True)


def problems(page_commands: list[str], folder: Path) -> list[tuple[str, str]]:
    """Each demon_lab command that would not start as written from ``folder``, with the reason
    (tests/test_doc_commands.py's check: composes and validates, or parses with its own parser)."""
    from tests.test_doc_commands import problem

    return [(command, why) for command in page_commands if (why := problem(words(command, folder))) is not None]


def test_the_page_parsers_find_files_commands_and_sections():
    page = ("intro\n\n## A worked example\n\nFile `a/b.yaml`:\n\n```yaml\nk: 1\n```\n\n```bash\n"
            "python -m demon_lab \\\n    seed=1   # a comment\n# a comment line\nmkdir x\n```\n\n## Next\n\n```text\n"
            "python -m demon_lab data.root=DIR\n```\n")
    assert files(page) == {"a/b.yaml": "k: 1\n"}
    assert commands(page) == ["python -m demon_lab      seed=1   # a comment", "mkdir x",
                              "python -m demon_lab data.root=DIR"]
    assert commands(section(page, EXAMPLE)) == commands(page)[:2]
    assert section(page, "## Next").startswith("## Next") and "A worked" not in section(page, "## Next")
    assert words('python -m x "a=[file://$PWD/c]"', Path("/f")) == ["python", "-m", "x", "a=[file:///f/c]"]
    assert problems(["python -m demon_lab.report NAME --studies my_studies --out=x --run"], Path("/f")) == []
    (refused,) = problems(["python -m demon_lab.report NAME --studies x --no-such-option"], Path("/f"))
    assert "refuses" in refused[1]
    assert problems(["python -m demon_lab iterations=-1", "mkdir x"], Path("/f")) == [
        ("python -m demon_lab iterations=-1", "iterations: expected an integer >= 0, got -1")]


def test_the_own_study_pages_commands_start_as_written_beside_its_files(tmp_path):
    """Every command of your_own_study.md, from the folder that holds the page's files: the
    experiment is found on the search path, every job composes and validates, and the report
    command takes the options the page gives it."""
    text = OWN_STUDY.read_text()
    write(files(text), tmp_path)
    found = commands(text)
    assert sum(c.startswith("python -m demon_lab -m +experiment=my_lr") for c in found) == 1
    assert sum(c.startswith("python -m demon_lab.report ") for c in found) >= 3
    assert problems(found, tmp_path) == []


def test_the_own_study_pages_specs_load_and_select_its_experiments_runs(tmp_path):
    """The spec files of your_own_study.md load as the report reads them (``extends`` applied), and
    their tables select the runs of the page's experiment."""
    from demon_lab.reporting.specs import load_spec

    written = files(OWN_STUDY.read_text())
    experiments = {yaml.safe_load(body)["experiment"] for name, body in written.items() if "/experiment/" in name}
    specs = [name for name in written if "/experiment/" not in name]
    assert experiments == {"my_lr"} and len(specs) == 2
    write(written, tmp_path)
    for name in specs:
        spec = load_spec(Path(name).stem, tmp_path / Path(name).parent)
        assert {t["experiment"] for t in spec["tables"]} == experiments, name


@pytest.mark.slow
def test_the_own_study_example_runs_as_written(tmp_path):
    """The worked example of your_own_study.md as a user follows it: its files written, its commands
    run in order from one folder (a temporary MLflow store and cache). The sweep's two jobs end
    FINISHED under the experiment the page names, and the report has each row of the spec with a
    value in every column on every test set."""
    from mlflow.tracking import MlflowClient

    from demon_lab.reporting.specs import load_spec

    example = section(OWN_STUDY.read_text(), EXAMPLE)
    write(files(example), tmp_path)
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    env = {**os.environ, "MLFLOW_TRACKING_URI": uri, "DEMON_LAB_CACHE": str(tmp_path / "cache"), "PWD": str(tmp_path)}
    ran = []
    for command in commands(example):
        done = subprocess.run(["bash", "-c", command], cwd=tmp_path, env=env, capture_output=True, text=True,
                              timeout=900)
        assert done.returncode == 0, f"{command}: exit {done.returncode}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
        ran.append((command, done.stdout + done.stderr))
    sweep = next(out for c, out in ran if c.startswith("python -m demon_lab -m "))
    assert "the sweep's jobs on synthetic_sun3d" in sweep and sweep.count(" finished ") == 2
    assert any(c.startswith("python -m demon_lab.report ") and "--run" in c for c, _ in ran)

    client = MlflowClient(tracking_uri=uri)
    experiment = client.get_experiment_by_name("my_lr")
    assert experiment is not None
    jobs = [r for r in client.search_runs([experiment.experiment_id]) if "demon_lab.run_key" in r.data.tags]
    assert len(jobs) == 2 and {r.info.status for r in jobs} == {"FINISHED"}  # (--run skipped both)
    assert {r.data.params["schedule.stages.flow1.lr"] for r in jobs} == {"0.00025", "0.0005"}

    spec = load_spec("my_lr", tmp_path / "my_studies")
    markdown = (tmp_path / "reports" / "my_lr.md").read_text()
    rows = table_rows(markdown)
    for table in spec["tables"]:
        labels = [row["label"] for row in table["rows"]] + [f"*{d['label']}*" for d in table["differences"]]
        for label in labels:
            found = [r[1:] for r in rows if r[0] == label]
            assert len(found) == len(spec["datasets"]), f"report row {label!r}: {len(found)} test sets\n{markdown}"
            for n, *cells in found:  # one seed: n = 1, and a value in every column
                assert n == "1" and len(cells) == len(table["columns"]) and "-" not in cells, (label, found)
    assert (tmp_path / "reports" / "my_lr.csv").is_file() and (tmp_path / "reports" / "my_lr.tex").is_file()


@pytest.mark.slow
def test_the_released_weights_pages_commands_compose_on_files_of_demons_layout(tmp_path):
    """released_weights.md's ``text`` commands with ``DIR`` a folder of DeMoN's test and training
    files (tiny ones, under their real names) and ``demon_original.pt`` a state dict of the released
    chain's shapes (DeMoN's v1 graph at full width): each composes and validates as written, the
    weights checked against the chain each command builds."""
    import torch
    from demon_lab_test_files import write_demon_test_files

    from demon_lab.nets import DeMoN

    root = tmp_path / "demon_data"
    write_demon_test_files(root, ["sun3d_test.h5", "nyu2_test.h5", "sun3d_train_0.1m_to_0.2m.h5"], size=(120, 160))
    torch.save(DeMoN(variant="v1").state_dict(), tmp_path / "demon_original.pt")
    found = [c.replace("DIR", str(root)).replace("demon_original.pt", str(tmp_path / "demon_original.pt"))
             for c in commands(RELEASED.read_text(), ("text",))]
    assert sum(c.startswith("python -m demon_lab") for c in found) >= 6
    assert problems(found, tmp_path) == []
    diagnose = [c for c in found if c.startswith("python -m demon_lab.diagnose ")]
    from demon_lab.__main__ import check

    assert diagnose and all(check(words(c, tmp_path)[3:]) is None for c in diagnose)  # (its overrides are the job's)
