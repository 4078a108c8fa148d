"""demon_lab: DeMoN (Depth and Motion Network, CVPR 2017) in PyTorch, with the paper's ablations
as tracked, reproducible experiments.

Modules: :mod:`demon_lab.geometry` (the layers tying flow, depth and motion together),
:mod:`demon_lab.metrics` (DeMoN's evaluation protocol), :mod:`demon_lab.bench` (benchmarks).
"""

__version__ = "0.1.0"
