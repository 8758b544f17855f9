"""Report writing shared by the methods: runs read back from MLflow, tables on disk.

Each method's ``report`` module turns a DataFrame of runs (as ``mlflow.search_runs``
returns them) into Markdown sections, writing its tables with :func:`write_table`. Every
file is written atomically (:func:`write_file`); a full disk is a DataError naming it.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd
from omegaconf import DictConfig, OmegaConf

from pipeline.core.errors import ConfigError
from pipeline.core.files import write_atomic
from pipeline.core.methods import CONF_DIR
from pipeline.core.store import use_store

TABLES_EXPERIMENT = "tables"  # where `python -m pipeline.tables` logs what it writes
TABLES_HINT = "free some space or point paths.runs elsewhere"


def fetch_runs(runs_dir: str | Path, experiments, filter_string: str | None) -> pd.DataFrame:
    """Finished runs of the given MLflow experiments (all when empty) as one DataFrame,
    with the experiment's name in the column ``experiment``.

    Named experiments that the store lacks, or a filter that matches no run, are a
    ConfigError naming what the store has; a folder without a store is a StoreError.
    """
    import mlflow

    use_store(runs_dir)
    # The tables' own runs hold outputs, not results.
    names_of = {
        e.experiment_id: e.name for e in mlflow.search_experiments() if e.name != TABLES_EXPERIMENT
    }
    found = list(names_of.values())
    missing = [e for e in experiments or [] if e not in found]
    if missing:
        raise ConfigError(
            f"tables.experiments: {missing} not in the store {runs_dir}; "
            f"its experiments: {found or 'none'}"
        )
    names = list(experiments or found)
    if not names:
        return pd.DataFrame()
    runs = mlflow.search_runs(
        experiment_names=names, filter_string=filter_string or "", output_format="pandas"
    )
    if runs.empty and filter_string:
        total = len(mlflow.search_runs(experiment_names=names, output_format="pandas"))
        raise ConfigError(
            f"tables.filter={filter_string!r} matches none of the {total} runs "
            f"of {names} in {runs_dir}"
        )
    if runs.empty:
        return runs
    runs = runs[runs["status"] == "FINISHED"]
    return runs.assign(experiment=runs["experiment_id"].map(names_of))


def logged_arrays(run_id: str, artifact_path: str) -> dict | None:
    """The ``.npz`` a run logged at ``artifact_path`` as ``{name: array}``; None when the
    run has no such file. Any other failure (a server out of reach) is raised."""
    import tempfile

    import mlflow
    import numpy as np
    from mlflow.exceptions import MlflowException

    with tempfile.TemporaryDirectory() as tmp:
        try:
            path = mlflow.artifacts.download_artifacts(
                run_id=run_id, artifact_path=artifact_path, dst_path=tmp
            )
        except MlflowException as error:
            if error.error_code == "RESOURCE_DOES_NOT_EXIST":
                return None
            raise
        with np.load(path) as data:
            return {name: data[name] for name in data.files}


def first_with_data(group: pd.DataFrame, data_of, what: str, log) -> list[tuple[str, dict]]:
    """Per model of ``group`` (labelled runs, sorted), ``(model, data)`` of the first run
    for which ``data_of(run_id)`` is not None; a model without one is named in a warning."""
    found = []
    for model, runs in group.groupby("model", sort=False):
        for _, run in runs.iterrows():
            data = data_of(str(run["run_id"]))
            if data is not None:
                found.append((str(model), data))
                break
        else:
            log.warning("%s: no run of %s logged its data (rerun it); left out", what, model)
    return found


def safe_stem(text: str) -> str:
    """ASCII letters and digits only, the rest "_" (a label like "synthetic 48²×6561" is
    not a file name)."""
    return "".join(c if c.isascii() and c.isalnum() else "_" for c in text)


def write_file(path: Path, content) -> Path:
    """Write a report file atomically (:func:`pipeline.core.files.write_atomic`, whose
    ``content`` it takes); a full disk is a DataError naming ``path``."""
    return write_atomic(path, content, hint=TABLES_HINT)


def save_figure(fig, path: Path, dpi: int = 110) -> Path:
    """Save a Matplotlib figure atomically (:func:`write_file`): whole or absent."""
    return write_file(path, lambda tmp: fig.savefig(tmp, dpi=dpi))


def write_table(
    table: pd.DataFrame, out: Path, stem: str, title: str, note: str = "", floatfmt: str = "g"
) -> str:
    """Write ``stem``.md/.csv/.tex into ``out`` (each atomically); return the Markdown
    section. A missing value is an empty CSV cell and "–" in Markdown and LaTeX;
    ``floatfmt`` formats the Markdown's numbers. A full disk is a DataError naming the file.
    """
    index = table.index.name is not None
    write_file(out / f"{stem}.csv", table.to_csv(index=index))
    write_file(
        out / f"{stem}.tex",
        table.to_latex(index=index, caption=title, label=f"tab:{stem}", na_rep="--"),
    )
    shown = table.astype(object).where(table.notna(), None)  # tabulate: None is missing
    markdown = f"## {title}\n\n{shown.to_markdown(index=index, missingval='–', floatfmt=floatfmt)}\n\n{note}\n"
    write_file(out / f"{stem}.md", markdown)
    return markdown


def param(runs: pd.DataFrame, name: str, default: str = "None") -> pd.Series:
    """The ``params.<name>`` column as strings, ``default`` where a run lacks it."""
    column = runs.get(f"params.{name}", pd.Series(default, index=runs.index))
    return column.fillna(default).astype(str)


def runs_of(runs: pd.DataFrame, methods) -> pd.DataFrame:
    """The runs whose ``method.name`` is one of ``methods``."""
    if runs.empty or "params.method.name" not in runs:
        return runs.iloc[0:0]
    return runs[runs["params.method.name"].isin(list(methods))]


def tables_settings() -> DictConfig:
    """The ``tables`` section of ``conf/tables.yaml``: the tables command's defaults."""
    return OmegaConf.load(CONF_DIR / "tables.yaml").tables


def summary_html(summary: str, folder: Path) -> str:
    """``summary`` (Markdown) as one self-contained HTML page, every image it references
    from ``folder`` inlined as a data URI: the MLflow UI renders an ``.html`` artifact, but
    cannot load a sibling file by a relative link.
    """
    import base64
    import re

    import markdown

    def inline(match: re.Match) -> str:
        path = folder / match.group(2)
        if not path.is_file():
            return match.group(0)
        data = base64.b64encode(path.read_bytes()).decode()
        return f"![{match.group(1)}](data:image/png;base64,{data})"

    body = re.sub(r"!\[([^\]]*)\]\(([^)\s]+\.png)\)", inline, summary)
    html = markdown.markdown(body, extensions=["tables"], output_format="html")
    style = (
        "body{font-family:sans-serif;max-width:1400px;margin:1em}"
        "table{border-collapse:collapse;font-size:13px}"
        "td,th{border:1px solid #ccc;padding:2px 6px;white-space:nowrap}"
        "img{max-width:100%}div.wide{overflow-x:auto}"
    )
    html = html.replace("<table>", '<div class="wide"><table>')
    html = html.replace("</table>", "</table></div>")
    return (
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><style>{style}</style>"
        f"</head><body>{html}</body></html>"
    )
