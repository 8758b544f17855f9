"""A sweep's MLflow parent run: one per Hydra multirun, its jobs as child runs."""

from __future__ import annotations

import atexit
import logging
import os
import socket
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from pipeline.core import stopping
from pipeline.core.errors import PipelineError
from pipeline.core.process import stop_children
from pipeline.core.run import PARENT_RUN_FILE, environment_tags, param_value
from pipeline.core.store import ENDED_BY_TAG, NOTE_TAG, fail_runs_at_stop, init_store, tracking_uri
from pipeline.core.sweeper import expand

log = logging.getLogger(__name__)


def swept_settings(config: DictConfig) -> dict[str, str]:
    """Each setting the multirun's jobs set, with its values in job order, from the jobs
    the sweeper launches (:func:`pipeline.core.sweeper.expand`: its arms, its axes and the
    command line): ``{"model": "neural_btf,clustered", "model.k": "128", "seed": "0,1"}``."""
    sweeper = config.hydra.sweeper
    jobs = expand(sweeper.get("arms"), sweeper.get("params"), list(config.hydra.overrides.task))
    values: dict[str, list[str]] = {}
    for job in jobs:
        for line in job:
            key, _, value = line.partition("=")
            given = values.setdefault(key.lstrip("+~"), [])
            if value not in given:
                given.append(value)
    return {key: ",".join(given) for key, given in values.items()}


class SweepParentRun(Callback):
    """Hydra callback (``hydra.callbacks``): one MLflow parent run per multirun, its jobs
    as children, which read its id from the sweep folder. When the launching process is
    stopped, the parent run ends FAILED, then the workers are stopped (their runs end
    FAILED too); workers also stop by themselves when the launcher is killed outright.
    """

    def __init__(self) -> None:
        self.run_id: str | None = None
        self.uri: str | None = None
        self._on_stop: list[int] = []  # tokens of pipeline.core.stopping.on_stop

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        from mlflow.tracking import MlflowClient

        from pipeline.core.refusal import debugging, refuse

        try:
            experiment_id = init_store(config.paths.runs, config.tracking.experiment, job=config)
        except PipelineError as error:  # a damaged store, a full disk: one line, no job runs
            if debugging():
                raise
            refuse(error)  # Hydra would only warn of an error and start the jobs
        self.uri = tracking_uri(config.paths.runs)
        client = MlflowClient(self.uri)
        sweep_dir = Path(config.hydra.sweep.dir)
        sweep_dir.mkdir(parents=True, exist_ok=True)
        tags = environment_tags()
        tags["sweep.dir"] = str(sweep_dir)
        swept = swept_settings(config)
        tags["sweep.overrides"] = " ".join(f"{k}={v}" for k, v in swept.items())
        # A later start marks the parent FAILED if this process dies.
        tags.update(host=socket.gethostname(), pid=str(os.getpid()))
        tags[NOTE_TAG] = (
            f"**Hydra sweep** over `{tags['sweep.overrides'] or 'one job'}`. Its jobs are the "
            "child runs below; each one's headline metrics are logged here as "
            "`<job>/<metric>` when the sweep ends, and the tables (when the experiment "
            "builds them) under `tables/`."
        )
        run = client.create_run(experiment_id, run_name=f"sweep {sweep_dir.name}", tags=tags)
        self.run_id = run.info.run_id
        # What the sweep varies (each job's value is among its own params) and what it fixes.
        for key, value in swept.items():
            client.log_param(self.run_id, key, param_value(value))
        (sweep_dir / PARENT_RUN_FILE).write_text(self.run_id)
        # If a job fails, Hydra exits without on_multirun_end: mark the parent FAILED then.
        atexit.register(self._end, "FAILED")
        # At a stop signal: the parent first, then the workers, then their runs (LIFO).
        fail_runs_at_stop(self.uri)
        os.environ[stopping.LAUNCHER_ENV] = f"{os.getpid()}@{socket.gethostname()}"
        folders = [config.paths.get(name) for name in ("runs", "cache", "data")]
        self._on_stop = [
            stopping.on_stop(lambda: stop_children([f for f in folders if f])),
            stopping.on_stop(self._stopped),
        ]
        log.info("MLflow parent run %s for sweep %s", self.run_id, sweep_dir)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        for token in self._on_stop:
            stopping.forget(token)
        self._end("FINISHED")

    def _stopped(self) -> None:
        run_id = self.run_id
        if run_id is not None:
            from mlflow.tracking import MlflowClient

            why = f"stopped by {stopping.describe()}"
            MlflowClient(self.uri).set_tag(run_id, ENDED_BY_TAG, why)
            self._end("FAILED")
            log.error("sweep run %s ends FAILED; stopping its workers", run_id)

    def _end(self, status: str) -> None:
        if self.run_id is None:
            return
        from mlflow.tracking import MlflowClient

        MlflowClient(self.uri).set_terminated(self.run_id, status=status)
        self.run_id = None
