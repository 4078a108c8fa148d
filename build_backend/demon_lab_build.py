"""demon_lab's build backend: setuptools' own (``setuptools.build_meta``), with one addition to an
editable install (``pip install -e .``): the sweeper plugin's module, ``hydra_plugins/demon_lab_sweeper``,
is installed as a file, as a wheel installs it.

Hydra finds plugins by listing the folders of the ``hydra_plugins`` namespace package. setuptools'
editable installs serve a package of the checkout through an import hook, which such a listing does
not see (setuptools' "Development Mode" documentation, its limitations), so Hydra would not find the
sweeper; its compat mode, a path entry for the checkout, cannot map ``demon_lab.conf`` and
``demon_lab.ablations`` to the checkout's ``conf/`` and ``ablations/``. The module holds no code of
its own (it names the class of ``demon_lab/app/sweeper.py``, which the import hook serves from the
checkout as usual), so the file stays current unless that module is renamed."""

from __future__ import annotations

import base64
import hashlib
import zipfile
from pathlib import Path

from setuptools import build_meta as _setuptools
from setuptools.build_meta import *  # noqa: F403 (the backend's hooks, unchanged)

PLUGIN = "hydra_plugins/demon_lab_sweeper/__init__.py"


def build_editable(wheel_directory, config_settings=None, metadata_directory=None):
    name = _setuptools.build_editable(wheel_directory, config_settings, metadata_directory)
    _add_file(Path(wheel_directory) / name, PLUGIN, (Path(__file__).parents[1] / PLUGIN).read_bytes())
    return name


def _add_file(wheel: Path, arcname: str, data: bytes) -> None:
    """Write ``data`` into the wheel as ``arcname``, with its line in the wheel's RECORD."""
    with zipfile.ZipFile(wheel) as z:
        members = [(info, z.read(info)) for info in z.infolist() if info.filename != arcname]
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    with zipfile.ZipFile(wheel, "w", zipfile.ZIP_DEFLATED) as z:
        for info, content in members:
            if info.filename.endswith(".dist-info/RECORD"):
                content += f"{arcname},sha256={digest},{len(data)}\n".encode()
            z.writestr(info, content)
        z.writestr(arcname, data)
