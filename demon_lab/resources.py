"""Files that ship inside the package: the Hydra configs, the study specs and the bundled real pair.

The configs and study specs sit at the top of the repository (``conf/``, ``ablations/``) and are
installed as the packages ``demon_lab.conf`` and ``demon_lab.ablations`` (pyproject.toml). All three
are located through the installed package (``importlib.resources``), the same way for a wheel and an
editable install, so demon_lab finds them wherever it is run from.
"""

from __future__ import annotations

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
