"""demon_lab's study specs, one per study (``python -m demon_lab.report NAME``), and the paper's
numbers, installed as the package ``demon_lab.ablations`` (pyproject.toml maps this folder there for
wheels and editable installs alike; :mod:`demon_lab.resources` finds it)."""
