"""Training of the Neural BTF autoencoder and computation of the stored latents.

A step takes ``batch_size`` texels (the paper's batch of 5 ABRDFs), encodes each one's
input ABRDF (its own for Neural BTF, its cluster's median for the clustered method), and
decodes ``queries_per_abrdf`` random training directions per texel against its target
values. An epoch visits every texel once in a seeded random order.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from tqdm.auto import tqdm

from pipeline.btf.model import Decoder, Encoder
from pipeline.btf.preprocess import Normalization
from pipeline.btf.train_settings import TrainSettings
from pipeline.errors import ConfigError

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
    epoch_losses: list[float]
    steps: int
    seconds: float
    queries: int


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
    target_from_source: bool = False,
    on_epoch: Callable[[int, float], None] | None = None,
) -> TrainResult:
    """Train encoder and decoder jointly.

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
    target_from_source : train against the representative's values instead of the texel's.
    """
    device = resolve_device(settings.device)
    if settings.threads:
        torch.set_num_threads(int(settings.threads))
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    m, n, _ = abrdf.shape
    encoder = Encoder(n, encoder_channels).to(device)
    decoder = Decoder().to(device)
    params = list(encoder.parameters()) + list(decoder.parameters())
    if settings.optimizer == "adam":
        optimizer = torch.optim.Adam(params, lr=settings.lr)
    else:
        optimizer = torch.optim.SGD(params, lr=settings.lr, momentum=settings.momentum)
    loss_fn = nn.MSELoss()
    features = torch.from_numpy(dir_features).to(device)
    train_dirs = np.asarray(train_dirs)
    q = len(train_dirs) if settings.queries_per_abrdf < 0 else settings.queries_per_abrdf
    q = min(q, len(train_dirs))
    b = settings.batch_size
    steps_per_epoch = m // b  # drop the last partial batch: batch-norm needs >= 2 samples
    total = steps_per_epoch * settings.epochs
    if settings.max_steps >= 0:
        total = min(total, settings.max_steps)
    if total < 1:
        raise ConfigError(f"no training step: M={m} texels, batch_size={b}, max_steps")

    losses: list[float] = []
    step = 0
    start = time.perf_counter()
    encoder.train()
    decoder.train()
    with tqdm(total=total, desc="train", unit="step", leave=False, mininterval=1.0) as bar:
        for epoch in range(settings.epochs):
            order = rng.permutation(m)
            running, count = 0.0, 0
            for first in range(0, steps_per_epoch * b, b):
                if step >= total:
                    break
                texels = np.sort(order[first : first + b])
                inputs = norm.encoder_input(sources[source_of_texel[texels]])
                x = torch.from_numpy(np.ascontiguousarray(inputs.transpose(0, 2, 1)))
                queries = train_dirs[rng.integers(0, len(train_dirs), size=(b, q))]
                rows = source_of_texel[texels] if target_from_source else texels
                values = (sources if target_from_source else abrdf)[rows]
                target = norm.target(np.take_along_axis(values, queries[:, :, None], axis=1))
                target = torch.from_numpy(target.reshape(-1, 3)).to(device)
                latents = encoder(x.to(device))
                pred = decoder(
                    latents.repeat_interleave(q, dim=0),
                    features[torch.from_numpy(queries.reshape(-1)).to(device)],
                )
                loss = loss_fn(pred, target)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                running += float(loss.detach())
                count += 1
                step += 1
                bar.update(1)
            if count:
                losses.append(running / count)
                bar.set_postfix(epoch=epoch, loss=f"{losses[-1]:.3g}")
                if on_epoch is not None:
                    on_epoch(epoch, losses[-1])
            if step >= total:
                break
    seconds = time.perf_counter() - start
    log.info("trained %d steps (%d epochs) in %.1f s, last loss %.4g", step, len(losses),
             seconds, losses[-1] if losses else float("nan"))
    return TrainResult(encoder.cpu(), decoder.cpu(), losses, step, seconds, step * b * q)


@torch.no_grad()
def encode(
    encoder: Encoder, sources: np.ndarray, norm: Normalization, chunk: int = 256
) -> np.ndarray:
    """Latents of every source ABRDF: (R, N, 3) -> (R, 8) float32 (batch-norm in eval mode)."""
    encoder.eval()
    out = np.empty((sources.shape[0], encoder.fc.out_features), dtype=np.float32)
    for start in range(0, sources.shape[0], chunk):
        inputs = norm.encoder_input(sources[start : start + chunk])
        x = torch.from_numpy(np.ascontiguousarray(inputs.transpose(0, 2, 1)))
        out[start : start + len(inputs)] = encoder(x).numpy()
    return out
