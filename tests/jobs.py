"""Helpers of the tests that run jobs: a smoke job's overrides into a temporary store, composing a config,
the store's client, the command line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from hydra import compose, initialize_config_dir

from demon_lab.__main__ import CONF
from tests.conftest import shared_renders

ROOT = Path(__file__).resolve().parents[1]


def smoke_overrides(tmp: Path, *extra: str) -> list[str]:
    """A smoke job whose store, artifacts and stage cache lie in ``tmp``; its scenes come from the
    tests' shared render cache."""
    return ["scale=smoke", f"tracking.uri=sqlite:///{tmp}/mlflow.db", f"tracking.artifact_dir={tmp}/artifacts",
            f"cache_dir={tmp}/cache", f"data.cache_dir={shared_renders()}", *extra]


def compose_config(overrides: list[str]):
    with initialize_config_dir(CONF, version_base="1.3"):
        return compose("config", overrides=overrides)


def client(tmp: Path):
    from mlflow.tracking import MlflowClient

    return MlflowClient(tracking_uri=f"sqlite:///{tmp}/mlflow.db")


def cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "demon_lab", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=600)


# DeMoN's design at every scale (the cpu scale's profile has four priors: design=demon turns them off).
DEMON_DESIGN = ("design=demon",)


FOUR_PRIORS_OFF = ("model.flow1_prior=null", "model.dm1_prior=null", "model.flow2_prior=null", "model.dm2_prior=null")


def settings(cfg):
    """A composed config as the job's settings, which the pipeline's functions take (the job builds them
    once: :func:`demon_lab.pipeline.validate.validate`)."""
    from demon_lab.pipeline.settings import JobSettings

    return JobSettings.of(cfg)
