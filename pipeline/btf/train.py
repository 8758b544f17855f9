"""Training of the Neural BTF autoencoder and computation of the stored latents.

A step takes ``batch_size`` texels (the paper's batch of 5 ABRDFs), encodes each one's
input ABRDF (its own for Neural BTF, its cluster's median for the clustered method), and
decodes ``queries_per_abrdf`` random training directions per texel (or all of them, in
order, with -1) against its target values. A pass visits every texel once in a seeded
random order; an epoch, the unit of ``train.epochs`` and of the schedule, is a pass or
``train.epoch_texels`` texels. The steps are deterministic for a seed and a number of threads.

How a step computes its gradients is ``train.backend`` (:mod:`pipeline.btf.backends`);
where its batches come from, the host or arrays kept on the device, is
:mod:`pipeline.btf.batches`.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from torch.optim.lr_scheduler import LambdaLR

from pipeline.btf.backends import make_step, resolve_backend
from pipeline.btf.batches import (
    DeviceBatches,
    HostBatches,
    Sampling,
    fits_on_device,
    resident_bytes,
)
from pipeline.btf.fast.tuning import training_tuning
from pipeline.btf.model import LATENT_DIM, Decoder, Encoder
from pipeline.btf.preprocess import Normalization
from pipeline.btf.train_settings import TrainSettings
from pipeline.core.errors import ConfigError
from pipeline.core.progress import progress

log = logging.getLogger(__name__)


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("train.device=cuda but no CUDA device is available")
    return torch.device(name)


@dataclass
class TrainResult:
    encoder: Encoder
    decoder: Decoder
    pass_losses: list[float]  # the mean loss of each pass over the texels
    steps: int
    seconds: float
    queries: int
    curve: list[dict] = field(default_factory=list)


class _Curve:
    """RMSE-versus-time points: the eq. 10 RMSE of fixed random texels at every training
    direction, measured with the model as it would be stored (batch-norm in eval mode).
    Its time is training time only; measuring is excluded from it."""

    def __init__(self, abrdf, sources, source_of_texel, norm, features, train_dirs, texels, seed):
        m = abrdf.shape[0]
        rows = np.sort(np.random.default_rng(seed + 7919).choice(m, min(texels, m), replace=False))
        self.inputs = norm.encoder_input(sources[source_of_texel[rows]])
        self.targets = torch.from_numpy(norm.target(abrdf[rows][:, train_dirs]))
        self.features = features[torch.from_numpy(np.asarray(train_dirs))]
        self.points: list[dict] = []

    @torch.no_grad()
    def measure(self, encoder, decoder, step, texel_pass, seconds, queries) -> dict:
        encoder.eval()
        decoder.eval()
        device = self.features.device
        x = torch.from_numpy(self.inputs).permute(0, 2, 1).to(device)
        latents = encoder(x)
        # 16 texels at a time: the whole subsample's hidden layer would not fit in cache.
        chunks = [latents[i : i + 16] for i in range(0, len(latents), 16)]
        pred = torch.cat([decoder.decode_grid(chunk, self.features).cpu() for chunk in chunks])
        encoder.train()
        decoder.train()
        rmse = float(torch.sqrt(torch.mean(torch.square(pred - self.targets))))
        point = {
            "step": step,
            "texel_pass": texel_pass,
            "seconds": seconds,
            "queries": queries,
            "rmse": rmse,
        }
        self.points.append(point)
        return point


def train(
    abrdf: np.ndarray,
    sources: np.ndarray,
    source_of_texel: np.ndarray,
    norm: Normalization,
    dir_features: np.ndarray,
    train_dirs: np.ndarray,
    settings: TrainSettings,
    seed: int,
    encoder_channels: tuple[int, ...] = (16, 32, 64),
    latent: int = LATENT_DIM,
    hidden: int = 106,
    layers: int = 3,
    target_from_source: bool = False,
    on_pass: Callable[[int, float, int], None] | None = None,
    on_curve: Callable[[dict], None] | None = None,
) -> TrainResult:
    """Train encoder and decoder jointly.

    The step is ``settings.backend``'s (:mod:`pipeline.btf.backends`): plain autograd, or
    the encoder under autograd and the decoder's forward and backward by
    :class:`pipeline.btf.fast.fused.DecoderStep` (chunked, on ``settings.threads`` threads).

    Parameters
    ----------
    abrdf : ndarray of shape (M, N, 3)
        Raw texel ABRDFs (targets unless ``target_from_source``); may be a memory map.
    sources : ndarray of shape (R, N, 3)
        Raw encoder inputs: ``abrdf`` itself (Neural BTF) or the k representatives.
    source_of_texel : ndarray of shape (M,), int
        Row of ``sources`` fed to the encoder for each texel (identity, or the list).
    norm : the eq. 1-6 normalization fitted on ``abrdf``.
    dir_features : ndarray of shape (N, 4), stereographic light and view coordinates.
    train_dirs : ndarray of int
        Indices of the directions training may query (held-out ones excluded).
    latent : values per latent (``btf.network.latent``), the encoder's output and the
        decoder's input besides the 4 direction coordinates.
    target_from_source : train against the representative's values instead of the texel's.
    on_curve : called with each point of the RMSE-versus-time curve.
    """
    device = resolve_device(settings.device)
    workers = 1 if device.type == "cuda" else (settings.threads or torch.get_num_threads())
    previous_threads = torch.get_num_threads()
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    m, n, _ = abrdf.shape
    encoder = Encoder(n, encoder_channels, latent=latent).to(device)
    decoder = Decoder(latent=latent, hidden=hidden, layers=layers).to(device)
    params = list(encoder.parameters()) + list(decoder.parameters())
    # fused: one kernel for all parameters instead of a loop of small ops over each
    # (docs/performance.md). Adam's step differs in the last bit; SGD's is identical.
    if settings.optimizer == "adam":
        optimizer = torch.optim.Adam(params, lr=settings.lr, fused=True)
    else:
        optimizer = torch.optim.SGD(params, lr=settings.lr, momentum=settings.momentum, fused=True)
    features = torch.from_numpy(dir_features).to(device)
    train_dirs = np.asarray(train_dirs)
    all_queries = settings.queries_per_abrdf < 0 or settings.queries_per_abrdf >= len(train_dirs)
    q = len(train_dirs) if all_queries else settings.queries_per_abrdf
    b = settings.batch_size
    steps_per_pass = m // b  # drop the last partial batch: batch-norm needs >= 2 samples
    # An epoch is one pass over the M texels, or epoch_texels texels whatever M is (so that
    # a smaller crop does not silently mean fewer steps and an earlier-decaying schedule).
    steps_per_epoch = (
        steps_per_pass if settings.epoch_texels is None else max(1, settings.epoch_texels // b)
    )
    total = steps_per_epoch * settings.epochs
    if settings.max_steps >= 0:
        total = min(total, settings.max_steps)
    if total < 1 or steps_per_pass < 1:
        raise ConfigError(f"no training step: M={m} texels, batch_size={b}, max_steps")
    if settings.schedule == "cosine":
        # Decays over the whole run: a run twice as long decays twice as slowly, so that
        # doubling it is a convergence check (the half-life schedule cannot be one).
        schedule = LambdaLR(
            optimizer, lambda s: 0.5 * (1 + math.cos(math.pi * min(s / total, 1.0)))
        )
    elif settings.lr_half_life > 0:
        half_life_steps = settings.lr_half_life * steps_per_epoch
        schedule = LambdaLR(optimizer, lambda s: 0.5 ** (s / half_life_steps))
    else:
        schedule = None
    bfloat16_on_cpu = settings.precision == "bfloat16" and device.type == "cpu"
    if bfloat16_on_cpu and not torch.ops.mkldnn._is_mkldnn_bf16_supported():
        # Without AVX512-BF16 or AMX, bfloat16 products run on emulated paths, many times
        # slower than float32 (docs/performance.md).
        log.warning(
            "train.precision=bfloat16 on a CPU without bfloat16 support (no "
            "AVX512-BF16 or AMX): expect training far slower than float32"
        )
    backend = resolve_backend(settings.backend, device)
    sampling = Sampling(b, q, all_queries, train_dirs, n, target_from_source)
    batches = _batches(abrdf, sources, source_of_texel, norm, sampling, rng, device, seed)
    source = "device" if isinstance(batches, DeviceBatches) else "host"
    message = "training on %s with the %s backend, %s, batches from the %s"
    log.info(message, device, backend, settings.precision, source)
    step_fn = make_step(
        backend, encoder, decoder, features, settings.precision, workers, settings.chunk
    )
    curve = None
    if settings.curve_every > 0:
        curve = _Curve(
            abrdf, sources, source_of_texel, norm, features, train_dirs, settings.curve_texels, seed
        )

    losses: list[float] = []
    step, seconds = 0, 0.0
    encoder.train()
    decoder.train()

    def measure(texel_pass: int) -> None:
        point = curve.measure(encoder, decoder, step, texel_pass, seconds, step * b * q)
        log.info("curve: step %d, %.0f s, RMSE %.4f", step, seconds, point["rmse"])
        if on_curve is not None:
            on_curve(point)

    try:
        with (
            training_tuning(settings, workers, on_cpu=device.type == "cpu"),
            progress(None, "train", total=total, unit="step") as bar,
        ):
            if curve is not None:
                measure(0)
            for texel_pass in range(-(-total // max(steps_per_pass, 1))):
                batches.new_pass()
                running, count = 0.0, 0
                clock = time.perf_counter()
                for first in range(0, steps_per_pass * b, b):
                    if step >= total:
                        break
                    batch = batches.batch(first)
                    optimizer.zero_grad(set_to_none=True)
                    # A float, or a 0-d tensor left on the device: summed there, it is read
                    # once per pass, so that a CUDA step does not wait for the device.
                    running += step_fn(batch)
                    if settings.clip_grad_norm is not None:
                        torch.nn.utils.clip_grad_norm_(params, settings.clip_grad_norm)
                    optimizer.step()
                    if schedule is not None:
                        schedule.step()
                    count += 1
                    step += 1
                    bar.update(1)
                    if curve is not None and step % settings.curve_every == 0:
                        seconds += _elapsed(clock, device)
                        measure(texel_pass)
                        clock = time.perf_counter()
                seconds += _elapsed(clock, device)
                if count:
                    losses.append(float(running) / count)
                    bar.set_postfix(texel_pass=texel_pass, loss=f"{losses[-1]:.3g}")
                    if on_pass is not None:
                        on_pass(texel_pass, losses[-1], step)
                if step >= total:
                    break
            if curve is not None and step % settings.curve_every:
                measure(len(losses) - 1)
    finally:
        step_fn.close()
        torch.set_num_threads(previous_threads)
    log.info(
        "trained %d steps (%d passes over the texels) in %.1f s, %.3f M queries/s, last loss %.4g",
        step,
        len(losses),
        seconds,
        step * b * q / max(seconds, 1e-9) / 1e6,
        losses[-1] if losses else float("nan"),
    )
    points = [] if curve is None else curve.points
    return TrainResult(encoder.cpu(), decoder.cpu(), losses, step, seconds, step * b * q, points)


def _batches(abrdf, sources, source_of_texel, norm, sampling, rng, device, seed):
    """The ABRDFs kept on a CUDA device where they fit (no per-step copies from the host),
    batches gathered on the host otherwise (:mod:`pipeline.btf.batches`)."""
    nbytes = resident_bytes(abrdf, sources, sampling.target_from_source)
    if device.type == "cuda":
        if fits_on_device(nbytes, device):
            return DeviceBatches(abrdf, sources, source_of_texel, norm, sampling, rng, device, seed)
        log.info(
            "the training ABRDFs (%.0f MiB) do not fit in the device's free memory: "
            "each batch is copied from the host",
            nbytes / 2**20,
        )
    return HostBatches(abrdf, sources, source_of_texel, norm, sampling, rng, device)


def _elapsed(clock: float, device: torch.device) -> float:
    """Seconds since ``clock``, once the device has finished the work queued meanwhile
    (CUDA runs asynchronously)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - clock


@torch.no_grad()
def encode(
    encoder: Encoder, sources: np.ndarray, norm: Normalization, chunk: int = 256
) -> np.ndarray:
    """Latents of every source ABRDF: (R, N, 3) -> (R, latent) float32 (batch-norm in eval
    mode)."""
    encoder.eval()
    out = np.empty((sources.shape[0], encoder.fc.out_features), dtype=np.float32)
    for start in range(0, sources.shape[0], chunk):
        inputs = norm.encoder_input(sources[start : start + chunk])
        x = torch.from_numpy(inputs).permute(0, 2, 1)
        out[start : start + len(inputs)] = encoder(x).numpy()
    return out
