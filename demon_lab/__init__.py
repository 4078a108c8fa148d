"""demon_lab: DeMoN (Depth and Motion Network, CVPR 2017) in PyTorch, with the paper's ablations
as tracked, reproducible experiments.

``python -m demon_lab`` runs a job (:mod:`demon_lab.app.job`); the README's "Layout" lists the modules.
"""

__version__ = "0.1.0"
