"""``python -m demon_lab.config_docs [--check]``: docs/config.md, every key of the configuration.

The command only; the code is :mod:`demon_lab.tools.config_docs`."""

from demon_lab.tools.config_docs import main

if __name__ == "__main__":
    raise SystemExit(main())
