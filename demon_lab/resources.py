"""Files that ship inside the package: the Hydra configs, the study specs and the bundled real pair.

Located through the installed package (``importlib.resources``), so a wheel installed into any
environment finds them wherever it is run from; nothing is looked up beside a source checkout.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

PACKAGE = Path(str(files("demon_lab")))
CONF = PACKAGE / "conf"
"""The Hydra config tree (``config_path`` of ``python -m demon_lab``)."""
STUDIES = PACKAGE / "studies"
"""One report spec per study, named after its experiment (``conf/experiment/NAME.yaml``)."""
DATA = PACKAGE / "data" / "real"
"""Real two-view samples that ship with demon_lab (``data/real/README.md``: origin and licence)."""
