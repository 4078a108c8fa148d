"""The data: the Sample type, the synthetic scene generator and its presets, the readers of real
formats (DeMoN's HDF5 files, pair folders, Middlebury), the datasets and the Lightning data module
that serve them, and the bundled real SUN3D pair (``data/real/``). Below the pipeline, beside the
nets and the baselines (docs/architecture.md)."""
