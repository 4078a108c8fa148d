"""LightningDataModule of a stage's training pairs, over any mix of sources.

``train`` is a list of ``{weight, dataset}`` entries: each step draws a source with probability
proportional to its weight and a sample of it (DeMoN divides a source's weight by its number of
files; here a weight is per source). The held-apart and test sets are scored by the stages'
callbacks and the job's evaluation, each set on its own loader (:mod:`demon_lab.pipeline.evaluate`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader

from demon_lab.data.datasets import LayersDataset, SyntheticDataset
from demon_lab.data.mixture import MixtureDataset, MixtureSampler, flow_order


def _seed_worker(worker_id: int) -> None:
    # demon_lab draws from explicit generators, but user code may use numpy's global one.
    np.random.seed(torch.initial_seed() % 2**32)  # noqa: NPY002


@dataclass(frozen=True)
class Draws:
    """How a stage draws its training pairs (:class:`demon_lab.data.mixture.MixtureSampler`'s options)."""

    batch_size: int = 8
    """This process's batch (under DDP each of ``world`` processes loads its share of a global batch)."""
    samples_per_epoch: int = 1000
    seed: int = 0
    skip: int = 0
    """Draws of the first epoch already consumed (a resumed stage continues the sequence)."""
    rank: int = 0
    world: int = 1
    easy_first: tuple[float, float] | None = None
    """A curriculum: the easiest fraction of samples first, widening to all."""
    layers_first: float | None = None
    """The first fraction of the stage on fresh 2-D layers (the sampler's lead), then the sources."""
    layers_size: tuple[int, int] = (96, 128)
    fresh_scenes: float = 0.0
    """New synthetic scenes per draw of a synthetic source, rendered by the loader's workers."""


class DemonDataModule(L.LightningDataModule):
    """A stage's training pairs: ``train`` is a list of ``{weight, dataset}`` sources, drawn as
    ``draws`` says; ``pin_memory``: page-locked batches (asynchronous copies to a CUDA device); ``fields``:
    what each draw carries besides its sample (:class:`demon_lab.data.mixture.MixtureDataset`)."""

    def __init__(self, train: Sequence[Mapping[str, Any]], draws: Draws = Draws(), num_workers: int = 0,
                 pin_memory: bool = False,
                 fields: Callable[[Mapping[str, torch.Tensor], tuple | None], Mapping[str, Any]] | None = None):
        super().__init__()
        self.train_sources = [(float(e["weight"]), e["dataset"]) for e in train]
        self.draws, self.num_workers, self.pin_memory = draws, int(num_workers), bool(pin_memory)
        self.fields = fields
        self.sampler: MixtureSampler | None = None

    def _loader(self, dataset, **kwargs) -> DataLoader:
        return DataLoader(dataset, batch_size=self.draws.batch_size, num_workers=self.num_workers,
                          worker_init_fn=_seed_worker, persistent_workers=self.num_workers > 0,
                          pin_memory=self.pin_memory,
                          generator=torch.Generator().manual_seed(self.draws.seed), **kwargs)

    def train_dataloader(self) -> DataLoader:
        if not self.train_sources:
            raise ValueError("data.train: no training source configured")
        d = self.draws
        weights, datasets = zip(*self.train_sources)
        order = None if d.easy_first is None else [flow_order(x) for x in datasets]
        lengths = [len(x) for x in datasets]  # (a fresh source's own scenes: the sampler grows it past them)
        fresh = [d.fresh_scenes if isinstance(x, SyntheticDataset) else 0.0 for x in datasets]
        if d.fresh_scenes:
            extra = math.ceil(d.fresh_scenes * d.samples_per_epoch)
            datasets = tuple(x.extended(extra) if f else x for x, f in zip(datasets, fresh, strict=True))
        lead = None
        if d.layers_first is not None:
            layers = LayersDataset(d.layers_size, d.seed)
            weights, datasets = (*weights, 0.0), (*datasets, layers)
            lengths, fresh = [*lengths, len(layers)], [*fresh, 0.0]
            lead = (len(datasets) - 1, d.layers_first)
        self.sampler = MixtureSampler(lengths, weights, d.samples_per_epoch, seed=d.seed, skip=d.skip, rank=d.rank,
                                       world=d.world, batch=d.batch_size, easy_first=d.easy_first, order=order,
                                       lead=lead, fresh=fresh)
        return self._loader(MixtureDataset(datasets, self.fields), sampler=self.sampler, drop_last=True)

    def fresh_scenes(self) -> list[SyntheticDataset]:
        """The sources' fresh scenes that this stage's draws meet (``Draws.fresh_scenes``), as the sets to
        render ahead of it (:func:`demon_lab.data.datasets.warm_cache`): each fresh source grown by the
        new scenes it meets. (After :meth:`train_dataloader`.)"""
        counts = self.sampler.fresh_scenes() if self.sampler is not None else []
        return [dataset.extended(n) for (_, dataset), n in zip(self.train_sources, counts) if n]
