"""``python -m demon_lab.config_docs [--check]``: writes ``docs/config.md``, every key of the job's
configuration, from the configs themselves (and, beside it, ``docs/cli.md``,
``docs/troubleshooting.md`` and ``docs/metrics.md``: :mod:`demon_lab.tools.reference_docs`).

Three tables, each read from where its values are defined, so that the page cannot drift from them:

* the config groups (``conf/GROUP/*.yaml``): each option and the first line of its file's header;
* every key of ``python -m demon_lab`` on its defaults (the ``cpu`` scale): its type and default as
  Hydra composes them (interpolations as written), and its meaning, the comment beside the key in
  the file that sets it (the group's default option, ``conf/config.yaml``, the scale's profile);
  allowed values where that comment lists them (``a | b | c``) or where the key is a group's;
* each stage kind's options (``schedule.stages.NAME``): the fields of its spec in
  :mod:`demon_lab.pipeline.kinds`, with their types, defaults and docstrings.

``--check`` writes nothing and exits 1 if the page is not what the configs give (the tests run it).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import itertools
import re
import sys
from pathlib import Path
from typing import Any

from demon_lab.resources import CONF

DEFAULT_OUT = Path("docs/config.md")
GROUPS = ("model", "data", "loss", "schedule", "eval", "tracking", "baseline", "scale", "design", "experiment")
KEY_LINE = re.compile(r"^(\s*)([A-Za-z_][\w]*):(.*)$")
ALTERNATIVES = re.compile(r"^([\w.\-]+(?: \| [\w.\-]+)+)")


def _comment(rest: str) -> str | None:
    """The comment of a YAML line's remainder after ``key:`` (a ``#`` outside quotes and braces)."""
    quote, depth = None, 0
    for i, ch in enumerate(rest):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch in "{[":
            depth += 1
        elif ch in "}]":
            depth -= 1
        elif ch == "#" and depth == 0 and (i == 0 or rest[i - 1].isspace()):
            return rest[i + 1:].strip()
    return None


def key_comments(path: Path, prefix: str = "") -> dict[str, str]:
    """Each block-style key of a YAML file (dotted, under ``prefix``) and its comment: the one on
    its line and the comment-only lines below it that align with that comment."""
    out: dict[str, str] = {}
    stack: list[tuple[int, str]] = []
    last: tuple[str, int] | None = None  # the key whose comment may continue, and the comment's column
    for line in path.read_text().splitlines():
        stripped = line.strip()
        if stripped.startswith("#"):
            if last is not None and line.index("#") == last[1]:
                out[last[0]] += " " + stripped[1:].strip()
                continue
            last = None
            continue
        match = KEY_LINE.match(line)
        last = None
        if not match or line.lstrip().startswith("-"):
            continue
        indent, key, rest = len(match.group(1)), match.group(2), match.group(3)
        stack = [(i, k) for i, k in stack if i < indent]
        dotted = ".".join([prefix, *[k for _, k in stack], key] if prefix else [*[k for _, k in stack], key])
        stack.append((indent, key))
        comment = _comment(rest)
        if comment:
            out[dotted] = comment
            last = (dotted, line.index("#", len(match.group(1)) + len(key) + 1))
    return out


def _package(path: Path, group: str) -> str:
    """The package a config file's keys land in: ``_global_`` files at the top, else the group's."""
    return "" if "# @package _global_" in path.read_text() else group


def _header(path: Path) -> str:
    """A config file's first comment sentence (its header), without the package line."""
    lines = [line[1:].strip() for line in path.read_text().splitlines() if line.startswith("#")
             and not line.startswith("# @package")]
    text = " ".join(lines)
    return (text.split(". ")[0].rstrip(".") + ".") if text else ""


def _composed() -> tuple[Any, dict[str, str]]:
    from hydra import compose, initialize_config_dir

    from demon_lab.pipeline.config import register_resolvers

    register_resolvers()
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("config", return_hydra_config=True)
    choices = {k: "null" if v is None else str(v) for k, v in cfg.hydra.runtime.choices.items()
               if not k.startswith("hydra/")}
    return cfg, choices


def _leaves(node: Any, prefix: str = "") -> list[tuple[str, Any]]:
    from omegaconf import DictConfig

    out = []
    for key in node:
        dotted = f"{prefix}.{key}" if prefix else str(key)
        value = node._get_node(key)
        if isinstance(value, DictConfig) and not value._is_none():
            out += _leaves(value, dotted)
        else:
            out.append((dotted, value))
    return out


def _type_and_default(value: Any) -> tuple[str, str]:
    from omegaconf import ListConfig, OmegaConf

    if value._is_interpolation():
        return "interpolation", f"`{value._value()}`"
    if isinstance(value, ListConfig):
        plain = OmegaConf.to_container(value, resolve=False)
        if all(not isinstance(v, (dict, list)) for v in plain):
            return "list", f"`{plain}`"
        return "list", f"{len(plain)} entries (`conf/` shows them)"
    raw = value._value()
    kind = "null" if raw is None else type(raw).__name__
    return kind, f"`{'null' if raw is None else str(raw).lower() if isinstance(raw, bool) else raw}`"


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def groups_table(choices: dict[str, str]) -> list[str]:
    lines = ["| group | default | options (`conf/GROUP/NAME.yaml`: its header) |", "|---|---|---|"]
    for group in GROUPS:
        options = sorted((CONF / group).glob("*.yaml"))
        listed = "<br>".join(f"`{p.stem}`: {_cell(_header(p))}" for p in options)
        lines.append(f"| `{group}` | `{choices.get(group, 'null')}` | {listed} |")
    return lines


def keys_table(cfg: Any, choices: dict[str, str]) -> list[str]:
    comments: dict[str, str] = {}
    sources = [CONF / "config.yaml", *[CONF / g / f"{choices[g]}.yaml" for g in GROUPS
                                       if choices.get(g) not in (None, "null") and g != "experiment"]]
    for path in sources:
        group = path.parent.name if path.parent != CONF else ""
        for key, text in key_comments(path, _package(path, group)).items():
            comments.setdefault(key, f"{text} ({path.relative_to(CONF).as_posix()})")
    lines = ["| key | type | default | allowed | meaning (the file that sets it) |", "|---|---|---|---|---|"]
    for key, value in _leaves(cfg):
        if key.split(".")[0] in ("hydra", "scale") or key.startswith("schedule.stages."):
            continue
        kind, default = _type_and_default(value)
        meaning = comments.get(key, "")
        match = ALTERNATIVES.match(meaning)
        allowed = schema_allowed(key) or (" \\| ".join(f"`{a}`" for a in match.group(1).split(" | ")) if match else "")
        lines.append(f"| `{key}` | {kind} | {_cell(default)} | {allowed} | {_cell(meaning)} |")
    return lines


def schema_allowed(key: str) -> str:
    """What the typed settings (:mod:`demon_lab.pipeline.settings`) accept for ``key``, where a
    section's field checks it ('' where none does): the dotted key followed from
    :class:`~demon_lab.pipeline.settings.JobSettings` through its sections."""
    import typing

    from demon_lab.pipeline import settings

    cls: Any = settings.JobSettings
    *path, name = key.split(".")
    for part in path:
        hint = typing.get_type_hints(cls).get(part) if dataclasses.is_dataclass(cls) else None
        cls = hint if isinstance(hint, type) and issubclass(hint, settings.Section) else None
        if cls is None:
            return ""
    field = next((f for f in dataclasses.fields(cls) if f.name == name), None)
    check = field.metadata.get("check") if field is not None else None
    if check is None or check.allowed() == "-":
        return ""
    return _cell(check.allowed())


def _field_docs(cls: type) -> dict[str, str]:
    """The docstrings written under a dataclass's fields (``x: int = 0`` then ``\"\"\"...\"\"\"``)."""
    import inspect

    tree = ast.parse(inspect.getsource(cls))
    body = tree.body[0].body
    out = {}
    for node, after in itertools.pairwise(body):
        if isinstance(node, ast.AnnAssign) and isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant):
            out[node.target.id] = " ".join(str(after.value.value).split())
    return out


def stages_table() -> list[str]:
    from demon_lab.pipeline.kinds import STAGE_SPECS

    lines = ["| kind | option | type | default | meaning |", "|---|---|---|---|---|"]
    for kind, spec in STAGE_SPECS.items():
        docs = {}
        for cls in reversed(spec.__mro__):
            if dataclasses.is_dataclass(cls):
                docs.update(_field_docs(cls))
        for f in dataclasses.fields(spec):
            if f.name == "name":
                continue
            default = "required" if f.default is dataclasses.MISSING else f"`{f.default}`"
            kind_type = _cell(f"`{f.type}`")
            lines.append(f"| `{kind}` | `{f.name}` | {kind_type} | {_cell(default)} | {_cell(docs.get(f.name, ''))} |")
    return lines


def page() -> str:
    from omegaconf import OmegaConf

    cfg, choices = _composed()
    job = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    return "\n".join([
        "# Configuration reference",
        "",
        "<!-- generated by python -m demon_lab.config_docs from conf/, demon_lab/pipeline/settings.py and kinds/; "
        "do not edit: tests/test_docs.py checks it is current -->",
        "",
        "Every key of `python -m demon_lab` and where its value comes from. A key is set on the command line "
        "(`key=value`; `+key=value` adds one a config leaves out), by a config group's option (`group=option`), "
        "by an experiment (`+experiment=NAME`), or by the scale's profile (`scale=smoke | cpu | paper`, applied "
        "after `conf/config.yaml`'s own keys). How the configs compose, and the checks each job passes before "
        "it runs: [running.md](running.md).",
        "",
        "## Config groups",
        "",
        *groups_table(choices),
        "",
        "## Keys, on the defaults (`scale=cpu`)",
        "",
        "Defaults as Hydra composes them: an interpolation (`${...}`) is shown as written (`scale.*` holds "
        "each profile's sizes and step counts: `conf/scale/`). The meaning is the comment beside the key in the "
        "file that sets it; allowed values as the typed settings check them (`demon_lab/pipeline/settings.py`), "
        "else where that comment lists them.",
        "",
        *keys_table(job, choices),
        "",
        "## Stage options (`schedule.stages.NAME`)",
        "",
        "Each stage of `schedule.stages` is a mapping told apart by its `kind`; its options, types and defaults "
        "are its kind's class (`demon_lab/pipeline/kinds/`). `conf/schedule/released.yaml` sets DeMoN's six "
        "stages; an option it leaves out takes the default here, and one its kind does not take is refused.",
        "",
        *stages_table(),
        "",
    ])


def pages(out: Path) -> dict[Path, str]:
    """The generated reference pages: ``out`` (the configuration) and, beside it, the command lines
    and the troubleshooting page (:mod:`demon_lab.tools.reference_docs`)."""
    from demon_lab.tools import reference_docs

    return {out: page(), out.with_name("cli.md"): reference_docs.cli_page(),
            out.with_name("troubleshooting.md"): reference_docs.troubleshooting_page(),
            out.with_name("metrics.md"): reference_docs.metrics_page()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m demon_lab.config_docs", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT,
                        help="the configuration page; cli.md, troubleshooting.md and metrics.md are written "
                             "beside it")
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 if a page is not current")
    args = parser.parse_args(argv)
    written = pages(args.out)
    if args.check:
        stale = [str(path) for path, text in written.items() if not (path.is_file() and path.read_text() == text)]
        if stale:
            print(f"error: {', '.join(stale)} not current: run python -m demon_lab.config_docs", file=sys.stderr)
        return 1 if stale else 0
    for path, text in written.items():
        path.write_text(text)
        print(f"wrote {path}")
    return 0
