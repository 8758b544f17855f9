"""The MLflow run of one job (:func:`job_run`); its stages log to it through the
context's :class:`~pipeline.core.run_log.RunLog`."""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import subprocess
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from importlib import metadata
from pathlib import Path
from typing import Any

from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from pipeline.core import stopping
from pipeline.core.errors import PipelineError
from pipeline.core.files import is_disk_full
from pipeline.core.recipe import recipe_id, render_recipe_id
from pipeline.core.store import (
    ENDED_BY_TAG,
    ERROR_TAG,
    NOTE_TAG,
    fail_runs_at_stop,
    hydra_config,
    init_store,
    store_full,
    tracking_uri,
)

log = logging.getLogger(__name__)

PARENT_RUN_FILE = "mlflow_parent_run_id"  # in a sweep's folder: its parent run's id
PACKAGES = ("torch", "numpy", "scikit-learn", "mlflow", "hydra-core", "OpenEXR", "pandas")


def flatten(config: Mapping | DictConfig, prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}``; lists are kept whole as strings."""
    if isinstance(config, DictConfig):
        config = OmegaConf.to_container(config, resolve=True)
    flat: dict[str, Any] = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(flatten(value, name + "."))
        else:
            flat[name] = value
    return flat


def environment_tags() -> dict[str, str]:
    """Git commit of the code and the versions of the packages that shape results."""
    tags = {"git.commit": _git_commit()}
    for package in PACKAGES:
        try:
            tags[f"version.{package}"] = metadata.version(package)
        except metadata.PackageNotFoundError:
            tags[f"version.{package}"] = "absent"
    return tags


def _git_commit() -> str:
    def git(*args: str) -> subprocess.CompletedProcess:
        here = Path(__file__).resolve().parent
        return subprocess.run(["git", *args], cwd=here, capture_output=True, text=True, timeout=10)

    try:
        out = git("rev-parse", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"
    if out.returncode != 0:
        return "unknown"
    return out.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")


def _sweep_dir() -> Path | None:
    """The sweep folder when this process is a job of a Hydra multirun, else None."""
    hydra_cfg = hydra_config()
    if hydra_cfg is None or hydra_cfg.mode != RunMode.MULTIRUN:
        return None
    return Path(hydra_cfg.sweep.dir)


def _parent_run_id() -> str | None:
    sweep = _sweep_dir()
    marker = sweep / PARENT_RUN_FILE if sweep is not None else None
    return marker.read_text().strip() if marker is not None and marker.is_file() else None


@contextmanager
def job_run(
    cfg: DictConfig,
    run_name: str | None = None,
    description: str = "",
    unused: Sequence[str] = (),
) -> Iterator[Any]:
    """Start the MLflow run of one job; it ends FAILED, naming the error, if the body raises.

    The run holds the flattened config as params (less ``unused``), the resolved config,
    the overrides, the code's commit and package versions, ``description`` as its note
    and, under Hydra, Hydra's files and the job's log (``hydra/``), logged as it ends.

    The body's error is the one raised, even when ending the run fails too (the run is
    then left RUNNING for the next start to mark FAILED). A full disk met writing the
    store is raised as :func:`store_full`'s error.
    """
    import mlflow

    experiment_id = init_store(cfg.paths.runs, cfg.tracking.experiment, job=cfg)
    uri = tracking_uri(cfg.paths.runs)
    fail_runs_at_stop(uri)
    tags = environment_tags()
    tags.update({str(k): str(v) for k, v in (cfg.tracking.get("tags") or {}).items()})
    params = {k: v for k, v in flatten(cfg).items() if k not in set(unused)}
    tags["recipe"] = recipe_id(params)  # equal for seeds of one model (pipeline.core.recipe)
    if any(key.startswith("btf.render.") for key in params):
        tags["render_recipe"] = render_recipe_id(params)  # and rendered alike
    # Who runs it: a later start marks it FAILED if this process dies without ending it.
    tags.update(host=socket.gethostname(), pid=str(os.getpid()))
    overrides = _task_overrides()
    tags["overrides"] = " ".join(overrides)
    if description:
        tags[NOTE_TAG] = description
    run_id = status = None  # the run, and the status it is left with when the job fails
    try:
        with mlflow.start_run(
            experiment_id=experiment_id,
            run_name=run_name,
            parent_run_id=_parent_run_id(),
            tags=tags,
        ) as run:
            run_id = run.info.run_id
            try:
                # Unset settings as "None": the tables compare a null like any other value.
                mlflow.log_params({k: param_value(v) for k, v in params.items()})
                mlflow.log_text(OmegaConf.to_yaml(cfg, resolve=True), "config/resolved.yaml")
                mlflow.log_text(OmegaConf.to_yaml(overrides), "config/overrides.yaml")
                log.info("MLflow run %s in %s", run_id, uri)
                yield run
                stopping.check()  # a stop the job's code swallowed: the run ends FAILED
                _log_hydra_output()
            except BaseException as error:
                # A refused setting or file, a full disk: the run says which (if it can).
                named = error if isinstance(error, PipelineError) else store_full(error, uri)
                if named is not None:
                    with contextlib.suppress(Exception):
                        mlflow.set_tag(ERROR_TAG, " ".join(str(named).split())[:5000])
                if stopping.requested() is not None:
                    with contextlib.suppress(Exception):
                        mlflow.set_tag(ENDED_BY_TAG, f"stopped by {stopping.describe()}")
                with contextlib.suppress(Exception):
                    _log_hydra_output()
                status = _end_failed_run(run_id)
                raise
    except Exception as error:
        # Also when the run could not be created, or not ended FINISHED (left RUNNING).
        full = store_full(error, uri, run_id, status)
        if full is None:
            raise
        raise full from error


def _end_failed_run(run_id: str) -> str:
    """End the active run FAILED before mlflow.start_run's exit would (whose error would
    replace the job's); returns FAILED, or RUNNING when the store cannot take it."""
    import mlflow

    try:
        mlflow.end_run("FAILED")  # takes it off MLflow's stack first, whatever follows
    except Exception as error:
        why = "the disk is full" if is_disk_full(error) else type(error).__name__
        log.warning("run %s is left RUNNING (%s): the next start marks it FAILED", run_id, why)
        return "RUNNING"
    return "FAILED"


def _task_overrides() -> list[str]:
    hydra_cfg = hydra_config()
    return list(hydra_cfg.overrides.task) if hydra_cfg is not None else []


def _log_hydra_output() -> None:
    """Log the job's Hydra folder (``.hydra/``: config, overrides; the job's ``.log``)."""
    import mlflow

    hydra_cfg = hydra_config()
    if hydra_cfg is None or not hydra_cfg.runtime.output_dir:
        return
    output = Path(hydra_cfg.runtime.output_dir)
    for handler in logging.getLogger().handlers:
        handler.flush()  # the job's .log file holds every line written so far
    for path in sorted(output.glob(".hydra/*.yaml")) + sorted(output.glob("*.log")):
        mlflow.log_artifact(str(path), "hydra")


def param_value(value: Any) -> str:
    text = str(value)
    return text if len(text) <= 6000 else text[:5997] + "..."
