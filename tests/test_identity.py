"""The identity of runs, stages and sweeps lives in demon_lab.pipeline.identity: the output-folder exclusions
agree with the non-semantic keys, and keys do not depend on where the package is installed."""

from __future__ import annotations

from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from demon_lab import resources
from demon_lab.pipeline import config, identity
from demon_lab.pipeline.stages.schedule import stage_dirs


def _compose(*overrides: str, hydra: bool = False):
    with initialize_config_dir(str(resources.CONF), version_base="1.3"):
        return compose("config", overrides=list(overrides), return_hydra_config=hydra)


def test_output_folders_exclude_exactly_the_non_semantic_keys_a_user_can_set():
    """The output folder names a job's overrides that change its result, and no other: the
    non-semantic ones (identity.NON_SEMANTIC, its groups and the keys under its subtrees) are left out."""
    overrides = ["seed=2", "model.width=0.5", "+schedule.stages.flow1.layers_first=0.4", "threads=1", "force=true",
                 "tracking=local_server", "tracking.server.port=5001", "tracking.log_every_n_steps=5",
                 "trainer.reuse_frozen=true", "model.channels_last=true", "eval.visualize=0", "data.num_workers=2"]
    cfg = _compose(*overrides, hydra=True)
    excluded = list(cfg.hydra.job.config.override_dirname.exclude_keys)
    assert excluded == ["threads", "force", "tracking", "tracking.server.port", "tracking.log_every_n_steps",
                        "trainer.reuse_frozen", "model.channels_last", "eval.visualize", "data.num_workers"]
    assert all(not identity.is_semantic(k) for k in excluded)
    assert cfg.hydra.job.override_dirname == "+schedule.stages.flow1.layers_first=0.4,model.width=0.5,seed=2"
    assert list(_compose(hydra=True).hydra.job.config.override_dirname.exclude_keys) == []
    assert "seed" not in excluded and identity.is_semantic("seed") and not identity.is_semantic("tracking.uri")


def test_run_key_ignores_non_semantic_keys_and_follows_semantic_ones(tmp_path):
    base = identity.run_key(_compose())
    assert identity.run_key(_compose("threads=1", "force=true", f"cache_dir={tmp_path}", "eval.visualize=0",
                                     f"tracking.uri=sqlite:///{tmp_path}/x.db", "tracking=local_server")) == base
    assert identity.run_key(_compose("seed=1")) != base
    assert identity.run_key(_compose("iterations=5")) != base


def test_keys_do_not_depend_on_where_the_package_is_installed(monkeypatch, tmp_path):
    cfg = _compose("data=pair_folder")  # trains on the bundled pair: its path is in the stage keys
    assert str(resources.DATA) in OmegaConf.to_container(cfg.data, resolve=True)["path"]
    run, stages = identity.run_key(cfg), [s.key for s in stage_dirs(cfg)]
    elsewhere = tmp_path / "site-packages" / "demon_lab" / "data" / "real"
    monkeypatch.setattr(resources, "DATA", elsewhere)
    monkeypatch.setattr(config, "DATA", elsewhere)
    moved = _compose("data=pair_folder")
    assert str(elsewhere) in OmegaConf.to_container(moved.data, resolve=True)["path"]
    assert identity.run_key(moved) == run and [s.key for s in stage_dirs(moved)] == stages
    # ... while a user's own folder is part of the key
    other = _compose("data=pair_folder", f"data.path={tmp_path}")
    assert identity.run_key(other) != run


def test_sweep_key_drops_non_semantic_overrides_and_keeps_their_order_irrelevant():
    key = identity.sweep_key("study", ["seed=0,1", "+experiment=study"])
    assert identity.sweep_key("study", ["+experiment=study", "threads=1", "seed=0,1",
                                        "hydra/launcher=joblib".replace("hydra/", "hydra.")]) == key
    assert identity.sweep_key("other", ["seed=0,1", "+experiment=study"]) != key


def test_keys_do_not_depend_on_where_scenes_are_cached(tmp_path):
    """The render cache's location (``data.cache_dir``, a source's own, or ``false``: no cache) is in no
    key and no output folder name; the default scales' keys, which hold it as null, are those pinned in
    tests/test_execution.py."""
    def keys(*overrides: str) -> tuple[str, list[str]]:
        cfg = _compose(*overrides)
        return identity.run_key(cfg), [s.key for s in stage_dirs(cfg)]

    for scale in ("scale=smoke", "scale=cpu", "scale=paper"):
        base = keys(scale)
        assert keys(scale, f"data.cache_dir={tmp_path}/renders") == base
        assert keys(scale, "data.cache_dir=false") == base
        assert keys(scale, f"cache_dir={tmp_path}") == base  # smoke's data.cache_dir follows cache_dir
        assert keys(scale, "data.size=[32,32]") != base
    assert not identity.is_semantic("data.cache_dir") and not identity.is_semantic("data.test.1.cache_dir")
    assert identity.is_semantic("data.size") and identity.is_semantic("data.path")
    cfg = _compose(f"data.cache_dir={tmp_path}/renders", "seed=2", hydra=True)
    assert cfg.hydra.job.override_dirname == "seed=2"
