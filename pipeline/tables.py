"""``python -m pipeline.tables``: regenerate the paper's tables and figures from MLflow.

Reads the finished runs back (``mlflow.search_runs``), and writes under
``${paths.runs}/tables/``: Table 1 (sizes), Table 2 (RMSE, mean ± std over seeds), the
interpolation table and the k-versus-error verdict, each as Markdown, CSV and LaTeX, plus
Fig. 7 (PNG and EXR), an RMSE-versus-k plot and the training RMSE-versus-time curves. Works with whatever subset of runs exists
and says what is missing. Options (Hydra overrides): ``paths.runs=...``,
``tables.experiments=[btf,...]``, ``tables.filter="tags.note = 'x'"``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

from pipeline.report import btf_tables  # noqa: E402
from pipeline.report.curves import curves_section  # noqa: E402
from pipeline.report.fourier_tables import fourier_sections  # noqa: E402
from pipeline.tracking import tracking_uri, use_store  # noqa: E402

log = logging.getLogger(__name__)
CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
BTF_METHODS = ("neural_btf", "clustered", "pca")


def default_settings() -> DictConfig:
    """The ``tables`` section of ``conf/tables.yaml`` (used after a sweep ends)."""
    return OmegaConf.load(CONF_DIR / "tables.yaml").tables


def fetch_runs(runs_dir: str | Path, experiments, filter_string: str | None) -> pd.DataFrame:
    """Finished runs of the given MLflow experiments as one DataFrame."""
    import mlflow

    use_store(runs_dir)
    found = [e.name for e in mlflow.search_experiments()]
    names = [e for e in (experiments or found) if e in found]
    if not names:
        return pd.DataFrame()
    runs = mlflow.search_runs(
        experiment_names=names, filter_string=filter_string or "", output_format="pandas"
    )
    if runs.empty:
        return runs
    return runs[runs["status"] == "FINISHED"]


def _write(table: pd.DataFrame, out: Path, stem: str, title: str, note: str = "") -> str:
    """Write ``stem``.md/.csv/.tex; return the Markdown section."""
    index = table.index.name is not None
    table.to_csv(out / f"{stem}.csv", index=index)
    table.to_latex(out / f"{stem}.tex", index=index, caption=title, label=f"tab:{stem}")
    markdown = f"## {title}\n\n{table.to_markdown(index=index)}\n\n{note}\n"
    (out / f"{stem}.md").write_text(markdown)
    return markdown


def build_tables(runs_dir: str | Path, settings: DictConfig | None = None) -> Path:
    """Write every table and figure; returns the ``tables`` folder."""
    settings = settings if settings is not None else default_settings()
    out = Path(runs_dir) / "tables"
    out.mkdir(parents=True, exist_ok=True)
    runs = fetch_runs(runs_dir, list(settings.experiments or []), settings.filter)
    sections = [f"# Tables regenerated from MLflow ({tracking_uri(runs_dir)})\n"]
    sections += fourier_sections(runs_dir, out)
    if not runs.empty and "params.method.name" in runs:
        runs = runs[runs["params.method.name"].isin(BTF_METHODS)]
    if runs.empty or "metrics.rmse" not in runs:
        sections.append("No finished Neural BTF run found (method A): `python -m pipeline`.\n")
        (out / "summary.md").write_text("\n".join(sections))
        print("\n".join(sections))
        return out
    runs = btf_tables.drop_repeats(runs[runs["metrics.rmse"].notna()])
    runs = btf_tables.label_runs(runs)

    sizes = btf_tables.table_sizes(runs)
    if not sizes.empty:
        sections.append(_write(sizes, out, "table1_sizes", "Table 1: stored sizes in bytes",
                               "Ratio (exact) = original bytes / total bytes. Ratio (paper) = "
                               "original in MB / total in whole KB, the paper's "
                               "convention. Original = M x N x 3 float32."))
    rmse = btf_tables.table_rmse(runs)
    sections.append(_write(rmse, out, "table2_rmse",
                           "Table 2: RMSE (eq. 10, normalized to [0, 1]), mean ± std over seeds",
                           "n = number of seeds. Clustered runs use each texel's own values as "
                           "the training target unless marked (rep. target)."))
    if "metrics.rmse_with_texel_scale" in runs:
        scaled = runs[runs["params.method.name"] == "clustered"]
        if not scaled.empty:
            both = pd.concat(
                {
                    "without scale": btf_tables.table_rmse(
                        scaled, "rmse_without_texel_scale").stack(),
                    "with per-texel scale": btf_tables.table_rmse(
                        scaled, "rmse_with_texel_scale").stack(),
                },
                axis=1,
            )
            both.index.names = ["dataset", "model"]
            sections.append(_write(both.reset_index(), out, "graininess",
                                   "Graininess fix: clustered RMSE without / with a per-texel scale",
                                   "The scale costs one float per texel (bytes_extra)."))
    interpolation = btf_tables.table_interpolation(runs)
    if not interpolation.empty:
        sections.append(_write(interpolation, out, "interpolation",
                               "Interpolation at directions never trained on (RMSE)",
                               "held-out: light directions removed from training, reference = "
                               "measured data. off-grid: random directions off the 81-grid, "
                               "reference = the synthetic generator's ground truth."))
    verdict = btf_tables.k_verdict(runs, alpha=float(settings.alpha))
    if not verdict.empty:
        sections.append(_write(verdict, out, "k_verdict", "Does k change the error?",
                               "One-way ANOVA over k (seed-to-seed spread as the noise), "
                               "Kruskal-Wallis as a check without normality."))
    tolerance = float(settings.convergence_tolerance)
    convergence = btf_tables.table_convergence(runs, tolerance)
    if not convergence.empty:
        sections.append(_write(convergence, out, "convergence",
                               "Converged? RMSE against the same model trained longer",
                               f"excess = RMSE / reference RMSE - 1, the reference being the "
                               f"longest run of the same model and seed; the goal is within "
                               f"{100 * tolerance:g} % of a run 4x as long "
                               f"(`tables.convergence_tolerance`)."))
    missing = btf_tables.missing_runs(runs, list(settings.paper_ks))
    sections.append("## Missing from the paper grid\n\n" + (
        "\n".join(f"- {m}" for m in missing) if missing else "Nothing.") + "\n")
    sections.append(_plot_rmse_vs_k(runs, out))
    sections.append(curves_section(runs, out, tolerance))
    if settings.fig7.enabled:
        from pipeline.report.fig7 import draw_fig7

        files = draw_fig7(runs, OmegaConf.to_container(settings.fig7.pairs), out)
        sections.append("## Fig. 7\n\n" + "\n".join(f"- {p.name}" for p in files
                                                   if p.suffix == ".png") + "\n")
    summary = "\n".join(sections)
    (out / "summary.md").write_text(summary)
    print(summary)
    log.info("tables written to %s", out)
    return out


def _plot_rmse_vs_k(runs: pd.DataFrame, out: Path) -> str:
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for dataset, group in runs.groupby("dataset"):
        clustered = group[group["params.method.name"] == "clustered"]
        stats = clustered.groupby("k")["metrics.rmse"].agg(["mean", "std", "count"])
        if not stats.empty:
            ax.errorbar(stats.index, stats["mean"], yerr=stats["std"].fillna(0), marker="o",
                        capsize=3, label=f"{dataset} clustered")
        neural = group[group["params.method.name"] == "neural_btf"]["metrics.rmse"]
        if not neural.empty:
            ax.axhline(neural.mean(), linestyle="--", label=f"{dataset} Neural BTF")
    ax.set_xlabel("k (clusters)")
    ax.set_ylabel("RMSE (normalized)")
    ax.set_xscale("log")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "rmse_vs_k.png", dpi=110)
    plt.close(fig)
    return "## RMSE versus k\n\n![rmse_vs_k](rmse_vs_k.png) (error bars: std over seeds)\n"


@hydra.main(version_base="1.3", config_path="../conf", config_name="tables")
def main(cfg: DictConfig) -> None:
    build_tables(cfg.paths.runs, cfg.tables)


if __name__ == "__main__":
    main()
