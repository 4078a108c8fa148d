"""demon_lab's sweeper as a Hydra plugin: Hydra instantiates a sweeper only from the ``hydra_plugins``
namespace (``conf/hydra/sweeper/demon_lab.yaml`` names this class). What it does is
:mod:`demon_lab.app.sweeper`.

Hydra finds plugins by scanning the namespace, which an editable install (``pip install -e .``) hides
from it; ``python -m demon_lab`` therefore registers the class itself (``demon_lab.__main__``)."""

import demon_lab.app.sweeper as _sweeper


class DemonLabSweeper(_sweeper.Sweeper):
    """:class:`demon_lab.app.sweeper.Sweeper`, under a name Hydra accepts for a sweeper."""
