"""``python -m demon_lab.data_stats [overrides]``: the supplementary's Table 1 for any configured source.

The command only; the code is :mod:`demon_lab.tools.data_stats`."""

from demon_lab.tools.data_stats import main

if __name__ == "__main__":
    raise SystemExit(main())
