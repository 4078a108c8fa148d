"""``trainer.reuse_frozen``: the memo of what a stage's frozen nets compute for a training pair."""

from __future__ import annotations

import pytest
import torch

from demon_lab.core import losses
from demon_lab.nets.chain import DeMoN
from demon_lab.pipeline.stages.memo import FrozenMemo
from tests.test_losses import _module, _stage_batch


class Counted:
    """A row-wise computation that counts the rows it is given."""

    def __init__(self):
        self.rows = 0

    def __call__(self, x, y):
        self.rows += x.shape[0]
        return x * 2 + y.sum(1, keepdim=True), x.sum(1)


def test_the_memo_computes_a_row_once_and_reads_it_back_at_its_next_draws():
    torch.manual_seed(0)
    x, y = torch.randn(4, 3), torch.randn(4, 5)
    compute, memo = Counted(), FrozenMemo()
    expected = Counted()(x, y)
    first = memo(compute, x, y)
    assert compute.rows == 4 and all(torch.equal(a, b) for a, b in zip(first, expected, strict=True))
    # a batch of two seen rows (in another order, one twice) and a new one computes the new one alone
    new_x, new_y = torch.randn(1, 3), torch.randn(1, 5)
    again = memo(compute, torch.cat([x[[2, 0, 2]], new_x]), torch.cat([y[[2, 0, 2]], new_y]))
    assert compute.rows == 5 and (memo.hits, memo.misses) == (3, 5)
    assert torch.equal(again[0][:3], expected[0][[2, 0, 2]]) and torch.equal(again[1][:3], expected[1][[2, 0, 2]])
    assert torch.equal(again[0][3:], Counted()(new_x, new_y)[0])
    # a row is its inputs' rows together: the same x with another y is another row
    memo(compute, x[:1], y[1:2])
    assert compute.rows == 6


def test_the_memo_lets_the_least_recently_read_rows_go_past_its_size_limit():
    x, y = torch.arange(12.0).view(4, 3), torch.zeros(4, 5)
    row_bytes = (3 + 1) * 4  # the two outputs of one row, float32
    compute, memo = Counted(), FrozenMemo(max_bytes=2 * row_bytes)
    memo(compute, x[:2], y[:2])
    memo(compute, x[:1], y[:1])  # row 0 read: row 1 is now the least recent
    memo(compute, x[2:3], y[2:3])
    assert len(memo.rows) == 2 and memo.bytes == 2 * row_bytes
    memo(compute, x[:1], y[:1])
    assert compute.rows == 3  # row 0 kept
    memo(compute, x[1:2], y[1:2])
    assert compute.rows == 4  # row 1 went


STAGES = {
    "flow1": ("flow", dict(net="flow1")),
    "flow2": ("flow", dict(net="flow2")),
    "dm1": ("depth_motion", dict(net="dm1")),
    "dm2": ("depth_motion", dict(net="dm2")),
    "iterative": ("iterative", dict(queue_size=0)),
    "refine": ("refine", dict(iterations=2)),
}


@pytest.mark.parametrize("priors", [False, True], ids=["demon", "four_priors"])
@pytest.mark.parametrize("stage", list(STAGES))
def test_every_stage_kind_computes_the_same_loss_from_the_memo_and_reads_a_seen_pair_from_it(stage, priors):
    """With ``reuse_frozen`` a stage's loss is the one it computes without (on a batch of pairs it
    has not seen the memo computes the whole batch at once, and at the next draw reads those rows
    back), and a pair seen before is not computed again."""
    from demon_lab.pipeline.kinds import STAGE_SPECS

    options = (dict(flow1_prior="dis", dm1_prior="ransac", flow2_prior="previous", dm2_prior="previous")
               if priors else {})
    torch.manual_seed(0)
    chain = DeMoN("v1", width=0.0625, size=(64, 64), **options)
    kind, kwargs = STAGES[stage]
    batch = _stage_batch()
    gt = losses.ground_truth(batch)

    def terms(module):
        with torch.no_grad():
            return {k: float(v) for k, v in module.stage_loss(batch, gt)[1].items()}

    spec = STAGE_SPECS[kind](name=stage, steps=300, lr=1e-3, **kwargs)
    plain = terms(_module(chain, spec))
    memoised = _module(chain, spec, reuse_frozen=True)
    first, second = terms(memoised), terms(memoised)
    assert first == plain and second == plain
    if stage == "flow1" and not priors:  # flow1 alone has no frozen computation without the DIS prior
        assert memoised.memo.hits + memoised.memo.misses == 0
    else:
        assert (memoised.memo.hits, memoised.memo.misses) == (2, 2)
