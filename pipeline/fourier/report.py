"""Method C's tables and figures from MLflow runs: Fig. 6 (held-out RMS over M x λ).

Pure functions of a DataFrame of runs (one row per MLflow run, columns ``params.*`` and
``metrics.*`` as ``mlflow.search_runs`` returns them), so that they are tested on
hand-made runs, plus :func:`sections`, which writes everything under ``out`` (Markdown,
CSV and LaTeX tables; PNG plots) for ``python -m pipeline.tables``.

A *setup* is one dataset (the built-in stack, a light-stack folder with its crop and
downsampling, or one view of a BTF) with one choice of normals and of the diffuse term;
each setup gets its own Fig. 6 table and plot, with PTM and HSH (which depend on neither
M nor λ) as rows. The held-out lights are split into validation lights, on which (M, λ)
is chosen (Fig. 6), and test lights, on which the chosen fit is reported; runs logged
before that split (no ``rmse_validation_fourier``) are left out.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.core.recipe import recipe_suffixes, with_recipe
from pipeline.core.report import param, save_figure, write_table

PAPER_CHOICE = (10, 3.14)
VALIDATION = "metrics.rmse_validation_fourier"
TEST = "metrics.rmse_test_fourier"
SPLITS = {"validation": VALIDATION, "test": TEST}
SOLVER_NAMES = {"svd": "SVD least squares (= np.linalg.lstsq)", "normal": "normal equations"}


def baselines(split: str) -> tuple[tuple[str, str], ...]:
    """(name, metric column) of PTM and HSH on ``split`` (validation or test) lights."""
    return (("PTM", f"metrics.rmse_{split}_ptm"), ("HSH", f"metrics.rmse_{split}_hsh"))


def _leaf(path: str) -> str:
    return path.rstrip("/").split("/")[-1]


def _shrink_label(crop: str, factor: str) -> str:
    """`` [crop 0,0,64,64 /4]`` from the logged params; empty when the images are whole."""
    parts = []
    if crop not in ("None", ""):
        parts.append("crop " + re.sub(r"[^0-9,]", "", crop))
    if factor not in ("1", "None", ""):
        parts.append(f"/{factor}")
    return f" [{' '.join(parts)}]" if parts else ""


def label_runs(runs: pd.DataFrame, method: str = "fourier") -> pd.DataFrame:
    """Finished runs of ``method`` with a held-out error, plus ``setup``, ``M``, ``lam``.

    ``setup`` reads e.g. ``synthetic_stack, normals=given``,
    ``neuralrti-example [crop 0,0,64,64 /4], normals=photometric, clamped`` or
    ``WOOL view [[30, 90]], normals=flat``.
    """
    if runs.empty or "params.method.name" not in runs:
        return runs.iloc[0:0].assign(setup=[], M=[], lam=[])
    runs = runs[runs["params.method.name"] == method]
    if "status" in runs:
        runs = runs[runs["status"] == "FINISHED"]
    if method == "fourier":
        runs = runs[runs[VALIDATION].notna()] if VALIDATION in runs else runs.iloc[0:0]
    runs = with_recipe(runs).copy()
    root = param(runs, "dataset.root")
    name = param(runs, "dataset.name", "?")
    dataset = np.where(root.isin(["None", ""]), name, root.map(_leaf))
    crop, factor = param(runs, "dataset.crop"), param(runs, "dataset.downsample", "1")
    shrunk = [_shrink_label(c, f) for c, f in zip(crop, factor, strict=True)]
    views = param(runs, "dataset.views")
    fmt = param(runs, "dataset.format")
    shrunk = [
        s if f == "None" else f" ({f}) view {v}{s}"
        for s, f, v in zip(shrunk, fmt, views, strict=True)
    ]
    normals = param(runs, "dataset.normals", "flat").map(_leaf)
    clamped = np.where(param(runs, "method.clamp_diffuse", "False") == "True", ", clamped", "")
    runs["setup"] = [
        f"{d}{s}, normals={n}{c}"
        for d, s, n, c in zip(dataset, shrunk, normals, clamped, strict=True)
    ]
    # One setup pools (or replaces) runs of one recipe only: others are set apart by
    # the settings in which they differ, M and λ being the table's axes.
    runs["setup"] = runs["setup"] + recipe_suffixes(
        runs, ["setup"], ignore=["method.M", "method.lam"]
    )
    runs["M"] = pd.to_numeric(param(runs, "method.M"), errors="coerce")
    runs["lam"] = pd.to_numeric(param(runs, "method.lam"), errors="coerce")
    return runs


def _latest(runs: pd.DataFrame, keys: list[str]) -> pd.DataFrame:
    """One run per ``keys``: the most recent (a repeated sweep point replaces the old one)."""
    if "start_time" in runs:
        runs = runs.sort_values("start_time")
    return runs.drop_duplicates(keys, keep="last")


def _lam_label(lam: float) -> str:
    return f"λ = {lam:g}"


def fig6_table(runs: pd.DataFrame, split: str = "validation") -> pd.DataFrame:
    """Held-out RMS of one setup on ``split`` lights: rows M (then PTM and HSH), columns λ.

    The baselines do not depend on M or λ: their row repeats one value in every column.
    """
    runs = _latest(runs, ["M", "lam"])
    table = runs.pivot(index="M", columns="lam", values=SPLITS[split]).sort_index()
    table = table.reindex(sorted(table.columns), axis=1)
    table.index = table.index.astype(int)
    for name, column in baselines(split):
        if column in runs and runs[column].notna().any():
            table.loc[name] = float(runs[column].median())
    table.columns = [_lam_label(lam) for lam in table.columns]
    table.index.name = "M"
    return table


def best_point(runs: pd.DataFrame) -> tuple[int, float, float, float]:
    """(M, λ, validation RMS, test RMS) of one setup: lowest RMS on the validation lights."""
    runs = _latest(runs, ["M", "lam"])
    best = runs.loc[runs[VALIDATION].idxmin()]
    test = float(best[TEST]) if TEST in runs else np.nan
    return int(best["M"]), float(best["lam"]), float(best[VALIDATION]), test


def solvers(runs: pd.DataFrame) -> str:
    """Which solver ran at each λ, e.g. ``λ = 0: SVD least squares ...; λ > 0: normal ...``."""
    if "tags.fourier_solver" not in runs or runs["tags.fourier_solver"].isna().all():
        return "solver not recorded (runs older than the tag)"
    runs = runs[runs["tags.fourier_solver"].notna()]
    parts = []
    for zero, label in ((True, "λ = 0"), (False, "λ > 0")):
        used = sorted(set(runs.loc[(runs["lam"] == 0) == zero, "tags.fourier_solver"]))
        if used:
            parts.append(f"{label}: " + " / ".join(SOLVER_NAMES.get(u, u) for u in used))
    return "; ".join(parts)


def condition_table(runs: pd.DataFrame) -> pd.DataFrame:
    """cond(A) of the unregularized design per M (it does not depend on λ)."""
    columns = {
        "metrics.cond_design_median": "cond(A) median",
        "metrics.cond_design_max": "cond(A) max",
        "metrics.frac_pixels_rank_deficient": "rank-deficient pixels",
    }
    present = [c for c in columns if c in runs]
    if not present:
        return pd.DataFrame()
    table = _latest(runs, ["M", "lam"]).groupby("M")[present].median().rename(columns=columns)
    table.index = table.index.astype(int)
    return table


def summary_table(runs: pd.DataFrame) -> pd.DataFrame:
    """One row per setup: (M, λ) chosen on validation lights, errors on test lights."""
    rows = []
    for setup, group in runs.groupby("setup", sort=True):
        M, lam, validation, test = best_point(group)
        group = _latest(group, ["M", "lam"])
        paper = group[(group["M"] == PAPER_CHOICE[0]) & np.isclose(group["lam"], PAPER_CHOICE[1])]
        row = {
            "setup": setup,
            "runs": len(group),
            "chosen M": M,
            "chosen λ": lam,
            "validation: Fourier (chosen)": validation,
            "test: Fourier (chosen)": test,
            "test: Fourier (M=10, λ=3.14)": float(paper[TEST].iloc[0]) if len(paper) else np.nan,
        }
        for name, column in baselines("test"):
            row[f"test: {name}"] = float(group[column].median()) if column in group else np.nan
        for column, label in (
            ("metrics.n_train_lights", "train lights"),
            ("metrics.n_validation_lights", "validation lights"),
            ("metrics.n_test_lights", "test lights"),
        ):
            if column in group:
                row[label] = int(group[column].max())
        rows.append(row)
    return pd.DataFrame(rows).set_index("setup")


def segmentation_table(runs: pd.DataFrame) -> pd.DataFrame:
    """Segmentation accuracy per setup, method and colour space: all and object pixels."""
    rows = []
    for setup, group in runs.groupby("setup", sort=True):
        latest = _latest(group, ["setup"]).iloc[0]
        for name, label in (("paper", "paper (representatives)"), ("kmeans", "k-means")):
            for space in ("rgb", "chromaticity"):
                column = f"metrics.segmentation_accuracy_{name}_{space}"
                if column not in latest or pd.isna(latest[column]):
                    continue
                obj = latest.get(f"metrics.segmentation_accuracy_object_{name}_{space}", np.nan)
                rows.append(
                    {
                        "setup": setup,
                        "method": label,
                        "colour space": space,
                        "all pixels": float(latest[column]),
                        "object pixels": float(obj),
                    }
                )
    if not rows:
        return pd.DataFrame()
    return pd.DataFrame(rows).set_index("setup")


def plot_rms_vs_m(runs: pd.DataFrame, path: Path, title: str) -> Path:
    """Fig. 6: validation RMS against M, one line per λ; PTM and HSH as dashed lines."""
    from matplotlib.figure import Figure

    runs = _latest(runs, ["M", "lam"])
    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    for lam, group in runs.groupby("lam"):
        group = group.sort_values("M")
        ax.plot(group["M"], group[VALIDATION], marker="o", label=_lam_label(lam))
    for (name, column), style in zip(baselines("validation"), ("--", ":"), strict=True):
        if column in runs and runs[column].notna().any():
            ax.axhline(float(runs[column].median()), color="k", ls=style, lw=1, label=name)
    M, lam, rms, _ = best_point(runs)
    chosen = f"chosen M={M}, λ={lam:g}"
    ax.plot([M], [rms], marker="*", ms=14, color="gold", mec="k", ls="none", label=chosen)
    ax.set_yscale("log")
    ax.set_xlabel("M (highest harmonic)")
    ax.set_ylabel("RMS on validation lights (linear RGB)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    save_figure(fig, path)
    return path


def pattern_table(runs: pd.DataFrame) -> pd.DataFrame:
    """Quilting against random tiling and segmentation accuracy, from pattern runs."""
    runs = label_runs(runs, "fourier_pattern")
    if runs.empty or "metrics.seam_cost_quilting" not in runs:
        return pd.DataFrame()
    runs = runs[runs["metrics.seam_cost_quilting"].notna()]
    columns = {
        "params.method.quilting.block_size": "block",
        "params.method.quilting.overlap": "overlap",
        "params.method.pattern.size": "output size",
        "metrics.seam_cost_quilting": "seam cost: quilting",
        "metrics.seam_cost_random": "seam cost: random tiling",
        "metrics.seconds_quilting": "quilting seconds (all regions)",
        "metrics.segmentation_accuracy_paper": "segmentation accuracy: paper",
        "metrics.segmentation_accuracy_object_paper": "segmentation accuracy (object): paper",
        "metrics.segmentation_accuracy_kmeans": "segmentation accuracy: k-means",
        "metrics.segmentation_accuracy_object_kmeans": "segmentation accuracy (object): k-means",
    }
    keep = ["setup", "M", "lam", *[c for c in columns if c in runs]]
    table = _latest(runs, ["setup", "M", "lam", *keep[3:5]])[keep].rename(columns=columns)
    return table.set_index("setup")


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_").lower()


def sections(runs: pd.DataFrame, out: Path, settings=None) -> list[str]:
    """Method C's sections for ``runs`` (any methods' runs; C's are picked out), with their
    tables and plots written into ``out``. ``settings`` (``conf/tables.yaml``) is unused."""
    out = Path(out)
    labelled = label_runs(runs)
    if labelled.empty:
        return [
            "## Method C (Fourier)\n\nNo finished `method=fourier` run found: run "
            "`python -m pipeline -m experiment=fourier_sweep` first.\n"
        ]
    sections = []

    def add(table: pd.DataFrame, stem: str, title: str, note: str) -> None:
        sections.append(write_table(table, out, stem, title, note))

    add(
        summary_table(labelled).reset_index(),
        "fourier_summary",
        "Method C: (M, λ) chosen on validation lights (Fig. 6), reported on test lights",
        "The held-out lights are split in two (`dataset.validation_every`): chosen = the "
        "(M, λ) with the lowest RMS on the validation lights; the test columns are the "
        "RMS on the other, test lights (linear RGB, all pixels and channels), which took "
        "no part in the choice. PTM and HSH are fitted on the same training lights. "
        "Synthetic: reference = the generator's noise-free renders.",
    )
    for setup, group in labelled.groupby("setup", sort=True):
        slug = _slug(setup)
        M, lam, validation, test = best_point(group)
        add(
            fig6_table(group, "validation"),
            f"fig6_{slug}",
            f"Fig. 6, {setup}: RMS on validation lights",
            f"Rows M, columns λ; PTM and HSH do not depend on M or λ (one value per row). "
            f"Lowest: M = {M}, λ = {lam:g} ({validation:.4g}; on the test lights "
            f"{test:.4g}); the paper chose M = 10, λ = 3.14. Solver: {solvers(group)}.",
        )
        add(
            fig6_table(group, "test"),
            f"fig6_test_{slug}",
            f"Fig. 6, {setup}: RMS on test lights (for reference; not used to choose)",
            "As above, on the test lights.",
        )
        plot = plot_rms_vs_m(group, out / f"fig6_{slug}.png", f"Fig. 6: {setup}")
        sections.append(f"![Fig. 6, {setup}]({plot.name})\n")
        condition = condition_table(group)
        if not condition.empty:
            add(
                condition,
                f"fourier_condition_{slug}",
                f"Method C, {setup}: conditioning of the unregularized fit",
                "cond(A) = σ_max / σ_min of each pixel's design matrix (lights x 2M + 2, "
                "eq. 17), median and largest over the pixels whose normal is not the "
                "view (where it is, A is singular by construction); "
                "rank-deficient = the fraction of pixels where np.linalg.lstsq's cutoff "
                "drops a singular value (e.g. normal = view, where θs = θd). "
                f"Solver: {solvers(group)}.",
            )
    segmentation = segmentation_table(labelled)
    if not segmentation.empty:
        add(
            segmentation.reset_index(),
            "fourier_segmentation",
            "Method C: segmentation accuracy, all pixels and object pixels",
            "Against the ground-truth region map, up to a renaming of the labels; object "
            "pixels = not the backdrop (label 0). RGB is the paper's colour space (the "
            "default, `method.segmentation.colour_space`); chromaticity divides by the "
            "channel sum (not in the paper). The paper's method uses one representative "
            "pixel per true region (the deepest one), k-means `n_regions` clusters.",
        )
    pattern = pattern_table(runs)
    if not pattern.empty:
        add(
            pattern.reset_index(),
            "fourier_pattern",
            "Method C: quilting and segmentation",
            "Seam cost: mean squared neighbour difference of the coefficients across the "
            "block seams (averaged over regions); random tiling uses the same block grid "
            "with straight seams. Segmentation accuracy against the synthetic ground truth.",
        )
    return sections
