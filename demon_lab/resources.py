"""Files that ship inside the package: the Hydra configs, the study specs and the bundled real pair.

The configs and study specs sit at the top of the repository (``conf/``, ``ablations/``) and are
installed as the packages ``demon_lab.conf`` and ``demon_lab.ablations`` (pyproject.toml). All three
are located through the installed package (``importlib.resources``), the same way for a wheel and an
editable install, so demon_lab finds them wherever it is run from.
"""

from __future__ import annotations

import functools
from importlib.resources import files
from pathlib import Path

PACKAGE = Path(str(files("demon_lab")))
CONF = Path(str(files("demon_lab.conf")))
"""The Hydra config tree (``config_path`` of ``python -m demon_lab``; ``conf/`` in the repository)."""
STUDIES = Path(str(files("demon_lab.ablations")))
"""One report spec per study, named after its experiment (``conf/experiment/NAME.yaml``), and the
paper's numbers (``ablations/`` in the repository)."""
DATA = PACKAGE / "data" / "real"
"""Real two-view samples that ship with demon_lab (``data/real/README.md``: origin and licence)."""


def cache_root() -> Path:
    """Where demon_lab caches what it computes (trained stages, rendered scenes): ``$DEMON_LAB_CACHE``,
    else ``~/.cache/demon_lab``. The one place this default is written: the config's ``cache_dir``
    (``${demon_lab_cache:}``) and the datasets' render cache (``<root>/data``) read it."""
    import os

    return Path(os.environ.get("DEMON_LAB_CACHE") or Path.home() / ".cache" / "demon_lab")


def source_digest(paths: list[str] | tuple[str, ...], root: Path = PACKAGE) -> str:
    """The first 16 hex digits of the sha256 of the Python sources under ``paths`` (files or folders
    relative to ``root``, the package by default; folders taken whole), as their tokens: comments, docstrings,
    blank lines and layout left out, so that only a change of code changes it (the same on every
    Python version, unlike an ``ast.dump``): what :data:`RECORDED_SOURCES` records."""
    import hashlib
    import io
    import tokenize

    skip = {tokenize.COMMENT, tokenize.NL, tokenize.ENCODING}
    h = hashlib.sha256()
    layout = {tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT}
    files = sorted({f for p in paths for f in ([root / p] if p.endswith(".py") else (root / p).rglob("*.py"))})
    for path in files:
        h.update(path.relative_to(root).as_posix().encode() + b"\0")
        tokens = [t for t in tokenize.generate_tokens(io.StringIO(path.read_text()).readline) if t.type not in skip]
        for i, t in enumerate(tokens):
            statement_start = i == 0 or tokens[i - 1].type in layout
            alone = i + 1 < len(tokens) and tokens[i + 1].type in (tokenize.NEWLINE, tokenize.ENDMARKER)
            if t.type == tokenize.STRING and statement_start and alone:
                continue  # a docstring (or a string standing alone as a statement): documentation
            h.update(f"{t.type}:{'' if t.type in layout else t.string}\0".encode())
    return h.hexdigest()[:16]


SOURCES = {
    "stage": ("nets", "core", "data/sample.py", "data/datasets.py", "data/mixture.py", "data/datamodule.py",
              "data/layers.py", "data/readers", "baselines/twoview.py", "pipeline/stages", "pipeline/kinds",
              "pipeline/schema.py", "pipeline/settings.py", "pipeline/config.py"),
    "generator": ("data/synthetic.py", "data/raycast.py", "data/textures.py", "data/sample.py", "core/geometry.py"),
}
"""The code behind each version of the keys, as folders and files of the package: ``stage``, what decides
what a stage produces (its nets, losses and priors, the data it draws, the stage kinds and modules, the options'
defaults: :data:`demon_lab.pipeline.identity.CODE_VERSION`); ``generator``, what renders a synthetic scene
(:data:`demon_lab.data.synthetic.GENERATOR_VERSION`)."""

RECORDED_SOURCES = {"stage": "c7c4b5f6060954ba", "generator": "52d5dbbab69255d8"}
""":func:`source_digest` of each of :data:`SOURCES` as its version names it. An edit of that code changes
the digest, and the fast tier (tests/test_identity.py) fails until the new digest is recorded here, with
the version bumped where the edit changes what a stage produces (or a scene). Code whose digest is not
the recorded one (an edited install) keys its stages, runs and scenes by its digest too
(:func:`versioned`), so nothing computed by other code is ever reused."""


@functools.cache
def versioned(version: int, name: str) -> int | str:
    """``version`` where the code of ``SOURCES[name]`` is the recorded code (:data:`RECORDED_SOURCES`),
    else ``"<version>+<digest of the code as it is>"``."""
    actual = source_digest(SOURCES[name])
    return version if actual == RECORDED_SOURCES[name] else f"{version}+{actual}"
