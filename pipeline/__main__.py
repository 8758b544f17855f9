"""``python -m pipeline``: the Hydra application (see conf/config.yaml)."""

import hydra
from omegaconf import DictConfig

from pipeline.app import run_job


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> float | None:
    return run_job(cfg)


if __name__ == "__main__":
    main()
