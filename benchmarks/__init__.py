"""Developer benchmarks and profilers of the pipeline: speed and memory, not correctness.

They live beside the package, not in it (pyproject.toml installs ``pipeline`` and
``hydra_plugins`` only), and run from a checkout's root, where ``python -m`` finds them:

- ``python -m benchmarks.train``: method A's training throughput at the paper's sizes
  (:mod:`benchmarks.train_figures`; ``--help`` lists the settings);
- ``python -m benchmarks.profile_step``: where a training step's time goes;
- ``python -m benchmarks.render``: the cost of a Fig. 8 frame per material;
- ``python -m benchmarks.ubo2014_load``: the peak memory of loading a UBO2014 crop.
- ``python -m benchmarks.ubo2014_chain``: method A's chain on a UBO2014-shaped file, per stage.

The ones that time loops in child interpreters pass :data:`ROOT` on their ``PYTHONPATH``
(:func:`child_env`), so that the children find this folder from any working directory.
"""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]  # the checkout, which holds benchmarks/


def child_env(env: dict[str, str] | None = None) -> dict[str, str]:
    """``env`` (by default this process's environment) with :data:`ROOT` first on
    ``PYTHONPATH``, for a child interpreter that runs ``python -m benchmarks....``."""
    env = dict(os.environ if env is None else env)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    return env
