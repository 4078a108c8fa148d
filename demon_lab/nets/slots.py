"""The chain's net slots: what a net in each one takes and returns.

The chain (:class:`demon_lab.nets.DeMoN`) calls five nets, and each can be a net of your own
(``model.nets.SLOT`` in a config: ``_target_`` and its arguments; docs/guides/your_own_net.md). A
slot's net is any ``nn.Module`` whose ``forward`` has the slot's signature below; the chain builds
every input, as it does for DeMoN's nets (:func:`demon_lab.nets.chain.flow_net_inputs`,
:func:`demon_lab.nets.chain.depth_motion_net_inputs`), and the stages train whatever the slot holds
with the slot's losses. Shapes for an input of H x W: level 2 is H/4 x W/4, level 5 H/32 x W/32;
flows are in DeMoN's normalised units (a fraction of the image's width and height).

==========  =========================  ============================================================
slot        DeMoN's net                forward
==========  =========================  ============================================================
``flow1``   :class:`FlowNet`           ``(pair, extra=None, prior2=None) -> (flowconf5, flowconf2)``
``flow2``   :class:`FlowNet`           ``(pair, extra) -> (flowconf5, flowconf2)``
``dm1``     :class:`DepthMotionNet`    ``(pair, extra) -> DepthMotion``
``dm2``     :class:`DepthMotionNet`    ``(pair, extra) -> DepthMotion``
``refine``  :class:`RefineNet`         ``(image1, inv_depth2) -> refined``
==========  =========================  ============================================================

- ``pair`` (B, 6, H, W): the two images, stacked. ``flowconf5`` (B, 4, H/32, W/32) and ``flowconf2``
  (B, 4, H/4, W/4): the flow (2 channels) and its confidence (2 channels, one per flow component).
- ``flow1``'s ``prior2`` (B, 2, H/4, W/4): the classical prior flow under ``model.flow1_prior``
  (None otherwise); a net may read it or not.
- ``flow2``'s ``extra`` (B, 9, H/4, W/4): image 2 warped with the flow of the previous pass's depth
  and motion, that flow, the previous inverse depth and its normals.
- ``dm1``'s ``extra`` (B, 7, H/4, W/4): image 2 warped with the flow, the flow, its confidence (8
  channels under ``model.dm1_prior``: the inverse depth triangulated with the prior motion too);
  ``dm2``'s (B, 8, H/4, W/4): the same with the inverse depth triangulated with the previous motion.
- :class:`DepthMotion`: ``inv_depth`` (B, 1, H/4, W/4), ``normals`` (B, 3, H/4, W/4), ``motion``
  (B, 6: angle-axis rotation, then the translation's direction) and ``scale`` (B, 1: the depth's
  scale, which DeMoN's net predicts and its losses do not read).
- ``refine``: ``image1`` (B, 3, H, W) and ``inv_depth2`` (B, 1, H/4, W/4), the last pass's inverse
  depth; ``refined`` (B, 1, H, W), the inverse depth at full resolution.

DeMoN's nets also start the prior options' corrections at none (``flow2_prior``, ``dm1_prior``,
``dm2_prior`` zero the heads that predict the correction); a net of your own starts as it builds
itself.
"""

from __future__ import annotations

import hashlib
import importlib
import inspect
from collections.abc import Mapping
from typing import Any, Protocol, runtime_checkable

import torch

from demon_lab.nets.depth_motion_net import DepthMotion

SLOTS = ("flow1", "dm1", "flow2", "dm2", "refine")
"""The chain's net slots, in the order its stages train them."""

ATTRIBUTES = {"flow1": "flow1", "dm1": "dm1", "flow2": "flow2", "dm2": "dm2", "refine": "refine_net"}
"""Each slot's net as the chain holds it (its attribute, the name a stage's weights file gives it)."""


@runtime_checkable
class FlowSlot(Protocol):
    """``flow1`` and ``flow2``: a flow and its confidence at levels 5 and 2."""

    def __call__(self, pair: torch.Tensor, extra: torch.Tensor | None = None,
                 prior2: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]: ...


@runtime_checkable
class DepthMotionSlot(Protocol):
    """``dm1`` and ``dm2``: inverse depth, normals and camera motion (:class:`DepthMotion`)."""

    def __call__(self, pair: torch.Tensor, extra: torch.Tensor) -> DepthMotion: ...


@runtime_checkable
class RefineSlot(Protocol):
    """``refine``: the last pass's inverse depth at full resolution."""

    def __call__(self, image1: torch.Tensor, inv_depth2: torch.Tensor) -> torch.Tensor: ...


def plugin_class(target: str) -> type:
    """The class a ``_target_`` names (``package.module.Class``), imported; one ValueError line
    where it cannot be."""
    module_name, _, name = str(target).rpartition(".")
    if not module_name:
        raise ValueError(f"_target_: expected package.module.Class, got {target!r}")
    try:
        module = importlib.import_module(module_name)
    except Exception as e:  # (an ImportError, or the module's own error)
        raise ValueError(f"_target_: cannot import {module_name!r} ({type(e).__name__}: {e}); is its folder "
                         f"the working directory or on PYTHONPATH?") from None
    found = getattr(module, name, None)
    if not isinstance(found, type) or not issubclass(found, torch.nn.Module):
        raise ValueError(f"_target_: {target!r} is not an nn.Module class")
    return found


def source_digest(cls: type) -> str:
    """A digest of the source of the module that defines ``cls``: an edit of it trains the net again."""
    try:
        source = inspect.getsource(inspect.getmodule(cls))
    except (OSError, TypeError):  # (no source file: the class's qualified name only)
        source = f"{cls.__module__}.{cls.__qualname__}"
    return hashlib.sha256(source.encode()).hexdigest()[:16]


def check_plugin(slot: str, node: Any, prefix: str = "model.nets.") -> None:
    """One ValueError line where ``node`` is not null nor a mapping with a ``_target_`` that names an
    ``nn.Module`` class."""
    if slot not in SLOTS:
        raise ValueError(f"{prefix}{slot}: no such slot; expected one of {', '.join(SLOTS)}")
    if node is None:
        return
    if not isinstance(node, Mapping) or "_target_" not in node:
        raise ValueError(f"{prefix}{slot}: expected null (DeMoN's net) or a net's config with _target_, got {node!r}")
    try:
        cls = plugin_class(node["_target_"])
    except ValueError as e:
        raise ValueError(f"{prefix}{slot}.{e}") from None
    args = {k: v for k, v in node.items() if k != "_target_"}
    try:
        inspect.signature(cls).bind(**args)
    except TypeError as e:
        raise ValueError(f"{prefix}{slot}: {node['_target_']}({', '.join(args)}): {e}") from None
