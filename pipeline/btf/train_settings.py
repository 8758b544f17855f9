"""Training settings, apart from the torch code so that computing a cache key needs no torch."""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.core.errors import ConfigError
from pipeline.core.settings import LOG, RESULT, SPEED, check_fields, setting

PRECISIONS = ("float32", "bfloat16")  # train.precision
BACKENDS = ("auto", "fused", "autograd")  # train.backend (pipeline.btf.backends)


@dataclass(frozen=True)
class TrainSettings:
    """Optimizer settings (``conf/train/*.yaml``).

    epochs : passes over all texels, or over ``epoch_texels`` texels.
    epoch_texels : None: an epoch is one pass over the crop's M texels; a number: an epoch
        is that many texels whatever M is, so the number of steps (epochs x epoch_texels /
        batch_size) and the schedule do not shrink with the crop (the loss is logged per
        pass over M).
    lr : SGD learning rate (paper: 0.05 Neural BTF, 0.08 clustered).
    batch_size : ABRDFs per step (paper: 5).
    queries_per_abrdf : direction queries per ABRDF per step; -1 for all training directions.
    max_steps : cap on the total number of steps, -1 for none.
    device : ``auto`` (CUDA when present), ``cpu`` or ``cuda``.
    backend : how a step computes its gradients (speed only; :mod:`pipeline.btf.backends`):
        ``autograd``, plain PyTorch (encoder, decoder, mean squared error,
        ``loss.backward()``), always available and the reference; ``fused``, the encoder
        under autograd and the decoder's forward and backward by the hand-written chunked
        step tuned for CPU caches (``pipeline/btf/fast/fused.py``); ``auto``, fused on the
        CPU where its C++ kernels build (autograd, with a warning, where they do not) and
        autograd on CUDA.
    momentum : SGD momentum (the paper: plain SGD, 0).
    optimizer : ``sgd`` (the paper) or ``adam`` (converges in far fewer steps on a CPU).
    lr_half_life : epochs over which the learning rate halves (per step, exponentially);
        0 keeps it constant. The schedule does not depend on the length of the run, so a
        shorter run is exactly the start of a longer one (the RMSE-versus-time curve).
    schedule : ``half_life`` (the above) or ``cosine``: from ``lr`` to 0 over the run's
        steps as half a cosine, ignoring ``lr_half_life``; a longer run stretches it, so
        doubling the run is a convergence check (``conf/train/converged.yaml``).
    curve_every : steps between two points of the RMSE-versus-time curve (RMSE of
        ``curve_texels`` fixed random texels at every training direction); 0 for none.
    curve_texels : texels of that subsample.
    threads : CPU threads that run the decoder's chunks side by side (each op on one
        thread; see ``pipeline/btf/fast/fused.py``); None = all cores. Use 1 when jobs run side
        by side: competing threads spin-wait and run several times slower.
    chunk : queries per chunk of the fused decoder step (speed only); None for the
        precision's default (``pipeline.btf.fast.fused.DEFAULT_CHUNK``: 1024 for float32, whose
        chunk's activations should fit in a core's L2 cache; 8192 for bfloat16).
    keep_awake, omp_spin_count, reuse_freed_memory : opt-in machine tuning, speed only
        (:mod:`pipeline.btf.fast.tuning`): spinning idle-class processes keep the cores
        awake when the job's threads are all its cores; ``GOMP_SPINCOUNT`` for OpenMP's
        idle threads (set when the job starts); glibc keeps freed buffers while training.
    precision : ``float32``, or ``bfloat16`` for the decoder's products (float32 master
        weights and optimizer; see ``pipeline/btf/fast/fused.py``); it pays on CPUs with
        AMX or AVX512-BF16 (``python -m pipeline.bench`` prints which the CPU has). With
        the autograd backend it is ``torch.autocast`` around the decoder (on CUDA, and
        on the CPU alike), which rounds the same products to bfloat16.
    """

    epochs: int = setting(1, role=RESULT)
    epoch_texels: int | None = setting(None, role=RESULT)
    lr: float = setting(0.05, role=RESULT)
    batch_size: int = setting(5, role=RESULT)
    queries_per_abrdf: int = setting(512, role=RESULT)
    max_steps: int = setting(-1, role=RESULT)
    device: str = setting("auto", role=SPEED)
    momentum: float = setting(0.0, role=RESULT)
    optimizer: str = setting("sgd", role=RESULT)
    lr_half_life: float = setting(0.0, role=RESULT)
    schedule: str = setting("half_life", role=RESULT)
    curve_every: int = setting(0, role=LOG)
    curve_texels: int = setting(256, role=LOG)
    threads: int | None = setting(None, role=SPEED)
    chunk: int | None = setting(None, role=SPEED)
    precision: str = setting("float32", role=RESULT)
    backend: str = setting("auto", role=SPEED)
    keep_awake: bool = setting(False, role=SPEED)
    omp_spin_count: int | None = setting(None, role=SPEED)
    reuse_freed_memory: bool = setting(False, role=SPEED)

    def __post_init__(self):
        check_fields(self, "train")  # types first: 1.5 epochs, "abc" as lr, NaN as a count
        if self.epochs < 1:
            raise ConfigError(f"train.epochs={self.epochs} must be >= 1")
        if self.epoch_texels is not None and self.epoch_texels < self.batch_size:
            raise ConfigError(
                f"train.epoch_texels={self.epoch_texels} must be null or >= "
                f"train.batch_size={self.batch_size}"
            )
        if self.batch_size < 2:
            # Batch-norm in training mode needs at least two samples.
            raise ConfigError(f"train.batch_size={self.batch_size} must be >= 2")
        if not self.lr > 0 or self.lr == float("inf"):  # also NaN
            raise ConfigError(f"train.lr={self.lr} must be a finite number > 0")
        if self.queries_per_abrdf != -1 and self.queries_per_abrdf < 1:
            raise ConfigError(
                f"train.queries_per_abrdf={self.queries_per_abrdf} must be "
                f">= 1, or -1 for every training direction"
            )
        if self.max_steps != -1 and self.max_steps < 1:
            raise ConfigError(f"train.max_steps={self.max_steps} must be >= 1, or -1 for none")
        if not 0 <= self.momentum < 1:  # also NaN
            raise ConfigError(f"train.momentum={self.momentum} must be in [0, 1)")
        if self.optimizer not in ("sgd", "adam"):
            raise ConfigError(f"train.optimizer={self.optimizer!r} must be sgd or adam")
        if self.schedule not in ("half_life", "cosine"):
            raise ConfigError(f"train.schedule={self.schedule!r} must be half_life or cosine")
        if not self.lr_half_life >= 0:  # also NaN
            raise ConfigError(f"train.lr_half_life={self.lr_half_life} must be >= 0")
        if self.curve_every < 0 or self.curve_texels < 1:
            raise ConfigError("train.curve_every must be >= 0 and train.curve_texels >= 1")
        if (self.chunk is not None and self.chunk < 1) or (
            self.threads is not None and self.threads < 1
        ):
            raise ConfigError("train.chunk and train.threads must be >= 1")
        if self.precision not in PRECISIONS:
            raise ConfigError(f"train.precision={self.precision!r} must be float32 or bfloat16")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ConfigError(f"train.device={self.device!r} must be auto, cpu or cuda")
        if self.backend not in BACKENDS:
            raise ConfigError(
                f"train.backend={self.backend!r} must be one of {', '.join(BACKENDS)}"
            )
