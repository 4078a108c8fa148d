"""The schedule's stages as cache entries: which stages a job trains, what each one's key hashes,
which nets it trains, and how a finished stage is loaded into the chain.

The schedule (``conf/schedule/``) lists the stages in the released code's order: flow1, dm1, flow2,
dm2, iterative, refine (DeMoN's ``training/v2/training.py``; docs/reference.md §5). Each stage's key
chains the keys of the stages before it, so a change upstream retrains everything downstream
(docs/running.md, "The stage cache").
"""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, OmegaConf

from demon_lab.core.execution import normalize_precision, prepare_nets
from demon_lab.nets.chain import DeMoN
from demon_lab.pipeline.identity import cpu_threads, leave_out_neutral, model_identity, stage_key, without_render_cache
from demon_lab.pipeline.schema import ModelSpec
from demon_lab.pipeline.stages.cache import CheckpointError, StageDir
from demon_lab.pipeline.stages.kinds import stage_spec


def scheduled_stages(cfg: DictConfig) -> list[str]:
    """The stages a job needs: the schedule's, up to ``schedule.until``."""
    names = list(cfg.schedule.stages)
    return names[: names.index(cfg.schedule.until) + 1]


def describe_stage(cfg: DictConfig, name: str, upstream: dict[str, str]) -> dict[str, Any]:
    """Everything that determines a stage's result (what its cache key hashes)."""
    plain = lambda node: OmegaConf.to_container(node, resolve=True)  # noqa: E731
    spec = stage_spec(cfg, name)
    return {
        "stage": name,
        "stage_config": plain(cfg.schedule.stages[name]),
        "optimisation": {k: cfg.schedule[k] for k in ("lr_schedule", "weight_decay", "grad_clip")},
        "batch_size": spec.batch_size or cfg.data.batch_size,
        "model": {**_stage_model(model_identity(plain(cfg.model)), name, list(cfg.schedule.stages)),
                  "size": list(cfg.data.size)},  # weights by content
        # Only the weights this stage's loss reads: ablations that change another stage's terms
        # (no_normals for the flow stages, say, or no_sig for a flow stage without sig terms)
        # share this stage.
        "loss": {k: float(cfg.loss[k]) for k in spec.weight_keys()},
        "train_data": without_render_cache(plain(cfg.data.train)),  # not where its scenes are cached
        # the held-apart sets that choose the kept nets (keep_best; left out where the stage keeps its last)
        **({"keep_best_on": without_render_cache(plain(cfg.data.val))} if spec.keep_best else {}),
        "seed": cfg.seed,
        "upstream": dict(upstream),
        # the nets' precision where the stage trains (a stage of 0 steps keeps its nets as they are)
        **leave_out_neutral({"precision": normalize_precision(cfg.precision)} if int(spec.steps) > 0 else {}),
        # the CPU threads it trains with (their rounding parts the weights), but for the neutral 2
        **(cpu_threads(cfg) if int(spec.steps) > 0 else {}),
    }


MODEL_OPTION_FROM = {"dm1_prior": "dm1", "flow2_prior": "flow2", "dm2_prior": "dm2"}
"""Model options that change only the nets from a stage on: the stages before it leave them out of
their keys (so flow1 is shared between chains with and without ``dm1_prior``, flow1 and dm1
between chains with and without ``flow2_prior``, and flow1, dm1 and flow2 between chains with and
without ``dm2_prior``)."""


def _stage_model(model: dict[str, Any], name: str, names: list[str]) -> dict[str, Any]:
    """``model`` as stage ``name`` keys it: without the options, and the nets of one's own, of the
    slots that a later stage trains first (a net of one's own in ``dm1`` shares ``flow1``)."""
    def later(stage: str) -> bool:
        return stage in names and names.index(name) < names.index(stage)

    out = {k: v for k, v in model.items() if not (k in MODEL_OPTION_FROM and later(MODEL_OPTION_FROM[k]))}
    if "nets" in out:
        nets = {slot: v for slot, v in out["nets"].items() if not later(slot)}
        out = {k: v for k, v in out.items() if k != "nets"} | ({"nets": nets} if nets else {})
    return out


def stage_dirs(cfg: DictConfig) -> list[StageDir]:
    """The cache entries of the scheduled stages (keys chained through the upstream keys)."""
    upstream: dict[str, str] = {}
    dirs = []
    for name in scheduled_stages(cfg):
        description = describe_stage(cfg, name, upstream)
        key = stage_key(description)
        dirs.append(StageDir(cfg.cache_dir, name, key, description))
        upstream[name] = key
    return dirs


def build_chain(cfg: DictConfig) -> DeMoN:
    """The chain of the config's model options and input size: untrained, or with ``model.weights``
    loaded (:func:`demon_lab.pipeline.weights.load_weights`); its nets in channels-last layout and
    compiled when ``model.channels_last`` / ``model.compile`` ask for it."""
    model = ModelSpec.of(cfg.model)
    chain = DeMoN(model.variant, model.width, tuple(cfg.data.size), model.compat, model.correlation, **model.priors(),
                  nets=model.plugins())
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
