"""Training settings, apart from the torch code so that computing a cache key needs no torch."""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.errors import ConfigError


@dataclass(frozen=True)
class TrainSettings:
    """Optimizer settings (``conf/train/*.yaml``).

    epochs : passes over all texels.
    lr : SGD learning rate (paper: 0.05 Neural BTF, 0.08 clustered).
    batch_size : ABRDFs per step (paper: 5).
    queries_per_abrdf : direction queries per ABRDF per step; -1 for all training directions.
    max_steps : cap on the total number of steps, -1 for none.
    device : ``auto`` (CUDA when present), ``cpu`` or ``cuda``.
    momentum : SGD momentum (the paper: plain SGD, 0).
    optimizer : ``sgd`` (the paper) or ``adam`` (converges in far fewer steps on a CPU).
    threads : CPU threads of torch; None keeps torch's default (all cores). Set it when
        jobs run side by side: torch's threads spin-wait, and two jobs with all cores each
        run several times slower than with their share.
    """

    epochs: int = 1
    lr: float = 0.05
    batch_size: int = 5
    queries_per_abrdf: int = 512
    max_steps: int = -1
    device: str = "auto"
    momentum: float = 0.0
    optimizer: str = "sgd"
    threads: int | None = None

    def __post_init__(self):
        if self.epochs < 1:
            raise ConfigError(f"train.epochs={self.epochs} must be >= 1")
        if self.batch_size < 2:
            # Batch-norm in training mode needs at least two samples.
            raise ConfigError(f"train.batch_size={self.batch_size} must be >= 2")
        if self.lr <= 0:
            raise ConfigError(f"train.lr={self.lr} must be > 0")
        if self.optimizer not in ("sgd", "adam"):
            raise ConfigError(f"train.optimizer={self.optimizer!r} must be sgd or adam")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ConfigError(f"train.device={self.device!r} must be auto, cpu or cuda")
