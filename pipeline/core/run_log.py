"""What a job's stages log to its MLflow run, through the context (``ctx.log``).

:data:`NO_RUN`, the context's default, does nothing, so a stage runs alike in a job, a
test or a benchmark and never asks MLflow whether a run is active. MLflow is imported
only when something is logged.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from collections.abc import Mapping, Sequence
from typing import Any


def _mlflow():
    """The ``mlflow`` module, imported on first use."""
    import mlflow

    return mlflow


class RunLog:
    """What a job's stages log to its MLflow run: metrics, tags, files. The job
    (:func:`pipeline.app.run_job`) puts one that logs on its context, inside its run."""

    def __init__(self, on: bool) -> None:
        self.on = on

    def metric(self, name: str, value: float, step: int | None = None) -> None:
        if self.on:
            _mlflow().log_metric(name, value, step=step)

    def metrics(self, values: Mapping[str, float], step: int | None = None) -> None:
        if self.on and values:
            _mlflow().log_metrics(dict(values), step=step)

    def series(self, name: str, values: Sequence[tuple[int, float]]) -> None:
        """A whole curve, ``(step, value)`` pairs, in one batch (not a call per step)."""
        if not self.on or not values:
            return
        from mlflow.entities import Metric
        from mlflow.tracking import MlflowClient

        now = int(time.time() * 1000)
        batch = [Metric(name, float(value), now, int(step)) for step, value in values]
        MlflowClient().log_batch(_mlflow().active_run().info.run_id, metrics=batch)

    def tags(self, values: Mapping[str, str]) -> None:
        if self.on and values:
            _mlflow().set_tags(dict(values))

    def file(self, path: str | os.PathLike, folder: str | None = None) -> None:
        if self.on:
            _mlflow().log_artifact(str(path), folder)

    def files(self, named: Mapping[str, str | os.PathLike], folder: str) -> None:
        """Files under new names: ``{name in the run: path}``, under ``folder``."""
        if not self.on:
            return
        with tempfile.TemporaryDirectory() as tmp:
            for name, path in named.items():
                shutil.copyfile(path, os.path.join(tmp, name))
            _mlflow().log_artifacts(tmp, folder)

    def folder(self, path: str | os.PathLike, folder: str | None = None) -> None:
        """Every file under ``path``, under ``folder`` of the run's artifacts."""
        if self.on:
            _mlflow().log_artifacts(str(path), folder)

    def arrays(self, values: Mapping[str, Any], name: str) -> None:
        """Arrays as one ``.npz`` file, ``name`` its path in the run (``folder/file.npz``)."""
        if not self.on:
            return
        import numpy as np

        folder, _, file = name.rpartition("/")
        with tempfile.TemporaryDirectory() as tmp:
            np.savez(os.path.join(tmp, file), **values)
            _mlflow().log_artifact(os.path.join(tmp, file), folder or None)

    def text(self, text: str, name: str) -> None:
        if self.on:
            _mlflow().log_text(text, name)

    def json(self, value: Any, name: str) -> None:
        self.text(json.dumps(value, indent=1), name)


NO_RUN = RunLog(on=False)
