"""Datasets: one class per source, all yielding prepared ``Sample``s of one size.

Every dataset loads a sample at its native resolution (``load``) and ``__getitem__`` prepares it
the same way for all sources: resample to ``size`` (optionally to fixed intrinsics), DeMoN's
translation normalisation, and DeMoN's augmentation for training. Indexing with an ``int`` gives
the un-augmented sample; indexing with ``(index, draw_seed)`` (what :class:`demon_lab.data.mixture.MixtureSampler`
yields) augments with a generator seeded by ``(seed, draw_seed)``, so the augmentation of a draw
does not depend on the number of workers.

Each class also carries the supplementary's Table 1 metadata (``perfect_gt``, ``photorealistic``,
``outdoor``: 'yes', 'no' or '(yes)').
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from demon_lab.data import sample as smp
from demon_lab.data import synthetic
from demon_lab.data.readers import demon_h5, middlebury, pair_folder, tum
from demon_lab.data.synthetic import generator_version, render_key
from demon_lab.resources import cache_root

SPLIT_SEEDS = {"train": 0, "val": 10_000_000, "test": 20_000_000}
"""Synthetic samples of split S use seeds SPLIT_SEEDS[S] + index: disjoint ranges."""
DEFAULT_CACHE = cache_root() / "data"


class SceneMemory:
    """Rendered scenes kept in this process's memory, by their set (its render key) and their seed: every
    dataset object of one set (each stage's, a fresh pool grown from it, the next stage's) reads the
    same copy, so a job loads a scene from the disk cache once, not once per stage; a loader worker
    started by fork sees the scenes kept before it started. At most ``budget`` bytes per set (the
    first ones loaded). The copies are never modified (every transform returns new tensors)."""

    def __init__(self):
        self.scenes: dict[tuple[str, int], smp.Sample] = {}
        self.used: dict[str, int] = {}

    def get(self, key: str, seed: int) -> smp.Sample | None:
        kept = self.scenes.get((key, seed))
        return None if kept is None else dict(kept)

    def keep(self, key: str, seed: int, sample: smp.Sample, budget: int) -> None:
        if (key, seed) in self.scenes:
            return
        size = sum(v.nbytes for v in sample.values() if isinstance(v, torch.Tensor))
        if self.used.get(key, 0) + size <= budget:
            self.scenes[(key, seed)] = dict(sample)
            self.used[key] = self.used.get(key, 0) + size

    def held(self, key: str) -> int:
        """The bytes kept of the set ``key`` (:attr:`SyntheticDataset.memory_key`)."""
        return self.used.get(key, 0)

    def clear(self) -> None:
        self.scenes.clear()
        self.used.clear()


MEMORY = SceneMemory()
"""This process's :class:`SceneMemory` (a process started by spawn begins with an empty one)."""


TRAINING_KEYS = ("id", "image1", "image2", "inv_depth", "motion", "intrinsics", "intrinsics2", "baseline")
"""The fields of a training draw: what the training stages (demon_lab.pipeline.stages) and their loss targets
(demon_lab.core.losses.GroundTruth) read."""


class PairDataset(torch.utils.data.Dataset):
    perfect_gt = "no"
    photorealistic = "yes"
    outdoor = "no"
    native_size: tuple[int, int] | None = None  # (H, W) of a pair at its own resolution; None: as stored

    def __init__(
        self,
        size: Sequence[int] | None = None,
        fixed_intrinsics: bool = False,
        normalize_translation: bool = True,
        augment: bool = False,
        seed: int = 0,
        gt_size: Sequence[int] | None = None,
        depthmask: bool = True,
        eigen_crop: bool = False,
        depthmask_intrinsics: Sequence[float] | None = None,
    ):
        """
        Args:
            size: (H, W) of the prepared samples; None keeps the native resolution.
            fixed_intrinsics: resample both views to DeMoN's intrinsics (a crop + scale);
                otherwise the source's own intrinsics are kept (DeMoN's reader does this).
            normalize_translation: |t| = 1 with depths scaled alike (DeMoN's training and
                prediction convention); ``baseline`` keeps the original |t|.
            augment: DeMoN's augmentation (180-degree rotation, mirror, p = 0.5 each) on draws.
            seed: seed of the augmentation draws.
            gt_size: (H, W) of the ground truth the evaluation scores against (``gt_inv_depth``,
                ``gt_flow``, ``gt_intrinsics`` of each sample, resampled from the native sample as
                the inputs are); None: the inputs' own. DeMoN's evaluation scores at 480x640.
            depthmask, eigen_crop, depthmask_intrinsics: the evaluation protocol of this set
                (:func:`demon_lab.core.metrics.evaluate_sample`): DeMoN's ``depthmask`` rule; Eigen's NYU
                crop of 480x640 ground truth (needs ``gt_size=[480, 640]``); the intrinsics the
                depthmask rule projects with (None: each sample's own).
        """
        self.size = None if size is None else (int(size[0]), int(size[1]))
        self.fixed_intrinsics = fixed_intrinsics
        self.normalize_translation = normalize_translation
        self.augment = augment
        self.seed = seed
        self.gt_size = None if gt_size is None else (int(gt_size[0]), int(gt_size[1]))
        if self.gt_size is not None and augment:
            raise ValueError("gt_size: evaluation ground truth at its own size cannot be augmented (augment=false)")
        if eigen_crop and self.gt_size != (480, 640):
            raise ValueError(f"eigen_crop: Eigen's crop is defined on 480x640 ground truth; set gt_size=[480, 640], "
                             f"got {self.gt_size}")
        self.depthmask, self.eigen_crop = bool(depthmask), bool(eigen_crop)
        self.depthmask_intrinsics = None if depthmask_intrinsics is None else [float(k) for k in depthmask_intrinsics]

    name = "pairs"

    def __len__(self) -> int:
        raise NotImplementedError

    def load(self, index: int) -> smp.Sample:
        """The raw sample at its native resolution."""
        raise NotImplementedError

    def load_training(self, index: int) -> smp.Sample:
        """The raw sample for a training draw: as :meth:`load`, or without the fields a draw drops
        (flow, normals, masks) where a source can skip computing them."""
        return self.load(index)

    def __getitem__(self, key: int | tuple[int, int]) -> smp.Sample:
        index, draw = (key, None) if isinstance(key, int | np.integer) else key
        self._check_index(index)
        if draw is not None:
            return self._training_draws(int(index), [self._augmentation(draw)])[0]
        native = self.load(int(index))
        native.pop("meta", None)
        unknown_motion = native.pop("motion_unknown", False)
        sample = self._prepare(native, self.size)
        if self.gt_size is not None:  # an evaluation's ground truth
            truth = sample if self.gt_size == tuple(sample["image1"].shape[1:]) else self._prepare(native, self.gt_size)
            sample.update(gt_inv_depth=truth["inv_depth"], gt_flow=truth["flow"], gt_intrinsics=truth["intrinsics"])
        return _without_motion(sample) if unknown_motion else sample

    def training_pairs(self, index: int) -> dict[int, smp.Sample]:
        """Every training draw sample ``index`` can give, each as ``self[(index, draw)]`` gives it, by
        its augmentation's number (:meth:`augmentation_of`)."""
        self._check_index(index)
        choices = list(smp.AUGMENTATIONS) if self.augment else [None]
        return dict(zip([_number(c) for c in choices], self._training_draws(int(index), choices), strict=True))

    def augmentation_of(self, draw: int) -> int:
        """The augmentation a training draw ``draw`` applies, by number: ``2 * rotate + mirror``
        (:data:`demon_lab.data.sample.AUGMENTATIONS`), -1 for none."""
        return _number(self._augmentation(draw))

    def _augmentation(self, draw: int) -> tuple[bool, bool] | None:
        """The ``(rotate, mirror)`` choice of training draw ``draw`` (seeded by ``(seed, draw)``); None
        where the set does not augment."""
        return smp.augmentation_choice(np.random.default_rng([self.seed, int(draw)])) if self.augment else None

    def pair_key(self, index: int, draw: int) -> tuple | None:
        """What identifies the pair of the training draw ``(index, draw)`` across jobs, where a set can
        say (its scenes cached on disk: :class:`SyntheticDataset`); None where it cannot."""
        return None

    def _check_index(self, index: int) -> None:
        if not 0 <= index < len(self):
            raise IndexError(f"{self.name}: index {index} out of range 0..{len(self) - 1}")

    def _training_draws(self, index: int, choices: list[tuple[bool, bool] | None]) -> list[smp.Sample]:
        """The training draws of sample ``index`` under each augmentation of ``choices`` (None: none)."""
        native = self.load_training(index)
        native.pop("meta", None)
        unknown_motion = native.pop("motion_unknown", False)
        # only what the stages and losses read (they derive flow and normals from the depth and motion),
        # so augmentation flips nothing else
        sample = {k: v for k, v in self._prepare(native, self.size, derived=False).items() if k in TRAINING_KEYS}
        draws = [sample if choice is None else smp.augmented(sample, *choice, normals=False) for choice in choices]
        return [_without_motion(d) for d in draws] if unknown_motion else draws

    def _prepare(self, sample: smp.Sample, size: tuple[int, int] | None, derived: bool = True) -> smp.Sample:
        target = smp.geo.DEMON_INTRINSICS if self.fixed_intrinsics else None
        if size is None and target is not None:  # the native resolution, cropped to DeMoN's intrinsics
            size = tuple(sample["image1"].shape[1:])
        if size is not None and (tuple(sample["image1"].shape[1:]) != size or target):
            sample = smp.resample(sample, size, target, derived=derived)
        if self.normalize_translation:
            sample = smp.normalize_translation(sample)
        return sample


def _number(choice: tuple[bool, bool] | None) -> int:
    return -1 if choice is None else 2 * choice[0] + choice[1]


def _without_motion(sample: smp.Sample) -> smp.Sample:
    """A sample of a source without camera poses (DeMoN's nyu2_test.h5): no motion, no flow."""
    sample["motion"] = torch.full_like(sample["motion"], math.nan)
    for key in ("flow", "gt_flow"):
        if key in sample:
            sample[key] = torch.full_like(sample[key], math.nan)
    return sample


class SyntheticDataset(PairDataset):
    """Procedural scenes of a preset (:mod:`demon_lab.data.synthetic`), rendered at ``size``.

    Samples are cached on disk (``cache_dir``, default ``$DEMON_LAB_CACHE`` or
    ``~/.cache/demon_lab``) under a key hashing the preset, size, supersampling and generator
    version, and reused; ``cache_dir=False`` renders every time. Loaded samples are also kept in
    the process's memory (:data:`MEMORY`, shared by every object of the set), up to ``memory_mb`` per
    set (default: ``$DEMON_LAB_MEMORY_MB`` or 1024; 0 turns it off): served from memory, the training
    path is faster than from the disk cache (``python -m demon_lab.bench data``; the rates:
    docs/data.md, "The disk cache and the in-memory copy"). The memory copy is never modified (every
    transform returns new tensors). It changes no result, so it is not part of any cache or run key.
    """

    perfect_gt = "yes"
    photorealistic = "no"
    native_size = (192, 256)  # scenes have no resolution of their own: DeMoN's

    def __init__(self, preset: str, split: str = "train", length: int = 1000,
                 size: Sequence[int] = (96, 128), supersample: int = 2,
                 cache_dir: str | Path | bool | None = None, memory_mb: float | None = None, **kwargs: Any):
        if preset not in synthetic.PRESETS:
            raise smp.DataError(f"preset {preset!r}: expected one of {sorted(synthetic.PRESETS)}")
        if split not in SPLIT_SEEDS:
            raise smp.DataError(f"split {split!r}: expected one of {sorted(SPLIT_SEEDS)}")
        if length < 1:
            raise smp.DataError(f"length must be >= 1, got {length}")
        super().__init__(size=size, **kwargs)
        self.preset = synthetic.PRESETS[preset]
        self.name = preset
        self.outdoor = {"synthetic_scenes11": "(yes)", "synthetic_mvs": "yes"}.get(preset, "no")
        self.split, self.length, self.supersample = split, int(length), int(supersample)
        self.render_size = self.size  # rendered directly at the target size and intrinsics
        self.fixed_intrinsics = False
        self.cache_key = render_key({"preset": dataclasses.asdict(self.preset), "size": self.render_size,
                                   "supersample": self.supersample, "version": generator_version()})
        if cache_dir is False:
            self.cache = None
        else:
            self.cache = Path(cache_dir or DEFAULT_CACHE) / "synthetic" / f"{preset}-{self.cache_key}"
        if memory_mb is None:
            memory_mb = float(os.environ.get("DEMON_LAB_MEMORY_MB", 1024))
        self.memory_budget = int(memory_mb * 2**20)

    def __len__(self) -> int:
        return self.length

    def seed_of(self, index: int) -> int:
        return SPLIT_SEEDS[self.split] + index

    def pair_key(self, index: int, draw: int) -> tuple | None:
        """``(cache folder, scene seed, augmentation)`` of the pair a training draw gives; None uncached."""
        return None if self.cache is None else (self.cache.name, self.seed_of(index), self.augmentation_of(draw))

    def extended(self, extra: int) -> SyntheticDataset:
        """This set with ``extra`` more scenes after its own (the next seeds of its split), rendered
        where first loaded and cached as the others: the pool a ``fresh`` source of
        :class:`demon_lab.data.mixture.MixtureSampler` grows into. Its own scenes, and so the cache
        entries of the set, are unchanged."""
        grown = copy.copy(self)
        grown.length = self.length + int(extra)
        return grown

    def load(self, index: int) -> smp.Sample:
        kept = MEMORY.get(self.memory_key, self.seed_of(index)) if self.memory_budget else None
        if kept is not None:
            return kept
        sample = self._load(index)
        if self.memory_budget:
            MEMORY.keep(self.memory_key, self.seed_of(index), sample, self.memory_budget)
        return sample

    @property
    def memory_key(self) -> str:
        """What names the set's scenes in :data:`MEMORY`: its preset and render key (its cache folder's name)."""
        return f"{self.name}-{self.cache_key}"

    def _load(self, index: int) -> smp.Sample:
        seed = self.seed_of(index)
        path = None if self.cache is None else self.cache / f"{seed}.pt"
        if path is not None and path.is_file():
            try:
                return torch.load(path, weights_only=True)
            except Exception:  # a truncated cache entry: render again and overwrite it
                pass
        sample = synthetic.render_pair(self.preset, seed, self.render_size, self.supersample)
        sample.pop("meta", None)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".tmp{os.getpid()}")
            torch.save(sample, tmp)
            os.replace(tmp, path)  # atomic: concurrent workers never read half a file
        return sample


def _render_into_cache(args: tuple[SyntheticDataset, list[int]]) -> int:
    dataset, indices = args
    for index in indices:
        dataset._load(index)  # (into the disk cache; the rendering process keeps none in memory)
    return len(indices)


def keep_in_memory(datasets: Sequence[PairDataset]) -> int:
    """Load every scene of the synthetic ``datasets`` (from the disk cache) into this process's
    :data:`MEMORY`, up to each set's budget, before training draws them: a job's stages, and the
    loader workers they fork, then read each scene from memory. Returns the number loaded."""
    loaded = 0
    for d in datasets:
        if isinstance(d, SyntheticDataset) and d.memory_budget:
            for index in range(len(d)):
                if MEMORY.get(d.memory_key, d.seed_of(index)) is None:
                    d.load(index)
                    if MEMORY.get(d.memory_key, d.seed_of(index)) is None:
                        break  # the set's budget is full
                    loaded += 1
    return loaded


def warm_cache(datasets: Sequence[PairDataset], processes: int | None = None) -> int:
    """Render the synthetic samples missing from the disk cache, in parallel processes.

    Training draws scenes at random, so without this the first epoch renders them one by one
    in the training loop; here all cores render them up front. Returns the number rendered.
    """
    import multiprocessing as mp

    jobs = []
    for d in datasets:
        if isinstance(d, SyntheticDataset) and d.cache is not None:
            missing = [i for i in range(len(d)) if not (d.cache / f"{d.seed_of(i)}.pt").is_file()]
            jobs += [(d, missing[k::8]) for k in range(8) if missing[k::8]]
    if not jobs:
        return 0
    processes = processes or os.cpu_count() or 1
    if mp.get_start_method(allow_none=True) not in (None, "fork", "spawn", "forkserver"):
        processes = 1  # inside a launcher's worker (joblib's loky): its children cannot spawn; jobs run in parallel
    if processes == 1:
        return sum(_render_into_cache(j) for j in jobs)
    with mp.get_context("spawn").Pool(processes) as pool:
        return sum(pool.imap_unordered(_render_into_cache, jobs))


class DemonH5Dataset(PairDataset):
    """A DeMoN HDF5 file (:mod:`demon_lab.data.readers.demon_h5`)."""

    def __init__(self, path: str | Path, test_phase: bool = True, outdoor: str = "no",
                 perfect_gt: str = "no", photorealistic: str = "yes", **kwargs: Any):
        super().__init__(**kwargs)
        self.path = Path(path)
        self.name = self.path.stem
        self.pairs = demon_h5.read_demon_h5_pairs(self.path, test_phase)
        if not self.pairs:
            raise smp.DataError(f"{self.path}: no usable image pair")
        self.outdoor, self.perfect_gt, self.photorealistic = outdoor, perfect_gt, photorealistic
        self._file = None
        self._pid = None

    def __len__(self) -> int:
        return len(self.pairs)

    def load(self, index: int, derived: bool = True) -> smp.Sample:
        if self._file is None or self._pid != os.getpid():  # h5py handles do not survive fork
            self._file = demon_h5._open(self.path)
            self._pid = os.getpid()
        return demon_h5.load_demon_h5_pair(self._file, self.path, *self.pairs[index], derived=derived)

    def load_training(self, index: int) -> smp.Sample:
        return self.load(index, derived=False)  # half of a draw's time went to flow, normals, visibility

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_file"] = None
        return state


class PairFolderDataset(PairDataset):
    """DPSNet/DeepSFM pair folders: one folder or a directory of them."""

    def __init__(self, path: str | Path, pair: Sequence[int] = (0, 1), **kwargs: Any):
        super().__init__(**kwargs)
        self.folders = pair_folder.find_pair_folders(path)
        self.pair = (int(pair[0]), int(pair[1]))
        self.name = Path(path).name

    def __len__(self) -> int:
        return len(self.folders)

    def load(self, index: int) -> smp.Sample:
        return pair_folder.read_pair_folder(self.folders[index], self.pair)


class MiddleburyDataset(PairDataset):
    """The Middlebury "motorcycle" pair that scikit-image ships (one sample)."""

    name = "middlebury"

    def __len__(self) -> int:
        return 1

    def load(self, index: int) -> smp.Sample:
        return middlebury.middlebury_motorcycle()


class TumDataset(PairDataset):
    """A TUM RGB-D sequence, pairs sampled by baseline (:mod:`demon_lab.data.readers.tum`)."""

    def __init__(self, root: str | Path, min_baseline: float = 0.05, max_baseline: float = 0.5,
                 stride: int = 10, intrinsics: Sequence[float] | None = None, **kwargs: Any):
        super().__init__(**kwargs)
        self.root = Path(root)
        self.name = self.root.name
        self.pairs = tum.read_tum_pairs(self.root, min_baseline, max_baseline, stride)
        if not self.pairs:
            raise smp.DataError(f"{self.root}: no frame pair with a baseline in "
                                f"[{min_baseline}, {max_baseline}] m")
        self.intrinsics = intrinsics

    def __len__(self) -> int:
        return len(self.pairs)

    def load(self, index: int) -> smp.Sample:
        return tum.load_tum_pair(self.root, self.pairs[index], self.intrinsics)


# ----------------------------------------------------------------------------- mixtures


class LayersDataset(torch.utils.data.Dataset):
    """Textured 2-D layers under affine motion (:func:`demon_lab.data.layers.render_layers`), a new
    pair for every index: rendered when drawn, never cached. Index ``i`` with the dataset's ``seed``
    is pair seed ``(seed, i)``; a draw ``(index, draw_seed)`` renders the pair of ``index`` (the
    sampler gives every draw its own index from a range of ``length``). A sample has ``flow`` and no
    depth or motion: only the flow stages read it (``layers_first``)."""

    name = "layers"
    LENGTH = 2**40

    def __init__(self, size: Sequence[int] = (96, 128), seed: int = 0, length: int = LENGTH):
        self.size, self.seed, self.length = (int(size[0]), int(size[1])), int(seed), int(length)

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, key: int | tuple[int, int]) -> smp.Sample:
        from demon_lab.data.layers import render_layers

        index = int(key if isinstance(key, int | np.integer) else key[0])
        if not 0 <= index < self.length:
            raise IndexError(f"{self.name}: index {index} out of range 0..{self.length - 1}")
        return render_layers(self.seed * self.LENGTH + index, self.size)
