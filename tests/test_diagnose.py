"""The per-pass diagnosis of a trained chain (demon_lab.tools.diagnose)."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import random_scene

from demon_lab.core import geometry as geo
from demon_lab.core import losses
from demon_lab.nets.chain import ChainOutput, Prediction
from demon_lab.pipeline.evaluate import run_chain
from demon_lab.tools.diagnose import diagnose_batch, format_table, summarize


class ScriptedChain(torch.nn.Module):
    """Pass 0: the ground truth itself; every later pass: no flow, no motion and inverse depth -1;
    refined: inverse depth 1."""

    def __init__(self, batch):
        super().__init__()
        self.gt = losses.ground_truth(batch)
        self.device_marker = torch.nn.Parameter(torch.zeros(()))  # run_chain's device

    def forward(self, image1, image2, intrinsics, iterations, oracle=None, gt=None, refine=True):
        passes = [self.bootstrap()]
        for _ in range(iterations):
            passes.append(self.iterate(passes[-1]))
        return ChainOutput(passes, self.refine(image1, passes[-1].inv_depth) if refine else None)

    def refine(self, image1, inv_depth2):
        return torch.ones_like(image1[:, :1])

    def bootstrap(self):
        flow = self.gt["flow2"]
        inv = self.gt["inv_depth2"]
        zeros5 = torch.zeros_like(self.gt["flow5"])
        return Prediction(flow, torch.ones_like(flow), zeros5, zeros5, inv, self.gt["normals2"], self.gt["motion"])

    def iterate(self, prev):
        flow = torch.zeros_like(prev.flow)
        return Prediction(flow, prev.conf, prev.flow5, prev.conf5, -torch.ones_like(prev.inv_depth),
                          prev.normals, torch.zeros_like(prev.motion))


def diagnose(chain, batch, iterations, refine=False):
    """The diagnosis of ``chain`` on one batch, run as the command runs it."""
    ((_, on_device, output),) = run_chain(chain, [batch], iterations)
    return diagnose_batch(on_device, output, refine=refine)


@pytest.fixture
def batch():
    b, h, w = 3, 64, 96
    inv, motion, K = random_scene(b, h, w, dtype=torch.float32, seed=3)
    g = torch.Generator().manual_seed(0)
    return {"image1": torch.rand(b, 3, h, w, generator=g), "image2": torch.rand(b, 3, h, w, generator=g),
            "intrinsics": K, "inv_depth": inv, "motion": motion}


def test_diagnosis_of_scripted_passes(batch):
    gt = losses.ground_truth(batch)
    gt_len = gt["flow2"].norm(dim=1).flatten(1).mean(1)
    assert (gt["flow2"].norm(dim=1) < 1).all()  # so the prior keeps every vector
    passes = diagnose(ScriptedChain(batch), batch, iterations=2)
    assert len(passes) == 3 and all(len(p) == 3 for p in passes)
    for i in range(3):
        p0, p1, p2 = (p[i] for p in passes)
        # pass 0 is the ground truth: no error, GT length, GT motion, positive depth, no prior
        assert p0["epe"] == pytest.approx(0, abs=1e-6)
        assert p0["flow"] == pytest.approx(p0["gt_flow"]) == pytest.approx(float(gt_len[i]), rel=1e-5)
        assert p0["t_norm"] == pytest.approx(0.5, rel=1e-5)
        assert p0["rot_deg"] == pytest.approx(p0["gt_rot_deg"]) and p0["rot_deg"] > 0.1
        assert p0["nonpositive_depth"] == 0 and math.isnan(p0["prior"]) and math.isnan(p0["follow"])
        # pass 1 is fed the flow of the GT depth+motion (exact) and returns no flow
        assert p1["prior_epe"] == pytest.approx(0, abs=1e-5)
        assert p1["prior"] == pytest.approx(p0["gt_flow"], rel=1e-5)
        assert p1["follow"] == pytest.approx(p1["prior"], rel=1e-5)
        assert p1["epe"] == pytest.approx(p0["gt_flow"], rel=1e-5) and p1["flow"] == 0
        assert p1["nonpositive_depth"] == 1 and p1["t_norm"] == 0 and p1["rot_deg"] == 0
        # pass 2 is fed the flow of no motion: none, and follows it exactly
        assert p2["prior"] == 0 and p2["follow"] == 0 and p2["prior_epe"] == pytest.approx(p0["gt_flow"], rel=1e-5)


def test_prior_is_what_the_iterative_flow_net_receives(batch):
    """Vectors of norm >= 1 are zeroed in the prior, as in the iterative flow net's input."""
    chain = ScriptedChain(batch)
    chain.gt["motion"] = chain.gt["motion"] * torch.tensor([1, 1, 1, 6, 6, 6])  # long flows
    induced = geo.flow_from_depth_motion(chain.gt["inv_depth2"], chain.gt["motion"], batch["intrinsics"])
    long = induced.norm(dim=1) >= 1
    assert 0.05 < long.float().mean() < 0.95
    kept = torch.where(long[:, None], torch.zeros_like(induced), induced).norm(dim=1).flatten(1).mean(1)
    p1 = diagnose(chain, batch, iterations=1)[1]
    for i in range(3):
        assert p1[i]["prior"] == pytest.approx(float(kept[i]), rel=1e-5)


def test_refined_row_counts_non_positive_depth(batch):
    chain = ScriptedChain(batch)
    chain.refine = lambda image1, inv: torch.where(torch.arange(image1.shape[-1]) < 24, -1.0, 1.0).expand(
        image1.shape[0], 1, *image1.shape[-2:])
    rows = diagnose(chain, batch, iterations=1, refine=True)
    assert len(rows) == 3 and all(r["nonpositive_depth"] == 0.25 and math.isnan(r["epe"]) for r in rows[2])


def test_summary_and_table(batch):
    results = {"scripted": summarize(diagnose(ScriptedChain(batch), batch, iterations=1))}
    assert results["scripted"][0]["pairs"] == 3 and math.isnan(results["scripted"][0]["prior"])
    table = format_table(results).splitlines()
    assert table[0].split()[:4] == ["test", "set", "pass", "EPE"] and len(table) == 4
    assert table[2].split()[:3] == ["scripted", "0", "0.000"]
