"""LightningDataModule over any mix of sources, with train/val/test splits.

``train`` is a list of ``{weight, dataset}`` entries: each step draws a source with probability
proportional to its weight and a sample of it (DeMoN divides a source's weight by its number of
files; here a weight is per source). ``val`` and ``test`` are lists of datasets evaluated one by
one (each keeps its name, so metrics are reported per dataset).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader

from demon_lab.data.datasets import LayersDataset, PairDataset, SyntheticDataset
from demon_lab.data.mixture import MixtureDataset, MixtureSampler, flow_order


def _seed_worker(worker_id: int) -> None:
    # demon_lab draws from explicit generators, but user code may use numpy's global one.
    np.random.seed(torch.initial_seed() % 2**32)  # noqa: NPY002


class DemonDataModule(L.LightningDataModule):
    def __init__(
        self,
        train: Sequence[Mapping[str, Any]] = (),
        val: Sequence[PairDataset] = (),
        test: Sequence[PairDataset] = (),
        batch_size: int = 8,
        num_workers: int = 0,
        samples_per_epoch: int = 1000,
        skip: int = 0,
        seed: int = 0,
        rank: int = 0,
        world: int = 1,
        easy_first: Sequence[float] | None = None,
        pin_memory: bool = False,
        layers_first: float | None = None,
        layers_size: Sequence[int] = (96, 128),
        fresh_scenes: float = 0.0,
    ):
        super().__init__()
        self.train_sources = [(float(e["weight"]), e["dataset"]) for e in train]
        self.val_sets, self.test_sets = list(val), list(test)
        self.batch_size, self.num_workers = int(batch_size), int(num_workers)
        self.samples_per_epoch, self.seed, self.skip = int(samples_per_epoch), int(seed), int(skip)
        self.rank, self.world = int(rank), int(world)  # data-parallel: this process's share of each batch
        self.easy_first = None if easy_first is None else tuple(easy_first)  # curriculum: MixtureSampler
        self.pin_memory = bool(pin_memory)  # page-locked batches: asynchronous copies to a CUDA device
        # the first fraction of the stage on fresh 2-D layers (MixtureSampler's lead), then the sources
        self.layers_first = None if layers_first is None else float(layers_first)
        self.layers_size = tuple(layers_size)
        # new synthetic scenes per draw of a synthetic source, rendered by the loader's workers (MixtureSampler's fresh)
        self.fresh_scenes = float(fresh_scenes)
        self._sampler: MixtureSampler | None = None

    def _loader(self, dataset, **kwargs) -> DataLoader:
        return DataLoader(dataset, batch_size=self.batch_size, num_workers=self.num_workers,
                          worker_init_fn=_seed_worker, persistent_workers=self.num_workers > 0,
                          pin_memory=self.pin_memory,
                          generator=torch.Generator().manual_seed(self.seed), **kwargs)

    def train_dataloader(self) -> DataLoader:
        if not self.train_sources:
            raise ValueError("data.train: no training source configured")
        weights, datasets = zip(*self.train_sources)
        order = None if self.easy_first is None else [flow_order(d) for d in datasets]
        lengths = [len(d) for d in datasets]  # (a fresh source's own scenes: the sampler grows it past them)
        fresh = [self.fresh_scenes if isinstance(d, SyntheticDataset) else 0.0 for d in datasets]
        if self.fresh_scenes:
            extra = math.ceil(self.fresh_scenes * self.samples_per_epoch)
            datasets = tuple(d.extended(extra) if f else d for d, f in zip(datasets, fresh, strict=True))
        lead = None
        if self.layers_first is not None:
            layers = LayersDataset(self.layers_size, self.seed)
            weights, datasets = (*weights, 0.0), (*datasets, layers)
            lengths, fresh = [*lengths, len(layers)], [*fresh, 0.0]
            lead = (len(datasets) - 1, self.layers_first)
        self._sampler = MixtureSampler(lengths, weights, self.samples_per_epoch, seed=self.seed, skip=self.skip,
                                       rank=self.rank, world=self.world, batch=self.batch_size,
                                       easy_first=self.easy_first, order=order, lead=lead, fresh=fresh)
        return self._loader(MixtureDataset(datasets), sampler=self._sampler, drop_last=True)

    def val_dataloader(self) -> list[DataLoader]:
        return [self._loader(d, shuffle=False) for d in self.val_sets]

    def test_dataloader(self) -> list[DataLoader]:
        return [self._loader(d, shuffle=False) for d in self.test_sets]

    @property
    def test_names(self) -> list[str]:
        return [d.name for d in self.test_sets]
