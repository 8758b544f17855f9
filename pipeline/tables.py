r"""``python -m pipeline.tables``: regenerate the papers' tables and figures from MLflow.

Reads the finished runs back once (``mlflow.search_runs``, with the user's experiments and
filter) and hands them to each method's report (:mod:`pipeline.btf.report`,
:mod:`pipeline.brdf_map.report`, :mod:`pipeline.fourier.report`), which write their
tables (Markdown, CSV, LaTeX) and figures (PNG, EXR) under ``${paths.runs}/tables/``; all
sections go into ``summary.md``. Works with whatever subset of runs exists and says what
is missing. Options (Hydra overrides): ``paths.runs=...``,
``tables.experiments=[btf,...]``, ``"tables.filter=\"tags.note = 'x'\""`` (quoted for the shell).
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from pipeline.brdf_map import report as brdf_map_report
from pipeline.btf import report as btf_report
from pipeline.core.report import TABLES_EXPERIMENT, fetch_runs, write_file
from pipeline.core.tracking import NOTE_TAG, environment_tags, init_store, tracking_uri
from pipeline.fourier import report as fourier_report
from pipeline.render import report as render_report

log = logging.getLogger(__name__)
CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
REPORTS = (btf_report, render_report, brdf_map_report, fourier_report)  # A, A's renders, B, C


def default_settings() -> DictConfig:
    """The ``tables`` section of ``conf/tables.yaml`` (used after a sweep ends)."""
    return OmegaConf.load(CONF_DIR / "tables.yaml").tables


def build_tables(
    runs_dir: str | Path, settings: DictConfig | None = None, log_to: str | None = None
) -> Path:
    """Write every method's tables and figures; returns the ``tables`` folder.

    Everything written is also logged under ``tables/`` to the MLflow run ``log_to`` (the
    sweep's parent) or, when None, to a run of its own in the experiment ``tables``.
    """
    settings = settings if settings is not None else default_settings()
    out = Path(runs_dir) / "tables"
    out.mkdir(parents=True, exist_ok=True)
    runs = fetch_runs(runs_dir, list(settings.experiments or []), settings.filter)
    sections = [f"# Tables regenerated from MLflow ({tracking_uri(runs_dir)})\n"]
    for report in REPORTS:
        sections += report.sections(runs, out, settings)
    summary = "\n".join(sections)
    write_file(out / "summary.md", summary)
    print(summary)
    log.info("tables written to %s", out)
    log_tables(runs_dir, out, settings, log_to, n_runs=len(runs))
    return out


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


@hydra.main(version_base="1.3", config_path="../conf", config_name="tables")
def main(cfg: DictConfig) -> None:
    build_tables(cfg.paths.runs, cfg.tables)


if __name__ == "__main__":
    main()
