"""A run's recipe: everything in its resolved config that can change its result, but the seed.

Runs are seeds of one model only when their recipes match. Left out: the seed, settings
that only change speed or where things go (threads, device, chunk size, machine tuning,
paths, tracking), and how the model is rendered (``btf.render``: a view of the model, not
the model). Method A's settings moved under ``btf.``; older runs' spellings are read
as the new ones, so that a store holding both still pools them.

>>> recipe_id({"seed": 0, "train.lr": 0.1, "train.threads": 1}) == recipe_id(
...     {"seed": 3, "train.lr": 0.1, "train.threads": 2})
True
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Mapping

import pandas as pd

from pipeline.core.cache import canonical_json

# Settings that do not change what a run computes (up to the order of floating-point sums).
NOT_RECIPE = re.compile(
    r"^(seed|paths\..*|tracking\..*|hydra\..*|variant|btf\.render\..*"
    r"|train\.(threads|device|chunk|keep_awake|omp_spin_count|reuse_freed_memory))$"
)
_MOVED = re.compile(r"^(crop|pca|kmeans|model|sizes|interpolation)\.")


def recipe_settings(params: Mapping[str, object]) -> dict[str, str]:
    """The recipe part of flattened settings (``{"train.lr": ...}``), values as strings."""
    found = {}
    for key, value in params.items():
        key = _MOVED.sub(r"btf.\1.", key)
        if not NOT_RECIPE.match(key):
            found[key] = str(value)
    return found


def recipe_id(params: Mapping[str, object]) -> str:
    """A short hash of :func:`recipe_settings`: equal for seeds of one model."""
    text = canonical_json(recipe_settings(params))
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def recipe_suffixes(runs: pd.DataFrame, by: list[str], most: int = 3) -> pd.Series:
    """For each run, ``" [key=value, ...]"`` naming the recipe settings in which it differs
    from other runs with the same values in the columns ``by`` (say, dataset and model
    label); ``""`` where they all agree. ``runs`` has MLflow's ``params.*`` columns.

    Settings are compared where every run of the group has them (a setting added to the
    code later does not split older runs from newer ones); the seed and settings of speed
    or location are not part of a recipe.
    """
    params = [c for c in runs.columns if c.startswith("params.")]
    suffix = pd.Series("", index=runs.index)
    for _, group in runs.groupby(by, sort=False):
        settings = pd.DataFrame(
            [recipe_settings({c[len("params."):]: v for c, v in row.items() if pd.notna(v)})
             for _, row in group[params].iterrows()], index=group.index)
        shared = settings.dropna(axis=1)
        varying = [c for c in shared.columns if shared[c].nunique() > 1]
        if not varying:
            continue
        for index, row in shared[varying].iterrows():
            parts = [f"{key}={row[key]}" for key in varying[:most]]
            more = f", +{len(varying) - most} more" if len(varying) > most else ""
            suffix[index] = " [" + ", ".join(parts) + more + "]"
    return suffix
