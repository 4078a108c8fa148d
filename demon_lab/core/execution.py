"""How the chain runs: on which device, in which precision, in which memory format, compiled or not.

None of these change what a job computes beyond floating-point rounding, except ``precision``:

- ``precision`` (Lightning's names: ``32`` / ``32-true``, ``bf16-mixed``, ``16-mixed``): the nets'
  convolutions and matrix products run in bfloat16 or float16 under ``torch.autocast``, for training
  (Lightning's precision plugin, with loss scaling for float16) and evaluation. Everything outside the
  nets stays float32: the nets return float32 and the functions marked :func:`float32` (the geometry
  layers: triangulation, rotations, warps, normals; the losses with their scale-invariant gradients;
  the nets' input builders) run with autocast off on float32 inputs. A non-default precision is part
  of a stage's and a run's key: bf16-trained weights are other weights.
- ``model.channels_last``: the nets' weights and the images in NHWC memory layout (tensor cores
  read it without a transpose); ``model.compile``: ``torch.compile`` of each net (in place, so
  checkpoints keep their keys). Neither is part of any key.
- the device: training's is Lightning's (``trainer.accelerator``); evaluation runs on the same
  kind of device (:func:`evaluation_device`).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import shutil
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import torch

PRECISIONS = ("32-true", "bf16-mixed", "16-mixed")
"""The precisions demon_lab trains and evaluates in (Lightning's names)."""

_ALIASES = {"32": "32-true", "32-true": "32-true", "bf16": "bf16-mixed", "bf16-mixed": "bf16-mixed",
            "16": "16-mixed", "16-mixed": "16-mixed"}
_DTYPES = {"bf16-mixed": torch.bfloat16, "16-mixed": torch.float16}
_AUTOCAST_DEVICES = ("cuda", "cpu")

F = TypeVar("F", bound=Callable[..., Any])
log = logging.getLogger(__name__)


def normalize_precision(value: Any) -> str:
    """Lightning's name of a precision setting (``32`` and ``"32"`` are ``"32-true"``, ``"bf16"`` is
    ``"bf16-mixed"``, ``"16"`` is ``"16-mixed"``); ValueError for anything else."""
    name = _ALIASES.get(str(value)) if not isinstance(value, bool) else None
    if name is None:
        raise ValueError(f"precision: expected one of 32, bf16-mixed, 16-mixed, got {value!r}")
    return name


def autocast_dtype(precision: Any) -> torch.dtype | None:
    """The dtype the nets compute in under ``precision`` (None: float32, no autocast)."""
    return _DTYPES.get(normalize_precision(precision))


def autocast(device: torch.device | str, precision: Any) -> contextlib.AbstractContextManager:
    """The nets' autocast region for ``precision`` on ``device`` (a no-op for ``32``)."""
    dtype = autocast_dtype(precision)
    if dtype is None:
        return contextlib.nullcontext()
    return torch.autocast(torch.device(device).type, dtype=dtype)


def _autocast_on(device_type: str) -> bool:
    try:
        return torch.is_autocast_enabled(device_type)
    except TypeError:  # torch < 2.4: one query per device type
        return torch.is_autocast_cpu_enabled() if device_type == "cpu" else torch.is_autocast_enabled()


def _has_half(x: Any) -> bool:
    if isinstance(x, torch.Tensor):
        return x.dtype in (torch.bfloat16, torch.float16)
    if isinstance(x, dict):
        return any(_has_half(v) for v in x.values())
    if isinstance(x, list | tuple):
        return any(_has_half(v) for v in x)
    return False


def _to_float32(x: Any) -> Any:
    if isinstance(x, torch.Tensor):
        return x.float() if x.dtype in (torch.bfloat16, torch.float16) else x
    if isinstance(x, dict):
        return {k: _to_float32(v) for k, v in x.items()}
    if isinstance(x, list | tuple) and not hasattr(x, "_fields"):
        return type(x)(_to_float32(v) for v in x)
    return x


def float32(fn: F) -> F:
    """Run ``fn`` in float32: autocast off, half-precision tensor arguments (also inside dicts,
    lists and tuples; not inside other mappings or dataclasses) cast to float32, inside an autocast
    region or not (an island called from another gets its half inputs cast too). Outside autocast,
    with no half argument, it is ``fn`` itself, called as it is (the float32 path is unchanged to
    the last bit)."""

    @functools.wraps(fn)
    def island(*args, **kwargs):
        active = [d for d in _AUTOCAST_DEVICES if _autocast_on(d)]
        if not active and not (_has_half(args) or _has_half(kwargs)):
            return fn(*args, **kwargs)
        with contextlib.ExitStack() as stack:
            for device_type in active:
                stack.enter_context(torch.autocast(device_type, enabled=False))
            return fn(*_to_float32(args), **_to_float32(kwargs))

    island.float32_island = True  # type: ignore[attr-defined]
    return island  # type: ignore[return-value]


def _mps_available() -> bool:
    mps = getattr(torch.backends, "mps", None)
    return mps is not None and mps.is_available()


def resolve_accelerator(accelerator: str) -> str:
    """The device type Lightning's ``accelerator`` setting trains on: ``cuda``, ``mps`` or ``cpu``
    (``gpu``: CUDA, or Apple's MPS where that is the GPU there is; ``auto``: also the CPU)."""
    accelerator = str(accelerator)
    if accelerator == "cuda":
        return "cuda"
    if accelerator in ("gpu", "auto"):
        if torch.cuda.is_available():
            return "cuda"
        if _mps_available():
            return "mps"
        return "cuda" if accelerator == "gpu" else "cpu"
    return accelerator


def evaluation_device(job) -> torch.device:
    """Where a job evaluates the chain: the device type it trains on (``trainer.accelerator``),
    this process's GPU (``LOCAL_RANK``) when that is CUDA; the CPU, with a log line, when that
    device is not here (every stage cached or ``train=false``: nothing trained on it)."""
    kind = resolve_accelerator(job.trainer.accelerator)
    if (kind == "cuda" and not torch.cuda.is_available()) or (kind == "mps" and not _mps_available()):
        log.info("trainer.accelerator=%s: no %s device here, evaluating on the CPU", job.trainer.accelerator, kind)
        return torch.device("cpu")
    if kind == "cuda":
        local = os.environ.get("LOCAL_RANK", "0")
        return torch.device("cuda", int(local) if local.isdigit() else 0)
    return torch.device(kind)


def precision_problem(precision: Any, device_type: str) -> str | None:
    """Why ``precision`` cannot run on ``device_type`` (one line), or None."""
    name = normalize_precision(precision)
    if name != "32-true" and device_type not in _AUTOCAST_DEVICES:
        return (f"precision={name}: demon_lab's float32 islands cover CUDA and the CPU; this job runs on "
                f"{device_type}: use precision=32 there")
    if name == "16-mixed" and device_type != "cuda":
        return (f"precision=16-mixed needs a CUDA device (float16 autocast with loss scaling); this job runs on "
                f"{device_type}: use bf16-mixed or 32 there")
    if name == "bf16-mixed" and device_type == "cuda" and torch.cuda.is_available() \
            and not torch.cuda.is_bf16_supported():
        return "precision=bf16-mixed: this GPU has no bfloat16 support; use 16-mixed or 32"
    return None


def compile_problem(device_type: str) -> str | None:
    """Why ``torch.compile`` cannot compile the nets on this platform for ``device_type`` (one
    line), or None: TorchDynamo unsupported here (a Python newer than this torch knows, Windows
    before torch 2.5), or no C++ compiler for Inductor's CPU kernels."""
    try:
        import torch._dynamo

        if not torch._dynamo.is_dynamo_supported():
            import sys

            return (f"model.compile=true: torch {torch.__version__} cannot compile on this platform "
                    f"(Python {sys.version.split()[0]}, {sys.platform}); leave model.compile=false")
    except Exception as e:  # an import failure is the same answer
        return f"model.compile=true: torch.compile is unavailable ({type(e).__name__}: {e}); leave model.compile=false"
    if device_type not in _COMPILERS:
        return None
    variable, names, what, example = _COMPILERS[device_type]
    compiler = os.environ.get(variable) or next((c for c in names if shutil.which(c)), None)
    if compiler is None or shutil.which(compiler) is None:
        return (f"model.compile=true on {device_type} needs {what} (none found: install {example} or set "
                f"{variable}); leave model.compile=false")
    return None


_COMPILERS = {"cpu": ("CXX", ("c++", "g++", "clang++"), "a C++ compiler for torch.compile's kernels", "g++"),
              "cuda": ("CC", ("cc", "gcc", "clang"), "a C compiler for Triton's kernel launchers", "gcc")}
"""What torch.compile builds its kernels with, per device type: variable, names, purpose, a package."""


def prepare_nets(chain: torch.nn.Module, channels_last: bool = False, compile: bool = False) -> torch.nn.Module:
    """Put the chain's nets in the memory format and compilation asked for (in place; returns it).
    Compilation wraps each net's call (``nn.Module.compile``): its parameters and state-dict keys are
    unchanged, so stages load and save as without it."""
    if channels_last:
        chain.to(memory_format=torch.channels_last)
    if compile:
        for net in chain.children():  # the chain's nets: flow1, dm1, flow2, dm2, refine_net
            if not getattr(net, "_compiled_call_impl", None):
                net.compile()
    return chain


def channels_last_batch(batch: dict, channels_last: bool) -> dict:
    """The batch's image-like (4-d) tensors in channels-last layout, when asked for."""
    if not channels_last:
        return batch
    return {k: v.contiguous(memory_format=torch.channels_last) if isinstance(v, torch.Tensor) and v.dim() == 4
            else v for k, v in batch.items()}


def plain_state(net: torch.nn.Module) -> dict[str, torch.Tensor]:
    """``net``'s state dict with every tensor in the default contiguous layout (a stage saved from
    a channels-last chain is the same file as one saved without it)."""
    return {k: v.contiguous() for k, v in net.state_dict().items()}


@contextlib.contextmanager
def peak_memory(device: torch.device) -> Iterator[dict[str, float]]:
    """Peak memory the block allocated on a CUDA device (``{"peak_gib": ...}``; empty elsewhere)."""
    out: dict[str, float] = {}
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    yield out
    if device.type == "cuda":
        out["peak_gib"] = torch.cuda.max_memory_allocated(device) / 2**30


def world_size(job: Any) -> int:
    """The processes of a job (its settings, or anything with their ``trainer`` section):
    ``trainer.devices x trainer.num_nodes``."""
    return int(job.trainer.devices) * int(job.trainer.num_nodes)


def global_rank(job: Any) -> int:
    """This process's rank in a multi-process (DDP) job, as Lightning's cluster environments read it:
    torchrun's (``TorchElasticEnvironment``), SLURM's under srun or submitit (``SLURMEnvironment``),
    or, in a process that Lightning's launcher started for a local multi-device run
    (``LightningEnvironment``), node rank x devices + local rank; 0 for a single process."""
    from lightning.fabric.plugins.environments import LightningEnvironment, SLURMEnvironment, TorchElasticEnvironment

    for environment in (TorchElasticEnvironment, SLURMEnvironment):
        if environment.detect():
            return environment().global_rank()
    local = LightningEnvironment()
    return local.node_rank() * int(job.trainer.devices) + local.local_rank()


def processes_launched_outside() -> bool:
    """True when torchrun or SLURM started this job's processes (Lightning then spawns none)."""
    import os

    return any(os.environ.get(var, "").isdigit() for var in ("RANK", "SLURM_PROCID", "LOCAL_RANK"))


def set_threads(n: int) -> None:
    """Limit this process's torch and OpenCV CPU threads: processes that share cores, each running
    a thread per core, slow each other down far more than the share they give up."""
    import cv2
    import torch

    torch.set_num_threads(n)
    cv2.setNumThreads(n)
