"""The identity of runs, stages and sweeps lives in demon_lab.pipeline.identity: the output-folder exclusions
agree with the non-semantic keys, and keys do not depend on where the package is installed."""

from __future__ import annotations

from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from demon_lab import resources
from demon_lab.pipeline import config, identity
from demon_lab.pipeline.settings import JobSettings
from demon_lab.pipeline.stages.schedule import stage_dirs

settings = JobSettings.of  # (this module also runs from an installed package, where tests.jobs is not importable)


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
    base = identity.run_key(settings(_compose("threads=1")))  # the thread count is keyed: held the same here
    assert identity.run_key(settings(_compose("threads=1", "force=true", f"cache_dir={tmp_path}", "eval.visualize=0",
                                     f"tracking.uri=sqlite:///{tmp_path}/x.db", "tracking=local_server"))) == base
    assert identity.run_key(settings(_compose("seed=1"))) != base
    assert identity.run_key(settings(_compose("iterations=5"))) != base


def test_keys_do_not_depend_on_where_the_package_is_installed(monkeypatch, tmp_path):
    cfg = _compose("data=pair_folder")  # trains on the bundled pair: its path is in the stage keys
    assert str(resources.DATA) in OmegaConf.to_container(cfg.data, resolve=True)["path"]
    run, stages = identity.run_key(settings(cfg)), [s.key for s in stage_dirs(settings(cfg))]
    elsewhere = tmp_path / "site-packages" / "demon_lab" / "data" / "real"
    monkeypatch.setattr(resources, "DATA", elsewhere)
    monkeypatch.setattr(config, "DATA", elsewhere)
    moved = _compose("data=pair_folder")
    assert str(elsewhere) in OmegaConf.to_container(moved.data, resolve=True)["path"]
    assert identity.run_key(settings(moved)) == run and [s.key for s in stage_dirs(settings(moved))] == stages
    # ... while a user's own folder is part of the key
    other = _compose("data=pair_folder", f"data.path={tmp_path}")
    assert identity.run_key(settings(other)) != run


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
        return identity.run_key(settings(cfg)), [s.key for s in stage_dirs(settings(cfg))]

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


def test_the_code_behind_each_version_is_recorded_beside_it():
    """resources.RECORDED_SOURCES holds the digests of the code as it is: an edit of a net, a loss, the data a
    stage draws, a stage module or the scene generator fails here until its digest is recorded, with
    identity.CODE_VERSION (or synthetic.GENERATOR_VERSION) bumped where the edit changes what a stage (or a
    scene) is."""
    from demon_lab.data import synthetic

    bump = {"stage": "demon_lab.pipeline.identity.CODE_VERSION",
            "generator": "demon_lab.data.synthetic.GENERATOR_VERSION"}
    for name, paths in resources.SOURCES.items():
        actual = resources.source_digest(paths)
        assert actual == resources.RECORDED_SOURCES[name], (
            f"the {name} code changed (digest {actual}): bump {bump[name]} if what it computes changes with it, "
            f"and record {name!r}: {actual!r} in demon_lab.resources.RECORDED_SOURCES")
    assert identity.versions() == {"code_version": identity.CODE_VERSION,
                                   "generator_version": synthetic.GENERATOR_VERSION}


def test_source_digest_follows_code_not_comments_docstrings_or_layout(tmp_path):
    def digest_of(text: str) -> str:
        (tmp_path / "pkg").mkdir(exist_ok=True)
        (tmp_path / "pkg" / "net.py").write_text(text)
        return resources.source_digest(["pkg"], root=tmp_path)

    base = digest_of('"""A net."""\n\ndef f(x):\n    """Doubles."""\n    return 2 * x  # twice\n')
    assert digest_of('"""A net, documented anew."""\n\n\ndef f(x):\n    """Doubles x."""\n\n'
                     '    return 2 * x  # two times\n') == base
    assert digest_of('"""A net."""\n\ndef f(x):\n  """Doubles."""\n  return 2 * x\n') == base  # indentation width
    assert digest_of('"""A net."""\n\ndef f(x):\n    """Doubles."""\n    return 3 * x\n') != base
    assert digest_of('"""A net."""\n\ndef f(x):\n    """Doubles."""\n    return "2" * x\n') != base  # a string in code
    (tmp_path / "pkg" / "other.py").write_text("y = 1\n")
    assert digest_of('"""A net."""\n\ndef f(x):\n    """Doubles."""\n    return 2 * x  # twice\n') != base  # a new file


def test_code_other_than_the_recorded_keys_its_stages_and_runs_apart(monkeypatch):
    """An edited install (the digest of its stage or generator code is not the recorded one) never reuses a
    stage or run of the recorded code: its version carries its digest, and so do its keys."""
    cfg = _compose("scale=smoke")
    stages, run = [s.key for s in stage_dirs(settings(cfg))], identity.run_key(settings(cfg))
    for name in resources.SOURCES:
        with monkeypatch.context() as m:
            m.setitem(resources.RECORDED_SOURCES, name, "0" * 16)
            resources.versioned.cache_clear()
            version = identity.versions()[{"stage": "code_version", "generator": "generator_version"}[name]]
            assert version.endswith("+" + resources.source_digest(resources.SOURCES[name]))
            assert identity.run_key(settings(cfg)) != run
            assert all(a != b for a, b in zip([s.key for s in stage_dirs(settings(cfg))], stages, strict=True))
        resources.versioned.cache_clear()
    assert [s.key for s in stage_dirs(settings(cfg))] == stages and identity.run_key(settings(cfg)) == run
