"""Training settings, apart from the torch code so that computing a cache key needs no torch."""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.core.errors import ConfigError
from pipeline.core.settings import (
    LOG,
    RESULT,
    SPEED,
    Either,
    Integer,
    OneOf,
    Real,
    check_fields,
    setting,
)

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
    backend : how a step computes its gradients (speed only): ``autograd`` (plain PyTorch,
        the reference), ``fused`` (the decoder by a hand-written chunked step tuned for CPU
        caches) or ``auto``; see :mod:`pipeline.btf.backends`.
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
    clip_grad_norm : None, or the largest norm of all parameters' gradients together,
        scaled down to it before each optimizer step (``torch.nn.utils.clip_grad_norm_``).
        A remedy to try for the jumps of the loss that long cosine runs show on the
        corduroy (docs/results.md); None (the default) clips nothing, as before it existed.
    keep_awake, omp_spin_count, reuse_freed_memory : opt-in machine tuning, speed only
        (:mod:`pipeline.btf.fast.tuning`): spinning idle-class processes keep the cores
        awake when the job's threads are all its cores; ``GOMP_SPINCOUNT`` for OpenMP's
        idle threads (set when the job starts); glibc keeps freed buffers while training.
    precision : ``float32``, or ``bfloat16`` for the decoder's products (float32 master
        weights and optimizer; see ``pipeline/btf/fast/fused.py``); it pays on CPUs with
        AMX or AVX512-BF16 (``python -m benchmarks.train`` prints which the CPU has); with
        the autograd backend, ``torch.autocast`` around the decoder.
    """

    epochs: int = setting(1, Integer(1), role=RESULT)
    epoch_texels: int | None = setting(None, Integer(1, optional=True), role=RESULT)
    lr: float = setting(0.05, Real(0.0, closed=False), role=RESULT)
    # Batch-norm in training mode needs at least two samples.
    batch_size: int = setting(5, Integer(2), role=RESULT)
    queries_per_abrdf: int = setting(512, Either(OneOf(-1), Integer(1)), role=RESULT)
    max_steps: int = setting(-1, Either(OneOf(-1), Integer(1)), role=RESULT)
    device: str = setting("auto", OneOf("auto", "cpu", "cuda"), role=SPEED)
    momentum: float = setting(0.0, Real(0.0, high=1.0, high_closed=False), role=RESULT)
    optimizer: str = setting("sgd", OneOf("sgd", "adam"), role=RESULT)
    lr_half_life: float = setting(0.0, Real(0.0), role=RESULT)
    schedule: str = setting("half_life", OneOf("half_life", "cosine"), role=RESULT)
    curve_every: int = setting(0, Integer(0), role=LOG)
    curve_texels: int = setting(256, Integer(1), role=LOG)
    threads: int | None = setting(None, Integer(1, optional=True), role=SPEED)
    chunk: int | None = setting(None, Integer(1, optional=True), role=SPEED)
    precision: str = setting("float32", OneOf(*PRECISIONS), role=RESULT)
    backend: str = setting("auto", OneOf(*BACKENDS), role=SPEED)
    keep_awake: bool = setting(False, role=SPEED)
    omp_spin_count: int | None = setting(None, Integer(0, optional=True), role=SPEED)
    reuse_freed_memory: bool = setting(False, role=SPEED)
    clip_grad_norm: float | None = setting(
        None, Real(0.0, closed=False, optional=True), role=RESULT, added=True
    )

    def __post_init__(self):
        check_fields(self, "train")  # 1.5 epochs, "abc" as lr, NaN as a count, 0 steps
        if self.epoch_texels is not None and self.epoch_texels < self.batch_size:
            raise ConfigError(
                f"train.epoch_texels={self.epoch_texels} must be null or >= "
                f"train.batch_size={self.batch_size}"
            )
