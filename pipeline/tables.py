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
from pipeline.core.report import fetch_runs
from pipeline.core.tracking import tracking_uri
from pipeline.fourier import report as fourier_report

log = logging.getLogger(__name__)
CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
REPORTS = (btf_report, brdf_map_report, fourier_report)  # methods A, B, C


def default_settings() -> DictConfig:
    """The ``tables`` section of ``conf/tables.yaml`` (used after a sweep ends)."""
    return OmegaConf.load(CONF_DIR / "tables.yaml").tables


def build_tables(runs_dir: str | Path, settings: DictConfig | None = None) -> Path:
    """Write every method's tables and figures; returns the ``tables`` folder."""
    settings = settings if settings is not None else default_settings()
    out = Path(runs_dir) / "tables"
    out.mkdir(parents=True, exist_ok=True)
    runs = fetch_runs(runs_dir, list(settings.experiments or []), settings.filter)
    sections = [f"# Tables regenerated from MLflow ({tracking_uri(runs_dir)})\n"]
    for report in REPORTS:
        sections += report.sections(runs, out, settings)
    summary = "\n".join(sections)
    (out / "summary.md").write_text(summary)
    print(summary)
    log.info("tables written to %s", out)
    return out


@hydra.main(version_base="1.3", config_path="../conf", config_name="tables")
def main(cfg: DictConfig) -> None:
    build_tables(cfg.paths.runs, cfg.tables)


if __name__ == "__main__":
    main()
