"""``python -m demon_lab.diagnose [overrides]``: what each pass of a trained chain passes on.

The command only; the code is :mod:`demon_lab.tools.diagnose`."""

from demon_lab.tools.diagnose import main

if __name__ == "__main__":
    raise SystemExit(main())
