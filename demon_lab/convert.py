"""``python -m demon_lab.convert``: DeMoN's released TensorFlow weights as a demon_lab weights file.

The command only; the code is :mod:`demon_lab.tools.convert`."""

from demon_lab.tools.convert import main

if __name__ == "__main__":
    raise SystemExit(main())
