"""The model library's tensor functions: geometry (warps, flow <-> depth + motion, normals,
rotations), execution (precision, device, threads), DeMoN's losses and its evaluation metrics.
The lowest layer: it imports nothing of demon_lab but :mod:`demon_lab.resources`
(docs/architecture.md)."""
