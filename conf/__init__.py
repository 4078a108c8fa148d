"""demon_lab's Hydra config tree, installed as the package ``demon_lab.conf`` (pyproject.toml maps
this folder there for wheels and editable installs alike; :mod:`demon_lab.resources` finds it)."""
