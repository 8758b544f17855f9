"""The Hydra job: compose the config, run the method's chain, record it in MLflow."""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Callable
from pathlib import Path

import mlflow
from omegaconf import DictConfig, OmegaConf

from pipeline.brdf_map import runner as brdf_runner
from pipeline.btf import report as btf_report
from pipeline.btf import runner as btf_runner
from pipeline.core import stopping
from pipeline.core.errors import ConfigError
from pipeline.core.memory import process_peak_mb
from pipeline.core.stage import Context
from pipeline.core.tracking import SweepParentRun, job_run
from pipeline.fourier import pattern_runner
from pipeline.fourier import runner as fourier_runner
from pipeline.render import RENDERED

log = logging.getLogger(__name__)


METHODS: dict[str, Callable[[Context], dict[str, float]]] = {
    "neural_btf": btf_runner.run,
    "clustered": btf_runner.run,
    "pca": btf_runner.run_linear,
    "brdf_map": brdf_runner.run,
    "fourier": fourier_runner.run,
    "fourier_pattern": pattern_runner.run,
}


_A = (
    "**Method A: Neural BTF{what}** (PAPERS.md A). `rmse`: eq. 10, over the crop's texels "
    "and the directions the model was trained on, with values divided by the crop's maximum "
    "(so in [0, 1]); held-out lights apart (`rmse_heldout_*`, against nearest and linear "
    "interpolation). Baseline: `rmse_mean_abrdf` predicts every texel as the crop's mean "
    "ABRDF; `rmse_ratio_to_mean_abrdf` = rmse / that (a tag `training_failed` marks >= 0.9). "
    "`bytes_*`: Table 1's sizes. Artifacts: `config/` (resolved config, overrides), "
    "`hydra/` (the job's log), `metrics.json`, the figures."
)
# The run's note in the MLflow UI: what it computed and how to read its metrics.
DESCRIPTIONS: dict[str, str] = {
    "neural_btf": _A.format(what=""),
    "clustered": _A.format(what=" with clustering: one latent per k-means cluster"),
    "pca": (
        "**Method A's comparator: PCA at matched bytes.** Each texel's ABRDF as a mean plus "
        "principal components (as many as the bytes of `method.match_clustered_k` allow, in `method.dtype`); `rmse` and "
        "`rmse_mean_abrdf` as for the neural models (eq. 10, values divided by the crop's "
        "maximum)."
    ),
    "brdf_map": (
        "**Method B: MAP reconstruction of an anisotropic BRDF** (PAPERS.md B). "
        "`rmse_measured*`: at the measured directions; `rmse_missing*`: at the missing ones "
        "against the ground truth (near and off the mirror direction); suffixes `_noprior` "
        "and `_as` are the fit without the prior and the Ashikhmin-Shirley baseline."
    ),
    "fourier": (
        "**Method C: Fourier-series reflectance from a light stack** (PAPERS.md C). "
        "`rmse_validation_*` chose M and lambda; `rmse_test_*` is the report, on held-out "
        "lights never used for a choice; `fourier` against the PTM and HSH baselines."
    ),
    "fourier_pattern": (
        "**Method C: optical pattern.** Regions segmented from the fitted coefficients, "
        "quilted and blended over a target shape; artifacts `pattern/` and `figures/`."
    ),
}


def run_job(cfg: DictConfig) -> float | None:
    """Run one job; returns the headline error (for Hydra sweepers) when there is one."""
    name = cfg.method.name
    if name not in METHODS:
        raise ConfigError(f"method.name={name!r} is not one of {sorted(METHODS)}")
    if not isinstance(cfg.seed, int) or isinstance(cfg.seed, bool) or cfg.seed < 0:
        raise ConfigError(f"seed={cfg.seed!r} must be an integer >= 0")
    k = f" k={cfg.method.k}" if name == "clustered" else ""
    run_name = f"{name}{k} s{cfg.seed}"
    if "train" in cfg:
        # libgomp reads its spin count once, when torch loads: before any stage runs.
        from pipeline.btf.fast.tuning import set_omp_spin_count

        set_omp_spin_count(cfg.train.get("omp_spin_count"))
    description = DESCRIPTIONS.get(name, "")
    # SIGTERM/SIGINT end the run FAILED and the process, wherever they land; its temporary
    # files under these folders go with it (pipeline.core.stopping).
    leftovers = [cfg.paths.get(folder) for folder in ("runs", "cache", "data")]
    with stopping.job_scope(leftovers_in=[f for f in leftovers if f]), \
            job_run(cfg, run_name=run_name, description=description):
        ctx = Context.from_config(cfg)
        try:
            metrics = METHODS[name](ctx)
            if name in RENDERED and cfg.btf.render.enabled:
                from pipeline.render import stage as render_stage

                metrics.update(render_stage.run(ctx))
        finally:
            mlflow.set_tags({f"cache.{stage}": key for stage, key in ctx.keys.items()})
            mlflow.log_metrics({f"seconds_{s}": t for s, t in ctx.seconds.items()})
            mlflow.log_metrics({f"peak_rss_mb_{s}": v for s, v in ctx.peak_rss_mb.items()})
            mlflow.log_metric("peak_rss_mb", process_peak_mb())
        mlflow.log_metrics(metrics)
        if name in FIGURES:
            log_job_figures(cfg, ctx.keys, FIGURES[name])
    return metrics.get("rmse")


# Figures drawn from a finished job's cache entries (each method's own runs log theirs).
FIGURES = {"neural_btf": btf_report.job_figures, "clustered": btf_report.job_figures}


def log_job_figures(cfg: DictConfig, cache_keys: dict[str, str], draw) -> None:
    """Draw the job's figures into a temporary folder and log them under ``figures/``."""
    from pipeline.tables import default_settings

    pairs = OmegaConf.to_container(default_settings().fig7.pairs)
    with tempfile.TemporaryDirectory() as folder:
        if draw(cfg, cache_keys, pairs, Path(folder)):
            mlflow.log_artifacts(folder, "figures")


class SweepRun(SweepParentRun):
    """The sweep's MLflow parent run (``conf/config.yaml``, ``hydra.callbacks``) and, with
    ``run_tables``, ``python -m pipeline.tables`` after the last job."""

    def __init__(self, run_tables: bool = False) -> None:
        super().__init__()
        self.run_tables = run_tables

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        if self.run_tables:
            from pipeline.tables import build_tables

            # The parent holds the tables and figures too: the UI shows what the disk does.
            build_tables(config.paths.runs, log_to=self.run_id)
        super().on_multirun_end(config, **kwargs)
