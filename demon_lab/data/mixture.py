"""Several sources behind one loader: :class:`MixtureDataset` indexes them by ``(source, index,
draw seed)`` and :class:`MixtureSampler` deals those keys for a training stage (source weights, an
``easy_first`` curriculum ordered by :func:`flow_order`, a lead of fresh 2-D layers, fresh synthetic
scenes, resumable and sharded across processes)."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import torch

from demon_lab.data import sample as smp
from demon_lab.data.datasets import PairDataset


def flow_order(dataset: PairDataset) -> np.ndarray:
    """The dataset's indices from the smallest to the largest mean ground-truth flow magnitude
    (un-augmented samples; pixels without flow left out, a sample without any last): the order of
    an ``easy_first`` curriculum (:class:`MixtureSampler`)."""
    magnitudes = []
    for i in range(len(dataset)):
        flow = dataset.load(i).get("flow")
        if flow is None:
            raise smp.DataError(f"easy_first: {dataset.name} has no ground-truth flow to order its samples by")
        norm = torch.linalg.vector_norm(flow.double(), dim=0)
        norm = norm[torch.isfinite(norm)]
        magnitudes.append(float(norm.mean()) if norm.numel() else math.inf)
    return np.argsort(np.asarray(magnitudes), kind="stable")


class MixtureDataset(torch.utils.data.Dataset):
    """Several datasets behind one index space of ``(dataset, index, draw_seed)`` keys. ``fields(sample,
    pair_key)``, a function of a drawn sample and what identifies its pair (:meth:`PairDataset.pair_key`),
    adds what it returns to the sample (the pair's classical priors: :mod:`demon_lab.pipeline.stages.priors`)."""

    def __init__(self, datasets: Sequence[PairDataset],
                 fields: Callable[[smp.Sample, tuple | None], Mapping[str, torch.Tensor]] | None = None):
        self.datasets, self.fields = list(datasets), fields

    def __len__(self) -> int:
        return sum(len(d) for d in self.datasets)

    def __getitem__(self, key: tuple[int, int, int]) -> smp.Sample:
        which, index, draw = key
        dataset = self.datasets[which]
        sample = dataset[(index, draw)]
        if self.fields is None:
            return sample
        return {**sample, **self.fields(sample, getattr(dataset, "pair_key", lambda *_: None)(index, draw))}


class MixtureSampler(torch.utils.data.Sampler):
    """Draws ``num_samples`` keys per epoch: a source with probability proportional to its weight,
    then a uniform sample of it, and a draw seed for the augmentation. Deterministic in
    ``(seed, epoch)``; the epoch advances each time the sampler is iterated (once per epoch in a
    DataLoader), or is set with :meth:`set_epoch`; ``skip`` drops the first keys of epoch 0, so a
    stage resumed at step k with batch b (``skip = k * b``) sees exactly the keys an uninterrupted
    run would have seen from step k on.

    Data-parallel training (``world`` processes, ``batch`` samples each per step): every process
    draws the same global sequence and keeps its slice of each global batch of ``batch x world``
    keys, so the processes together see exactly the batches of a single-process run (and ``skip``
    still counts keys of the global sequence).

    ``easy_first = (start, until)`` is a curriculum: key ``n`` of the sequence draws its sample among
    the first ``q(n)`` of each source's ``order`` (easiest first, :func:`flow_order`), ``q`` rising
    linearly from ``start`` at the first key to 1 at ``until x num_samples`` keys (a training stage
    is one epoch: fractions of the stage); from there on every sample, uniformly, as the plain
    sampler draws (the same call, though not always at the same position of the random stream:
    a smaller bound can use fewer draws).

    ``lead = (source, fraction)``: the first ``fraction`` of the epoch's keys, rounded to whole global
    batches, all come from ``source`` (whatever its weight; 0 keeps it out of the rest), the others as
    above: a stage that starts on one kind of data (``layers_first``) and never mixes it into a batch.

    ``fresh[s]`` (new scenes per draw of source ``s``, 0 for none) grows a source as it is drawn: at its
    c-th draw of the epoch the source holds its first ``lengths[s] + floor(fresh[s] * c)`` samples
    (its dataset must hold that many: :meth:`SyntheticDataset.extended`), and a draw at which that
    number rises is the newest sample, drawn for the first time; the others draw uniformly from the
    pool so far. So a stage meets new scenes at a steady rate, each rendered once by a loader worker,
    and its sequence is a function of the seed alone (a resumed stage sees the same keys)."""

    def __init__(self, lengths: Sequence[int], weights: Sequence[float], num_samples: int, *, seed: int = 0,
                 skip: int = 0, rank: int = 0, world: int = 1, batch: int = 1,
                 easy_first: Sequence[float] | None = None, order: Sequence[Sequence[int]] | None = None,
                 lead: tuple[int, float] | None = None, fresh: Sequence[float] | None = None):
        if len(lengths) != len(weights) or not lengths:
            raise ValueError("weights: expected one weight per source")
        w = np.asarray(weights, dtype=np.float64)
        if (w < 0).any() or w.sum() <= 0:
            raise ValueError(f"weights: expected non-negative weights with a positive sum, got {list(w)}")
        self.lengths, self.p = list(lengths), w / w.sum()
        self.num_samples, self.seed, self.epoch = int(num_samples), int(seed), 0
        self.skip = int(skip)  # keys of epoch 0 already consumed (a resumed stage continues the sequence)
        self.rank, self.world, self.batch = int(rank), int(world), int(batch)
        if not 0 <= self.rank < self.world:
            raise ValueError(f"rank {rank} of a world of {world}")
        self.easy_first = None if easy_first is None else (float(easy_first[0]), float(easy_first[1]))
        if self.easy_first is not None and not all(0 < f <= 1 for f in self.easy_first):
            raise ValueError(f"easy_first: expected (start, until) in (0, 1], got {self.easy_first}")
        if self.easy_first is not None and (order is None or [len(o) for o in order] != self.lengths):
            raise ValueError("easy_first: expected an order of every source's samples")
        self.order = None if order is None else [np.asarray(o, dtype=np.int64) for o in order]
        self.lead_source, self.lead_keys = -1, 0
        if lead is not None:
            source, fraction = int(lead[0]), float(lead[1])
            if not 0 <= source < len(self.lengths) or not 0 < fraction <= 1:
                raise ValueError(f"lead: expected (source, fraction in (0, 1]), got {lead}")
            if self.easy_first is not None:
                raise ValueError("lead: one curriculum at a time (easy_first is set)")
            step = self.batch * self.world
            self.lead_source, self.lead_keys = source, round(fraction * self.num_samples / step) * step
        self.fresh = None
        if fresh is not None and any(fresh):
            if len(fresh) != len(self.lengths) or not all(0 <= f <= 1 for f in fresh):
                raise ValueError(f"fresh: expected one rate in [0, 1] per source, got {list(fresh)}")
            if self.easy_first is not None:
                raise ValueError("fresh: the easy_first order is of a fixed set (easy_first is set)")
            self.fresh = [float(f) for f in fresh]

    def _share(self, key: int) -> float:
        """The easiest fraction of each source that key ``key`` of the sequence draws from."""
        if self.easy_first is None:
            return 1.0
        start, until = self.easy_first
        return min(1.0, start + (1.0 - start) * key / (until * self.num_samples))

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        # The full epoch even when skipping: Lightning counts a resumed epoch's batches from its
        # checkpointed position, so the epoch and the stage end together after the skipped keys.
        return self.num_samples // self.world

    def _sources(self, rng: np.random.Generator, epoch: int) -> np.ndarray:
        """The source of each key of ``epoch``: the epoch's first draw of ``rng``, then the lead."""
        sources = rng.choice(len(self.lengths), size=self.num_samples, p=self.p)
        if self.lead_keys and epoch == 0:
            sources[: self.lead_keys] = self.lead_source
        return sources

    def fresh_scenes(self, epoch: int = 0) -> list[int]:
        """The new scenes each source meets in ``epoch`` (0 for a source without ``fresh``): its
        ``lengths[s]`` to ``lengths[s] + n - 1``, to render ahead of the stage."""
        if self.fresh is None:
            return [0] * len(self.lengths)
        draws = np.bincount(self._sources(np.random.default_rng([self.seed, epoch]), epoch),
                            minlength=len(self.lengths))
        return [math.floor(f * int(c)) for f, c in zip(self.fresh, draws, strict=True)]

    def __iter__(self):
        epoch = self.epoch
        self.epoch += 1
        skip = self.skip if epoch == 0 else 0
        rng = np.random.default_rng([self.seed, epoch])
        sources = self._sources(rng, epoch)
        step = self.batch * self.world
        drawn = [0] * len(self.lengths)  # draws of each source so far (fresh: its pool grows with them)
        for n, s in enumerate(sources):
            share = self._share(epoch * self.num_samples + n)
            if self.fresh is not None and self.fresh[s]:
                c = drawn[s] = drawn[s] + 1
                new, before = math.floor(self.fresh[s] * c), math.floor(self.fresh[s] * (c - 1))
                index = self.lengths[s] + new - 1 if new > before else int(rng.integers(self.lengths[s] + new))
            elif share >= 1:  # every sample, as the plain sampler draws
                index = int(rng.integers(self.lengths[s]))
            else:
                index = int(self.order[s][rng.integers(max(1, math.ceil(share * self.lengths[s])))])
            if n >= skip and (n % step) // self.batch == self.rank:
                yield (int(s), index, epoch * self.num_samples + n)
