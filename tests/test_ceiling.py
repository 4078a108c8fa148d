"""The ceiling table's measures: how precise a flow is, and the motion each reader reads from it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from demon_lab.baselines import ceiling
from demon_lab.baselines.twoview import BaselineFailure, pixel_intrinsics


def _pair(seed: int = 3, size=(96, 128)):
    from demon_lab.data import synthetic

    sample = synthetic.render_pair("synthetic_sun3d", seed, size, supersample=1)
    return {k: v.numpy() if hasattr(v, "numpy") else v for k, v in sample.items()}


def test_precision_counts_the_vectors_within_each_distance_of_the_truth_among_those_with_a_truth():
    truth = np.zeros((1, 5, 2))
    flow = truth + np.array([[0.5, 0], [1.5, 0], [0, 3.0], [4.5, 0], [0, 0]])[None]
    truth[0, 4] = np.nan  # no truth there: not counted
    assert ceiling.precision(flow, truth) == {"within_1px": 0.25, "within_2px": 0.5, "within_4px": 0.75,
                                              "median_px": 2.25}
    flow[0, 0] = np.nan  # a vector the flow does not give is not within any distance, and infinitely far
    assert ceiling.precision(flow, truth)["within_1px"] == 0.0
    assert ceiling.precision(flow, truth)["median_px"] == 3.75


def test_every_reader_reads_the_true_motion_from_the_true_flow():
    """On a rendered pair's ground-truth flow every vector is exact, so each reader's motion is the
    pair's (within 0.1 degrees), and every vector is within 1 pixel."""
    sample = _pair()
    out = ceiling.ceiling(sample["flow"], sample["flow"], sample)
    assert {out[f"within_{n}px"] for n in ceiling.PIXELS} == {1.0}
    for reader in ceiling.READERS:
        assert out[f"{reader}/n_failed"] == 0.0, reader
        assert out[f"{reader}/rot_deg"] < 0.1 and out[f"{reader}/tran_deg"] < 0.1, (reader, out)


def test_the_oracles_pick_keeps_the_precise_vectors_and_a_reader_without_enough_fails():
    """A flow whose vectors are off by 5 pixels but for a tenth that are exact: the oracle's pick reads
    the motion from those (as from the truth), and where no vector is within a pixel it fails: NaN
    errors and its failure counted, the other readers unaffected."""
    sample = _pair()
    truth = ceiling.pixel_flow(sample["flow"], sample)
    h, w = truth.shape[:2]
    rng = np.random.default_rng(0)
    angle = rng.uniform(0, 2 * np.pi, (h, w))
    off = truth + 5.0 * np.stack([np.cos(angle), np.sin(angle)], -1)
    exact = rng.random((h, w)) < 0.1
    mixed = np.where(exact[..., None], truth, off)
    K = pixel_intrinsics(sample["intrinsics"], h, w)
    motion = ceiling.read_motion(mixed, K, "pick1", truth)
    from demon_lab.core.metrics import motion_errors

    errors = motion_errors(motion, sample["motion"])
    assert errors["rot_deg"] < 0.1 and errors["tran_deg"] < 0.1
    with pytest.raises(BaselineFailure, match="vectors to read the motion from"):
        ceiling.read_motion(off, K, "pick1", truth)
    scale = np.array([w, h], dtype=np.float64)
    normalised = np.moveaxis(off / scale, -1, 0)
    out = ceiling.ceiling(normalised, sample["flow"], sample)
    assert out["pick1/n_failed"] == 1.0 and math.isnan(out["pick1/rot_deg"]) and out["within_4px"] == 0.0
    assert out["lmeds/n_failed"] == 0.0 and math.isfinite(out["lmeds/tran_deg"])
    with pytest.raises(ValueError, match="reader: expected one of"):
        ceiling.read_motion(off, K, "eight_point", truth)


def test_a_job_with_eval_ceiling_scores_the_bootstrap_flow_of_each_test_set_and_its_key_only_then(tmp_path):
    """``eval.ceiling=true`` adds the ceiling's means to each test set's summary (``ceiling/...``: the
    precise vectors' shares, in order, and each reader's errors and failures); off (the default) it
    adds nothing and is in no key."""
    from demon_lab.pipeline.evaluate import evaluate_test_sets
    from demon_lab.pipeline.identity import run_key
    from demon_lab.pipeline.stages.schedule import build_chain
    from tests.jobs import compose_config, settings, smoke_overrides

    base = smoke_overrides(tmp_path, "train=false", "iterations=0", "eval.max_samples=2")
    job = settings(compose_config([*base, "eval.ceiling=true"]))
    chain = build_chain(job).eval()
    results = evaluate_test_sets(job, chain, refined=False)
    for r in results:
        s = r.summary
        assert 0 <= s["ceiling/within_1px"] <= s["ceiling/within_2px"] <= s["ceiling/within_4px"] <= 1, r.name
        for reader in ceiling.READERS:
            assert 0 <= s[f"ceiling/{reader}/n_failed"] <= 2 and f"ceiling/{reader}/tran_deg" in s, (r.name, reader)
    plain = settings(compose_config(base))
    assert not any(k.startswith("ceiling/") for k in evaluate_test_sets(plain, chain, refined=False)[0].summary)
    # under oracle=flow the flow dm1 reads is the truth's at level 2, not the untrained flow1's
    untrained = {r.name: r.summary["ceiling/within_1px"] for r in results}
    oracle = settings(compose_config([*base, "eval.ceiling=true", "oracle=flow"]))
    for r in evaluate_test_sets(oracle, chain, refined=False):
        assert r.summary["ceiling/within_4px"] > 0.9 and r.summary["ceiling/within_1px"] > untrained[r.name], r.name
    assert run_key(plain) == run_key(settings(compose_config([*base, "eval.ceiling=false"]))) != run_key(job)


def test_a_reader_whose_solver_aborts_draws_again_and_fails_in_one_line_if_it_keeps_aborting(monkeypatch):
    """OpenCV's 5-point solver aborts on some degenerate minimal samples (an assertion in ``solvePoly``):
    the least-median fit, as the RANSAC one, is run again on the vectors in another order, and where
    every run aborts the reader fails (a counted failure, not a failed job)."""
    import cv2

    from demon_lab.baselines import twoview

    sample = _pair()
    truth = ceiling.pixel_flow(sample["flow"], sample)
    K = pixel_intrinsics(sample["intrinsics"], *truth.shape[:2])
    real, calls = cv2.findEssentialMat, []

    def aborting(*args, **kwargs):
        calls.append(kwargs["method"])
        if len(calls) == 1:
            raise cv2.error("solvePoly: (-215:Assertion failed)")
        return real(*args, **kwargs)

    monkeypatch.setattr(twoview.cv2, "findEssentialMat", aborting)
    from demon_lab.core.metrics import motion_errors

    errors = motion_errors(ceiling.read_motion(truth, K, "lmeds"), sample["motion"])
    assert calls == [cv2.LMEDS, cv2.LMEDS] and errors["tran_deg"] < 0.1

    def always(*args, **kwargs):
        raise cv2.error("solvePoly: (-215:Assertion failed)")

    monkeypatch.setattr(twoview.cv2, "findEssentialMat", always)
    with pytest.raises(BaselineFailure, match="least median of squares aborted 3 times"):
        ceiling.read_motion(truth, K, "lmeds")
    out = ceiling.ceiling(sample["flow"], sample["flow"], sample)
    assert out["lmeds/n_failed"] == 1.0 and out["ransac/n_failed"] == 1.0


def test_distances_count_in_pixels_of_the_input_image():
    """A level-2 flow (a grid pixel is 4 input pixels): a vector half a grid pixel off is 2 input
    pixels off, within 2 px and not within 1 px, and the oracle's pick of the vectors within 1 px
    keeps none of them."""
    truth = np.zeros((4, 4, 2))
    flow = truth + np.array([0.5, 0.0])
    assert ceiling.precision(flow, truth, image_px=4.0) == {"within_1px": 0.0, "within_2px": 1.0, "within_4px": 1.0,
                                                            "median_px": 2.0}
    sample = _pair()
    K = pixel_intrinsics(sample["intrinsics"], *sample["flow"].shape[1:])
    exact = ceiling.pixel_flow(sample["flow"], sample)
    with pytest.raises(BaselineFailure, match="0 vectors"):
        ceiling.read_motion(exact + 0.5, K, "pick1", exact, image_px=4.0)
    assert np.isfinite(ceiling.read_motion(exact + 0.1, K, "pick1", exact, image_px=4.0)).all()
