"""The training mixture: the sampler's weights, shards and curricula, fresh scenes, the DataModule, the data
configs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from demon_lab import resources
from demon_lab.data import sample as smp
from demon_lab.data.datasets import (
    MiddleburyDataset,
    SyntheticDataset,
)
from demon_lab.data.mixture import MixtureSampler, flow_order


def test_mixture_sampler_follows_weights_and_is_deterministic():
    sampler = MixtureSampler([10, 1000], [3.0, 1.0], num_samples=4000, seed=1)
    first = list(sampler)
    second = list(sampler)  # the next epoch draws anew
    assert first != second
    replay = MixtureSampler([10, 1000], [3.0, 1.0], num_samples=4000, seed=1)
    assert list(replay) == first
    share = np.mean([s == 0 for s, _, _ in first])
    assert share == pytest.approx(0.75, abs=0.03)
    assert all(0 <= i < (10 if s == 0 else 1000) for s, i, _ in first)
    assert len({d for _, _, d in first + second}) == 8000  # every draw has its own seed


@pytest.mark.parametrize("skip", [0, 24])
def test_mixture_sampler_shards_every_batch_across_data_parallel_processes(skip):
    """Three processes with 4 samples each per step see, together, the 12-sample batches of one
    process, in order, also when a resumed stage skips the keys it already consumed."""
    args = ([10, 1000], [3.0, 1.0], 120)
    seeded = {"seed": 5, "skip": skip}
    batches = lambda keys, b: [keys[i:i + b] for i in range(0, len(keys), b)]  # noqa: E731
    whole = batches(list(MixtureSampler(*args, **seeded)), 12)
    shards = [MixtureSampler(*args, **seeded, rank=r, world=3, batch=4) for r in range(3)]
    assert all(len(s) == 40 for s in shards)
    parts = [batches(list(s), 4) for s in shards]
    assert [[key for p in parts for key in p[k]] for k in range(len(whole))] == whole
    with pytest.raises(ValueError, match="rank 3 of a world of 3"):
        MixtureSampler(*args, **seeded, rank=3, world=3, batch=4)


def test_an_easy_first_curriculum_widens_from_the_easiest_samples_to_all():
    """easy_first=(0.2, 0.5): key n draws among the first ceil(q(n) x length) of the source's order,
    q rising from 0.2 at the first key to 1 at half the keys; shards and a resumed stage see the keys
    of one uninterrupted process; start 1 is the plain sampler."""
    order = [list(range(9, -1, -1)), list(range(19, -1, -1))]  # easiest: the highest indices
    args = ([10, 20], [1.0, 1.0], 400)
    seeded = {"seed": 3}
    keys = list(MixtureSampler(*args, **seeded, easy_first=(0.2, 0.5), order=order))
    for n, (s, i, _) in enumerate(keys):
        share = min(1.0, 0.2 + 0.8 * n / 200)
        assert order[s].index(i) < math.ceil(share * (10, 20)[s]), (n, s, i)
    first = [(s, i) for s, i, _ in keys[:20]]  # q < 0.28: 3 of 10, 6 of 20
    assert {i for s, i in first if s == 0} <= {9, 8, 7} and {i for s, i in first if s == 1} <= set(range(14, 20))
    assert {i for s, i, _ in keys[200:] if s == 1} == set(range(20))  # the whole source after until
    resumed = list(MixtureSampler(*args, **seeded, skip=120, easy_first=(0.2, 0.5), order=order))
    assert resumed == keys[120:]
    shards = [list(MixtureSampler(*args, **seeded, rank=r, world=2, batch=4, easy_first=(0.2, 0.5), order=order))
              for r in range(2)]
    assert [k for b in range(50) for shard in shards for k in shard[4 * b:4 * b + 4]] == keys
    plain = list(MixtureSampler(*args, **seeded))
    assert keys[:200] != plain[:200]
    assert list(MixtureSampler(*args, **seeded, easy_first=(1.0, 0.5), order=order)) == plain
    # every key's pool is exactly ceil(q(n) x length), replayed from the sampler's stream
    rng = np.random.default_rng([3, 0])
    sources = rng.choice(2, size=400, p=[0.5, 0.5])
    for n, s in enumerate(sources):
        q = min(1.0, 0.2 + 0.8 * n / 200)
        expected = int(rng.integers((10, 20)[s])) if q == 1 else order[s][int(rng.integers(math.ceil(q * (10, 20)[s])))]
        assert keys[n][:2] == (int(s), expected), n
    # the ramp counts keys of the whole sequence: a later epoch is past it, drawn as the plain sampler
    later = MixtureSampler(*args, **seeded, easy_first=(0.2, 0.5), order=order)
    plain_later = MixtureSampler(*args, **seeded)
    later.set_epoch(1)
    plain_later.set_epoch(1)
    assert list(later) == list(plain_later)
    with pytest.raises(ValueError, match="easy_first: expected an order"):
        MixtureSampler(*args, **seeded, easy_first=(0.2, 0.5))
    with pytest.raises(ValueError, match=r"easy_first: expected \(start, until\) in \(0, 1\]"):
        MixtureSampler(*args, **seeded, easy_first=(0.2, 0.0), order=order)


def test_flow_order_ranks_samples_by_their_mean_flow():
    dataset = SyntheticDataset("synthetic_sun3d", length=4, size=(32, 32), cache_dir=False)
    means = [float(torch.linalg.vector_norm(dataset.load(i)["flow"].double(), dim=0).nanmean()) for i in range(4)]
    assert list(flow_order(dataset)) == sorted(range(4), key=means.__getitem__)
    assert list(flow_order(dataset)) == [1, 3, 2, 0]  # not the identity: the order is the flows'
    pairs = MiddleburyDataset()
    pairs.load = lambda i: {"image1": torch.zeros(3, 4, 4)}  # no flow: not orderable
    with pytest.raises(smp.DataError, match="easy_first: middlebury has no ground-truth flow"):
        flow_order(pairs)


def test_datamodule_batches_a_mix(tmp_path):
    from demon_lab.data.datamodule import DemonDataModule, Draws

    common = dict(size=(32, 64), cache_dir=tmp_path)
    train = [{"weight": 1.0, "dataset": SyntheticDataset("synthetic_sun3d", "train", length=4, augment=True, **common)},
             {"weight": 1.0, "dataset": MiddleburyDataset(size=(32, 64), augment=True)}]
    draws = Draws(batch_size=4, samples_per_epoch=8, seed=3)
    dm = DemonDataModule(train, draws)
    batch = next(iter(dm.train_dataloader()))
    assert batch["image1"].shape == (4, 3, 32, 64) and batch["motion"].shape == (4, 6)
    assert torch.allclose(batch["motion"][:, 3:].norm(dim=1), torch.ones(4))  # normalised
    assert len(batch["id"]) == 4
    again = next(iter(DemonDataModule(train, draws).train_dataloader()))
    assert torch.equal(batch["image1"], again["image1"])


def test_every_data_config_composes(tmp_path):

    from hydra import compose, initialize_config_dir

    conf = resources.CONF
    names = sorted(p.stem for p in (conf / "data").glob("*.yaml"))
    assert {"synthetic_scenes11", "synthetic_sun3d", "synthetic_mvs", "demon_h5", "pair_folder",
            "middlebury", "tum", "default"} <= set(names)
    with initialize_config_dir(str(conf), version_base="1.3"):
        for name in names:
            extra = {"demon_h5": ["data.path=x"], "tum": ["data.root=x"]}.get(name, [])
            cfg = compose("data_stats", overrides=[f"data={name}", *extra])
            assert cfg.data.name == (cfg.data.preset if name == "synthetic" else name)  # the presets' base
            assert cfg.data.train and "test" in cfg.data
            for entry in cfg.data.train:
                assert str(entry.dataset._target_).startswith("demon_lab.data.datasets.")


def test_a_lead_source_fills_the_first_fraction_of_the_stage_in_whole_batches():
    """lead=(2, 0.25) over 200 keys in global batches of 8 (4 per process, 2 processes): the first 48
    keys (0.25 x 200 = 50, rounded to 6 whole batches) come from source 2, none after it (weight 0);
    the rest draw as the plain sampler; shards and a resumed stage see the keys of one process."""
    args = ([10, 20, 10**9], [1.0, 1.0, 0.0], 200)
    seeded = {"seed": 4}
    keys = list(MixtureSampler(*args, **seeded, batch=8, lead=(2, 0.25)))
    assert [s for s, _, _ in keys[:48]] == [2] * 48 and all(s != 2 for s, _, _ in keys[48:])
    assert len({i for _, i, _ in keys[:48]}) == 48  # (a fresh pair per key)
    plain = list(MixtureSampler(*args, **seeded, batch=8))
    assert [k[0] for k in keys[48:]] == [k[0] for k in plain[48:]]
    shards = [list(MixtureSampler(*args, **seeded, rank=r, world=2, batch=4, lead=(2, 0.25))) for r in range(2)]
    assert [k for b in range(25) for shard in shards for k in shard[4 * b:4 * b + 4]] == keys
    assert list(MixtureSampler(*args, **seeded, batch=8, skip=40, lead=(2, 0.25))) == keys[40:]
    later = MixtureSampler(*args, **seeded, batch=8, lead=(2, 0.25))
    later.set_epoch(1)
    assert all(s != 2 for s, _, _ in later)  # the lead is the start of the stage (its first epoch)
    with pytest.raises(ValueError, match="lead: expected"):
        MixtureSampler(*args, **seeded, lead=(3, 0.3))
    with pytest.raises(ValueError, match="one curriculum at a time"):
        MixtureSampler([10, 20], [1.0, 1.0], 200, lead=(1, 0.3), easy_first=(0.5, 0.5), order=[range(10), range(20)])


def test_a_fresh_source_grows_by_one_new_scene_at_its_rate_and_replays_from_any_step():
    """fresh=[0.1, 0]: source 0 (10 scenes) gains one scene every 10 of its draws, and the draw at
    which it grows is that new scene, its first appearance; every other draw of it is uniform over the
    pool so far; source 1 draws as the plain sampler (the same sources, key for key); shards and a
    resumed stage see the keys of one process; fresh 0 everywhere is the plain sampler."""
    args = ([10, 20], [1.0, 1.0], 400)
    seeded = {"seed": 3}
    keys = list(MixtureSampler(*args, **seeded, batch=8, fresh=[0.1, 0.0]))
    plain = list(MixtureSampler(*args, **seeded, batch=8))
    assert [k[0] for k in keys] == [k[0] for k in plain]
    grown = [i for s, i, _ in keys if s == 0]
    first_seen: dict[int, int] = {}
    for c, index in enumerate(grown, start=1):
        pool = 10 + (c // 10)
        assert index < pool
        first_seen.setdefault(index, c)
        if c % 10 == 0:  # the c-th draw grows the pool: it draws the new scene, never seen before
            assert index == pool - 1 and first_seen[index] == c
    assert sorted(i for i in first_seen if i >= 10) == list(range(10, 10 + len(grown) // 10))
    assert max(i for s, i, _ in keys if s == 1) < 20
    shards = [list(MixtureSampler(*args, **seeded, rank=r, world=2, batch=4, fresh=[0.1, 0.0])) for r in range(2)]
    assert [k for b in range(50) for shard in shards for k in shard[4 * b:4 * b + 4]] == keys
    assert list(MixtureSampler(*args, **seeded, batch=8, skip=96, fresh=[0.1, 0.0])) == keys[96:]
    assert list(MixtureSampler(*args, **seeded, batch=8, fresh=[0.0, 0.0])) == plain
    with pytest.raises(ValueError, match="fresh: expected one rate"):
        MixtureSampler(*args, **seeded, fresh=[0.1])
    with pytest.raises(ValueError, match="fresh: the easy_first order"):
        MixtureSampler(*args, **seeded, fresh=[0.1, 0.0], easy_first=(0.5, 0.5), order=[range(10), range(20)])


def test_fresh_scenes_render_new_scenes_of_the_next_seeds_in_the_loaders_worker(tmp_path):
    """DemonDataModule(fresh_scenes=0.25) over a 3-scene synthetic set: the set's draws reach scenes
    past its own three (the next seeds of its split, the scenes a longer set has at those indices),
    rendered by the loader's worker and cached beside the others; the layers lead keeps its own keys."""
    from demon_lab.data.datamodule import DemonDataModule, Draws

    scenes = SyntheticDataset("synthetic_sun3d", length=3, size=(64, 64), cache_dir=tmp_path)
    module = DemonDataModule([{"weight": 1.0, "dataset": scenes}], Draws(
        batch_size=2, samples_per_epoch=24, fresh_scenes=0.25, layers_first=0.25, layers_size=(64, 64)), num_workers=1)
    loader = module.train_dataloader()
    drawn = [i for s, i, _ in module.sampler if s == 0]
    assert max(drawn) == 3 + 18 // 4 - 1 and len(scenes) == 3
    ahead = module.fresh_scenes()  # what a stage renders before it trains: the set and the new scenes drawn
    assert [len(d) for d in ahead] == [max(drawn) + 1] and ahead[0].cache == scenes.cache
    module.sampler.set_epoch(0)
    batches = list(loader)
    assert len(batches) == 12
    cached = sorted(int(p.stem) for p in scenes.cache.glob("*.pt"))
    assert cached == sorted(set(drawn))  # every drawn scene, the new ones too, rendered once and cached
    longer = SyntheticDataset("synthetic_sun3d", length=8, size=(64, 64), cache_dir=False, memory_mb=0)  # rendered
    again = scenes.extended(5)
    assert len(again) == 8 and torch.equal(again.load(7)["image1"], longer.load(7)["image1"])
