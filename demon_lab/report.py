"""``python -m demon_lab.report NAME [--all] [--run]``: a study's paper-style tables and figures from its MLflow runs.

The command only; the code is :mod:`demon_lab.reporting.report`."""

from demon_lab.reporting.report import main

if __name__ == "__main__":
    raise SystemExit(main())
