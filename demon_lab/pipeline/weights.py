"""Weights files for ``model.weights=FILE``: what they hold, whether they fit a chain, their
content hash (the run and stage keys name the weights by content, not by path), loading.

A weights file is either a state dict of :class:`demon_lab.nets.DeMoN` (flat keys
``flow1.conv1.y.conv.weight`` ...; what ``python -m demon_lab.convert`` writes from DeMoN's
released weights, or ``torch.save(chain.state_dict(), FILE)``), or a stage file of demon_lab's
stage cache (``weights.pt``: net name -> that net's state dict). Either may hold a subset of the
nets (flow1, dm1, flow2, dm2, refine_net); each net present is loaded strictly.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from demon_lab.pipeline.identity import content_hash, describe

__all__ = ["NETS", "CheckpointError", "check_fits", "content_hash", "describe", "load_checkpoint", "load_weights",
           "misfit", "read_nets"]

NETS = ("flow1", "dm1", "flow2", "dm2", "refine_net")
RELEASED_HINT = ("DeMoN's converted weights are a v1 chain of width 1.0 for 256x192 inputs: "
                 "scale=paper, or model.width=1.0 data.size=[192,256]")

class CheckpointError(RuntimeError):
    """A stage checkpoint that cannot be used (unreadable, truncated, another architecture)."""


def load_checkpoint(path: Path | str) -> Any:
    """``torch.load(weights_only=True)``; any failure is one CheckpointError naming the file."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"checkpoint {path} cannot be read ({reason[:200]}); delete it to retrain "
                              f"that stage") from None


def read_nets(path: str | Path, mmap: bool = False) -> dict[str, dict[str, torch.Tensor]]:
    """The file's weights as net name -> state dict (one CheckpointError line if it is neither
    layout)."""
    if mmap:
        try:
            state = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
        except Exception:
            state = load_checkpoint(path)  # the one-line error, or a file mmap cannot map
    else:
        state = load_checkpoint(path)
    if not isinstance(state, dict) or not state:
        raise CheckpointError(f"model.weights {path}: not a state dict")
    if all(isinstance(v, dict) for v in state.values()):
        nets = {k: dict(v) for k, v in state.items()}
    elif all(isinstance(v, torch.Tensor) for v in state.values()):
        nets = {}
        for key, tensor in state.items():
            net, _, rest = key.partition(".")
            nets.setdefault(net, {})[rest] = tensor
    else:
        raise CheckpointError(f"model.weights {path}: neither a DeMoN state dict nor a stage weights file")
    unknown = sorted(set(nets) - set(NETS))
    if unknown:
        raise CheckpointError(f"model.weights {path}: holds {', '.join(unknown)}, which are not nets of the "
                              f"chain ({', '.join(NETS)})")
    return nets


def misfit(chain: torch.nn.Module, nets: dict[str, dict[str, torch.Tensor]]) -> str | None:
    """Why ``nets`` do not load strictly into ``chain`` (first difference), or None."""
    for net, weights in nets.items():
        expected = getattr(chain, net).state_dict()
        missing = [k for k in expected if k not in weights]
        extra = [k for k in weights if k not in expected]
        if missing or extra:
            what = f"lacks {net}.{missing[0]}" if missing else f"has {net}.{extra[0]}, which the chain has not"
            return f"{what} (another variant?)"
        for k, tensor in weights.items():
            if tuple(tensor.shape) != tuple(expected[k].shape):
                return (f"{net}.{k} is {list(tensor.shape)} in the file, {list(expected[k].shape)} in this chain "
                        f"(another width or input size?)")
    return None


def check_fits(path: str | Path, variant: str, width: float, size: tuple[int, int],
               correlation: tuple[int, int] | None = None, **priors: str | None) -> str | None:
    """Why the weights file does not fit the chain a config builds, or None (shapes only: no
    weights are copied, and the chain is built on the meta device). ``priors``: the chain's prior
    options and motion fit (``flow1_prior=...``, ``motion_fit=...``)."""
    from demon_lab.nets import DeMoN

    try:
        nets = read_nets(path, mmap=True)
    except CheckpointError as e:
        return str(e)
    with torch.device("meta"):
        chain = DeMoN(variant, width, tuple(size), correlation=correlation, **priors)
    why = misfit(chain, nets)
    if why is None:
        return None
    front = "" if correlation is None else f" model.correlation={list(correlation)}"
    front += "".join(f" model.{k}={v}" for k, v in priors.items() if v is not None)
    return (f"{path} does not fit the chain of model.variant={variant} model.width={width}{front} "
            f"data.size={list(size)}: {why}. {RELEASED_HINT}")


def load_weights(chain: torch.nn.Module, path: str | Path) -> list[str]:
    """Load the file's nets into ``chain`` (strictly, net by net). Returns the nets loaded."""
    nets = read_nets(path)
    why = misfit(chain, nets)
    if why is not None:
        raise CheckpointError(f"model.weights {path} does not fit this chain: {why}. {RELEASED_HINT}")
    for net, weights in nets.items():
        getattr(chain, net).load_state_dict(weights, strict=True)
    return [n for n in NETS if n in nets]
