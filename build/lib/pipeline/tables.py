r"""``python -m pipeline.tables``: regenerate the papers' tables and figures from MLflow.

Reads the finished runs back once (``mlflow.search_runs``, with the user's experiments and
filter) and hands them to the reports of every registered method
(:func:`pipeline.core.methods.registered`), which write their tables (Markdown, CSV,
LaTeX) and figures (PNG, EXR); all sections go into ``summary.md``. The set is written
whole into a new folder that then replaces ``${paths.runs}/tables/``: no file of an
earlier run is left beside it. Works with whatever subset of runs exists and says what
is missing; experiments or a filter that match nothing are an error. Options (Hydra overrides): ``paths.runs=...``,
``tables.experiments=[btf,...]``, ``"tables.filter=\"tags.note = 'x'\""`` (quoted for the shell).
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import hydra
from omegaconf import DictConfig

from pipeline.core.methods import registered, reports
from pipeline.core.report import TABLES_EXPERIMENT, fetch_runs, summary_html, write_file
from pipeline.core.report import tables_settings as default_settings
from pipeline.core.tracking import NOTE_TAG, environment_tags, init_store, tracking_uri

log = logging.getLogger(__name__)


def build_tables(
    runs_dir: str | Path, settings: DictConfig | None = None, log_to: str | None = None
) -> Path:
    """Write every method's tables and figures; returns the ``tables`` folder.

    Everything written is also logged under ``tables/`` to the MLflow run ``log_to`` (the
    sweep's parent) or, when None, to a run of its own in the experiment ``tables``.
    """
    settings = settings if settings is not None else default_settings()
    runs = fetch_runs(runs_dir, list(settings.experiments or []), settings.filter)
    out = Path(runs_dir) / "tables"
    new = Path(runs_dir) / f".tables.new-{os.getpid()}"
    shutil.rmtree(new, ignore_errors=True)
    new.mkdir(parents=True)
    try:
        sections = [f"# Tables regenerated from MLflow ({tracking_uri(runs_dir)})\n"]
        for report in reports(registered()):
            sections += report.sections(runs, new, settings)
        summary = "\n".join(sections)
        write_file(new / "summary.md", summary)
        write_file(new / "summary.html", summary_html(summary, new))
        replace_folder(out, new)
    finally:
        shutil.rmtree(new, ignore_errors=True)
    print(summary)
    log.info("tables written to %s", out)
    log_tables(runs_dir, out, settings, log_to, n_runs=len(runs))
    return out


def replace_folder(old: Path, new: Path) -> None:
    """Put the complete folder ``new`` in the place of ``old`` (two renames, so a reader
    sees the old set or the new one; a crash between them leaves ``old`` absent, never
    mixed)."""
    trash = old.with_name(f".{old.name}.old-{os.getpid()}")
    if old.exists():
        old.rename(trash)
    new.rename(old)
    shutil.rmtree(trash, ignore_errors=True)


def log_tables(runs_dir, out: Path, settings: DictConfig, run_id: str | None, n_runs: int) -> str:
    """Log the ``tables`` folder to run ``run_id``, or to a new run of the experiment
    ``tables`` recording what it read (experiments, filter, number of runs)."""
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri(runs_dir))
    if run_id is None:
        experiment_id = init_store(runs_dir, TABLES_EXPERIMENT)
        tags = environment_tags()
        tags[NOTE_TAG] = (
            "`python -m pipeline.tables`: every method's tables and figures, regenerated "
            "from the finished runs of the experiments and filter in its params."
        )
        run = client.create_run(experiment_id, run_name=f"tables {out.parent.name}", tags=tags)
        run_id = run.info.run_id
        client.log_param(run_id, "tables.experiments", str(list(settings.experiments or [])))
        client.log_param(run_id, "tables.filter", str(settings.filter))
        client.log_param(run_id, "tables.runs_read", str(n_runs))
        client.log_artifacts(run_id, str(out), "tables")
        client.set_terminated(run_id, "FINISHED")
    else:
        client.log_artifacts(run_id, str(out), "tables")
    return run_id


@hydra.main(version_base="1.3", config_path="conf", config_name="tables")
def main(cfg: DictConfig) -> None:
    build_tables(cfg.paths.runs, cfg.tables)


if __name__ == "__main__":
    main()
