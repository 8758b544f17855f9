"""Method A's report: Tables 1 and 2, the graininess fix, interpolation, the k verdict,
convergence, the RMSE-versus-k plot, training curves and Fig. 7, from a DataFrame of runs.

The tables themselves are pure functions in :mod:`pipeline.btf.tables`; this module picks
A's runs, writes each table (Markdown, CSV, LaTeX) and figure into ``out`` and returns the
Markdown sections for ``python -m pipeline.tables``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from pipeline.btf import paper, rate_distortion, tables
from pipeline.btf.curves import curves_section
from pipeline.btf.models import models_of
from pipeline.core.report import runs_of, save_figure, write_file, write_table

METHODS = ("btf",)
FAILED = 0.9  # RMSE / mean-ABRDF baseline at which training failed (tables.failed_runs)


def sections(runs: pd.DataFrame, out: Path, settings) -> list[str]:
    """Method A's sections; ``settings`` is the ``tables`` node of ``conf/tables.yaml``."""
    runs = runs_of(runs, METHODS)
    if runs.empty or "metrics.rmse" not in runs:
        return ["No finished Neural BTF run found (method A): `python -m pipeline`.\n"]
    runs = tables.drop_repeats(runs[runs["metrics.rmse"].notna()])
    runs = tables.label_runs(runs)
    if runs.empty:
        return ["No Neural BTF run with a recipe tag found (method A): `python -m pipeline`.\n"]
    found = []

    def add(table, stem: str, title: str, note: str, floatfmt="g", always=False) -> None:
        """Write ``table`` unless it is empty (Tables 2 are written ``always``)."""
        if always or not table.empty:
            found.append(write_table(table, out, stem, title, note, floatfmt))

    add(
        tables.table_sizes(runs),
        "table1_sizes",
        "Table 1: stored sizes in bytes",
        "Bytes as stored, in the types of the 'stored as' column (read from the written "
        "tensors). Ratio (exact) = original bytes / total bytes. Ratio (paper) = original in MB "
        "/ total in whole KB, the paper's convention. Original = M x N x 3 float32.",
    )
    add(
        tables.with_truth_floor(tables.table_rmse(runs), runs),
        "table2_rmse",
        "Table 2: RMSE (eq. 10, normalized to [0, 1]), mean ± std over seeds",
        "Over all N directions, held-out lights included (btf.interpolation.holdout_lights; the "
        "interpolation table has them apart). n = number of seeds. Clustered runs use each "
        "texel's own values as the training target unless marked (rep. target). data vs truth "
        "(built-in data only): the data's own RMSE against the generator's analytic truth (its "
        "8-bit and JPEG rounding): what a model that recovered the truth exactly would score. "
        f"Learning rates: {tables.learning_rates(runs) or 'not logged'}. A column is one "
        "recipe; a label names what tells it apart from the other columns of its model (all the "
        "settings in which they differ: table2_columns.csv).",
        always=True,
    )
    write_file(out / "table2_columns.csv", tables.column_recipes(runs).to_csv(index=False))
    add(
        paper.TABLE2,
        "table2_paper",
        "The paper's Table 2, beside ours (not a reproduction)",
        "RMSE of eq. 10 as published, one model per cell. Its data are measured UBO2003 "
        "BTFs with their camera noise (the built-in data are generated materials rounded "
        "to 8-bit JPEGs); it trains by plain SGD (lr 0.05 / 0.08, batches of 5) for 2-3 hours a "
        "model on a GTX 970 with no stopping criterion stated (Table 2's learning rates and "
        "table2_columns.csv say ours). Its largest step between two k is "
        f"{100 * paper.largest_k_step():.1f} % (fabric02, 500 -> 1000); its largest "
        f"clustering penalty {100 * paper.largest_clustering_penalty():+.1f} % "
        "(fabric02, k = 500 over the Neural BTF).",
        floatfmt=".4f",  # as published: 0.0200, not 0.02
        always=True,
    )
    add(
        tables.table_graininess(runs),
        "graininess",
        "Graininess fix at equal bytes: clustered RMSE without / with a per-texel scale",
        "The scale costs one btf.sizes.extra_dtype value per texel (Table 1's '+ per-texel "
        "scale' rows); 'bytes' are without it, also for a model that stores it. 'nearest in "
        "bytes': the model of the same recipe but k, without a scale, whose total bytes are "
        "closest to the scaled model's, so that the scale is compared with spending its bytes "
        "on the model itself (more clusters). Every RMSE is over all the crop's directions, as "
        "Table 2's.",
    )
    add(
        tables.failed_runs(runs),
        "failed_runs",
        "WARNING: runs that did not beat the trivial baseline",
        "These models end within 10 % of the mean-ABRDF baseline (every texel "
        "reconstructed as the mean ABRDF) or above it: their training failed, and their "
        "RMSE in Table 2 measures no compression. Check train.* (lr, steps, schedule) "
        "against the crop size.",
    )
    add(
        tables.table_interpolation(runs),
        "interpolation",
        "Interpolation at directions never trained on (RMSE)",
        "held-out: light directions removed from training, reference = measured data. off-grid: "
        "random directions off the 81-grid, reference = the synthetic generator's ground truth. "
        "Not a blind test of the model: its encoder and the normalisation saw each texel's "
        "values at the held-out directions, while nearest and linear see only the training "
        "directions.",
    )
    add(
        tables.k_verdict(runs, alpha=float(settings.alpha)),
        "k_verdict",
        "Does k change the error?",
        "Seeds are blocks (a seed shares its initialisation, batch order and k-means seed "
        "across k): two-way ANOVA without interaction over the seeds run at every k, Friedman's "
        "rank test (a sign test for two k; its exact permutation p where the blocks are few, "
        "else the chi-square) as the check without normality, the trend of RMSE per doubling of "
        "k within seeds, and each step's effect with its Bonferroni interval, Holm-adjusted p "
        "and size relative to the smaller k's mean. Without evidence: the step these runs "
        "detect with 80 % power and the seeds needed for a "
        f"{100 * paper.largest_k_step():.1f} % difference (the paper's largest step between "
        f"two k: fabric02, k = 500 -> 1000; its {100 * paper.largest_clustering_penalty():.1f} % "
        "is k = 500 over the Neural BTF, no step). Runs pooled only within one recipe (see the "
        "column labels).",
    )
    tolerance = float(settings.convergence_tolerance)
    add(
        tables.table_convergence(runs, tolerance),
        "convergence",
        "Converged? RMSE against the same model trained longer",
        f"excess = RMSE / reference RMSE - 1, the reference being the longest run of the "
        f"same model and seed; the goal is within {100 * tolerance:g} % of a run 4x as "
        f"long (`tables.convergence_tolerance`).",
    )
    missing = tables.missing_runs(runs, list(settings.paper_ks))
    found.append(
        "## Missing from the paper grid\n\n"
        + ("\n".join(f"- {m}" for m in missing) if missing else "Nothing.")
        + "\n"
    )
    found.append(plot_rmse_vs_k(runs, out))
    found.append(curves_section(runs, out, tolerance))
    if settings.fig7.enabled:
        from pipeline.btf.fig7 import draw_fig7

        files = draw_fig7(runs, out)
        found.append(
            "## Fig. 7\n\n"
            + "\n\n".join(f"![{p.stem}]({p.name})" for p in files if p.suffix == ".png")
            + "\n"
        )
    found.append(
        rate_distortion.section(
            runs, out, alpha=float(settings.alpha), budgets_kb=tuple(settings.budgets_kb)
        )
    )
    return found


def verdict(runs: pd.DataFrame, limit: int = 12) -> list[str]:
    """Method A's result on ``runs`` (a sweep's) in a few lines: per dataset, each model's
    RMSE (mean over seeds) against the mean-ABRDF baseline, and its stored bytes."""
    runs = runs_of(runs, METHODS)
    if runs.empty or "metrics.rmse" not in runs:
        return []
    runs = tables.label_runs(tables.drop_repeats(runs[runs["metrics.rmse"].notna()]))
    lines = []
    for dataset, group in runs.groupby("dataset", sort=False):
        baseline = pd.to_numeric(group.get("metrics.rmse_mean_abrdf"), errors="coerce").mean()
        lines.append(
            f"{dataset}: RMSE (mean-ABRDF baseline {baseline:.4f}) and stored bytes"
            if pd.notna(baseline)
            else f"{dataset}: RMSE and stored bytes"
        )
        models = list(group.sort_values(["order", "model"]).groupby("model", sort=False))
        rows = [_verdict_row(model, of_model, baseline) for model, of_model in models[:limit]]
        widths = [max(len(row[i]) for row in rows) for i in range(4)]
        for row in rows:
            cells = [row[i].ljust(widths[i]) for i in range(3)]
            cells += [row[3].rjust(widths[3]), row[4]]
            lines.append("  " + "  ".join(cells).rstrip())
        if len(models) > limit:
            lines.append(f"  … and {len(models) - limit} more models (see the tables)")
    return lines


def _verdict_row(model: str, runs: pd.DataFrame, baseline: float) -> list[str]:
    """Label, RMSE (± std, n), its ratio to ``baseline``, bytes and a failure flag."""
    rmse = pd.to_numeric(runs["metrics.rmse"], errors="coerce")
    spread = f" ± {rmse.std(ddof=1):.4f} (n={len(rmse)})" if len(rmse) > 1 else ""
    ratio = rmse.mean() / baseline if pd.notna(baseline) else np.nan
    total = pd.to_numeric(
        runs.get("metrics.bytes_total", pd.Series(dtype=float)), errors="coerce"
    ).dropna()
    return [
        model,
        f"{rmse.mean():.4f}{spread}",
        f"= {ratio:.2f} x baseline" if pd.notna(ratio) else "",
        f"{int(total.iloc[0]):,} B" if not total.empty else "",
        "training failed (not below 0.9 x baseline)" if ratio >= FAILED else "",
    ]


def job_figures(
    cfg, cache_keys: dict[str, str], pairs_degrees: list, out: Path, left_out=()
) -> list[Path]:
    """Fig. 7 of one finished job (the reference crops and its reconstruction), drawn into
    ``out`` (PNG and EXR) with its data (``fig7_data.npz``, which the tables draw from);
    nothing for PCA, which has no decoder to query. ``left_out``: the settings the job's
    run did not log (``Method.left_out``), left out of its recipe as the run's are."""
    from pipeline.btf.fig7 import DATA_NAME, draw_fig7, job_data
    from pipeline.core.cache import StageCache
    from pipeline.core.recipe import recipe_id
    from pipeline.core.run import flatten

    if "train" not in cache_keys:
        return []
    cache = StageCache(cfg.paths.cache)
    cropped, prep, trained = (
        cache.lookup(stage, cache_keys[stage]) for stage in ("crop", "preprocess", "train")
    )
    evaluated = (
        cache.lookup("evaluate", cache_keys["evaluate"]) if "evaluate" in cache_keys else None
    )
    data = job_data(cropped, prep, trained, evaluated, pairs_degrees)
    settings = {k: v for k, v in flatten(cfg).items() if k not in set(left_out)}
    row = {f"params.{k}": str(v) for k, v in settings.items()}
    row["tags.recipe"] = recipe_id(settings)
    row["run_id"] = "this job"
    written = draw_fig7(tables.label_runs(pd.DataFrame([row])), out, data_of=lambda _: data)
    np.savez(out / DATA_NAME, **data)
    return [*written, out / DATA_NAME]


def plot_rmse_vs_k(runs: pd.DataFrame, out: Path) -> str:
    """``rmse_vs_k.png``: clustered RMSE (mean and std over seeds) against k, per dataset,
    with Neural BTF as a dashed line; returns its Markdown section."""
    fig = Figure(figsize=(5, 3.5))
    ax = fig.subplots()
    for dataset, group in runs.groupby("dataset"):
        # One line per model family (one recipe but k), never runs of different recipes.
        clustered = group[[m is not None and m.clusters for m in models_of(group)]]
        for name, runs_of_family in clustered.groupby("family"):
            stats = runs_of_family.groupby("k")["metrics.rmse"].agg(["mean", "std"])
            ax.errorbar(
                stats.index,
                stats["mean"],
                yerr=stats["std"].fillna(0),
                marker="o",
                capsize=3,
                label=f"{dataset} {name}",
            )
        neural = group[group["model"].str.startswith("Neural BTF")]
        for name, runs_of_model in neural.groupby("model"):
            ax.axhline(
                runs_of_model["metrics.rmse"].mean(), linestyle="--", label=f"{dataset} {name}"
            )
    if not ax.get_legend_handles_labels()[0]:
        return "## RMSE versus k\n\nNo clustered or Neural BTF run to draw.\n"
    ax.set_xlabel("k (clusters)")
    ax.set_ylabel("RMSE (normalized)")
    ax.set_xscale("log")
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out / "rmse_vs_k.png")
    return "## RMSE versus k\n\n![rmse_vs_k](rmse_vs_k.png) (error bars: std over seeds)\n"
