"""Tables 1-2 of the clustered Neural BTF paper, the interpolation table and the k verdict.

Pure functions of a DataFrame of runs (one row per MLflow run, columns ``params.*`` and
``metrics.*`` as ``mlflow.search_runs`` returns them), so that they are tested on
hand-made runs.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.btf.k_verdict import PAPER_LARGEST_K_STEP, blocked_verdict, describe
from pipeline.btf.models import models_of
from pipeline.core.recipe import (
    ABSENT,
    RECIPE_TAG,
    RENDER_RECIPE_TAG,
    run_settings,
    with_recipe,
)
from pipeline.core.report import param

SIZE_ROWS = [
    ("bytes_decoder", "decoder"),
    ("bytes_latents", "latents"),
    ("bytes_list", "list"),
    ("bytes_extra", "per-texel scale"),
    ("bytes_total", "total"),
]
INTERPOLATION_COLUMNS = [
    ("rmse_heldout_model", "held-out dirs: model"),
    ("rmse_heldout_nearest", "held-out dirs: nearest"),
    ("rmse_heldout_linear", "held-out dirs: linear"),
    ("rmse_offgrid_model", "off-grid vs truth: model"),
    ("rmse_offgrid_nearest", "off-grid vs truth: nearest"),
    ("rmse_offgrid_linear", "off-grid vs truth: linear"),
]


def _num(series: pd.Series) -> pd.Series:
    return pd.to_numeric(series, errors="coerce")


def _lights(value: str) -> str:
    return "no lights held out" if value in ("0", "None") else f"{value} lights held out"


# Settings a column label names in words, in the order they are preferred for telling two
# recipes apart (the storage types first: what the rate-distortion arms vary). Any other
# setting is named as key=value in brackets.
WORDS = {
    "btf.network.latent": lambda v: f"latent {v}",
    "model.dtype": str,
    "btf.sizes.weight_dtype": str,
    "btf.sizes.list_dtype": lambda v: f"list {v}",
    "btf.sizes.extra_dtype": lambda v: f"scale {v}",
    "model.k": lambda v: f"k = {v}",
    "model.n_components": lambda v: f"c = {v}",
    "model.match_clustered_k": lambda v: "c set by hand" if v == "None" else f"bytes of k = {v}",
    "btf.crop.size": lambda v: f"{v}² crop",
    "dataset.synthetic.size": lambda v: f"{v}² texture",
    "btf.interpolation.holdout_lights": _lights,
    "train.epochs": lambda v: f"{v} epochs",
    "train.max_steps": lambda v: "no step cap" if v == "-1" else f"{v} steps",
    "model.texel_scale": lambda v: "no scale" if v == "none" else f"scale {v}",
    "train.precision": str,
    "train.optimizer": str,
}


def distinguishing(settings: pd.DataFrame) -> list[str]:
    """The fewest columns of ``settings`` (one row per run, values as strings) whose values
    tell its distinct rows apart: greedily the column that splits the runs into the most
    groups, ties going to settings every run logged, then to those of :data:`WORDS` in
    their order. Two recipes that differ in ten correlated settings (a smoke run against a
    demo run) are told apart by one.
    """
    varying = [c for c in settings.columns if settings[c].nunique() > 1]
    if not varying:
        return []
    target = len(settings[varying].drop_duplicates())
    rank = {key: i for i, key in enumerate(WORDS)}
    chosen: list[str] = []
    while not chosen or len(settings[chosen].drop_duplicates()) < target:
        best = max(
            (c for c in varying if c not in chosen),
            key=lambda c: (
                len(settings[[*chosen, c]].drop_duplicates()),
                not (settings[c] == ABSENT).any(),
                -rank.get(c, len(rank)),
                -len(c),
            ),
        )
        chosen.append(best)
    return sorted(chosen, key=lambda c: (rank.get(c, len(rank)), c))


def in_words(values: pd.Series, absent: bool = False) -> str:
    """``" (latent 2, float16) [train.lr=0.01]"``: settings (name -> value) in words where
    :data:`WORDS` has them, the others as key=value; a setting the run did not log
    (:data:`ABSENT`) is left out, or with ``absent`` said to be."""
    logged = values[values != ABSENT]
    worded = [WORDS[k](v) for k, v in logged.items() if k in WORDS]
    plain = [f"{k}={v}" for k, v in logged.items() if k not in WORDS]
    plain += [f"{k} not logged" for k in values.index[values == ABSENT]] if absent else []
    return (f" ({', '.join(worded)})" if worded else "") + (
        f" [{', '.join(plain)}]" if plain else ""
    )


def recipe_labels(runs: pd.DataFrame, by: list[str], ignore=(), render: bool = False) -> pd.Series:
    """For each run, what tells its recipe apart from the other recipes with the same
    values in the columns ``by`` (say, dataset and model label), in words
    (:func:`in_words` of :func:`distinguishing`); ``""`` where the group has one recipe.

    Runs with equal labels in a group have equal recipes, less the settings in ``ignore``
    (the table's own axis, such as ``model.k``): grouping by ``by`` plus the label pools
    seeds only. Where the logged settings are equal but the recipe tags are not (``recipe``,
    or ``render_recipe`` with ``render``), the tag's first 6 characters are added: the one
    case a hash says more than words.
    """
    labels = pd.Series("", index=runs.index, dtype=object)
    if runs.empty:
        return labels
    tag = RENDER_RECIPE_TAG if render else RECIPE_TAG
    settings = run_settings(runs, render).drop(columns=list(ignore), errors="ignore")
    for _, group in settings.groupby([runs[b] for b in by], sort=False, dropna=False):
        keys = distinguishing(group)
        if keys:
            for index in group.index:
                labels[index] = in_words(group.loc[index, keys])
        if keys and labels[group.index].nunique() < len(group[keys].drop_duplicates()):
            # Only a setting some run did not log tells them apart: name it after all.
            for index in group.index:
                labels[index] = in_words(group.loc[index, keys], absent=True)
        if tag in runs and not ignore:
            tags = runs.loc[group.index, tag].astype(str)
            for _, same in tags.groupby(labels[group.index]):
                if same.nunique() > 1:
                    for index in same.index:
                        labels[index] += f" recipe {tags[index][:6]}"
    return labels


def label_runs(runs: pd.DataFrame, render: bool = False) -> pd.DataFrame:
    """Add ``dataset``, ``model`` (column label), ``k`` and ``seed`` columns.

    The dataset label is the preset's name (``synthetic:<material>`` for the built-in
    BTF, ``ubo2003:<folder>`` for a generic layout) with the crop and the direction count.

    The model label is the paper's column (``Neural BTF``, ``k = <k>``), marked ``+scale``,
    ``(rep. target)``, ``(bfloat16)`` or ``(<E> epochs)`` where the run's settings differ
    from the defaults (the epochs: from most runs of its dataset). Runs with one label are
    seeds of one model only when their recipes are equal (:mod:`pipeline.core.recipe`);
    where they are not, each label gets the settings in which its runs differ (``render``:
    the render settings count too). Runs without a recipe tag are left out.
    """
    runs = with_recipe(runs, RENDER_RECIPE_TAG if render else RECIPE_TAG).copy()
    if runs.empty:
        return runs.assign(
            dataset=[], model=[], base_model=[], family=[], k=[], seed=[], epochs=[], order=[]
        )
    root = param(runs, "dataset.root")
    name = param(runs, "dataset.name", "?")
    leaf = root.map(lambda r: r.rstrip("/").split("/")[-1] if r not in ("", "None") else "")
    # Generic formats are told apart by their folder; presets (WOOL, ...) by their name.
    generic = name.isin(["ubo2003", "utia"]) & (leaf != "")
    label = pd.Series(np.where(generic, name + ":" + leaf, name), index=runs.index)
    material = param(runs, "dataset.synthetic.material")
    label = label.where(name != "synthetic", label + ":" + material)
    # The same source cropped or subset differently is a different dataset: a 12 x 12
    # smoke crop must never be averaged with a 48 x 48 one.
    crop = _num(param(runs, "btf.crop.size"))
    n_dirs = _num(runs.get("metrics.n_directions", pd.Series(np.nan, index=runs.index)))
    shape = [
        f" {int(c)}²×{int(n)}" if pd.notna(c) and pd.notna(n) else ""
        for c, n in zip(crop, n_dirs, strict=True)
    ]
    runs["dataset"] = label + shape
    runs["k"] = _num(param(runs, "model.k"))
    runs["seed"] = _num(runs["params.seed"])
    models = models_of(runs)
    columns, sizes = [], []
    for m, (_, run) in zip(models, runs.iterrows(), strict=True):
        columns.append(m.column(run) if m else "?")
        sizes.append(_num(pd.Series([run.get(m.size[0]) if m else None])).iloc[0])
    label = pd.Series(columns, index=runs.index)
    # Only the clustered model has these settings: absent elsewhere, so at their defaults.
    scale = param(runs, "model.texel_scale", "none")
    label = np.where(scale != "none", label + " +scale", label)
    target = param(runs, "model.target", "texel")
    label = np.where(target == "representative", label + " (rep. target)", label)
    # The decoder's products in bfloat16 (train.precision) give other numbers.
    precision = param(runs, "train.precision", "float32")
    label = np.where(precision == "float32", label, label + " (" + precision + ")")
    # A run trained for another number of epochs than most runs of its dataset (say, a 4x
    # longer convergence check) is another model, not another seed.
    # PCA trains nothing and logs no train.* (its "" is left out of the usual count).
    epochs = param(runs, "train.epochs", "").replace("None", "")
    usual = (
        epochs.where(epochs != "")
        .groupby(runs["dataset"])
        .transform(lambda e: e.mode().iloc[0] if e.notna().any() else "")
    )
    runs["base_model"] = label
    runs["epochs"] = _num(epochs)
    label = np.where((epochs != "") & (epochs != usual), label + " (" + epochs + " epochs)", label)
    runs["model"] = label
    # A clustered family (Table 2's k columns of one recipe but k), for the k verdict.
    clustered = runs["model"].str.replace(r"^k = \d+", "clustered", regex=True)
    runs["family"] = np.where(_clusters(runs), clustered, "")
    runs["family"] = runs["family"] + recipe_labels(
        runs, ["dataset", "family"], ignore=["model.k"], render=render
    )
    runs["model"] = runs["model"] + recipe_labels(runs, ["dataset", "model"], render=render)
    runs["order"] = [
        1e9 * (m.rank if m else 9) + (0 if pd.isna(s) else s)
        for m, s in zip(models, sizes, strict=True)
    ]
    return runs


def column_recipes(runs: pd.DataFrame) -> pd.DataFrame:
    """One row per column of labelled runs (dataset, model label): its recipe tag, its
    runs, and every setting in which it differs from the other columns of its model
    (``base_model``), where its label names only the fewest that tell them apart."""
    if runs.empty:
        return pd.DataFrame(columns=["dataset", "model", "recipe", "runs", "differs in"])
    settings = run_settings(runs)
    rows = []
    for (dataset, _), group in runs.groupby(["dataset", "base_model"], sort=False):
        of_group = settings.loc[group.index]
        varying = sorted(c for c in of_group.columns if of_group[c].nunique() > 1)
        for model, of_model in group.groupby("model", sort=False):
            first = of_model.index[0]
            rows.append(
                {
                    "dataset": dataset,
                    "model": model,
                    "recipe": of_model[RECIPE_TAG].iloc[0],
                    "runs": len(of_model),
                    "differs in": ", ".join(f"{k}={of_group.at[first, k]}" for k in varying),
                }
            )
    return pd.DataFrame(rows)


def _clusters(runs: pd.DataFrame) -> pd.Series:
    """Whether each run's model clusters (Table 2's k columns)."""
    return pd.Series([m is not None and m.clusters for m in models_of(runs)], index=runs.index)


def drop_repeats(runs: pd.DataFrame) -> pd.DataFrame:
    """Keep one run per computation: a rerun of the same job (all its stages cache hits)
    records the same result again and must not count as another seed."""
    key = pd.Series(runs["run_id"], index=runs.index, dtype=object)
    for tag in ("tags.cache.linear", "tags.cache.evaluate"):
        if tag in runs:
            key = runs[tag].where(runs[tag].notna(), key)
    return runs.loc[~key.duplicated()]


def model_columns(runs: pd.DataFrame) -> list[str]:
    """The model labels of labelled runs in the paper's column order (Neural BTF, k, PCA)."""
    return list(runs.sort_values(["order", "model"]).drop_duplicates("model")["model"])


PARTS = ("decoder", "latents", "list", "extra")  # Table 1's parts (tags stored_as.<part>)


def stored_as(run: pd.Series) -> str:
    """``"decoder float32, latents float32, list int32"``: the types a run's parts were
    written in (tags ``stored_as.*``, read from the stored tensors), "?" when not logged."""
    parts = [
        f"{dict(SIZE_ROWS)[f'bytes_{p}']} {run[f'tags.stored_as.{p}']}"
        for p in PARTS
        if pd.notna(run.get(f"tags.stored_as.{p}"))
    ]
    return ", ".join(parts) or "?"


def scale_bytes(run: pd.Series) -> int:
    """The bytes a per-texel scale adds to a clustered run that did not store one: one
    ``btf.sizes.extra_dtype`` value per texel."""
    from pipeline.btf.evaluate import DTYPE_BYTES

    dtype = str(run.get("params.btf.sizes.extra_dtype", "float32"))
    return int(float(run["metrics.n_texels"])) * DTYPE_BYTES[dtype]


def table_sizes(runs: pd.DataFrame) -> pd.DataFrame:
    """Table 1: exact bytes per dataset and model, the types they are stored in, and the
    compression ratios.

    A clustered model evaluated with a per-texel scale it does not store (the graininess
    table's "with scale" RMSE) gets a row of its own, ``<model> + per-texel scale``, with
    the scale's bytes. Ratio conventions: ``ratio (exact)`` = original bytes / total bytes;
    ``ratio (paper)`` = original in MB (2^20 B, rounded to 1 MB) / total in KB (2^10 B,
    rounded to 1 KB), which reproduces the paper's 1:1885, 1:5127, 1:4633, 1:3904.
    """
    rows = []
    needed = [f"metrics.{m}" for m, _ in SIZE_ROWS] + ["metrics.bytes_original"]
    if any(column not in runs for column in needed):
        return pd.DataFrame()
    runs = runs.assign(_clusters=_clusters(runs))
    for (dataset, model), group in runs.groupby(["dataset", "model"], sort=False):
        group = group.dropna(subset=needed)
        if group.empty:
            continue
        first = group.iloc[0]
        parts = {name: int(first[f"metrics.{metric}"]) for metric, name in SIZE_ROWS}
        original = float(first["metrics.bytes_original"])
        rows.append(_size_row(dataset, model, parts, original, stored_as(first)))
        if (
            first["_clusters"]
            and parts["per-texel scale"] == 0
            and pd.notna(first.get("metrics.rmse_with_texel_scale"))
            and pd.notna(first.get("metrics.n_texels"))
        ):
            extra = scale_bytes(first)
            scaled = {**parts, "per-texel scale": extra, "total": parts["total"] + extra}
            dtype = first.get("params.btf.sizes.extra_dtype", "float32")
            stored = f"{stored_as(first)}, per-texel scale {dtype}"
            rows.append(_size_row(dataset, f"{model} + per-texel scale", scaled, original, stored))
    table = pd.DataFrame(rows)
    if table.empty:
        return table
    order = {m: i for i, m in enumerate(model_columns(runs))}
    table["_order"] = table["model"].map(
        lambda m: order.get(m, order.get(m.removesuffix(" + per-texel scale"), 0) + 0.5)
    )
    table = table.sort_values(["dataset", "_order"]).drop(columns="_order")
    return table.reset_index(drop=True)


def _size_row(dataset: str, model: str, parts: dict, original: float, stored: str) -> dict:
    total = parts["total"]
    return {
        "dataset": dataset,
        "model": model,
        **{f"{k} [B]": v for k, v in parts.items()},
        "original [B]": int(original),
        "stored as": stored,
        "ratio (exact)": f"1:{original / total:.1f}",
        "ratio (paper)": f"1:{round(original / 2**20) * 1024 / round(total / 1024):.0f}",
    }


# What a scale changes: runs equal in every other recipe setting are one model with and
# without it (and with another k, the scale's bytes spent on clusters).
SCALE_SETTINGS = ["model.k", "model.texel_scale", "btf.sizes.extra_dtype"]


def table_graininess(runs: pd.DataFrame) -> pd.DataFrame:
    """The graininess fix at equal bytes: each clustered model's RMSE without and with a
    per-texel scale, the bytes of each, and the unscaled model of the same recipe but k
    whose total bytes are nearest to the scaled one's, with its RMSE: does the scale beat
    spending its bytes on more clusters? Mean ± std over seeds.

    Every RMSE here is over all the crop's directions, as Table 2's. A model that stores its
    scale has it in ``bytes_total``; its "bytes" are those without it.
    """
    clustered = runs[
        _clusters(runs)
        & runs.get("metrics.rmse_with_texel_scale", pd.Series(np.nan, index=runs.index)).notna()
    ]
    if clustered.empty or "metrics.bytes_total" not in runs:
        return pd.DataFrame()
    extra = _num(runs.get("metrics.bytes_extra", pd.Series(0, index=runs.index))).fillna(0)
    rest = run_settings(runs).drop(columns=SCALE_SETTINGS, errors="ignore")
    recipe_but_scale = rest.apply("\x1f".join, axis=1)
    unscaled = runs[_clusters(runs) & (extra == 0)].assign(
        _rest=recipe_but_scale, _rmse=_num(runs["metrics.rmse"])
    )
    rows = []
    ordered = clustered.sort_values(["dataset", "order", "model"])
    for (dataset, model), group in ordered.groupby(["dataset", "model"], sort=False):
        first = group.iloc[0]
        stored_extra = int(extra[first.name])
        without = int(first["metrics.bytes_total"]) - stored_extra
        with_scale = without + (stored_extra or scale_bytes(first))
        row = {
            "dataset": dataset,
            "model": model,
            "without scale": mean_std(_num(group["metrics.rmse_without_texel_scale"])),
            "bytes": without,
            "with per-texel scale": mean_std(_num(group["metrics.rmse_with_texel_scale"])),
            "bytes with scale": with_scale,
        }
        others = unscaled[
            (unscaled["dataset"] == dataset)
            & (unscaled["_rest"] == recipe_but_scale[first.name])
            & (unscaled["k"] != first["k"])
        ]
        if not others.empty:
            sizes = others.groupby("model")["metrics.bytes_total"].first()
            nearest = (sizes - with_scale).abs().idxmin()
            row["nearest in bytes, no scale"] = nearest
            row["its bytes"] = int(sizes[nearest])
            row["its RMSE"] = mean_std(others.loc[others["model"] == nearest, "_rmse"])
        rows.append(row)
    return pd.DataFrame(rows)


def mean_std(values: pd.Series) -> str:
    """``"mean ± std (n=…)"`` of the values (sample std), or the value with n=1, or "–"."""
    values = values.dropna()
    if values.empty:
        return "–"
    if len(values) == 1:
        return f"{values.iloc[0]:.4f} (n=1)"
    return f"{values.mean():.4f} ± {values.std(ddof=1):.4f} (n={len(values)})"


def table_rmse(runs: pd.DataFrame, metric: str = "rmse") -> pd.DataFrame:
    """Table 2: RMSE per dataset (rows) x model (columns), mean ± std over seeds (n)."""
    columns = model_columns(runs)
    table = runs.pivot_table(
        index="dataset", columns="model", values=f"metrics.{metric}", aggfunc=mean_std
    )
    table = table.reindex(columns=[c for c in columns if c in table.columns])
    return table.fillna("–")  # no run of that model on that dataset


def with_truth_floor(table: pd.DataFrame, runs: pd.DataFrame) -> pd.DataFrame:
    """Table 2 with a first column ``data vs truth``: the data's own RMSE against the
    built-in generator's analytic truth (``metrics.rmse_data_vs_truth``), the score of a
    model that recovers the truth exactly (not a lower bound: fitting the data's rounding
    noise scores below it); "–" for measured data, which has no truth."""
    column = "metrics.rmse_data_vs_truth"
    if column not in runs or runs[column].isna().all():
        return table
    floors = _num(runs[column]).groupby(runs["dataset"]).agg(["min", "max"])
    cell = {
        d: "–" if pd.isna(lo) else f"{lo:.4f}" if hi - lo < 5e-5 else f"{lo:.4f}–{hi:.4f}"
        for d, (lo, hi) in floors.iterrows()
    }
    table = table.copy()
    table.insert(0, "data vs truth", [cell.get(d, "–") for d in table.index])
    return table


def failed_runs(runs: pd.DataFrame, near: float = 0.9) -> pd.DataFrame:
    """Runs whose RMSE is within ``1 - near`` of the mean-ABRDF baseline or above it: the
    model learnt next to nothing."""
    if "metrics.rmse_mean_abrdf" not in runs:
        return pd.DataFrame()
    ratio = _num(runs["metrics.rmse"]) / _num(runs["metrics.rmse_mean_abrdf"])
    failed = runs[ratio >= near]
    return pd.DataFrame(
        {
            "dataset": failed["dataset"],
            "model": failed["model"],
            "seed": failed["seed"],
            "RMSE": failed["metrics.rmse"].round(4),
            "mean-ABRDF baseline": failed["metrics.rmse_mean_abrdf"].round(4),
            "ratio": ratio[failed.index].round(2),
            "run": failed["run_id"],
        }
    ).reset_index(drop=True)


def learning_rates(runs: pd.DataFrame) -> str:
    """``"Neural BTF: 0.05; k = 500: 0.08"``: each trained column's learning rate
    (``train.lr``, or the model's ``model.lr`` where ``train.lr`` is null)."""
    train = runs.get("params.train.lr", pd.Series(None, index=runs.index))
    model_lr = runs.get("params.model.lr", pd.Series(None, index=runs.index))
    rate = train.where(~train.isin([None, "None"]) & train.notna(), model_lr)
    trains = pd.Series([m is not None and m.trains for m in models_of(runs)], index=runs.index)
    trained = runs.assign(rate=rate)[rate.notna() & ~rate.isin(["None"]) & trains]
    parts = [
        f"{model}: {', '.join(sorted(map(str, group['rate'].unique())))}"
        for model, group in trained.sort_values(["order", "model"]).groupby("model", sort=False)
    ]
    return "; ".join(parts)


def table_interpolation(runs: pd.DataFrame) -> pd.DataFrame:
    """RMSE at directions training never saw: model vs nearest and linear interpolation."""
    present = [(m, n) for m, n in INTERPOLATION_COLUMNS if f"metrics.{m}" in runs]
    if not present:
        return pd.DataFrame()
    rows = []
    ordered = runs.sort_values(["dataset", "order", "model"])
    for (dataset, model), group in ordered.groupby(["dataset", "model"], sort=False):
        row = {"dataset": dataset, "model": model}
        for metric, name in present:
            row[name] = mean_std(_num(group[f"metrics.{metric}"]))
        rows.append(row)
    return pd.DataFrame(rows)


def k_verdict(
    runs: pd.DataFrame, alpha: float = 0.05, target: float = PAPER_LARGEST_K_STEP
) -> pd.DataFrame:
    """Does k change the error beyond the seed-to-seed spread? (:mod:`pipeline.btf.k_verdict`)

    For each dataset and clustered model family (runs whose labels differ only in k: the
    same recipe otherwise), the seeds run at every k are the blocks of a two-way ANOVA
    without interaction, checked by Friedman's rank test, with the trend against log k,
    each step's effect with its 95 % interval and, without evidence, the power.
    """
    rows = []
    clustered = runs[_clusters(runs)]
    for (dataset, name), group in clustered.groupby(["dataset", "family"]):
        table = group.pivot_table(
            index="seed", columns="k", values="metrics.rmse", aggfunc="mean"
        ).dropna()
        row = {
            "dataset": dataset,
            "model": name,
            "k values": ", ".join(str(int(k)) for k in sorted(group["k"].unique())),
        }
        if table.shape[0] < 2 or table.shape[1] < 2:
            row["verdict"] = (
                "not enough runs: need >= 2 seeds, each run at every one of "
                ">= 2 values of k (complete blocks)"
            )
        else:
            table.columns = [int(k) for k in table.columns]
            row.update(describe(blocked_verdict(table, alpha, target), alpha, target))
        rows.append(row)
    return pd.DataFrame(rows)


def table_convergence(runs: pd.DataFrame, tolerance: float = 0.05) -> pd.DataFrame:
    """Is a model converged? Its RMSE against the same model and seed trained longest.

    One row per (dataset, model, seed, epochs) that has a longer run beside it: the RMSE of
    both, how many times longer the reference trained, and the excess of the shorter run's
    RMSE over the reference's, judged against ``tolerance`` (0.05 = within 5 %).
    """
    if "epochs" not in runs or runs["epochs"].isna().all():
        return pd.DataFrame()
    rows = []
    ordered = runs.sort_values(["dataset", "order", "base_model", "seed", "epochs"])
    for (dataset, model, seed), group in ordered.groupby(
        ["dataset", "base_model", "seed"], sort=False
    ):
        rmse = _num(group["metrics.rmse"]).groupby(group["epochs"]).mean().dropna()
        if len(rmse) < 2:
            continue
        longest = rmse.index.max()
        for epochs, value in rmse.drop(longest).items():
            excess = value / rmse[longest] - 1
            rows.append(
                {
                    "dataset": dataset,
                    "model": model,
                    "seed": int(seed),
                    "epochs": int(epochs),
                    "RMSE": f"{value:.4f}",
                    "reference epochs": int(longest),
                    "reference RMSE": f"{rmse[longest]:.4f}",
                    "length ratio": f"{longest / epochs:g}",
                    "excess": f"{100 * excess:+.1f} %",
                    f"within {100 * tolerance:g} %": bool(abs(excess) <= tolerance),
                }
            )
    return pd.DataFrame(rows)


def missing_runs(runs: pd.DataFrame, ks: list[int]) -> list[str]:
    """The paper grid cells (Neural BTF and each k, per dataset) with no finished run,
    and cells with fewer than two seeds (no spread can be measured)."""
    notes = []
    for dataset, group in runs.groupby("dataset"):
        for model in ["Neural BTF"] + [f"k = {k}" for k in ks]:
            n = int((group["model"] == model).sum())
            if n == 0:
                notes.append(f"{dataset}: no run of {model}")
            elif n == 1:
                notes.append(f"{dataset}: {model} has 1 seed (no seed spread)")
    return notes
