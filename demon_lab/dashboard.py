"""``python -m demon_lab.dashboard``: MLflow's dashboard on demon_lab's runs.

The command only; the code is :mod:`demon_lab.reporting.dashboard`."""

from demon_lab.reporting.dashboard import main

if __name__ == "__main__":
    raise SystemExit(main())
