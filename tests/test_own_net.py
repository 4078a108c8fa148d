"""A net of one's own in a slot of the chain (model.nets.SLOT, demon_lab.nets.slots): the chain holds it,
the stages train it, the keys name its class, arguments and source from its slot's stage on and leave
every other key as it was; a bad one is refused in one line before any job starts; and the worked
example of docs/guides/your_own_net.md runs as written (slow)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from conftest import table_rows
from hydra import compose, initialize_config_dir

from demon_lab.__main__ import CONF, check
from tests.jobs import settings
from tests.test_guides import EXAMPLE, commands, files, problems, section, write

ROOT = Path(__file__).resolve().parents[1]
OWN_NET = ROOT / "docs" / "guides" / "your_own_net.md"

TINY = '''
import torch
from torch import nn

from demon_lab.nets import DepthMotion


class Tiny(nn.Module):
    def __init__(self, channels: int = 4, extra_channels: int = 7):
        super().__init__()
        self.conv = nn.Conv2d(6 + extra_channels, channels, 3, padding=1)
        self.maps = nn.Conv2d(channels, 4, 1)
        self.motion = nn.Linear(channels, 6)

    def forward(self, pair, extra):
        x = torch.relu(self.conv(torch.cat([nn.functional.avg_pool2d(pair, 4), extra], 1)))
        maps = self.maps(x)
        motion = self.motion(x.mean(dim=(2, 3)))
        return DepthMotion(maps[:, :1], maps[:, 1:], motion, torch.ones_like(motion[:, :1]))
'''


@pytest.fixture
def own_module(tmp_path, monkeypatch):
    """A module ``own_nets_<n>`` with a depth-motion net ``Tiny`` in a folder on the import path."""
    name = f"own_nets_{abs(hash(tmp_path)) % 10**8}"
    (tmp_path / f"{name}.py").write_text(textwrap.dedent(TINY))
    monkeypatch.syspath_prepend(str(tmp_path))
    return name, tmp_path / f"{name}.py"


def _compose(*overrides: str):
    with initialize_config_dir(CONF, version_base="1.3"):
        return compose("config", list(overrides))


def test_a_slot_left_null_is_in_no_key_and_a_net_of_ones_own_keys_its_stage_and_those_after(own_module):
    import demon_lab.pipeline.config  # noqa: F401  (registers the resolvers, as the app does)
    from demon_lab.pipeline.identity import run_key, semantic_config
    from demon_lab.pipeline.stages.schedule import build_chain, stage_dirs

    name, _ = own_module
    plain = _compose("scale=smoke")
    own = _compose("scale=smoke", f"+model.nets.dm1={{_target_: {name}.Tiny, channels: 3}}")
    assert "nets" not in semantic_config(settings(plain))["model"]
    keyed = semantic_config(settings(own))["model"]["nets"]
    assert keyed == {"dm1": {"class": f"{name}.Tiny", "args": {"channels": 3}, "source": keyed["dm1"]["source"]}}
    a, b = stage_dirs(settings(plain)), stage_dirs(settings(own))
    names = [d.name for d in a]
    cut = names.index("dm1")
    assert all(x.key == y.key for x, y in zip(a[:cut], b[:cut], strict=True))  # flow1 shared
    assert all(x.key != y.key for x, y in zip(a[cut:], b[cut:], strict=True))
    assert run_key(settings(plain)) != run_key(settings(own))
    chain = build_chain(settings(own))
    assert type(chain.dm1).__name__ == "Tiny" and chain.dm1.conv.out_channels == 3 and chain.plugins == ("dm1",)
    assert type(build_chain(settings(plain)).dm1).__name__ == "DepthMotionNet"


def test_an_edit_of_the_nets_file_changes_its_key(own_module):
    import importlib

    import demon_lab.pipeline.config  # noqa: F401
    from demon_lab.pipeline.stages.schedule import stage_dirs

    name, path = own_module
    override = f"+model.nets.dm1={{_target_: {name}.Tiny}}"
    before = [d.key for d in stage_dirs(settings(_compose("scale=smoke", override)))]
    path.write_text(path.read_text() + "\n# a comment is an edit too\n")
    importlib.invalidate_caches()
    sys.modules.pop(name, None)
    after = [d.key for d in stage_dirs(settings(_compose("scale=smoke", override)))]
    assert before[0] == after[0] and before[1:] != after[1:] and all(a != b for a, b in zip(before[1:], after[1:]))


@pytest.mark.parametrize("node, message", [
    ("{_target_: no_such_package.Net}", "model.nets.dm1._target_: cannot import 'no_such_package'"),
    ("{_target_: collections.OrderedDict}", "model.nets.dm1._target_: 'collections.OrderedDict' is not an nn.Module"),
    ("{_target_: MODULE.Tiny, depth: 3}", "model.nets.dm1: MODULE.Tiny(depth): got an unexpected keyword argument"),
    ("{channels: 3}", "model.nets.dm1: expected null (DeMoN's net) or a net's config with _target_"),
])
def test_a_bad_net_is_refused_in_one_line_before_the_job_starts(own_module, node, message):
    name, _ = own_module
    problem = check(["scale=smoke", f"+model.nets.dm1={node.replace('MODULE', name)}"])
    assert problem is not None and message.replace("MODULE", name) in problem and "\n" not in problem


def test_a_stage_trains_the_net_of_its_slot_and_the_chain_evaluates_with_it(own_module, tmp_path):
    """A smoke job with a net of one's own in dm1 trains it (its weights move), caches it under its stage,
    and evaluates the chain with it; the stage's weights file holds it by the slot's name."""
    from demon_lab.app.job import run
    from tests.jobs import smoke_overrides

    name, _ = own_module
    cfg = _compose(*smoke_overrides(tmp_path, "threads=1", "schedule.until=dm1", "iterations=0",
                                    f"+model.nets.dm1={{_target_: {name}.Tiny}}"))
    torch.manual_seed(0)
    from demon_lab.pipeline.stages.schedule import build_chain, stage_dirs

    untrained = build_chain(settings(cfg)).dm1.state_dict()
    threads = torch.get_num_threads()
    try:
        run(cfg)
    finally:
        torch.set_num_threads(threads)
    dm1 = next(d for d in stage_dirs(settings(cfg)) if d.name == "dm1")
    saved = dm1.load()["dm1"]
    assert saved.keys() == untrained.keys()
    assert any(not torch.equal(saved[k], untrained[k]) for k in saved)


@pytest.mark.slow
def test_the_own_net_example_runs_as_written(tmp_path):
    """The worked example of your_own_net.md as a user follows it: its files written, its commands run in
    order from one folder (a temporary MLflow store and cache); the report has both rows on every test set,
    each with a value in every column, and names the net of one's own in its Provenance."""
    example = section(OWN_NET.read_text(), EXAMPLE)
    write(files(example), tmp_path)
    assert (tmp_path / "my_nets" / "tiny_dm.py").is_file()
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path}/mlflow.db",
           "DEMON_LAB_CACHE": str(tmp_path / "cache"), "PWD": str(tmp_path)}
    for command in commands(example):
        done = subprocess.run(["bash", "-c", command], cwd=tmp_path, env=env, capture_output=True, text=True,
                              timeout=900)
        assert done.returncode == 0, f"{command}: exit {done.returncode}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    markdown = (tmp_path / "reports" / "my_dm.md").read_text()
    rows = table_rows(markdown)
    for label in ("DeMoN's dm1", "my TinyDepthMotion", "*mine minus DeMoN's*"):
        found = [r[1:] for r in rows if r[0] == label]
        assert len(found) == 2, (label, markdown)  # synthetic_sun3d and middlebury
        assert all(n == "1" and "-" not in cells for n, *cells in found), (label, found)
    assert "model.nets.dm1._target_=my_nets.tiny_dm.TinyDepthMotion" in markdown


def test_the_own_net_pages_commands_start_as_written_beside_its_files(tmp_path):
    """Every command of your_own_net.md composes and validates from the folder that holds its files."""
    text = OWN_NET.read_text()
    write(files(text), tmp_path)
    sys.path.insert(0, str(tmp_path))
    try:
        assert problems(commands(text), tmp_path) == []
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop("my_nets.tiny_dm", None)
        sys.modules.pop("my_nets", None)
