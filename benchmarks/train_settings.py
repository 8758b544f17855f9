"""The settings of ``python -m benchmarks.train``, given as ``key=value`` arguments like every
other command's (``paths.runs=...``), read without torch so that a bad argument is
answered at once, before the seconds torch takes to load.

>>> parse(["steps=5", "paths.runs=/tmp/runs", "mlflow=false"])
BenchSettings(steps=5, threads=None, device='cpu', runs='/tmp/runs', mlflow=False, paper_run=0, load_size=0)
>>> parse(["steps=0"])
Traceback (most recent call last):
...
pipeline.core.errors.ConfigError: steps=0 must be an integer >= 1
"""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.core import cli
from pipeline.core.settings import Integer, OneOf

PROG = "python -m benchmarks.train"
DECODER_MACS = 12 * 106 + 2 * 106 * 106 + 106 * 3  # per query: the paper decoder's products


@dataclass(frozen=True)
class BenchSettings:
    """The bench's settings; :data:`KEYS` describes each (``runs`` is ``paths.runs``)."""

    steps: int = 30
    threads: int | None = None
    device: str = "cpu"
    runs: str = "runs"
    mlflow: bool = True
    paper_run: int = 0
    load_size: int = 0


# Each key of the command line: its field, what it may be, and what it sets.
KEYS = {
    "steps": ("steps", Integer(1), "training steps per timing"),
    "threads": ("threads", Integer(1, optional=True), "CPU threads (null: all cores)"),
    "device": (
        "device",
        OneOf("cpu", "cuda"),
        "cpu: every figure, both training backends on the CPU; cuda: the training "
        "loops at the paper's batch on the GPU, per backend and precision, and at "
        "paper_cpu's batch (and paper_run, load_size when asked)",
    ),
    "paths.runs": ("runs", cli.Text(), "the folder holding mlflow.db (and paper_run's outputs)"),
    "mlflow": (
        "mlflow",
        OneOf(True, False),
        "log the figures to MLflow (experiment bench under paths.runs)",
    ),
    "paper_run": (
        "paper_run",
        Integer(0),
        "also run paper-size jobs with this many training steps and report each "
        "stage's time and peak RSS (0: not run)",
    ),
    "load_size": (
        "load_size",
        Integer(0),
        "also time loading a 6561-file UBO2003 folder of this texture size "
        "(256 = the real datasets; 0: not run)",
    ),
}


COMMAND = cli.Command(
    PROG,
    KEYS,
    BenchSettings,
    "Method A's training benchmark (benchmarks/train_figures.py). Settings and their defaults:",
    what="the bench",
    notes="Timings are medians of interleaved rounds: compare them as ratios within one run.",
)
usage = COMMAND.usage
parse = COMMAND.parse  # raises ConfigError naming a bad argument (and the closest key)
parse_args = COMMAND.parse_args  # --help: usage, exit 0; a bad argument: its error, exit 2
