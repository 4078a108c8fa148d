"""A memo of what a stage's frozen nets compute for a training pair (``trainer.reuse_frozen``).

A stage's upstream nets are frozen, so what they compute for a pair is a function of the pair
alone: the bootstrap pass that every stage after ``dm1`` feeds on, ``flow1``'s flow and its
5-point RANSAC motion for ``dm1``, the DIS prior flow for ``flow1``. A training set of N scenes
under DeMoN's augmentation (two flips) holds at most 4N distinct pairs, and a stage draws each of
them many times; the memo computes a pair's outputs at its first draw and reads them at the next.

The rows a memo returns are the rows the computation gives on the batch of the pairs it has not
seen, so they can differ from those of the whole batch in floating-point rounding (a convolution's
rounding depends on the batch it runs in), as a thread count does: ``reuse_frozen`` is not part of
any key.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Callable

import torch

DEFAULT_MAX_BYTES = 2**30
"""The memo's size limit: the least recently read rows go first."""


def _digest(rows: tuple[torch.Tensor, ...]) -> bytes:
    h = hashlib.blake2b(digest_size=20)
    for row in rows:
        h.update(str((row.dtype, tuple(row.shape))).encode())
        h.update(memoryview(row.detach().contiguous().cpu().numpy()).cast("B"))
    return h.digest()


class FrozenMemo:
    """``memo(compute, *inputs)`` is ``compute(*inputs)`` (a tuple of tensors whose first dimension
    is the batch's) with each row read from the memo where the same input rows were seen before.
    ``compute`` must be a function of its input rows alone: one memo per computation."""

    def __init__(self, max_bytes: int = DEFAULT_MAX_BYTES):
        self.max_bytes, self.bytes = int(max_bytes), 0
        self.rows: OrderedDict[bytes, tuple[torch.Tensor, ...]] = OrderedDict()
        self.hits = self.misses = 0

    def __call__(self, compute: Callable[..., tuple[torch.Tensor, ...]],
                 *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        keys = [_digest(tuple(x[i] for x in inputs)) for i in range(inputs[0].shape[0])]
        found = {k: self.rows[k] for k in keys if k in self.rows}
        for k in found:
            self.rows.move_to_end(k)
        missing = [i for i, k in enumerate(keys) if k not in found]
        self.hits, self.misses = self.hits + len(keys) - len(missing), self.misses + len(missing)
        if missing:
            index = torch.tensor(missing, device=inputs[0].device)
            fresh = compute(*(x.index_select(0, index) for x in inputs))
            for j, i in enumerate(missing):
                found[keys[i]] = row = tuple(t[j].clone() for t in fresh)
                self._store(keys[i], row)
        return tuple(torch.stack(parts) for parts in zip(*(found[k] for k in keys), strict=True))

    def _store(self, key: bytes, row: tuple[torch.Tensor, ...]) -> None:
        if key in self.rows:
            return
        self.rows[key] = row
        self.bytes += sum(t.numel() * t.element_size() for t in row)
        while self.bytes > self.max_bytes and self.rows:
            _, old = self.rows.popitem(last=False)
            self.bytes -= sum(t.numel() * t.element_size() for t in old)
