"""``python -m pipeline``: the Hydra application (see conf/config.yaml)."""

import re
import sys

import hydra
from omegaconf import DictConfig

from pipeline.app import run_job

# Method A's settings moved from the root of the config to btf.* (its own config group).
_MOVED = re.compile(r"^([+~]{0,2})(crop|pca|kmeans|model|sizes|interpolation)([.=].*)$")


def moved_settings(overrides: list[str]) -> list[str]:
    """A message for each command-line override that uses a setting's old spelling."""
    return [f"{arg!r}: method A's settings moved under btf., write "
            f"{m.group(1)}btf.{m.group(2)}{m.group(3)!s}"
            for arg in overrides if (m := _MOVED.match(arg))]


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> float | None:
    return run_job(cfg)


if __name__ == "__main__":
    if problems := moved_settings(sys.argv[1:]):
        sys.exit("\n".join(problems))
    main()
