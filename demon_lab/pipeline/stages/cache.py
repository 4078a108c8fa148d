"""The stage cache (docs/running.md, "The stage cache").

Every stage's result is stored under a key hashing everything that determines it
(:func:`demon_lab.pipeline.identity.stage_key` of :func:`demon_lab.pipeline.identity.describe_stage`: the stage's
own config, the model and loss config, the training data config, the seed, the upstream stages'
keys and the code's and the scene generator's versions). A finished stage is reused instead of
retrained (so an iteration sweep trains once and evaluates N times), an interrupted one resumes
from its last checkpoint, and a file lock keeps concurrent jobs from training the same stage twice.

Layout: ``<cache>/stages/<stage>-<key>/`` with ``last.ckpt`` (Lightning, for resuming),
``weights.pt`` (the trained nets' state dicts, written atomically when the stage finishes) and
``stage.json`` (what the key hashes, for humans).
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import torch
from filelock import FileLock

from demon_lab.pipeline.weights import CheckpointError, load_checkpoint

__all__ = ["CheckpointError", "StageDir", "atomic_checkpoint_io", "atomic_torch_save", "load_checkpoint"]


class StageDir:
    def __init__(self, root: Path, name: str, key: str, description: Mapping[str, Any]):
        self.path = Path(root) / "stages" / f"{name}-{key}"
        self.name, self.key, self.description = name, key, description

    @property
    def weights(self) -> Path:
        return self.path / "weights.pt"

    @property
    def last_checkpoint(self) -> Path:
        return self.path / "last.ckpt"

    def done(self) -> bool:
        return self.weights.is_file()

    @contextlib.contextmanager
    def lock(self) -> Iterator[None]:
        """Exclusive lock: a second job needing this stage waits, then finds it done."""
        self.path.mkdir(parents=True, exist_ok=True)
        with FileLock(self.path.parent / f"{self.path.name}.lock"):
            yield

    def save(self, state: Mapping[str, Mapping[str, torch.Tensor]]) -> None:
        self.path.mkdir(parents=True, exist_ok=True)
        (self.path / "stage.json").write_text(json.dumps(self.description, indent=2, default=str) + "\n")
        atomic_torch_save({k: dict(v) for k, v in state.items()}, self.weights)

    def load(self) -> dict[str, dict[str, torch.Tensor]]:
        return load_checkpoint(self.weights)


def atomic_torch_save(obj: Any, path: Path | str) -> None:
    """``torch.save`` to a temporary file in the same folder, fsync, then rename over ``path``:
    a kill at any moment leaves the previous file or the complete new one, never a torn one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def atomic_checkpoint_io():
    """Lightning checkpoint I/O for the stage cache: atomic writes (:func:`atomic_torch_save`) and
    ``weights_only=True`` loads (a checkpoint may hold tensors and plain containers only)."""
    from lightning.pytorch.plugins.io import TorchCheckpointIO

    class AtomicCheckpointIO(TorchCheckpointIO):
        def save_checkpoint(self, checkpoint, path, storage_options=None):
            atomic_torch_save(checkpoint, path)

        def load_checkpoint(self, path, map_location=None, weights_only=None):
            return load_checkpoint(path)

    return AtomicCheckpointIO()
