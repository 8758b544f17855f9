"""Plain helpers shared by the tests (fixtures live in ``conftest.py``).

Tests import from here (``from helpers import compose_config``): pytest's default
"prepend" import mode puts ``tests/`` (a folder without ``__init__.py``) at the front of
``sys.path`` before it imports a test module, so ``helpers`` is found there.
"""

from __future__ import annotations

from pathlib import Path

from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

ROOT = Path(__file__).resolve().parents[1]  # the repository
CONF_DIR = ROOT / "conf"
SHARED = ROOT.parent / "shared"  # real datasets, where the checkout has them


def compose_config(*overrides: str, return_hydra_config: bool = False) -> DictConfig:
    """Compose ``conf/config.yaml`` exactly as ``python -m pipeline`` would (with the
    ``hydra`` section too if asked: its sweeper's parameters, for instance)."""
    from pipeline.core.methods import register_schemas

    register_schemas()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides),
                       return_hydra_config=return_hydra_config)


def recipe_tags(params: dict) -> dict[str, str]:
    """The ``recipe`` and ``render_recipe`` tags a job with these flattened settings logs
    (:func:`pipeline.core.tracking.job_run`): hand-made runs need them to be tabled."""
    from pipeline.core.recipe import recipe_id, render_recipe_id

    return {"recipe": recipe_id(params), "render_recipe": render_recipe_id(params)}
