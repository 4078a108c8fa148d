"""The commands on the front page and in the guides work as written: every ``python -m demon_lab``
command composes and validates every job it would run (without running it), every other entry point
parses its arguments with its own parser, and the guides quote no result that no committed report
prints (README's numbers: tests/test_docs.py)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from demon_lab.tools.reference_docs import ENTRY_POINTS
from tests.test_docs import THREE_DECIMALS, _outside_blocks, _reports_text, untraced

ROOT = Path(__file__).resolve().parents[1]
GUIDES = sorted((ROOT / "docs" / "guides").glob("*.md"))
PAGES = [ROOT / "README.md", *GUIDES]
BLOCK = re.compile(r"```(?:bash|sh|shell)\n(.*?)```", re.S)
ASSIGNMENT = re.compile(r"^[A-Z_][A-Z0-9_]*=\S*$")
PARSED = {command: module for command, module, _ in ENTRY_POINTS}
"""The entry points with an argument parser (the command-line page's), by the name a command gives
them, and the module of its ``main``."""


def commands(text: str) -> list[list[str]]:
    """Each command of a page's ``bash`` blocks as its words: continuations joined, ``&&`` chains
    split, comments and leading environment assignments dropped."""
    out = []
    for block in BLOCK.findall(text):
        for line in block.replace("\\\n", " ").splitlines():
            for part in line.split("&&"):
                words = shlex.split(part, comments=True)
                while words and ASSIGNMENT.match(words[0]):
                    words = words[1:]
                if words:
                    out.append(words)
    return out


def problem(words: list[str]) -> str | None:
    """Why the command would not start as written (None: it would)."""
    from demon_lab.__main__ import check
    from demon_lab.resources import STUDIES
    from demon_lab.tools.reference_docs import parser_of

    if words[:3] == ["python", "-m", "demon_lab"]:
        return check(words[3:])
    target = words[2] if words[:2] == ["python", "-m"] else words[0]
    if target == "demon_lab.diagnose":
        args = list(words[3:])
        if "--out" in args:
            del args[args.index("--out"):args.index("--out") + 2]
        return check(args)
    if target == "demon_lab.data_stats":
        from hydra import compose, initialize_config_dir

        from demon_lab.resources import CONF

        with initialize_config_dir(str(CONF), version_base="1.3"):
            compose("data_stats", overrides=words[3:])
        return None
    if target in PARSED:
        import importlib

        parser = parser_of(importlib.import_module(PARSED[target]).main)
        try:
            args = parser.parse_args(words[3:] if words[0] == "python" else words[1:])
        except SystemExit:
            return f"{target}: its parser refuses {words}"
        if target == "demon_lab.report" and args.studies == STUDIES:  # each study it names is a shipped spec
            from demon_lab.reporting.specs import ReportError, load_spec

            for name in args.names:
                try:
                    load_spec(name)
                except ReportError as e:
                    return str(e)
        return None
    if target.startswith("demon_lab"):
        return f"{target}: an entry point this test does not know"
    return None  # pip, ruff, git, mlflow, ...: not demon_lab's


def test_commands_are_found_and_a_broken_one_is_named():
    page = "```bash\nFOO=1 python -m demon_lab seed=1 \\\n  iterations=2  # a comment\npip install x && " \
           "python -m demon_lab.report --no-such-flag\n```\n"
    found = commands(page)
    assert found == [["python", "-m", "demon_lab", "seed=1", "iterations=2"], ["pip", "install", "x"],
                     ["python", "-m", "demon_lab.report", "--no-such-flag"]]
    assert problem(found[0]) is None and problem(found[1]) is None
    assert "refuses" in problem(found[2])
    assert problem(["python", "-m", "demon_lab", "iterations=-1"]) == "iterations: expected an integer >= 0, got -1"
    assert "no ablations/no_such_study.yaml" in problem(["python", "-m", "demon_lab.report", "no_such_study"])


@pytest.mark.slow
@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_command_on_the_page_starts_as_written(page):
    found = commands(page.read_text())
    assert found, f"{page.name} has no commands"
    assert [(" ".join(w), p) for w in found if (p := problem(w)) is not None] == []


def test_the_guides_exist():
    assert {p.name for p in GUIDES} >= {"README.md", "ablations.md", "your_own_study.md", "sweeps.md",
                                        "released_weights.md", "archives.md", "dashboard.md"}


@pytest.mark.parametrize("page", GUIDES, ids=lambda p: str(p.relative_to(ROOT)))
def test_the_guides_quote_only_numbers_a_report_prints(page):
    """A guide quotes no result (a number with its interval, or with three decimals) that no
    committed report prints."""
    reports = _reports_text()
    text = page.read_text()
    assert untraced(text, reports) == []
    printed = {n.lstrip("-") for n in THREE_DECIMALS.findall(reports)}
    assert [n for n in THREE_DECIMALS.findall(_outside_blocks(text)) if n.lstrip("-") not in printed] == []
