"""The Hydra job: run the chain of the method that ``method.spec`` names
(:class:`pipeline.core.methods.Method`) and record it in MLflow."""

from __future__ import annotations

import contextlib
import logging
import re
import tempfile
from pathlib import Path

from omegaconf import DictConfig
from threadpoolctl import threadpool_limits

from pipeline.core import stopping
from pipeline.core.errors import ConfigError
from pipeline.core.memory import process_peak_mb
from pipeline.core.methods import Method, method_of
from pipeline.core.run import job_run
from pipeline.core.run_log import RunLog
from pipeline.core.settings import Integer
from pipeline.core.stage import Context
from pipeline.core.store import NOTE_TAG, results_url, share_results_view
from pipeline.core.sweep_run import SweepParentRun

log = logging.getLogger(__name__)


def run_job(cfg: DictConfig) -> float | None:
    """Run one job; returns its first headline metric (for Hydra sweepers), if any."""
    import mlflow

    method = method_of(cfg)
    if not Integer(0).ok(cfg.seed):
        raise ConfigError(f"seed={cfg.seed!r} must be an integer >= 0")
    threads = cfg.get("threads")
    if not Integer(1, optional=True).ok(threads):
        raise ConfigError(f"threads={threads!r} must be an integer >= 1 or null (all cores)")
    if method.check is not None:
        method.check(cfg)
    if method.prepare is not None:
        method.prepare(cfg)
    # A stop ends the run FAILED; its temporary files under these folders go with it.
    leftovers = [cfg.paths.get(folder) for folder in ("runs", "cache", "data")]
    name = method.name_run(cfg)
    with (
        stopping.job_scope(leftovers_in=[f for f in leftovers if f]),
        job_run(
            cfg,
            run_name=name,
            description=method.description,
            unused=method.left_out(cfg),
        ) as run,
    ):
        ctx = Context.from_config(cfg, log=RunLog(on=True))
        try:
            with threadpool_limits(cfg.get("threads")):  # numpy's BLAS and OpenMP pools
                metrics = method.run(ctx)
            # The UI lists metrics in the order they were logged: the headline first.
            first = {name: metrics[name] for name in method.headline if name in metrics}
            ctx.log.metrics(first)
            ctx.log.metrics({k: v for k, v in metrics.items() if k not in first})
            if first and method.description:  # the run page shows its note first
                result = ", ".join(f"`{name}` {value:.4g}" for name, value in first.items())
                ctx.log.tags({NOTE_TAG: f"**Result:** {result}\n\n{method.description}"})
            share_results_view(run.info.experiment_id, list(first), cfg)
        except BaseException:
            # The job's error is the answer, not a second one from logging (a full disk).
            with contextlib.suppress(Exception):
                log_usage(ctx)
            raise
        else:
            log_usage(ctx)
            if method.figures is not None:
                log_job_figures(ctx, method)  # reads the entries: released after it
        finally:
            ctx.cache.release()  # the entries it used may go now (pipeline.cache gc)
        artifacts = mlflow.get_artifact_uri()
        print_result(method, name, metrics, run.info.run_id, artifacts, cfg.paths.runs)
    headline = [metrics[name] for name in method.headline if name in metrics]
    return headline[0] if headline else None


def log_usage(ctx: Context) -> None:
    """Log the stages' cache keys (tags), seconds and peak memory to the job's run, under
    "time/" and "memory/" (the UI folds names by their prefix)."""
    ctx.log.tags({f"cache.{stage}": key for stage, key in ctx.keys.items()})
    ctx.log.metrics({f"time/{s}_seconds": t for s, t in ctx.seconds.items()})
    ctx.log.metrics({f"memory/{s}_peak_rss_mb": v for s, v in ctx.peak_rss_mb.items()})
    ctx.log.metric("memory/peak_rss_mb", process_peak_mb())


def log_job_figures(ctx: Context, method: Method) -> None:
    """Draw the job's figures into a temporary folder and log them under ``figures/``."""
    with tempfile.TemporaryDirectory() as folder:
        if method.figures(ctx.cfg, ctx.keys, Path(folder)):
            ctx.log.folder(folder, "figures")


def print_result(
    method: Method, name: str, metrics: dict[str, float], run_id: str, artifacts: str, runs_dir
) -> None:
    """The job's last words: its headline metrics, its run and where its files are."""
    from urllib.parse import unquote, urlparse

    lines = [f"{name}: run {run_id} finished"]
    lines += [f"  {name:<26} {metrics[name]:.6g}" for name in method.headline if name in metrics]
    uri = urlparse(artifacts)
    folder = Path(unquote(uri.path)) if uri.scheme in ("", "file") else None
    lines.append(f"  files    {folder or artifacts}")
    figures = sorted(p.name for p in (folder / "figures").glob("*.png")) if folder else []
    if figures:
        lines.append(f"  figures  {folder / 'figures'}: {', '.join(figures)}")
    lines.append(f"  tables   python -m pipeline.tables paths.runs={runs_dir}")
    print("\n".join(lines), flush=True)


class SweepRun(SweepParentRun):
    """The sweep's MLflow parent run (``hydra.callbacks``) and, with ``run_tables``, its
    experiment's tables after the last job (:func:`print_sweep_result`)."""

    def __init__(self, run_tables: bool = False) -> None:
        super().__init__()
        self.run_tables = run_tables

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        if self.run_id is not None:
            log_headlines(self.uri, self.run_id)
        if self.run_tables:
            print_sweep_result(config, self.uri, self.run_id)
        super().on_multirun_end(config, **kwargs)


def print_sweep_result(config: DictConfig, uri: str | None, parent_id: str | None) -> None:
    """Build the tables of the sweep's experiment, then print what the sweep found
    (:func:`pipeline.tables.verdict`) and where the tables are; the parent run's note
    leads with the same lines."""
    from pipeline.core.report import fetch_runs
    from pipeline.tables import build_tables, default_settings, verdict

    experiment = config.tracking.experiment
    settings = default_settings()
    settings.experiments = [experiment]
    # The parent holds the tables and figures too: the UI shows what the disk does.
    out = build_tables(config.paths.runs, settings, log_to=parent_id)
    runs = fetch_runs(config.paths.runs, [experiment], None)
    if parent_id is not None and "tags.mlflow.parentRunId" in runs:
        runs = runs[runs["tags.mlflow.parentRunId"] == parent_id]
    found = verdict(runs)
    jobs = f"{len(runs)} job{'s' * (len(runs) != 1)}"
    head = f"Sweep finished: {jobs}, MLflow experiment {experiment!r}"
    if parent_id is not None:
        head += f", parent run {parent_id}"
    tables = Path(config.paths.runs) / "tables"
    lines = [
        head,
        *found,
        f"Tables: {(tables / 'summary.html').resolve()} (this "
        f"experiment's: {(out / 'summary.html').resolve()})",
    ]
    if "experiment_id" in runs and len(runs):
        lines.append(f"In `mlflow ui`: {results_url(str(runs['experiment_id'].iloc[0]))}")
    print("\n".join(lines), flush=True)
    if parent_id is not None and uri is not None and found:
        from mlflow.tracking import MlflowClient

        client = MlflowClient(uri)
        note = client.get_run(parent_id).data.tags.get(NOTE_TAG, "")
        result = "**Result**\n\n```\n" + "\n".join(found) + "\n```\n\n"
        client.set_tag(parent_id, NOTE_TAG, result + note)


def log_headlines(uri: str, parent_id: str) -> None:
    """Log each finished child run's headline metrics to the sweep's parent run as
    ``<job>/<metric>``: ``<job>`` is the child's run name, with its swept settings where
    two children share a name."""
    from collections import Counter

    from mlflow.entities import Metric
    from mlflow.tracking import MlflowClient

    from pipeline.core.methods import resolve

    client = MlflowClient(uri)
    parent = client.get_run(parent_id)
    swept = {key for key, value in parent.data.params.items() if "," in value}  # a list
    query = f"tags.mlflow.parentRunId = '{parent_id}'"
    children = [
        child
        for child in client.search_runs([parent.info.experiment_id], query)
        if child.info.status == "FINISHED" and child.data.params.get("method.spec")
    ]
    names = Counter(child.info.run_name for child in children)
    values = []
    for child in children:
        job = child.info.run_name or child.info.run_id
        if names[child.info.run_name] > 1:
            job += " " + " ".join(
                o
                for o in child.data.tags.get("overrides", "").split()
                if o.split("=")[0] in swept and not o.startswith("seed=")
            )
        # MLflow takes letters, digits and "_-. :/" in a metric's name.
        job = re.sub(r"[^\w\-. :/]", "_", job.strip())
        ended = child.info.end_time or 0
        for name in resolve(child.data.params["method.spec"]).headline:
            if name in child.data.metrics:
                values.append(Metric(f"{job}/{name}", child.data.metrics[name], ended, 0))
    if values:
        client.log_batch(parent_id, metrics=values)
