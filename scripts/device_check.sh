#!/usr/bin/env bash
# demon_lab's accelerator check: one table (tests on CUDA, inference and per-stage training rates at
# scale=paper, peak memory, DeMoN's HDF5 data path, the job's loop, the cpu profile on the GPU,
# torch.compile) in under 8 minutes on one GPU, written to reports/device_check.md
# (docs/running.md, "Paper scale").
#
#   scripts/device_check.sh [--dry-run] [--budget SECONDS] [--out FILE]
#
# --dry-run runs every part at toy sizes on whatever device there is (CI runs it on its CPU).
# It runs from a source checkout without installing demon_lab. It needs torch, Lightning, numpy,
# OpenCV, scikit-image, h5py, PyYAML and pytest, and for its parts 4-6 lz4, Hydra and OmegaConf. On a
# GPU host whose Python lacks some of them, put their wheels in .whl/ first (git-ignored), for that
# host's Python version; they are installed into a scratch folder, not into the host's Python:
#   PYV=$(python3 -c 'import sys; print("%d.%d" % sys.version_info[:2])')   # on the GPU host
#   python3 -m pip download --no-deps --only-binary=:all: --python-version "$PYV" \
#       --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64 -d .whl \
#       hydra-core==1.3.8 omegaconf==2.3.1 lz4==4.4.5
#   python3 -m pip wheel --no-deps -w .whl antlr4-python3-runtime==4.9.3   # source only on PyPI: build it
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-python3}"
if compgen -G ".whl/*.whl" >/dev/null && ! "$PY" -c "import hydra, omegaconf, lz4" 2>/dev/null; then
    SITE="$(mktemp -d)"
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$SITE" .whl/*.whl
    export PYTHONPATH="$SITE${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
exec "$PY" -m demon_lab.device_check "$@"
