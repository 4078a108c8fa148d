"""The classical priors of the training pairs, computed once per pair (demon_lab.pipeline.stages.priors), are
the values the chain computes for a batch of the same pairs, and a stage computes the same with them as
without them: the loss, every gradient, to the bit."""

from __future__ import annotations

import math

import pytest
import torch
from hydra import compose, initialize_config_dir
from torch.utils.data import default_collate

from demon_lab import resources
from demon_lab.core import losses
from demon_lab.data.datasets import SyntheticDataset
from demon_lab.nets.chain import DeMoN
from demon_lab.pipeline.kinds import DepthMotionStage, FlowStage, IterativeStage, RefineStage
from demon_lab.pipeline.stages import priors as pair_priors
from demon_lab.pipeline.stages.base import StageModule
from tests.jobs import settings

SIZE = (96, 128)  # the cpu scale's, where the 5-point motion finds its solutions


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    cache = tmp_path_factory.mktemp("scenes")
    return [SyntheticDataset(preset, length=2, size=SIZE, augment=True, cache_dir=cache)
            for preset in ("synthetic_sun3d", "synthetic_scenes11")]


def _batch(samples):
    return default_collate([{k: v for k, v in s.items() if k != "id"} for s in samples])


def test_a_pairs_priors_are_the_chains_for_a_batch_of_the_same_pairs(scenes):
    """Computed pair by pair (as the cache holds them), the DIS prior flow and its 5-point motion equal to the
    bit what the chain computes for a batch: flow1's prior flow and dm1's prior motion (ransac_prior)."""
    samples = [p for d in scenes for i in range(len(d)) for p in d.training_pairs(i).values()]
    batch = _batch(samples)
    chain = DeMoN("v1", 0.25, SIZE, flow1_prior="dis_x2", dm1_prior="ransac_prior")
    pair = torch.cat([batch["image1"], batch["image2"]], 1)
    flow = chain.prior_flow(pair)
    motion = chain.prior_motion(flow, batch["intrinsics"], flow)
    ours = pair_priors.PairPriors.of(chain).compute(samples)
    assert torch.equal(torch.stack([o["prior_flow"] for o in ours]), flow)
    assert torch.equal(torch.stack([o["prior_motion"] for o in ours]), motion)
    assert (motion[:, 3:].norm(dim=1) > 0.99).all()  # every pair has its motion: nothing fell back to zeros
    assert pair_priors.PairPriors.of(DeMoN("v1", 0.25, SIZE)) is None
    assert pair_priors.PairPriors.of(DeMoN("v1", 0.25, SIZE, flow1_prior="dis", dm1_prior="ransac")) == \
        pair_priors.PairPriors("dis", motion=False)  # ransac reads flow1's own flow: not the pair's alone


def test_the_priors_are_computed_once_per_training_pair_and_read_at_every_draw(scenes, monkeypatch):
    """warm_priors computes each scene's four augmented pairs once (in processes), saves them beside the scenes
    and reads them back; a draw of any of them is a hit; a pair it never saw is computed at its first draw."""
    priors = pair_priors.PairPriors("dis", motion=True)
    table, computed = pair_priors.warm_priors(scenes, priors, processes=2)
    assert computed == 4 and len(table.known) == 16  # 2 sets x 2 scenes x 4 augmentations
    assert all(pair_priors._path(d, priors).is_file() for d in scenes)
    calls, compute = [], pair_priors.PairPriors.compute
    monkeypatch.setattr(pair_priors.PairPriors, "compute", lambda self, samples: calls.append(len(samples)) or
                        compute(self, samples))
    again, computed = pair_priors.warm_priors(scenes, priors)
    assert computed == 0 and calls == [] and again.known.keys() == table.known.keys()
    draws = [(d[(i, draw)], d.pair_key(i, draw)) for d in scenes for i in range(len(d)) for draw in range(6)]
    assert len({key for _, key in draws}) == 16  # 4 scenes x 4 augmentations, each drawn
    for draw, key in draws:
        expected = priors.compute([draw])[0]
        got = again(draw, key)
        assert got.keys() == {"prior_flow", "prior_motion"}
        assert all(torch.equal(got[k], expected[k]) for k in got)
    assert again.misses == {} and calls == [1] * len(draws)  # (the expected values' calls, none of the table's)
    uncached = SyntheticDataset("synthetic_mvs", length=1, size=SIZE, augment=True, cache_dir=False)
    other = uncached[(0, 0)]
    assert uncached.pair_key(0, 0) is None
    first = again(other, None)
    assert len(again.misses) == 1 and again(other, None) is first and calls[-1] == 1
    fresh = scenes[0].extended(1)  # a scene past the set's own: not computed ahead
    first = again(fresh[(2, 0)], fresh.pair_key(2, 0))
    assert len(again.misses) == 2 and again(fresh[(2, 0)], fresh.pair_key(2, 0)) is first


def _chain():
    torch.manual_seed(0)
    return DeMoN("v1", 0.25, SIZE, flow1_prior="dis_x2", dm1_prior="ransac_prior", flow2_prior="previous",
                 dm2_prior="previous")


@pytest.mark.parametrize("kind", ["flow1", "dm1", "flow2", "dm2", "iterative", "refine"])
def test_a_stage_computes_the_same_with_its_pairs_priors_as_without(scenes, kind, monkeypatch):
    """A stage fed the priors its batch carries gives the loss and the gradients it gives computing them itself,
    and computes none of them."""
    from demon_lab.nets import chain as chain_module
    from demon_lab.nets import flow_net

    samples = [d[(i, draw)] for d in scenes for i in range(len(d)) for draw in range(2)]
    plain = _batch(samples)
    chain = _chain()
    with_priors = {**plain, **default_collate(pair_priors.PairPriors.of(chain).compute(samples))}
    w = dict(name=kind, steps=100, lr=1e-4)
    spec = {"flow1": FlowStage(net="flow1", **w), "dm1": DepthMotionStage(net="dm1", **w),
            "flow2": FlowStage(net="flow2", **w), "dm2": DepthMotionStage(net="dm2", **w),
            "iterative": IterativeStage(queue_size=4, **w), "refine": RefineStage(iterations=1, **w)}[kind]
    make = lambda c: StageModule(c, spec, weights=losses.preset("released_code"))  # noqa: E731
    results = []
    for batch in (plain, with_priors):
        if batch is with_priors:
            def computed(*args, **kwargs):
                raise AssertionError("a prior the batch carries was computed again")
            monkeypatch.setattr(flow_net, "dis_prior", computed)
            monkeypatch.setattr(chain_module, "dis_prior", computed)
            monkeypatch.setattr(chain_module, "ransac_motion", computed)
        module = make(_chain())
        module.ramp = lambda *args, **kwargs: 1.0  # every term on
        module.train()
        loss, _ = module.stage_loss(batch, losses.ground_truth(batch))
        loss.backward()
        results.append((loss.detach(), [p.grad.clone() for p in module.parameters() if p.grad is not None]))
    (loss_a, grads_a), (loss_b, grads_b) = results
    assert torch.isfinite(loss_a) and torch.equal(loss_a, loss_b)
    assert len(grads_a) == len(grads_b) > 0 and all(torch.equal(a, b) for a, b in zip(grads_a, grads_b, strict=True))


def test_a_job_with_priors_draws_its_pairs_with_them(tmp_path):
    """The profile's job warms its training pairs' priors before its first stage, and each batch a stage
    draws carries them: the values the chain computes for that batch."""
    from demon_lab.pipeline.stages import training

    with initialize_config_dir(str(resources.CONF), version_base="1.3"):
        cfg = compose("config", ["scale=smoke", f"cache_dir={tmp_path}", "data.size=[96,128]",
                                 "model.flow1_prior=dis", "model.dm1_prior=ransac_prior"])
    from demon_lab.pipeline.config import instantiate
    from demon_lab.pipeline.stages.schedule import build_chain

    chain = build_chain(settings(cfg))
    train = [instantiate(e.dataset) for e in cfg.data.train]
    table, computed = pair_priors.warm_priors(train, pair_priors.PairPriors.of(chain), processes=1)
    assert computed == 4 * len(train)  # smoke: 4 scenes per preset
    batch = next(iter(training.build_datamodule(settings(cfg), 4, 8, priors=table).train_dataloader()))
    pair = torch.cat([batch["image1"], batch["image2"]], 1)
    assert torch.equal(batch["prior_flow"], chain.prior_flow(pair))
    assert torch.equal(batch["prior_motion"], chain.prior_motion(batch["prior_flow"], batch["intrinsics"],
                                                                 batch["prior_flow"]))
    assert table.misses == {}


@pytest.mark.parametrize("kind", ["flow1", "dm1"])
def test_held_apart_scoring_reads_each_pairs_priors_once_and_scores_what_the_chain_computes(kind, monkeypatch):
    """A stage's held-apart scoring (StageValidation) computes the held-apart pairs' priors at its first scoring
    only, and its scores equal those of the chain computing the priors itself, to the bit."""
    from demon_lab.nets import chain as chain_module
    from demon_lab.nets import flow_net
    from demon_lab.pipeline.stages.validation import StageValidation

    with initialize_config_dir(str(resources.CONF), version_base="1.3"):
        cfg = compose("config", ["scale=smoke"])
    from demon_lab.pipeline.kinds import stage_spec

    chain = _chain().eval()
    held_apart = SyntheticDataset("synthetic_sun3d", length=3, size=SIZE, split="val", cache_dir=False)
    scorer = StageValidation(stage_spec(cfg, kind), [held_apart], every_n_steps=1, batch_size=2)
    loader = torch.utils.data.DataLoader(held_apart, batch_size=2, shuffle=False)
    with torch.no_grad():
        expected = scorer._scores(chain, list(loader))  # plain batches: the chain computes the priors
    calls = {"dis": 0, "ransac": 0}
    dis, ransac = flow_net.dis_prior, chain_module.ransac_motion
    for module in (flow_net, chain_module):
        monkeypatch.setattr(module, "dis_prior",
                            lambda *a, **k: calls.__setitem__("dis", calls["dis"] + 1) or dis(*a, **k))
    monkeypatch.setattr(chain_module, "ransac_motion",
                        lambda *a, **k: calls.__setitem__("ransac", calls["ransac"] + 1) or ransac(*a, **k))
    computed, compute = [], pair_priors.PairPriors.compute
    monkeypatch.setattr(pair_priors.PairPriors, "compute", lambda self, samples: computed.append(len(samples)) or
                        compute(self, samples))
    with torch.no_grad():
        first = scorer._scores(chain, scorer.batches(chain, 0))
        again = scorer._scores(chain, scorer.batches(chain, 0))
    assert all(b.keys() >= {"prior_flow", "prior_motion"} for b in scorer.batches(chain, 0))
    assert computed == [2, 1] and calls == {"dis": 0, "ransac": 0}  # each pair once, and never by the chain
    assert first == again and first.keys() == expected.keys()
    assert all(first[k] == expected[k] or (math.isnan(first[k]) and math.isnan(expected[k])) for k in first)
