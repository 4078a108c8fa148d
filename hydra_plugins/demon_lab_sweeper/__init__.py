"""demon_lab's sweeper as a Hydra plugin: Hydra finds plugins in the ``hydra_plugins`` namespace and
instantiates a sweeper only from there (``conf/hydra/sweeper/demon_lab.yaml`` names this class). What
it does is :mod:`demon_lab.app.sweeper`. (An editable install carries this file as a file, where
Hydra's scan sees it: ``build_backend/demon_lab_build.py``.)"""

import demon_lab.app.sweeper as _sweeper


class DemonLabSweeper(_sweeper.Sweeper):
    """:class:`demon_lab.app.sweeper.Sweeper`, under a name Hydra accepts for a sweeper."""
