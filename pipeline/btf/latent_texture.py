"""A latent-texture model of method A: per-texel latents optimised directly (issue 40).

Neural BTF (PAPERS.md A) gets each texel's latent from an encoder run on its ABRDF. Here,
as in NeuMIP (Kuznetsov et al. 2021), there is no encoder: the latents are a texture of
parameters optimised jointly with the decoder (an auto-decoder), optionally as a pyramid.

Pyramid. Level 0 is a (latent, rows, cols) tensor, one latent per texel; level l a
(latent, ceil(rows / 2^l), ceil(cols / 2^l)) one, whose cell covers 2^l x 2^l texels.
The latent of texel (r, c) is level 0's value plus, for every coarser level, the bilinear
lookup at the texel's centre: the point ((r + 0.5) / 2^l - 0.5, (c + 0.5) / 2^l - 0.5) in
the level's cell-centre coordinates, clamped to the edge (OpenGL's GL_LINEAR with
CLAMP_TO_EDGE). Summing keeps the decoder's input at
latent + 4 whatever the number of levels, and lets the coarse levels learn what
neighbouring texels share from the gradients of all of them (a multiresolution
preconditioner, as in multiresolution feature grids).

What NeuMIP does and we leave out. NeuMIP's pyramid is a mipmap: a query's filter-kernel
size picks two adjacent levels, interpolated trilinearly, each level trained against the
material prefiltered at its scale; and a neural offset network shifts the lookup for
parallax. Here every query is at a texel centre at full resolution (the eq. 10 evaluation
of this project), there is no filtering loss and no offset network. At texel centres the
pyramid can be folded into level 0 without changing any output, so its extra bytes (about
a third more latents) buy only what training gains from it and later filtering.

The decoder is :class:`pipeline.btf.model.Decoder`, stored as in
:mod:`pipeline.btf.compressed`; training is :func:`train_latent_texture`.
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from pipeline.btf.model import Decoder
from pipeline.core.progress import progress

INIT_STD = 0.01  # latents start small: the decoder first sees mostly the directions
WARMUP = 0.02  # fraction of the steps over which the learning rate rises linearly


def level_shape(rows: int, cols: int, level: int) -> tuple[int, int]:
    """(rows, cols) of pyramid level ``level``: ceil(rows / 2^level), ceil(cols / 2^level)."""
    return -(-rows // 2**level), -(-cols // 2**level)


def bilinear_taps(rows: int, cols: int, level: int) -> tuple[np.ndarray, np.ndarray]:
    """The four cells of level ``level`` that every texel centre reads, and their weights.

    Returns ``indices`` (rows * cols, 4) int64 into the level's (rows_l * cols_l) cells in
    row-major order and ``weights`` (rows * cols, 4) float64 summing to 1, texels in
    row-major order (texel t is row t // cols, column t % cols).
    """
    row_cells, row_weights = _taps_1d(rows, level)
    col_cells, col_weights = _taps_1d(cols, level)
    cols_l = level_shape(rows, cols, level)[1]
    indices = row_cells[:, None, :, None] * cols_l + col_cells[None, :, None, :]
    weights = row_weights[:, None, :, None] * col_weights[None, :, None, :]
    return indices.reshape(rows * cols, 4), weights.reshape(rows * cols, 4)


def _taps_1d(n: int, level: int) -> tuple[np.ndarray, np.ndarray]:
    """The lower and upper cell of level ``level`` around texel centres 0 .. n-1 along one
    axis (clamped to the edge) and their weights: (n, 2) int64 and (n, 2) float64."""
    position = (np.arange(n) + 0.5) / 2**level - 0.5  # in cell-centre coordinates
    lower = np.floor(position)
    upper_weight = position - lower
    cells = np.clip(lower.astype(np.int64)[:, None] + [0, 1], 0, -(-n // 2**level) - 1)
    return cells, np.stack([1 - upper_weight, upper_weight], 1)


def _check_shape(rows: int, cols: int, latent: int, levels: int) -> None:
    if rows < 1 or cols < 1:
        raise ValueError(f"crop_size=({rows}, {cols}) must have at least one row and column")
    if latent < 1:
        raise ValueError(f"latent={latent} must be >= 1")
    if levels < 1 or 2 ** (levels - 1) > min(rows, cols):
        raise ValueError(
            f"levels={levels} must be >= 1 with 2^(levels-1) <= min(rows, cols)={min(rows, cols)}"
        )


class LatentTexture(nn.Module):
    """A pyramid of latent textures and a decoder: (texel, direction features) -> RGB."""

    def __init__(
        self,
        rows: int,
        cols: int,
        latent: int,
        levels: int = 1,
        hidden: int = 106,
        layers: int = 3,
        seed: int = 0,
    ):
        super().__init__()
        _check_shape(rows, cols, latent, levels)
        self.rows, self.cols, self.latent = rows, cols, latent
        generator = torch.Generator().manual_seed(seed)
        self.levels = nn.ParameterList(
            nn.Parameter(
                torch.randn(latent, *level_shape(rows, cols, level), generator=generator) * INIT_STD
            )
            for level in range(levels)
        )
        # nn.Linear's own initialisation, seeded, leaving torch's global random state as it was.
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.decoder = Decoder(latent=latent, hidden=hidden, layers=layers)
        for level in range(1, levels):
            indices, weights = bilinear_taps(rows, cols, level)
            self.register_buffer(f"taps_{level}", torch.from_numpy(indices), persistent=False)
            self.register_buffer(
                f"weights_{level}", torch.from_numpy(weights).float(), persistent=False
            )

    def texel_latents(self, texels: torch.Tensor) -> torch.Tensor:
        """texels (n,) int64 in [0, rows * cols) -> their latents (n, latent)."""
        z = self.levels[0].flatten(1)[:, texels]
        for level in range(1, len(self.levels)):
            taps = getattr(self, f"taps_{level}")[texels]  # (n, 4)
            weights = getattr(self, f"weights_{level}")[texels]
            z = z + (self.levels[level].flatten(1)[:, taps] * weights).sum(-1)
        return z.T

    def forward(self, texels: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """Texel ``texels[i]`` at direction features ``features[i]``: (n,), (n, 4) -> (n, 3)."""
        return self.decoder(self.texel_latents(texels), features)


def stored_parts(module: LatentTexture, weight_dtype: str) -> dict[str, np.ndarray]:
    """The arrays a compressed file stores, in ``weight_dtype`` (float32 or float16):
    ``decoder.{i}.weight`` (out, in), ``decoder.{i}.bias`` (out,) and ``latent_texture.{l}``
    (rows_l, cols_l, latent) for each pyramid level l."""
    if weight_dtype not in ("float32", "float16"):
        raise ValueError(f"weight_dtype={weight_dtype!r} must be 'float32' or 'float16'")
    linears = [layer for layer in module.decoder.net if isinstance(layer, nn.Linear)]
    parts = {}
    for i, layer in enumerate(linears):
        for name in ("weight", "bias"):
            parts[f"decoder.{i}.{name}"] = getattr(layer, name).detach().cpu().numpy()
    for level, values in enumerate(module.levels):
        parts[f"latent_texture.{level}"] = values.detach().cpu().permute(1, 2, 0).numpy()
    return {name: np.ascontiguousarray(a.astype(weight_dtype)) for name, a in parts.items()}


def payload_bytes(parts: dict[str, np.ndarray]) -> int:
    """Bytes of the stored arrays (without any file header)."""
    return sum(int(a.nbytes) for a in parts.values())


def query(parts: dict[str, np.ndarray], texels, features) -> np.ndarray:
    """What :class:`LatentTexture` computes, from :func:`stored_parts` in numpy (float64):
    ndarray of shape (n, 3), normalised, unclamped.

    Parameters
    ----------
    parts : the stored arrays (either dtype).
    texels : array_like of ints of shape (n,), row-major indices in [0, rows * cols).
    features : array_like of shape (n, 4), the direction features of each query.
    """
    if "latent_texture.0" not in parts or "decoder.0.weight" not in parts:
        raise ValueError("parts need latent_texture.0 and decoder.0.weight (stored_parts)")
    rows, cols, latent = parts["latent_texture.0"].shape
    texels = np.asarray(texels)
    features = np.asarray(features, dtype=np.float64)
    if texels.ndim != 1 or not np.issubdtype(texels.dtype, np.integer):
        raise ValueError(
            f"texels must be a 1-D array of ints, got shape {texels.shape} of {texels.dtype}"
        )
    if features.shape != (len(texels), 4):
        raise ValueError(f"features must have shape ({len(texels)}, 4), got {features.shape}")
    if texels.size and (texels.min() < 0 or texels.max() >= rows * cols):
        raise ValueError(f"texels must lie in [0, {rows * cols}) for a {rows}x{cols} texture")
    z = parts["latent_texture.0"].reshape(-1, latent)[texels].astype(np.float64)
    level = 1
    while f"latent_texture.{level}" in parts:
        cells = parts[f"latent_texture.{level}"].reshape(-1, latent).astype(np.float64)
        indices, weights = bilinear_taps(rows, cols, level)
        z += np.einsum("nk,nkd->nd", weights[texels], cells[indices[texels]])
        level += 1
    h = np.concatenate([z, features], axis=1)
    layers = sum(1 for name in parts if name.startswith("decoder.") and name.endswith(".weight"))
    for i in range(layers):
        h = h @ parts[f"decoder.{i}.weight"].astype(np.float64).T
        h = h + parts[f"decoder.{i}.bias"].astype(np.float64)
        h = np.maximum(h, 0.0) if i < layers - 1 else h
    return h


def learning_rate(step: int, steps: int, lr: float) -> float:
    """The learning rate of step ``step`` (0-based) of a run of ``steps``: a linear warm-up
    over the first 2 % of the steps, then a cosine decay to 0 at ``steps``. A function of
    ``step / steps`` alone, so that doubling ``steps`` stretches the whole schedule."""
    x = step / steps
    if x < WARMUP:
        return lr * x / WARMUP
    return lr * 0.5 * (1.0 + math.cos(math.pi * (x - WARMUP) / (1.0 - WARMUP)))


@dataclass
class LatentTextureResult:
    """module: the trained model (on the CPU); curve: one point per block of steps,
    {"step", "seconds", "loss"} with the block's mean training MSE; seconds: training time."""

    module: LatentTexture
    curve: list[dict] = field(default_factory=list)
    steps: int = 0
    seconds: float = 0.0


def train_latent_texture(
    targets: np.ndarray,
    features: np.ndarray,
    train_directions: np.ndarray,
    crop_size: tuple[int, int],
    *,
    latent: int,
    levels: int,
    hidden: int,
    layers: int,
    steps: int,
    batch_texels: int,
    queries_per_texel: int,
    lr: float,
    seed: int,
    device: str = "cpu",
) -> LatentTextureResult:
    """Optimise a :class:`LatentTexture` and its decoder jointly with Adam, MSE loss.

    A step draws ``batch_texels`` texels without replacement and, for each, draws
    ``queries_per_texel`` of ``train_directions`` with replacement. The latents start at
    N(0, 0.01^2) from a ``torch.Generator`` seeded with ``seed``, the decoder with
    nn.Linear's initialisation under the same seed, the batches from
    ``np.random.default_rng(seed)``; one thread: deterministic for a seed. The learning rate
    follows :func:`learning_rate` over exactly ``steps``.

    Parameters
    ----------
    targets : (M, N, 3) normalised targets, texels in row-major order: an array, or an
        array-like read a batch at a time (``targets[np.ix_(texels, directions)]``), such
        as :meth:`~pipeline.btf.preprocess.Normalization.targets` of a crop's ABRDFs.
    features : ndarray of shape (N, 4), the direction features.
    train_directions : ndarray of ints, the directions trained on (held-out ones excluded).
    crop_size : (rows, cols) with rows * cols = M.
    device : where the model trains (``cuda`` when lent one); batches are drawn on the
        host either way, so a seed gives the same batches.
    """
    features = np.asarray(features, dtype=np.float32)
    train_directions = np.asarray(train_directions)
    rows, cols = (int(v) for v in crop_size)
    if targets.ndim != 3 or targets.shape[2] != 3:
        raise ValueError(f"targets must have shape (M, N, 3), got {targets.shape}")
    m, n, _ = targets.shape
    if rows * cols != m:
        raise ValueError(
            f"crop_size=({rows}, {cols}) holds {rows * cols} texels but targets has M={m}"
        )
    if features.shape != (n, 4):
        raise ValueError(f"features must have shape ({n}, 4), got {features.shape}")
    ints = train_directions.ndim == 1 and np.issubdtype(train_directions.dtype, np.integer)
    if not (
        ints and train_directions.size and np.all((train_directions >= 0) & (train_directions < n))
    ):
        raise ValueError(f"train_directions must be a non-empty 1-D array of ints in [0, {n})")
    counts = {"steps": steps, "batch_texels": batch_texels, "queries_per_texel": queries_per_texel}
    for name, value in counts.items():
        if value < 1:
            raise ValueError(f"{name}={value} must be >= 1")
    if batch_texels > m:
        raise ValueError(f"batch_texels={batch_texels} exceeds the M={m} texels")
    if not lr > 0:
        raise ValueError(f"lr={lr} must be > 0")
    _check_shape(rows, cols, latent, levels)

    block = max(1, steps // 100)  # steps per point of the loss curve
    device = torch.device(device)
    module = LatentTexture(rows, cols, latent, levels, hidden, layers, seed=seed).to(device)
    optimizer = torch.optim.Adam(module.parameters(), lr=lr)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: learning_rate(s, steps, 1))
    rng = np.random.default_rng(seed)
    features = torch.from_numpy(features).to(device)
    curve: list[dict] = []
    running, count, seconds = 0.0, 0, 0.0
    with _one_thread(), progress(None, "latent texture", total=steps, unit="step") as bar:
        clock = time.perf_counter()
        for step in range(1, steps + 1):
            texels = rng.choice(m, batch_texels, replace=False)
            picks = rng.integers(0, len(train_directions), (batch_texels, queries_per_texel))
            directions = train_directions[picks]
            # The batch's directions for its texels, read as one block of the directions
            # drawn (a crop's ABRDFs served from a file decode only those).
            drawn, column = np.unique(directions, return_inverse=True)
            read = np.asarray(targets[np.ix_(texels, drawn)], dtype=np.float32)
            target = read[np.arange(batch_texels)[:, None], column.reshape(directions.shape)]
            prediction = module(
                torch.from_numpy(np.repeat(texels, queries_per_texel)).to(device),
                features[torch.from_numpy(directions.ravel()).to(device)],
            )
            target = torch.from_numpy(target).reshape(-1, 3).to(device)
            loss = torch.mean(torch.square(prediction - target))
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            schedule.step()
            running += loss.item()
            count += 1
            if step % block == 0 or step == steps:
                seconds += time.perf_counter() - clock
                point = {"step": step, "seconds": seconds, "loss": running / count}
                curve.append(point)
                bar.set_postfix(loss=f"{point['loss']:.3g}")
                running, count = 0.0, 0
                clock = time.perf_counter()
            bar.update(1)
    return LatentTextureResult(module.cpu().eval(), curve, steps, seconds)


@contextmanager
def _one_thread():
    """Torch on one thread (the same sums in the same order: deterministic for a seed),
    its previous number of threads restored afterwards."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
