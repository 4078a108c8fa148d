"""Convert DeMoN's released TensorFlow weights into a demon_lab state dict.

    python -m demon_lab.convert PREFIX OUT.pt

``PREFIX`` is the checkpoint's prefix (``weights/demon_original`` as DeMoN's
``weights/download_weights.sh`` leaves it: ``demon_original.index`` and
``demon_original.data-00000-of-00001``) or the path of one of its files. ``OUT.pt`` is read by
``torch.load(OUT, weights_only=True)`` as the state dict of ``demon_lab.nets.DeMoN(variant="v1")``
(full width, 256x192 inputs): a strict ``load_state_dict`` succeeds, and ``model.weights=OUT.pt``
runs it in a job (docs/released_model.md).

The checkpoint is read by :mod:`demon_lab.tools.tf_checkpoint`, a reader of TensorFlow's checkpoint
format that needs no TensorFlow (a user converts once; TensorFlow is a 600 MB install whose
pins move numpy and h5py). The names and layouts are those of DeMoN's v1 graph
(``BootstrapNet``, ``IterativeNet`` and ``RefinementNet`` of
`python/depthmotionnet/networks_original.py`, built from `blocks_original.py`):

- ``netFlow1``, ``netDM1``, ``netFlow2``, ``netDM2``, ``netRefine`` are demon_lab's ``flow1``,
  ``dm1``, ``flow2``, ``dm2`` and ``refine_net``;
- ``convrelu2_caffe_padding`` layer ``NAME`` is ``NAMEy`` + ``NAMEx`` (``conv2_extra_inputs`` is
  demon_lab's ``conv2_extra``); a prediction head's ``conv1``/``conv2`` are its ``hidden``/``out``
  (``predict_depthnormal2`` is ``predict_depth2``); ``upconv`` is an up-convolution's ``deconv``;
- conv kernels are ``[kh, kw, in, out]`` (torch: ``[out, in, kh, kw]``), transposed-conv kernels
  ``[kh, kw, out, in]`` (torch: ``[in, out, kh, kw]``), dense kernels ``[in, out]`` (torch:
  ``[out, in]``); ``motion_fc1`` reads its features flattened in C, H, W order in both.

Variables that are not part of the graph (optimiser slots, step counters) are skipped and
counted; nothing is written unless every tensor of the chain mapped. Bad input is one line on
stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from demon_lab.tools.tf_checkpoint import CheckpointFormatError, CheckpointReader

TF_NETS = {"flow1": "netFlow1", "dm1": "netDM1", "flow2": "netFlow2", "dm2": "netDM2", "refine_net": "netRefine"}
TF_LAYERS = {"conv2_extra": "conv2_extra_inputs", "predict_depth2": "predict_depthnormal2"}
HEAD_CONVS = {"hidden": "conv1", "out": "conv2"}


class ConversionError(ValueError):
    """The checkpoint does not map onto the chain (one line)."""


@dataclass(frozen=True)
class Variable:
    """One TensorFlow variable of DeMoN's graph and the state-dict entry it becomes."""

    key: str  # demon_lab state-dict key
    name: str  # TensorFlow variable name
    tf_shape: tuple[int, ...]
    permutation: tuple[int, ...] | None  # numpy axes that turn the TF layout into torch's


def _tf_layer(path: list[str]) -> str:
    """demon_lab's module path within a net (``conv2_extra.y.conv``) -> DeMoN's scope (``conv2_extra_inputsy``)."""
    layer = TF_LAYERS.get(path[0], path[0])
    rest = path[1:]
    if rest and rest[-1] in ("conv", "deconv"):
        rest = rest[:-1] + (["upconv"] if rest[-1] == "deconv" else [])
    if rest and rest[0] in ("y", "x"):
        return layer + rest[0]
    if rest and rest[0] in HEAD_CONVS:
        return f"{layer}/{HEAD_CONVS[rest[0]]}"
    return "/".join([layer, *rest])


def layout(module: nn.Module, param: str) -> tuple[int, ...] | None:
    """The numpy axes that turn a TensorFlow variable into ``module``'s parameter ``param``:
    conv [out, in, kh, kw] <- [kh, kw, in, out]; transposed conv [in, out, kh, kw] <-
    [kh, kw, out, in]; dense [out, in] <- [in, out]; biases as they are (None)."""
    if param == "bias":
        return None
    if isinstance(module, (nn.Conv2d, nn.ConvTranspose2d)):
        return (3, 2, 0, 1)
    if isinstance(module, nn.Linear):
        return (1, 0)
    raise TypeError(f"no TensorFlow layout known for {type(module).__name__}.{param}")


def to_torch(array: np.ndarray, module: nn.Module, param: str) -> torch.Tensor:
    """A TensorFlow variable as ``module``'s parameter ``param``."""
    perm = layout(module, param)
    return torch.from_numpy(np.ascontiguousarray(array if perm is None else array.transpose(perm)))


def graph_variables(chain: nn.Module) -> list[Variable]:
    """Every parameter of ``chain`` (a v1 :class:`demon_lab.nets.DeMoN`) as DeMoN's variable."""
    variables = []
    for key, tensor in chain.state_dict().items():
        net, *path, param = key.split(".")
        perm = layout(chain.get_submodule(".".join([net, *path])), param)
        name = f"{TF_NETS[net]}/{_tf_layer(path)}/{'kernel' if param == 'weight' else param}"
        # the TF shape is the torch shape through the inverse permutation
        tf_shape = tuple(tensor.shape) if perm is None else tuple(tensor.shape[perm.index(i)] for i in range(len(perm)))
        variables.append(Variable(key, name, tf_shape, perm))
    return variables


@dataclass
class Conversion:
    state_dict: dict[str, torch.Tensor]
    parameters: int
    skipped: list[str] = field(default_factory=list)


def convert_checkpoint(prefix: str | Path) -> Conversion:
    """The state dict of ``DeMoN(variant="v1")`` from DeMoN's TensorFlow checkpoint ``prefix``.

    Raises CheckpointFormatError (unreadable files) or ConversionError (not DeMoN's graph), one line each.
    """
    from demon_lab.nets import DeMoN

    reader = CheckpointReader(prefix)
    with torch.device("meta"):
        variables = graph_variables(DeMoN("v1"))
    for v in variables:  # a wrong shape is the more telling error: checked before missing ones
        entry = reader.entries.get(v.name)
        if entry is not None and entry.shape != v.tf_shape:
            raise ConversionError(f"{reader.prefix}: {v.name}: shape mismatch: expected {list(v.tf_shape)}, "
                                  f"found {list(entry.shape)}")
        if entry is not None and entry.dtype_name != "float32":
            raise ConversionError(f"{reader.prefix}: {v.name}: expected float32, found {entry.dtype_name}")
    missing = [v.name for v in variables if v.name not in reader.entries]
    if missing:
        shown = ", ".join(missing[:4]) + (", ..." if len(missing) > 4 else "")
        raise ConversionError(f"{reader.prefix}: not DeMoN's v1 checkpoint: {len(missing)} of its graph's "
                              f"{len(variables)} variables are missing ({shown})")
    state = {}
    for v in variables:
        array = reader.read(v.name)
        state[v.key] = torch.from_numpy(np.ascontiguousarray(array if v.permutation is None
                                                             else array.transpose(v.permutation)))
    graph = {v.name for v in variables}
    skipped = sorted(name for name in reader.entries if name not in graph)
    return Conversion(state, sum(t.numel() for t in state.values()), skipped)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m demon_lab.convert", description=__doc__.splitlines()[0])
    parser.add_argument("prefix", help="the checkpoint's prefix (e.g. weights/demon_original) or one of its files")
    parser.add_argument("out", type=Path, help="the state dict to write (e.g. demon_original.pt)")
    args = parser.parse_args(argv)
    from demon_lab.pipeline.identity import content_hash
    from demon_lab.pipeline.stages.cache import atomic_torch_save

    try:
        result = convert_checkpoint(args.prefix)
    except (CheckpointFormatError, ConversionError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # unreadable (permissions, a folder where a file should be, ...)
        print(f"error: {e.filename or args.prefix}: cannot read ({e.strerror or e})", file=sys.stderr)
        return 2
    try:
        atomic_torch_save(result.state_dict, args.out)
    except OSError as e:
        print(f"error: {args.out}: cannot write ({e.strerror or e})", file=sys.stderr)
        return 2
    print(f"converted {len(result.state_dict)} tensors ({result.parameters:,} parameters) of DeMoN's v1 graph")
    if result.skipped:
        shown = ", ".join(result.skipped[:3]) + (", ..." if len(result.skipped) > 3 else "")
        print(f"skipped {len(result.skipped)} variables that are not part of the graph ({shown})")
    else:
        print("skipped 0 variables (the checkpoint holds the graph's variables only)")
    print(f"wrote {args.out} (sha256 {content_hash(args.out)[:16]}); use it with model.weights={args.out}")
    return 0

