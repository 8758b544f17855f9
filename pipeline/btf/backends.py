"""How a training step computes its gradients (``train.backend``).

- ``autograd`` (:class:`AutogradStep`): plain PyTorch, mean squared error and
  ``loss.backward()``. Always available, and the reference the other backend is tested
  against (``tests/test_backends.py``). With ``train.precision=bfloat16`` the decoder runs
  under ``torch.autocast``, which rounds its products to bfloat16 as the fused step does.
- ``fused`` (:class:`FusedStep`): the encoder under autograd, the decoder's forward and
  backward by :class:`pipeline.btf.fast.fused.DecoderStep`, chunked to stay in a CPU
  core's cache, on threads, with C++ kernels where they build. On CUDA it runs torch ops
  in one chunk of up to 2**20 queries (for comparison; ``auto`` does not pick it there).
- ``auto`` (:func:`resolve_backend`): fused on the CPU where the C++ kernels build, else
  autograd with a warning; autograd on CUDA, where the decoder's products are large
  enough for the GPU and there are no CPU caches to fit.

A step takes a :class:`pipeline.btf.batches.StepBatch`, leaves each parameter's gradient in
its ``.grad`` (the caller zeroes them and steps the optimizer) and returns the batch's mean
squared error: a float, or a 0-d tensor left on the device (a CUDA step does not wait).

``torch.compile`` is not used: its benefit on the GPU has not been measured here.
"""

from __future__ import annotations

import logging
from contextlib import nullcontext

import torch
import torch.nn.functional as F

from pipeline.btf.batches import StepBatch
from pipeline.btf.fast import kernels
from pipeline.btf.fast.fused import Batch, DecoderStep
from pipeline.btf.model import Decoder, Encoder
from pipeline.btf.train_settings import BACKENDS
from pipeline.core.errors import ConfigError

log = logging.getLogger(__name__)

CUDA_CHUNK = 1 << 20  # the fused step's chunk on CUDA: one chunk for any batch up to it


def resolve_backend(name: str, device: torch.device) -> str:
    """``fused`` or ``autograd`` for ``train.backend=name`` on ``device`` (see the module's
    docstring); ``auto`` builds the C++ kernels on the CPU to find out whether they can."""
    if name not in BACKENDS:
        raise ConfigError(f"train.backend={name!r} must be one of {', '.join(BACKENDS)}")
    if name != "auto":
        return name
    if device.type != "cpu":
        return "autograd"
    if kernels.available():
        return "fused"
    log.warning(
        "train.backend=auto: the fused decoder step's C++ kernels did not build on "
        "this machine, so training uses the autograd backend (set "
        "train.backend=fused to use the fused step with plain torch ops instead)"
    )
    return "autograd"


class AutogradStep:
    """The plain PyTorch step (see the module's docstring) on ``workers`` intra-op threads
    (CPU). ``features``: (N, 4) stereographic direction features on the training device."""

    def __init__(
        self,
        encoder: Encoder,
        decoder: Decoder,
        features: torch.Tensor,
        precision: str = "float32",
        workers: int = 1,
    ):
        self.encoder, self.decoder, self.features = encoder, decoder, features
        self.workers = workers
        if precision == "bfloat16":
            self._autocast = torch.autocast(features.device.type, dtype=torch.bfloat16)
        else:
            self._autocast = nullcontext()

    def __call__(self, batch: StepBatch) -> torch.Tensor:
        if self.features.is_cpu:
            torch.set_num_threads(self.workers)  # the caller restores its own setting
        b, q = batch.directions.shape
        latents = self.encoder.forward_layers(batch.inputs)  # plain layers: the reference
        with self._autocast:
            predicted = self.decoder(
                latents.repeat_interleave(q, 0), self.features[batch.directions.reshape(-1)]
            )
        # float32 loss (autocast leaves bfloat16 outputs): the same mean as the fused step's.
        loss = F.mse_loss(predicted.float(), batch.targets.reshape(b * q, -1))
        loss.backward()
        return loss.detach().double()  # summed over a pass in float64, as the fused step's

    def close(self) -> None:
        pass


class FusedStep:
    """The encoder under autograd and the decoder by :class:`DecoderStep`: the encoder's
    convolutions on ``workers`` threads, the decoder's chunks one per thread on the
    ``workers``, each op single-threaded. ``chunk``: queries per chunk (None: the
    precision's default; on CUDA :data:`CUDA_CHUNK`)."""

    def __init__(
        self,
        encoder: Encoder,
        decoder: Decoder,
        features: torch.Tensor,
        precision: str = "float32",
        workers: int = 1,
        chunk: int | None = None,
    ):
        self.encoder, self.workers = encoder, workers
        self.on_cpu = features.device.type == "cpu"
        self.decoder_step = DecoderStep(
            decoder,
            features,
            workers=workers,
            chunk=chunk if self.on_cpu else CUDA_CHUNK,
            precision=precision,
        )

    def __call__(self, batch: StepBatch) -> float:
        if self.on_cpu:
            torch.set_num_threads(self.workers)
        latents = self.encoder(batch.inputs)
        if self.on_cpu:
            torch.set_num_threads(1)
        grads = self.decoder_step(Batch(latents, batch.directions, batch.targets))
        if self.on_cpu:
            torch.set_num_threads(self.workers)
        self.decoder_step.assign(grads)
        latents.backward(grads.latents)
        return grads.loss

    def close(self) -> None:
        self.decoder_step.close()


def make_step(
    backend: str,
    encoder: Encoder,
    decoder: Decoder,
    features: torch.Tensor,
    precision: str,
    workers: int,
    chunk: int | None,
) -> AutogradStep | FusedStep:
    """The step of a resolved ``backend`` (``fused`` or ``autograd``)."""
    if backend == "fused":
        return FusedStep(encoder, decoder, features, precision, workers, chunk)
    if backend == "autograd":
        return AutogradStep(encoder, decoder, features, precision, workers)
    raise ValueError(f"backend={backend!r} is not resolved (fused or autograd)")
