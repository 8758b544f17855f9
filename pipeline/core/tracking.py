"""MLflow tracking: one run per Hydra job, a parent run per sweep.

The store is SQLite at ``${paths.runs}/mlflow.db`` with artifacts in
``${paths.runs}/artifacts`` unless ``MLFLOW_TRACKING_URI`` points at a shared server.
MLflow 3.x creates its SQLite schema on first use and several processes doing that at
once crash ("duplicate column"), so :func:`init_store` creates it under a file lock
before any job logs; sweeps call it once in the launching process as well.
"""

from __future__ import annotations

import atexit
import fcntl
import logging
import os
import subprocess
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from importlib import metadata
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from pipeline.core.recipe import recipe_id

log = logging.getLogger(__name__)

_OWN_URI = "PIPELINE_TRACKING_URI_SET_BY_PIPELINE"
PARENT_RUN_FILE = "mlflow_parent_run_id"
PACKAGES = ("torch", "numpy", "scikit-learn", "mlflow", "hydra-core", "OpenEXR", "pandas")


def tracking_uri(runs: str | os.PathLike) -> str:
    """The tracking URI: ``MLFLOW_TRACKING_URI`` if set, else SQLite under ``runs``."""
    env = os.environ.get("MLFLOW_TRACKING_URI")
    # mlflow.set_tracking_uri exports MLFLOW_TRACKING_URI for subprocesses; a value that we
    # set ourselves is not the user's choice of server and must not outlive paths.runs.
    if env and env != os.environ.get(_OWN_URI):
        return env
    return f"sqlite:///{Path(runs).resolve() / 'mlflow.db'}"


def use_store(runs: str | os.PathLike) -> str:
    """Point this process's MLflow client at the store of ``runs``; returns the URI."""
    import mlflow

    uri = tracking_uri(runs)
    mlflow.set_tracking_uri(uri)
    os.environ[_OWN_URI] = uri
    return uri


def init_store(runs: str | os.PathLike, experiment: str) -> str:
    """Create (or upgrade) the store and the experiment once; return the experiment id."""
    from mlflow.tracking import MlflowClient

    runs = Path(runs).resolve()
    runs.mkdir(parents=True, exist_ok=True)
    uri = use_store(runs)
    # The lock serializes schema creation between processes that share this folder.
    with open(runs / ".mlflow.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            client = MlflowClient(uri)
            found = client.get_experiment_by_name(experiment)
            if found is not None:
                return found.experiment_id
            location = None
            if uri.startswith("sqlite:"):
                location = (runs / "artifacts").as_uri()
            return client.create_experiment(experiment, artifact_location=location)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


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
    here = Path(__file__).resolve().parent
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=10
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=here,
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"
    if out.returncode != 0:
        return "unknown"
    return out.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")


def _sweep_dir() -> Path | None:
    """The sweep folder when this process is a job of a Hydra multirun, else None."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        hydra_cfg = HydraConfig.get()
    except (ImportError, ValueError):
        return None
    if hydra_cfg.mode != RunMode.MULTIRUN:
        return None
    return Path(hydra_cfg.sweep.dir)


def _parent_run_id() -> str | None:
    sweep = _sweep_dir()
    if sweep is None:
        return None
    marker = sweep / PARENT_RUN_FILE
    return marker.read_text().strip() if marker.is_file() else None


@contextmanager
def job_run(cfg: DictConfig, run_name: str | None = None) -> Iterator[Any]:
    """Start the MLflow run of one job; it ends FAILED if the body raises."""
    import mlflow

    experiment_id = init_store(cfg.paths.runs, cfg.tracking.experiment)
    tags = environment_tags()
    tags.update({str(k): str(v) for k, v in (cfg.tracking.get("tags") or {}).items()})
    params = flatten(cfg)
    tags["recipe"] = recipe_id(params)  # equal for seeds of one model (pipeline.core.recipe)
    with mlflow.start_run(
        experiment_id=experiment_id,
        run_name=run_name,
        parent_run_id=_parent_run_id(),
        tags=tags,
    ) as run:
        mlflow.log_params({k: _param_value(v) for k, v in params.items()})
        log.info("MLflow run %s in %s", run.info.run_id, tracking_uri(cfg.paths.runs))
        yield run


def _param_value(value: Any) -> str:
    text = str(value)
    return text if len(text) <= 6000 else text[:5997] + "..."


class SweepParentRun(Callback):
    """Hydra callback: one MLflow parent run per multirun, its jobs as children.

    Registered in ``conf/config.yaml`` under ``hydra.callbacks``. The parent's id is
    written into the sweep folder, where every job (joblib worker or SLURM task) reads it.
    """

    def __init__(self) -> None:
        self.run_id: str | None = None
        self.uri: str | None = None

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        from mlflow.tracking import MlflowClient

        experiment_id = init_store(config.paths.runs, config.tracking.experiment)
        self.uri = tracking_uri(config.paths.runs)
        client = MlflowClient(self.uri)
        sweep_dir = Path(config.hydra.sweep.dir)
        sweep_dir.mkdir(parents=True, exist_ok=True)
        tags = environment_tags()
        tags["sweep.dir"] = str(sweep_dir)
        tags["sweep.overrides"] = " ".join(config.hydra.overrides.task)
        run = client.create_run(experiment_id, run_name=f"sweep {sweep_dir.name}", tags=tags)
        self.run_id = run.info.run_id
        (sweep_dir / PARENT_RUN_FILE).write_text(self.run_id)
        # If a job fails, Hydra exits without on_multirun_end: mark the parent FAILED then.
        atexit.register(self._end, "FAILED")
        log.info("MLflow parent run %s for sweep %s", self.run_id, sweep_dir)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        self._end("FINISHED")

    def _end(self, status: str) -> None:
        if self.run_id is None:
            return
        from mlflow.tracking import MlflowClient

        MlflowClient(self.uri).set_terminated(self.run_id, status=status)
        self.run_id = None
