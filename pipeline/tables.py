r"""``python -m pipeline.tables``: regenerate the papers' tables and figures from MLflow.

The finished runs are read once and, one MLflow experiment at a time (a table never mixes
experiments), handed to the reports of the registered methods that have runs there, which
write tables (Markdown, CSV, LaTeX) and figures into ``${paths.runs}/tables/<experiment>/``
with its ``summary.md``/``.html``; ``tables/summary.md``/``.html`` hold them all. The set is
written into a new folder that replaces ``tables/`` whole (with ``tables.experiments`` set,
the other experiments' folders are kept). Experiments or a filter that match nothing are an
error, as is a ``paths.runs`` without a store. Options (Hydra overrides): ``paths.runs=...``,
``tables.experiments=[btf,...]``, ``"tables.filter=\"tags.note = 'x'\""`` (quoted for the shell).
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import sys
from pathlib import Path

import hydra
import pandas as pd
from omegaconf import DictConfig

from pipeline.core.methods import CONF_DIR, Method, registered, resolve
from pipeline.core.report import (
    TABLES_EXPERIMENT,
    fetch_runs,
    runs_of,
    safe_stem,
    summary_html,
    write_file,
)
from pipeline.core.report import tables_settings as default_settings
from pipeline.core.run import environment_tags
from pipeline.core.store import NOTE_TAG, init_store, tracking_uri

log = logging.getLogger(__name__)
SUMMARY = "summary.md"
LIMIT = 12  # lines of one method's verdict on a sweep; the tables hold the rest


def build_tables(
    runs_dir: str | Path, settings: DictConfig | None = None, log_to: str | None = None
) -> Path:
    """Write every method's tables and figures, one folder per MLflow experiment; returns
    ``tables/<experiment>/`` when the runs read are of one experiment, else ``tables/``.
    Everything written is also logged under ``tables/`` to the MLflow run ``log_to`` (the
    sweep's parent) or, when None, to a run of its own in the experiment ``tables``.

    Raises
    ------
    StoreError
        When ``runs_dir`` holds no MLflow store.
    ConfigError
        When ``settings.experiments`` names an experiment the store lacks, or
        ``settings.filter`` matches no run.
    """
    settings = settings if settings is not None else default_settings()
    chosen = list(settings.experiments or [])
    runs = fetch_runs(runs_dir, chosen, settings.filter)
    by_experiment = _by_experiment(runs, chosen)
    out = Path(runs_dir) / "tables"
    new = Path(runs_dir) / f".tables.new-{os.getpid()}"
    shutil.rmtree(new, ignore_errors=True)
    new.mkdir(parents=True)
    try:
        if chosen and out.is_dir():  # the other experiments' tables stay as they were
            for kept in out.iterdir():
                if kept.is_dir() and kept.name not in {safe_stem(e) for e in chosen}:
                    shutil.copytree(kept, new / kept.name)
        for experiment, of_experiment in by_experiment.items():
            write_experiment(
                runs_dir, experiment, of_experiment, new / safe_stem(experiment), settings
            )
        write_index(new, tracking_uri(runs_dir))
        replace_folder(out, new)
    finally:
        shutil.rmtree(new, ignore_errors=True)
    written = out / safe_stem(next(iter(by_experiment))) if len(by_experiment) == 1 else out
    log.info("tables written to %s", written)
    log_tables(runs_dir, written, settings, log_to, n_runs=len(runs))
    return written


def _by_experiment(runs: pd.DataFrame, chosen: list[str]) -> dict[str, pd.DataFrame]:
    """The runs of each experiment that has finished runs (and each named one), in order."""
    names = list(chosen) or (sorted(runs["experiment"].unique()) if not runs.empty else [])
    return {name: runs[runs["experiment"] == name] if not runs.empty else runs for name in names}


def report_methods() -> list[tuple[object, list[Method]]]:
    """Each report module of the registered methods with the methods it reports on."""
    pairs: dict[str, list[Method]] = {}
    for method in registered():
        for name in method.reports:
            pairs.setdefault(name, []).append(method)
    return [(resolve(name), methods) for name, methods in pairs.items()]


def write_experiment(
    runs_dir, experiment: str, runs: pd.DataFrame, folder: Path, settings: DictConfig
) -> str:
    """Write one experiment's tables and figures into ``folder`` (made here) with its
    ``summary.md`` and ``summary.html``; return the summary."""
    folder.mkdir(parents=True)
    sections = []
    for report, methods in report_methods():
        of_methods = runs_of(runs, [m.name for m in methods])
        if not of_methods.empty:
            sections += report.sections(of_methods, folder, settings)
    if not sections:
        sections = [f"No finished run in this experiment of {tracking_uri(runs_dir)}.\n"]
    jobs = int(runs["params.method.name"].notna().sum()) if "params.method.name" in runs else 0
    summary = "\n".join([f"# Experiment `{experiment}`: {jobs} finished jobs\n", *sections])
    write_file(folder / SUMMARY, summary)
    write_file(folder / "summary.html", summary_html(summary, folder))
    return summary


def write_index(tables: Path, uri: str) -> None:
    """``summary.md`` and ``summary.html`` of ``tables``: its experiment folders' summaries
    one after the other."""
    folders = sorted(p for p in tables.iterdir() if (p / SUMMARY).is_file())
    parts = [f"# Tables regenerated from MLflow ({uri})\n"]
    if not folders:
        parts.append("No finished run in the store: `python -m pipeline` runs the demo.\n")
    else:
        links = ", ".join(f"[{p.name}/]({p.name}/summary.html)" for p in folders)
        parts.append(f"One section per MLflow experiment, its files in its folder: {links}\n")
    for folder in folders:
        text = (folder / SUMMARY).read_text()
        # Figures are linked by name from their folder's summary: here, by folder/name.
        parts.append(re.sub(r"(!\[[^\]]*\]\()([^)/\s]+\))", rf"\g<1>{folder.name}/\g<2>", text))
    summary = "\n".join(parts)
    write_file(tables / SUMMARY, summary)
    write_file(tables / "summary.html", summary_html(summary, tables))


def replace_folder(old: Path, new: Path) -> None:
    """Put the complete folder ``new`` in the place of ``old`` (two renames: a reader sees
    the old set or the new one, never a mix; a crash between them leaves ``old`` absent)."""
    trash = old.with_name(f".{old.name}.old-{os.getpid()}")
    if old.exists():
        old.rename(trash)
    new.rename(old)
    shutil.rmtree(trash, ignore_errors=True)


def log_tables(runs_dir, out: Path, settings: DictConfig, run_id: str | None, n_runs: int) -> str:
    """Log the ``tables`` folder to run ``run_id``, or to a new run of the experiment
    ``tables`` recording what it read."""
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri(runs_dir))
    if run_id is None:
        note = (
            "`python -m pipeline.tables`: every method's tables and figures, regenerated "
            "from the finished runs of the experiments and filter in its params."
        )
        experiment_id = init_store(
            runs_dir,
            TABLES_EXPERIMENT,
            note=(
                "**Tables**: one run per `python -m pipeline.tables`; its artifacts are the "
                "tables it wrote (open `tables/summary.html`), its params what it read."
            ),
        )
        tags = {**environment_tags(), NOTE_TAG: note}
        run = client.create_run(experiment_id, run_name=f"tables {out.name}", tags=tags)
        client.log_param(
            run.info.run_id, "tables.experiments", str(list(settings.experiments or []))
        )
        client.log_param(run.info.run_id, "tables.filter", str(settings.filter))
        client.log_param(run.info.run_id, "tables.runs_read", str(n_runs))
        client.log_artifacts(run.info.run_id, str(out), "tables")
        client.set_terminated(run.info.run_id, "FINISHED")
        return run.info.run_id
    client.log_artifacts(run_id, str(out), "tables")
    return run_id


def verdict(runs: pd.DataFrame, limit: int = LIMIT) -> list[str]:
    """A few lines saying what ``runs`` found: each method's report's ``verdict(runs,
    limit)`` where it has one, else each run's headline metrics."""
    lines: list[str] = []
    for report, methods in report_methods():
        of_methods = runs_of(runs, [m.name for m in methods])
        if of_methods.empty or not hasattr(report, "verdict"):
            continue
        lines += report.verdict(of_methods, limit)
        runs = runs.drop(of_methods.index)
    for method in registered():
        shown = []
        for _, run in runs_of(runs, [method.name]).iterrows():
            values = [
                f"{h} {run[f'metrics.{h}']:.4g}"
                for h in method.headline
                if pd.notna(run.get(f"metrics.{h}"))
            ]
            shown.append(f"  {run.get('tags.mlflow.runName', run['run_id'])}: " + ", ".join(values))
        lines += shown[:limit] + (
            [f"  … and {len(shown) - limit} more runs"] if len(shown) > limit else []
        )
    return lines


def refuse_a_missing_store(argv: list[str]) -> None:
    """Before Hydra makes its output folder: a ``paths.runs`` without an MLflow store ends
    the command in one line naming the path."""
    from hydra import compose, initialize_config_dir

    from pipeline.core.errors import ConfigError, StoreError
    from pipeline.core.refusal import check_command_line, debugging, refuse

    if debugging():
        return
    try:
        check_command_line(argv, CONF_DIR, "tables")
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose("tables", overrides=[a for a in argv if not a.startswith("-")])
        tracking_uri(cfg.paths.runs)
    except (ConfigError, StoreError) as error:
        refuse(error)


@hydra.main(version_base="1.3", config_path="conf", config_name="tables")
def main(cfg: DictConfig) -> None:
    from pipeline.core.errors import PipelineError
    from pipeline.core.refusal import debugging, refuse

    try:
        out = build_tables(cfg.paths.runs, cfg.tables)
    except PipelineError as error:  # a typo in an experiment's name, a filter: one line
        if debugging():
            raise
        refuse(error)
    tables = out if out.name == "tables" else out.parent
    folders = sorted(p.name for p in tables.iterdir() if (p / SUMMARY).is_file())
    print(
        f"tables of {len(folders)} experiments ({', '.join(folders) or 'none'}) in "
        f"{tables.resolve()}/<experiment>/; all of them: {tables.resolve() / 'summary.html'}"
    )


if __name__ == "__main__":
    refuse_a_missing_store(sys.argv[1:])
    main()
