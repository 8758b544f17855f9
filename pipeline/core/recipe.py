"""A run's recipe: everything in its resolved config that can change a number in a table.

Runs are seeds of one model only when their recipes are equal. Left out are
:data:`NOT_RECIPE` (each with its reason) and the methods' settings declared ``speed`` or
``log`` (:func:`pipeline.core.settings.setting`); everything else is in, null included.
Rendering (``btf.render.*``) has a recipe of its own (:func:`render_recipe_id`).

>>> recipe_id({"seed": 0, "train.lr": 0.1, "train.threads": 1}) == recipe_id(
...     {"seed": 3, "train.lr": 0.1, "train.threads": 2})
True
>>> recipe_id({"train.lr": None}) == recipe_id({"train.lr": 0.1})
False
"""

from __future__ import annotations

import functools
import hashlib
import logging
from collections.abc import Mapping, Sequence
from fnmatch import fnmatchcase

import pandas as pd

from pipeline.core.cache import canonical_json

log = logging.getLogger(__name__)

SPEED = "changes how fast the same numbers are computed (up to the order of float sums)"
# Glob patterns over flattened setting names (a test checks every leaf setting is here or in
# the recipe).
NOT_RECIPE: dict[str, str] = {
    "seed": "the seed: runs that differ only in it are the seeds of one model",
    "paths.*": "where files go",
    "tracking.*": "how the run is filed in MLflow (experiment, tags)",
    "method.spec": "where the code of method.name lives (method.name is in the recipe)",
    "threads": SPEED,
    "btf.render.*": "how a model is rendered: the render recipe (render_recipe_id)",
}
WHY = {"speed": SPEED, "log": "what is logged or drawn, not the model"}


@functools.cache
def _patterns() -> dict[str, str]:
    """:data:`NOT_RECIPE` and every setting a registered method declares with a role other
    than ``result`` (:func:`pipeline.core.settings.setting`), with its reason."""
    from pipeline.core.methods import registered

    declared = {
        key: WHY[role]
        for method in registered()
        for key, role in method.roles().items()
        if role != "result"
    }
    return {**NOT_RECIPE, **declared}


RENDER = "btf.render.*"
RECIPE_TAG = "tags.recipe"
RENDER_RECIPE_TAG = "tags.render_recipe"
ABSENT = "(absent)"  # a setting a run did not log: never equal to a logged value


def left_out(key: str, render: bool = False) -> bool:
    """Whether the flattened setting ``key`` is outside the recipe (``render``: the render
    recipe, which also holds ``btf.render.*``)."""
    return any(
        fnmatchcase(key, pattern) for pattern in _patterns() if not (render and pattern == RENDER)
    )


def recipe_settings(params: Mapping[str, object], render: bool = False) -> dict[str, str]:
    """The recipe part of flattened settings (``{"train.lr": ...}``), values as strings
    (``None`` as ``"None"``, as MLflow logs it); ``render`` keeps ``btf.render.*`` too."""
    return {key: str(value) for key, value in params.items() if not left_out(key, render)}


def _hash(settings: Mapping[str, str]) -> str:
    return hashlib.sha256(canonical_json(dict(settings)).encode()).hexdigest()[:12]


def recipe_id(params: Mapping[str, object]) -> str:
    """A short hash of :func:`recipe_settings`: equal for seeds of one model."""
    return _hash(recipe_settings(params))


def render_recipe_id(params: Mapping[str, object]) -> str:
    """A short hash of the recipe and the render settings (``btf.render.*``): equal for the
    renders that a render table may pool as seeds."""
    return _hash(recipe_settings(params, render=True))


def with_recipe(runs: pd.DataFrame, tag: str = RECIPE_TAG) -> pd.DataFrame:
    """``runs`` less those without the recipe ``tag`` (logged by something other than a
    job, so whether they pool as seeds cannot be checked), with one warning."""
    if runs.empty:
        return runs
    has = runs[tag].notna() if tag in runs else pd.Series(False, index=runs.index)
    if not has.all():
        log.warning(
            "%d of %d runs carry no %s tag (not logged by a job of this pipeline): "
            "left out of the tables",
            int((~has).sum()),
            len(runs),
            tag.removeprefix("tags."),
        )
    return runs[has]


def run_settings(runs: pd.DataFrame, render: bool = False) -> pd.DataFrame:
    """One row per run: its recipe settings from MLflow's ``params.*`` columns, as strings;
    :data:`ABSENT` where a run did not log a setting that another run has."""
    names = [c[len("params.") :] for c in runs.columns if c.startswith("params.")]
    kept = [n for n in names if not left_out(n, render)]
    settings = runs[[f"params.{n}" for n in kept]].astype(object)
    settings.columns = kept
    return settings.where(settings.notna(), ABSENT).astype(str)


def recipe_suffixes(
    runs: pd.DataFrame,
    by: Sequence[str],
    ignore: Sequence[str] = (),
    render: bool = False,
    most: int = 3,
) -> pd.Series:
    """For each run, ``" [key=value, ...]"`` naming the recipe settings in which it differs
    from the other runs with the same values in the columns ``by``; ``""`` where their
    recipes are equal. ``runs`` has MLflow's ``params.*``.

    Runs with the same suffix in a group have equal recipes (less ``ignore``, the table's
    own axes), so grouping by ``by`` plus the suffix pools seeds only. A setting one run
    lacks counts as a difference; when the ``most`` settings shown do not tell two recipes
    apart, the recipe's hash is added.
    """
    suffix = pd.Series("", index=runs.index, dtype=object)
    if runs.empty:
        return suffix
    settings = run_settings(runs, render).drop(columns=list(ignore), errors="ignore")
    for _, group in settings.groupby([runs[b] for b in by], sort=False, dropna=False):
        varying = [c for c in group.columns if group[c].nunique() > 1]
        if not varying:
            continue
        shown = varying[:most]
        more = f", +{len(varying) - most} more" if len(varying) > most else ""
        labels = {i: ", ".join(f"{k}={group.at[i, k]}" for k in shown) for i in group.index}
        recipes = {i: _hash(group.loc[i, varying].to_dict()) for i in group.index}
        for index in group.index:
            same_label = [i for i in group.index if labels[i] == labels[index]]
            ambiguous = len({recipes[i] for i in same_label}) > 1
            tail = f", recipe {recipes[index]}" if ambiguous else ""
            suffix[index] = f" [{labels[index]}{more}{tail}]"
    return suffix
