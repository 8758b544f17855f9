"""Rate-distortion of method A: which model, at which setting, has the lowest error at a
byte budget (``experiment=rate_distortion``)?

A **point** is one recipe (:mod:`pipeline.core.recipe`) on one dataset: its seeds pooled
(mean ± sample std of ``rmse``, n seeds) at its ``bytes_total`` (Table 1's bytes, equal for
every seed). Runs of different recipes are never one point. An **arm** is a method and the
types it stores (``PCA (float16)``, ``clustered (float32, list uint16, +scale float16)``,
``Neural BTF (float32)``); a **line** joins the points of an arm that differ only in the
arm's size setting (PCA's components, clustered's k, Neural BTF's latent size), other recipe
differences naming the line apart (:func:`pipeline.btf.tables.recipe_labels`).

What the report gives, per dataset: RMSE against bytes (log x) with the Pareto front, the
best point at each budget against the best point of another method (is the win beyond the
seeds' noise?), and the bytes each line needs to reach a few RMSE levels.

Pure functions of labelled runs (:func:`pipeline.btf.tables.label_runs`), tested on
hand-made runs; :func:`section` writes the files.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from pipeline.btf.models import MODELS, models_of
from pipeline.btf.tables import recipe_labels
from pipeline.core.recipe import RECIPE_TAG
from pipeline.core.report import param, safe_stem, save_figure, write_file, write_table

BUDGETS_KB = (64, 128, 256, 512)  # KB = 1024 bytes, as Table 1's; tables.budgets_kb sets them
N_LEVELS = 4  # RMSE levels of the bytes-to-reach table, per dataset
# Mean RMSEs closer than this are a tie, which the fewer bytes win (the front and the best
# at a budget): a model stored in float16 differs from its float32 copy by rounding alone
# (far below this; docs/results.md has the measured gaps), and at twice the bytes that is
# no win.
RMSE_TIE = 1e-5


def _num(series: pd.Series) -> pd.Series:
    return pd.to_numeric(series, errors="coerce")


def arms(runs: pd.DataFrame) -> pd.DataFrame:
    """Labelled runs with ``arm`` (method and storage types), ``setting`` (``c = 4``,
    ``k = 500``, ``latent 8``), ``size`` (that number) and ``line`` (the arm plus the recipe
    settings, other than the size setting, in which its runs differ)."""
    runs = runs.copy()
    models = models_of(runs)
    arm, size = [], []
    for m, (_, run) in zip(models, runs.iterrows(), strict=True):
        arm.append(f"{m.title} ({m.stored_types(run)})" if m else "? (?)")
        value = run.get(m.size[0]) if m else None
        size.append(_num(pd.Series([value])).iloc[0])
    runs["arm"] = arm
    runs["size"] = size
    runs["setting"] = [
        (m.size[1] if m else "") + ("?" if pd.isna(v) else str(int(v)))
        for m, v in zip(models, size, strict=True)
    ]
    runs["line"] = runs["arm"]
    names = pd.Series([m.name if m else None for m in models], index=runs.index)
    for model in MODELS.values():
        rows = names == model.name
        if rows.any():
            runs.loc[rows, "line"] = runs.loc[rows, "arm"] + recipe_labels(
                runs[rows], ["dataset", "arm"], ignore=model.size_settings
            )
    return runs


def points(runs: pd.DataFrame) -> pd.DataFrame:
    """One row per (dataset, recipe) of labelled runs that logged ``rmse`` and
    ``bytes_total``: dataset, method, arm, line, setting, size, bytes, rmse_mean, rmse_std
    (sample std; NaN for one seed), n (seeds), seeds, rmse_mean_abrdf, heldout (lights
    held out of training: that RMSE is over the training directions only)."""
    needed = ["metrics.rmse", "metrics.bytes_total", "params.model.name", RECIPE_TAG]
    if runs.empty or any(column not in runs for column in needed):
        return pd.DataFrame()
    runs = runs.dropna(subset=["metrics.rmse", "metrics.bytes_total"])
    if runs.empty:
        return pd.DataFrame()
    runs = arms(runs)
    baseline = runs.get("metrics.rmse_mean_abrdf", pd.Series(np.nan, index=runs.index))
    runs = runs.assign(
        _baseline=_num(baseline),
        _heldout=_num(param(runs, "btf.interpolation.holdout_lights", "0")),
    )
    rows = []
    for (dataset, _), group in runs.groupby(["dataset", RECIPE_TAG], sort=False):
        first = group.iloc[0]
        rmse = _num(group["metrics.rmse"])
        rows.append(
            {
                "dataset": dataset,
                "method": first["params.model.name"],
                "arm": first["arm"],
                "line": first["line"],
                "setting": first["setting"],
                "size": first["size"],
                "bytes": int(round(_num(group["metrics.bytes_total"]).mean())),
                "rmse_mean": float(rmse.mean()),
                "rmse_std": float(rmse.std(ddof=1)) if len(rmse) > 1 else np.nan,
                "n": len(rmse),
                "seeds": ",".join(str(int(s)) for s in sorted(group["seed"])),
                "rmse_by_seed": dict(
                    zip(group["seed"].astype(int), rmse.astype(float), strict=True)
                ),
                "rmse_mean_abrdf": float(group["_baseline"].mean()),
                "heldout": bool((group["_heldout"].fillna(0) > 0).any()),
            }
        )
    table = pd.DataFrame(rows)
    table["label"] = table["line"] + " " + table["setting"]
    return table.sort_values(["dataset", "line", "bytes"]).reset_index(drop=True)


def pareto_front(points_of_dataset: pd.DataFrame, tie: float = RMSE_TIE) -> pd.Series:
    """True for the points no other point beats in both bytes and mean RMSE: going up in
    bytes, a point is on the front when its mean RMSE is lower than every smaller point's
    by more than ``tie`` (:data:`RMSE_TIE`)."""
    ordered = points_of_dataset.sort_values(["bytes", "rmse_mean"])
    best = np.inf
    front = pd.Series(False, index=points_of_dataset.index)
    for index, rmse in ordered["rmse_mean"].items():
        if rmse < best - tie:
            front[index] = True
            best = rmse
    return front


def lowest(points_of_dataset: pd.DataFrame, tie: float = RMSE_TIE) -> pd.Series:
    """The point with the lowest mean RMSE, the one with the fewest bytes among those within
    ``tie`` of it (:data:`RMSE_TIE`)."""
    near = points_of_dataset[
        points_of_dataset["rmse_mean"] <= points_of_dataset["rmse_mean"].min() + tie
    ]
    return near.loc[near["bytes"].idxmin()]


def welch_interval(
    a: pd.Series, b: pd.Series, alpha: float = 0.05
) -> tuple[float, float, float] | None:
    """Difference of means ``b - a`` of two points with its (1 - alpha) Welch interval, from
    rows with rmse_mean, rmse_std and n; None when a point has a single seed (no spread)."""
    from scipy import stats

    if a["n"] < 2 or b["n"] < 2:
        return None
    difference = b["rmse_mean"] - a["rmse_mean"]
    va, vb = a["rmse_std"] ** 2 / a["n"], b["rmse_std"] ** 2 / b["n"]
    se = np.sqrt(va + vb)
    if se == 0:  # no spread on either side: the difference is exact
        return difference, difference, difference
    df = (va + vb) ** 2 / (va**2 / (a["n"] - 1) + vb**2 / (b["n"] - 1))
    half = stats.t.ppf(1 - alpha / 2, df) * se
    return difference, difference - half, difference + half


def best_at_budgets(
    table: pd.DataFrame, budgets_kb=BUDGETS_KB, alpha: float = 0.05
) -> pd.DataFrame:
    """Per dataset and budget: the point with the lowest mean RMSE among those with at most
    the budget's bytes (:func:`lowest`: a tie goes to the fewer bytes), and the best point
    of every other method within the budget, with the difference of means, its Welch
    interval and whether the win is beyond seed noise (the interval excludes 0). Since the
    best is chosen among ``arms compared`` points by the seeds that score it, the row also
    gives the arm chosen on one seed and its RMSE on the others
    (:func:`selected_on_one_seed`)."""
    rows = []
    level = f"{100 * (1 - alpha):g} %"
    for dataset, group in table.groupby("dataset", sort=False):
        for kb in budgets_kb:
            budget = int(kb) * 1024
            row = {"dataset": dataset, "budget [KB]": int(kb), "budget [B]": budget}
            fits = group[group["bytes"] <= budget]
            if fits.empty:
                smallest = group.loc[group["bytes"].idxmin()]
                row["best"] = f"nothing fits (smallest: {smallest['label']}, {smallest['bytes']} B)"
                rows.append(row)
                continue
            best = lowest(fits)
            row |= {
                "best": best["label"],
                "method": best["method"],
                "bytes": int(best["bytes"]),
                "RMSE mean": best["rmse_mean"],
                "RMSE std": best["rmse_std"],
                "seeds": int(best["n"]),
                "arms compared": len(fits),
            }
            row |= selected_on_one_seed(fits)
            others = fits[fits["method"] != best["method"]]
            if others.empty:
                row["verdict"] = "no other method fits this budget"
                rows.append(row)
                continue
            other = lowest(others)
            row |= {
                "best other method": other["label"],
                "its bytes": int(other["bytes"]),
                "its RMSE mean": other["rmse_mean"],
                "its RMSE std": other["rmse_std"],
                "its seeds": int(other["n"]),
                "difference": other["rmse_mean"] - best["rmse_mean"],
            }
            found = welch_interval(best, other, alpha)
            if found is None:
                row["verdict"] = "untested: a point has 1 seed (run seed=0,1,2)"
            else:
                _, low, high = found
                row[f"{level} interval"] = f"[{low:.4g}, {high:.4g}]"
                row["verdict"] = "wins beyond seed noise" if low > 0 else "within seed noise"
            rows.append(row)
    table = pd.DataFrame(rows)
    floats = table.select_dtypes("float").columns
    table[floats] = table[floats].round(6)
    return table


def selected_on_one_seed(fits: pd.DataFrame) -> dict:
    """The best of many arms is chosen by the same seeds it is scored on, so its mean is
    biased low (the more arms, the more). The honest figure: choose on one seed, score on
    the others. Among the arms with the lowest seed any arm has and at least one more:
    the arm with the lowest RMSE on that seed (``chosen on one seed``, with ``the seed``
    and ``chosen among`` arms) and its mean RMSE over its other seeds (``its RMSE on the
    other seeds``); {} when no arm has two seeds."""
    by_seed = [dict(seeds) for seeds in fits["rmse_by_seed"]]
    usable = [i for i, seeds in enumerate(by_seed) if len(seeds) >= 2]
    if not usable:
        return {}
    first = min(min(by_seed[i]) for i in usable)
    among = [i for i in usable if first in by_seed[i]]
    choice = min(among, key=lambda i: by_seed[i][first])
    rest = [value for seed, value in by_seed[choice].items() if seed != first]
    return {
        "chosen on one seed": fits.iloc[choice]["label"],
        "the seed": first,
        "chosen among": len(among),
        "its RMSE on the other seeds": float(np.mean(rest)),
    }


def winners(budget: pd.DataFrame) -> pd.DataFrame:
    """The budget table (:func:`best_at_budgets`) read across datasets: one row per budget,
    one column per dataset, each cell the best point with its mean RMSE, and how far the
    best point of another method is behind it with the verdict."""

    def cell(row) -> str:
        if pd.isna(row.get("method")):
            return "nothing fits"
        text = f"{row['best']}: {row['RMSE mean']:.4f}"
        if pd.isna(row.get("best other method")):
            return f"{text} ({row['verdict']})"
        verdict = row["verdict"].split(":")[0]  # "untested: a point has 1 seed ...": untested
        return f"{text}; {row['best other method']} +{row['difference']:.4f} ({verdict})"

    cells = budget.assign(cell=budget.apply(cell, axis=1))
    table = cells.pivot(index="budget [KB]", columns="dataset", values="cell")
    table = table[list(dict.fromkeys(budget["dataset"]))].reset_index()
    table.columns.name = None
    return table


def rmse_levels(group: pd.DataFrame, count: int = N_LEVELS) -> list[float]:
    """``count`` RMSE levels between a dataset's worst and best mean RMSE (geometric,
    endpoints left out), at two significant digits."""
    low, high = group["rmse_mean"].min(), group["rmse_mean"].max()
    if not (np.isfinite(low) and np.isfinite(high)) or low <= 0 or high <= low:
        return []
    inner = np.geomspace(high, low, count + 2)[1:-1]
    return sorted({float(f"{v:.2g}") for v in inner}, reverse=True)


def bytes_to_reach(table: pd.DataFrame, count: int = N_LEVELS) -> pd.DataFrame:
    """Per dataset and line: the fewest bytes of a point whose mean RMSE is at or below
    each level (:func:`rmse_levels`); "–" where no point of the line reaches it."""
    rows = []
    for dataset, group in table.groupby("dataset", sort=False):
        levels = rmse_levels(group, count)
        for line, of_line in group.groupby("line", sort=False):
            row = {"dataset": dataset, "line": line}
            for level in levels:
                reached = of_line[of_line["rmse_mean"] <= level]
                row[f"RMSE ≤ {level:g}"] = (
                    "–"
                    if reached.empty
                    else f"{int(reached['bytes'].min())} "
                    f"({reached.loc[reached['bytes'].idxmin(), 'setting']})"
                )
            rows.append(row)
    return pd.DataFrame(rows)


def reach_sections(table: pd.DataFrame, out: Path) -> list[str]:
    """Write :func:`bytes_to_reach` as one table per dataset
    (``rate_distortion_reach_<dataset>``), each with its own RMSE levels as columns;
    return their Markdown sections."""
    reach = bytes_to_reach(table)
    if reach.empty:
        return []
    sections = []
    for dataset, of_dataset in reach.groupby("dataset", sort=False):
        of_dataset = of_dataset.dropna(axis=1, how="all")  # the other datasets' levels
        if of_dataset.shape[1] > 2:
            sections.append(
                write_table(
                    of_dataset,
                    out,
                    f"rate_distortion_reach_{safe_stem(dataset)}",
                    f"Bytes to reach an RMSE: {dataset}",
                    "The fewest stored bytes (and the setting) at which a line's mean RMSE is at "
                    "or below each level; levels spread geometrically between the dataset's "
                    "worst and best points. –: no point of the line reaches it. Means only: see "
                    "the error bars for the spread.",
                )
            )
    return sections


def plot(group: pd.DataFrame, dataset: str, path: Path, budgets_kb=BUDGETS_KB) -> Path:
    """RMSE (mean ± std over seeds) against bytes (log) of one dataset's points, one line
    per line, the Pareto front circled and joined, the budgets as dotted verticals."""
    fig = Figure(figsize=(7.5, 4.8))
    ax = fig.subplots()
    for line, of_line in group.sort_values("bytes").groupby("line", sort=False):
        ax.errorbar(
            of_line["bytes"],
            of_line["rmse_mean"],
            yerr=of_line["rmse_std"].fillna(0),
            marker="o",
            markersize=4,
            capsize=3,
            label=line,
        )
    front = group[pareto_front(group)].sort_values("bytes")
    ax.plot(
        front["bytes"],
        front["rmse_mean"],
        linestyle="--",
        color="black",
        linewidth=0.8,
        marker="o",
        markersize=11,
        markerfacecolor="none",
        label="Pareto front",
    )
    for kb in budgets_kb:
        ax.axvline(kb * 1024, color="grey", linestyle=":", linewidth=0.8)
    ax.set_xscale("log")
    ax.set_xlabel(
        "stored bytes (bytes_total); dotted: budgets " + ", ".join(f"{kb} KB" for kb in budgets_kb)
    )
    ax.set_ylabel("RMSE (eq. 10, normalized)")
    ax.set_title(dataset, fontsize=9)
    ax.legend(fontsize=6, loc="best")
    fig.tight_layout()
    return save_figure(fig, path)


def missing(table: pd.DataFrame) -> list[str]:
    """What the points lack for a curve or a verdict, per dataset."""
    notes = []
    for dataset, group in table.groupby("dataset", sort=False):
        absent = [m.title for m in MODELS.values() if m.name not in set(group["method"])]
        if absent:
            notes.append(f"{dataset}: no run of {', '.join(absent)}")
        for line, of_line in group.groupby("line", sort=False):
            if len(of_line) < 2:
                notes.append(f"{dataset}: {line} has 1 point (no curve)")
        single = group[group["n"] < 2]
        if not single.empty:
            notes.append(
                f"{dataset}: {len(single)} of {len(group)} points have 1 seed "
                "(no seed spread; add seed=0,1,2)"
            )
        if group["heldout"].any():
            notes.append(
                f"{dataset}: some neural runs held lights out of training "
                "(btf.interpolation.holdout_lights): their RMSE is over the "
                "training directions, PCA's over all"
            )
    return notes


def section(runs: pd.DataFrame, out: Path, alpha: float = 0.05, budgets_kb=BUDGETS_KB) -> str:
    """Write ``rate_distortion_<dataset>.png``, ``rate_distortion_points.csv``,
    ``rate_distortion_budget.{md,csv,tex}``, ``rate_distortion_winners.{md,csv,tex}`` (with
    more than one dataset) and ``rate_distortion_reach_<dataset>.{md,csv,tex}`` into ``out``
    from labelled runs; return the Markdown section."""
    table = points(runs)
    if table.empty:
        return (
            "## Rate-distortion\n\nNo run with `rmse` and `bytes_total`: "
            "`python -m pipeline -m experiment=rate_distortion seed=0,1,2`.\n"
        )
    write_file(out / "rate_distortion_points.csv", table.to_csv(index=False))
    parts = [
        "## Rate-distortion: RMSE against stored bytes\n",
        "One point per recipe (its seeds pooled: mean ± std, the error bars), one line "
        "per method and storage types (PCA over its components, clustered over k, Neural "
        "BTF over its latent size), every model scored as stored. Circled and dashed: "
        f"the Pareto front (mean RMSEs within {RMSE_TIE:g} are a tie, which the fewer "
        "bytes win). Points: `rate_distortion_points.csv`.\n",
    ]
    for dataset, group in table.groupby("dataset", sort=False):
        path = plot(group, dataset, out / f"rate_distortion_{safe_stem(dataset)}.png", budgets_kb)
        parts.append(f"![{path.stem}]({path.name})\n")
    budget = best_at_budgets(table, budgets_kb, alpha)
    parts.append(
        write_table(
            budget,
            out,
            "rate_distortion_budget",
            "Best model at a byte budget",
            f"best: the lowest mean RMSE among the points with at most the budget's bytes (KB = "
            f"1024 B; within {RMSE_TIE:g} of it, the fewest bytes). best other method: the best "
            "point of another method within the budget; difference = its mean RMSE - the best's, "
            f"with a {100 * (1 - alpha):g} % Welch interval over the seeds of both; 'wins beyond "
            "seed noise' when that interval excludes 0. Seeds: n of each point.",
        )
    )
    if table["dataset"].nunique() > 1:
        parts.append(
            write_table(
                winners(budget),
                out,
                "rate_distortion_winners",
                "Who wins at a budget, per dataset",
                "Each cell: the best point within the budget and its mean RMSE; then the best "
                "point of another method, how much higher its mean RMSE is, and the verdict of "
                "the budget table (untested: a point has a single seed).",
            )
        )
    parts += reach_sections(table, out)
    notes = missing(table)
    parts.append(
        "### Missing from the rate-distortion grid\n\n"
        + ("\n".join(f"- {n}" for n in notes) if notes else "Nothing.")
        + "\n"
    )
    return "\n".join(parts)
