"""``python -m demon_lab.device_check (scripts/device_check.sh)``: the accelerator check.

The command only; the code is :mod:`demon_lab.tools.device_check`."""

from demon_lab.tools.device_check import main

if __name__ == "__main__":
    raise SystemExit(main())
