"""The schedule's stages as cache entries: which stages a job trains, their keys (each one's
description is :func:`demon_lab.pipeline.identity.describe_stage`), and how a finished stage is loaded
into the chain.

The schedule (``conf/schedule/``) lists the stages in the released code's order: flow1, dm1, flow2,
dm2, iterative, refine (DeMoN's ``training/v2/training.py``; docs/reference.md §5). Each stage's key
chains the keys of the stages before it, so a change upstream retrains everything downstream
(docs/running.md, "The stage cache").
"""

from __future__ import annotations

from demon_lab.core.execution import prepare_nets
from demon_lab.nets.chain import DeMoN
from demon_lab.pipeline.identity import describe_stage, stage_key
from demon_lab.pipeline.settings import JobSettings
from demon_lab.pipeline.stages.cache import CheckpointError, StageDir


def stage_dirs(job: JobSettings) -> list[StageDir]:
    """The cache entries of the stages the job trains (the schedule's, up to ``schedule.until``; keys
    chained through the upstream keys)."""
    upstream: dict[str, str] = {}
    dirs = []
    for name in job.schedule.trained():
        description = describe_stage(job, name, upstream)
        key = stage_key(description)
        dirs.append(StageDir(job.cache_dir, name, key, description))
        upstream[name] = key
    return dirs


def build_chain(job: JobSettings) -> DeMoN:
    """The chain of the job's model options and input size: untrained, or with ``model.weights``
    loaded (:func:`demon_lab.pipeline.weights.load_weights`); its nets in channels-last layout and
    compiled when ``model.channels_last`` / ``model.compile`` ask for it."""
    model = job.model
    chain = DeMoN(model.variant, model.width, tuple(job.data.size), model.compat, model.correlation,
                  **model.net_options(), nets=model.plugins())
    if model.weights:
        from demon_lab.pipeline.weights import load_weights

        load_weights(chain, model.weights)
    return prepare_nets(chain, model.channels_last, model.compile)


def load_stage(chain: DeMoN, stage: StageDir) -> None:
    """Load a finished stage's nets into ``chain`` (one CheckpointError line if they do not fit)."""
    state = stage.load()
    for net, weights in state.items():
        try:
            getattr(chain, net).load_state_dict(weights)
        except (AttributeError, RuntimeError) as e:
            first = str(e).strip().splitlines()[0]
            raise CheckpointError(f"checkpoint {stage.weights} does not fit this chain's {net} "
                                  f"(another architecture, variant or width? {first[:160]})") from None
