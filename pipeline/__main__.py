"""``python -m pipeline``: the Hydra application (see conf/config.yaml)."""

# First: a stop during the imports below must end the process saying so.
from pipeline.core import stopping

if __name__ == "__main__":  # the command only: importing this module installs nothing
    stopping.install()

import sys

import hydra
from omegaconf import DictConfig

from pipeline.core.errors import ConfigError, PipelineError
from pipeline.core.methods import CONF_DIR, register_schemas
from pipeline.core.refusal import check_command_line, debugging, refuse
from pipeline.core.settings import check_added_keys


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> float | None:
    from hydra.core.hydra_config import HydraConfig

    # A typo is answered here, before the job imports torch and MLflow.
    try:
        check_added_keys(
            cfg,
            list(HydraConfig.get().overrides.task),
            CONF_DIR,
            compose=lambda overrides: hydra.compose("config", overrides),
        )
        from pipeline.app import run_job

        return run_job(cfg)
    except PipelineError as error:  # a bad setting or file, a full disk: its message is the answer
        if debugging():
            raise
        refuse(error)


if __name__ == "__main__":
    register_schemas()  # the settings dataclasses the YAML files extend, before composing
    if not debugging():
        try:  # Hydra's own errors (a misspelt key, a wrong type) as one line, before any job
            check_command_line(sys.argv[1:], CONF_DIR)
        except ConfigError as error:
            refuse(error)
    main()
