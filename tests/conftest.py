"""Shared fixtures: the real Hydra config, composed and shrunk with experiment=smoke."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
SHARED = Path(__file__).resolve().parents[2] / "shared"


def compose_config(*overrides: str) -> DictConfig:
    """Compose ``conf/config.yaml`` exactly as ``python -m pipeline`` would."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


@pytest.fixture
def smoke_cfg(tmp_path):
    """A factory: the smoke experiment writing under a temporary ``paths.runs``."""

    def make(*overrides: str) -> DictConfig:
        return compose_config("experiment=smoke", f"paths.runs={tmp_path / 'runs'}", *overrides)

    return make
