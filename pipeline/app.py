"""The Hydra job: compose the config, run the method's chain, record it in MLflow."""

from __future__ import annotations

import logging
from collections.abc import Callable

import mlflow
from omegaconf import DictConfig

from pipeline.btf import runner as btf_runner
from pipeline.memory import process_peak_mb
from pipeline.methods import brdf_runner, fourier_runner, pattern_runner
from pipeline.stages import Context
from pipeline.tracking import job_run

log = logging.getLogger(__name__)


METHODS: dict[str, Callable[[Context], dict[str, float]]] = {
    "neural_btf": btf_runner.run,
    "clustered": btf_runner.run,
    "pca": btf_runner.run_linear,
    "brdf_map": brdf_runner.run,
    "fourier": fourier_runner.run,
    "fourier_pattern": pattern_runner.run,
}


def run_job(cfg: DictConfig) -> float | None:
    """Run one job; returns the headline error (for Hydra sweepers) when there is one."""
    name = cfg.method.name
    if name not in METHODS:
        raise KeyError(f"method.name={name!r} is not one of {sorted(METHODS)}")
    k = f" k={cfg.method.k}" if name == "clustered" else ""
    run_name = f"{name}{k} s{cfg.seed}"
    with job_run(cfg, run_name=run_name):
        ctx = Context.from_config(cfg)
        try:
            metrics = METHODS[name](ctx)
        finally:
            mlflow.set_tags({f"cache.{stage}": key for stage, key in ctx.keys.items()})
            mlflow.log_metrics({f"seconds_{s}": t for s, t in ctx.seconds.items()})
            mlflow.log_metrics({f"peak_rss_mb_{s}": v for s, v in ctx.peak_rss_mb.items()})
            mlflow.log_metric("peak_rss_mb", process_peak_mb())
        mlflow.log_metrics(metrics)
    return metrics.get("rmse")
