"""The methods a job can score (``method``), each with what it is, in one place.

``demon`` is the chain: it trains the stages the cache lacks and is scored pass by pass (and on the
refined depth). The classical baselines (:mod:`demon_lab.baselines`) are scored once per pair, on
one summary row; ``base_mat_f`` among them reads the trained chain's flow, so it trains the chain
as ``demon`` does and reads each pair at the chain's size. What depends on the method (the keys'
precision and threads, the checks of weights and devices, training, evaluation, the printed table,
a sweep's table, a report's rows, a run's design) asks :func:`method` instead of its name.
"""

from __future__ import annotations

from dataclasses import dataclass

from demon_lab.baselines.methods import METHODS as BASELINES


@dataclass(frozen=True)
class Method:
    """A method by what it does."""

    name: str
    runs_chain: bool
    """It runs DeMoN's chain (trains what the stage cache lacks; its nets' precision, threads and
    weights matter): ``demon``, and ``base_mat_f``, which reads the chain's flow."""
    scores_passes: bool
    """It is scored pass by pass, with the refined depth where the refinement net is trained
    (``demon``); else on one row per pair, ``baseline``."""

    @property
    def at_chain_size(self) -> bool:
        """It reads each pair at the chain's input size; a classical method that reads no net reads it
        at ``baseline.size`` (the source's native one by default)."""
        return self.runs_chain

    def passes(self, iterations: int, refined: bool, priors: bool = False) -> list[int | str]:
        """The rows of its results table: the chain's passes 0..``iterations`` (after ``priors``, the
        classical priors alone, where the chain has them; then ``refined``), or ``baseline``."""
        if not self.scores_passes:
            return ["baseline"]
        return [*(["priors"] if priors else []), *range(iterations + 1), *(["refined"] if refined else [])]

    def summary_metrics(self, iterations: int | str) -> str:
        """The prefix of its summary metrics that a report row reads (``it<iterations>``: the last pass;
        ``""``: the baseline's own)."""
        return f"it{iterations}" if self.scores_passes else ""


METHODS: dict[str, Method] = {
    "demon": Method("demon", runs_chain=True, scores_passes=True),
    **{name: Method(name, runs_chain=name == "base_mat_f", scores_passes=False) for name in BASELINES},
}
"""Every method a job can score, by name (``method``)."""


def method(name: str) -> Method:
    """The method ``name`` (:data:`METHODS`); one ValueError line where there is none."""
    try:
        return METHODS[str(name)]
    except KeyError:
        raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {name!r}") from None
