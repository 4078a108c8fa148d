"""The classical priors of the training pairs, computed once per pair (``model.flow1_prior``,
``model.dm1_prior=ransac_prior``: the ``cpu`` profile's).

flow1's DIS prior flow and the 5-point RANSAC motion ``dm1`` corrects (:mod:`demon_lab.nets.prior`)
are functions of the image pair alone, and costly: computed in the step, they held the profile's
``flow1`` loop to half its rate (reports/timing/loops_before_after.txt). A stage would compute them at
every draw of a pair (or, with ``trainer.reuse_frozen``, at its first draw in each stage). Instead,
before the first stage trains, :func:`warm_priors` computes them for every training pair that a
synthetic set can give (each scene under each of DeMoN's four augmentations,
:meth:`demon_lab.data.datasets.PairDataset.training_pairs`) in parallel processes, and keeps them on
disk beside the set's rendered scenes (``priors-<key>.pt`` in its cache folder), where every seed,
row and stage that draws the same scenes reads them, by scene and augmentation. A drawn pair carries its
priors as ``prior_flow`` (2, h, w) and, with ``dm1_prior=ransac_prior``, ``prior_motion`` (6,)
(:class:`PriorTable`), and the stage modules read them instead of computing them. A pair not computed
ahead (fresh 2-D layers, DeMoN's HDF5 files) gets its priors at its first draw, in the loader, kept in
memory from then on.

They are the values the chain computes for the same pair: the same functions on the same images, one
pair at a time, where a batch's priors are computed pair by pair too (tests/test_priors.py checks
both, and a stage's nets, for equality to the bit). So no key changes: what a stage computes is the
same, only when and where.
"""

from __future__ import annotations

import hashlib
import logging
import multiprocessing as mp
import os
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from demon_lab.data.datasets import PairDataset, SyntheticDataset
from demon_lab.nets import prior as classical
from demon_lab.pipeline.identity import digest

log = logging.getLogger(__name__)

FILE_VERSION = 1
"""The layout of a priors file (``{scene seed: {augmentation: priors}}``), part of its name."""


@dataclass(frozen=True)
class PairPriors:
    """Which classical priors a chain reads from its pairs: flow1's prior flow (``flow``: ``dis`` or
    ``dis_x2``) and, where ``dm1`` corrects the 5-point motion of that flow (``dm1_prior=ransac_prior``),
    that motion (``motion``)."""

    flow: str
    motion: bool

    @classmethod
    def of(cls, chain) -> PairPriors | None:
        """The priors of a :class:`demon_lab.nets.chain.DeMoN` that are functions of the pair alone;
        None where it has none. (``dm1_prior=ransac`` reads flow1's own flow: not a function of the pair.)"""
        if not chain.flow1_prior:
            return None
        return cls(chain.flow1_prior, chain.dm1_prior == "ransac_prior")

    @property
    def key(self) -> str:
        """What the priors' values depend on besides the pair: the settings and OpenCV's version."""
        import cv2

        settings = {"file": FILE_VERSION, "flow": self.flow, "upsample": classical.DIS_UPSAMPLE[self.flow],
                    "dis": classical.DIS_SETTINGS,
                    "opencv": cv2.__version__}
        if self.motion:
            settings["motion"] = classical.RANSAC_SETTINGS["ransac_prior"]
        return digest(settings)

    def compute(self, samples: Sequence[Mapping[str, torch.Tensor]]) -> list[dict[str, torch.Tensor]]:
        """The priors of each pair of ``samples`` (``image1``, ``image2`` (3, H, W), ``intrinsics`` (4,)):
        ``prior_flow`` (2, H/4, W/4) and, with :attr:`motion`, ``prior_motion`` (6,), as the chain
        computes them for a batch of the same pairs (:meth:`demon_lab.nets.flow_net.FlowNet.prior_flow`,
        :meth:`demon_lab.nets.chain.DeMoN.prior_motion`)."""
        pair = torch.stack([torch.cat([s["image1"], s["image2"]], 0) for s in samples])
        flow = classical.dis_prior(pair, level=2, upsample=classical.DIS_UPSAMPLE[self.flow])
        out = [{"prior_flow": f} for f in flow]
        if self.motion:
            intrinsics = torch.stack([s["intrinsics"] for s in samples])
            motion = classical.ransac_motion(flow, intrinsics, *classical.RANSAC_SETTINGS["ransac_prior"])
            for o, m in zip(out, motion, strict=True):
                o["prior_motion"] = m
        return out


def pair_digest(sample: Mapping[str, torch.Tensor]) -> bytes:
    """What identifies a training pair that its set cannot name (:meth:`PairDataset.pair_key`): its two
    images and its intrinsics, byte for byte."""
    h = hashlib.blake2b(digest_size=16)
    for key in ("image1", "image2", "intrinsics"):
        x = sample[key]
        h.update(str((x.dtype, tuple(x.shape))).encode())
        h.update(memoryview(x.detach().contiguous().numpy()).cast("B"))
    return h.digest()


class PriorTable:
    """``table(sample, pair_key)``: the priors of a drawn pair (:class:`PairPriors`), read from the pairs
    computed ahead (``known``, by their sets' pair keys: :meth:`PairDataset.pair_key`) or computed at
    the pair's first draw and kept, by its key or, where its set names none, by its content
    (:func:`pair_digest`); up to ``max_misses`` such pairs, the least recently drawn dropped first
    (fresh 2-D layers are new at every draw)."""

    def __init__(self, priors: PairPriors, known: Mapping[tuple, dict[str, torch.Tensor]] | None = None,
                 max_misses: int = 20_000):
        self.priors, self.known = priors, dict(known or {})
        self.misses: OrderedDict[tuple | bytes, dict[str, torch.Tensor]] = OrderedDict()
        self.max_misses = int(max_misses)

    def __call__(self, sample: Mapping[str, torch.Tensor], pair_key: tuple | None = None) -> dict[str, torch.Tensor]:
        found = None if pair_key is None else self.known.get(pair_key)
        if found is not None:
            return found
        key = pair_digest(sample) if pair_key is None else pair_key
        found = self.misses.get(key)
        if found is None:
            found = self.misses[key] = self.priors.compute([sample])[0]
            while len(self.misses) > self.max_misses:
                self.misses.popitem(last=False)
        self.misses.move_to_end(key)
        return found


def _path(dataset: SyntheticDataset, priors: PairPriors) -> Path:
    return dataset.cache / f"priors-{priors.key}.pt"


def _compute_scenes(args: tuple[SyntheticDataset, PairPriors, list[int]]) -> dict[int, dict[int, dict]]:
    """``{seed: {augmentation: priors}}`` for the scenes ``indices`` (:meth:`PairDataset.training_pairs`)."""
    dataset, priors, indices = args
    out = {}
    for index in indices:
        pairs = dataset.training_pairs(index)
        out[dataset.seed_of(index)] = dict(zip(pairs, priors.compute(list(pairs.values())), strict=True))
    return out


def _one_thread() -> None:
    import cv2

    torch.set_num_threads(1)  # each process one core: the processes are the parallelism
    cv2.setNumThreads(1)


def warm_priors(datasets: Sequence[PairDataset], priors: PairPriors, processes: int | None = None
                ) -> tuple[PriorTable, int]:
    """The priors of every training pair of the synthetic sets among ``datasets`` (their scenes under
    each augmentation), from their cache folders, computing the scenes missing there in ``processes``
    parallel processes (default: one per core) and saving them (atomically: jobs sharing a cache may
    write at once). Returns the table a stage's loader reads (:class:`PriorTable`) and the number of
    scenes computed."""
    sets = [d for d in datasets if isinstance(d, SyntheticDataset) and d.cache is not None]
    saved: list[dict[int, dict[int, dict]]] = []
    jobs = []
    for which, dataset in enumerate(sets):
        path, entries = _path(dataset, priors), {}
        if path.is_file():
            try:
                entries = torch.load(path, weights_only=True)
            except Exception:  # a truncated file: compute its scenes again
                entries = {}
        saved.append(entries)
        missing = [i for i in range(len(dataset)) if dataset.seed_of(i) not in entries]
        jobs += [(which, (dataset, priors, missing[k::16])) for k in range(16) if missing[k::16]]
    if jobs:
        processes = processes or os.cpu_count() or 1
        if processes == 1 or mp.get_start_method(allow_none=True) not in (None, "fork", "spawn", "forkserver"):
            parts = [_compute_scenes(job) for _, job in jobs]  # (inside a launcher's worker: its children cannot spawn)
        else:
            with mp.get_context("spawn").Pool(processes, initializer=_one_thread) as pool:
                parts = pool.map(_compute_scenes, [job for _, job in jobs])
        for (which, _), part in zip(jobs, parts, strict=True):
            saved[which].update(part)
        for which in sorted({which for which, _ in jobs}):
            path = _path(sets[which], priors)
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".tmp{os.getpid()}")
            torch.save(saved[which], tmp)
            os.replace(tmp, path)
    known: dict[tuple, dict[str, torch.Tensor]] = {}
    for dataset, entries in zip(sets, saved, strict=True):
        for i in range(len(dataset)):
            seed = dataset.seed_of(i)
            known.update({(dataset.cache.name, seed, augmentation): fields
                          for augmentation, fields in entries[seed].items()})
    return PriorTable(priors, known), sum(len(job[2]) for _, job in jobs)
