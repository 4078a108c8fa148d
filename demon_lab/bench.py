"""``python -m demon_lab.bench SECTION [...]``: the benchmark tables.

The command only; the code is :mod:`demon_lab.tools.bench`."""

from demon_lab.tools.bench import main

if __name__ == "__main__":
    raise SystemExit(main())
