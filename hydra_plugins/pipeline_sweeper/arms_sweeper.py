"""The sweeper of ``conf/hydra/sweeper/arms.yaml``: Hydra's basic sweeper with arms, the
command line replacing what it names (:func:`pipeline.core.sweeper.expand` says how).
Hydra finds sweepers only in the ``hydra_plugins`` namespace, hence this module."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from omegaconf import OmegaConf

from pipeline.core.sweeper import expand

log = logging.getLogger(__name__)


class ArmsSweeper(BasicSweeper):
    """Hydra's basic sweeper with arms, the command line replacing what it names."""

    def __init__(
        self, max_batch_size: int | None, params: dict | None = None, arms: list | None = None
    ) -> None:
        super().__init__(max_batch_size=max_batch_size, params=params)
        self.arms = [dict(arm) for arm in arms] if arms else None

    def sweep(self, arguments: list[str]) -> Any:
        """BasicSweeper.sweep with the jobs of :func:`expand` (its own crosses
        ``params`` with ``arguments``)."""
        jobs = expand(self.arms, self.params, list(arguments), announce=log.info)
        size = self.max_batch_size or max(len(jobs), 1)
        self.overrides = [jobs[i : i + size] for i in range(0, len(jobs), size)]
        sweep_dir = Path(self.config.hydra.sweep.dir)
        sweep_dir.mkdir(parents=True, exist_ok=True)
        OmegaConf.save(self.config, sweep_dir / "multirun.yaml")
        returns, first = [], 0
        while not self.is_done():
            batch = self.get_job_batch()
            # Every job composes and is checked before any runs (what Hydra's own
            # validate_batch_is_legal does, a composition per job, is part of this).
            self.check_settings(batch)
            results = self.launcher.launch(batch, initial_job_idx=first)
            for result in results:
                _ = result.return_value  # raises where the job failed
            first += len(batch)
            returns.append(results)
        return returns

    def check_settings(self, batch) -> None:
        """Each job's settings checked by its method (``Method.check``) before any job
        runs: a bad value in the last job must not wait for the first to train."""
        from pipeline.core.errors import ConfigError
        from pipeline.core.methods import method_of
        from pipeline.core.refusal import debugging, refuse

        loader = self.hydra_context.config_loader
        for number, overrides in enumerate(batch):
            cfg = loader.load_sweep_config(
                master_config=self.config, sweep_overrides=list(overrides)
            )
            job = OmegaConf.masked_copy(cfg, [key for key in cfg if key != "hydra"])
            method = method_of(job)
            try:
                if method.check is not None:
                    method.check(job)
            except ConfigError as error:
                if debugging():
                    raise
                refuse(
                    ConfigError(
                        f"job #{number} ({' '.join(overrides)}): {error}; no job of the sweep ran"
                    )
                )
