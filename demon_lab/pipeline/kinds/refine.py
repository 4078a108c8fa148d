"""The refinement net's stage kind."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import ClassVar

from demon_lab.core import losses
from demon_lab.core.losses import REFINE_WEIGHTS
from demon_lab.nets.chain import DeMoN
from demon_lab.pipeline.kinds.base import StageSpec, pair_priors


@dataclass(frozen=True)
class RefineStage(StageSpec):
    """The refinement net on the depth of the frozen chain after ``iterations`` iterative passes; its
    depth-sig weight ramps in over the stage."""

    kind: ClassVar[str] = "refine"
    loss_weights: ClassVar[tuple[str, ...]] = REFINE_WEIGHTS
    best_metric: ClassVar[str] = "l1_inv"  # of the refined depth
    iterations: int = 3
    """The passes of the frozen chain whose depth the refinement net refines (DeMoN: 3)."""

    def trained_nets(self) -> tuple[str, ...]:
        return ("refine_net",)

    def validation_passes(self) -> int:
        return self.iterations

    def loss(self, stage, batch, gt):
        pair, image2_2, K = stage.inputs(batch)
        inv_depth, = stage.frozen(functools.partial(_passes, stage.chain, self.iterations), pair, image2_2, K,
                                  *pair_priors(batch))
        refined = stage.chain.refine(batch["image1"], inv_depth)
        return losses.refine_loss(refined, gt, stage.weights, ramp=stage.ramp(1.0))


def _passes(chain: DeMoN, iterations: int, pair, image2_2, K, *priors):
    """The inverse depth of the frozen chain's last pass."""
    p = chain.bootstrap(pair, image2_2, K, None, None, *priors)
    for _ in range(iterations):
        p = chain.iterate(pair, image2_2, K, p)
    return (p.inv_depth,)
