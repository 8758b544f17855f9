"""Where a training step's batch comes from: the ABRDFs on the host, or kept on the device.

A batch is ``batch_size`` texels of a seeded random pass over the M texels (sorted, so
that a memory map is read in order), each with its encoder input (its own ABRDF, or its
cluster's representative) and ``q`` queried training directions with their targets.

:class:`HostBatches` gathers each batch with numpy on the host (the CPU training's
batches); :class:`DeviceBatches` keeps the raw ABRDFs on a CUDA device where they fit
(:func:`fits_on_device`), so that a step copies nothing from the host but the pass's order.
Both draw the order of each pass from the same numpy generator: their texels are the same
for a seed, their random queries not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pipeline.btf.preprocess import Normalization

# Share of the device's free memory that the resident ABRDFs may take: the rest is left
# to the step's activations and to the allocator's slack.
DEVICE_SHARE = 0.5
_UPLOAD_TEXELS = 1024  # texels per host-to-device copy while uploading (bounds host memory)


@dataclass
class StepBatch:
    """One step's inputs, on the training device.

    inputs : (B, 3, N) float32 encoder inputs (a channels-last view of (B, N, 3) memory).
    directions : (B, q) int64 indices of the queried directions.
    targets : (B, q, 3) float32 normalized target values.
    """

    inputs: torch.Tensor
    directions: torch.Tensor
    targets: torch.Tensor


@dataclass(frozen=True)
class Sampling:
    """What a batch holds: ``batch_size`` texels x ``queries`` of the ``train_dirs``
    (random ones, or all of them in order when ``all_queries``) among the ABRDFs'
    ``n_directions``, and whether the targets are the representative's values
    (``target_from_source``)."""

    batch_size: int
    queries: int
    all_queries: bool
    train_dirs: np.ndarray
    n_directions: int
    target_from_source: bool

    @property
    def in_order(self) -> bool:
        """Every direction of the ABRDFs, in their stored order: no gather needed."""
        return self.all_queries and bool(
            np.array_equal(self.train_dirs, np.arange(self.n_directions))
        )


class HostBatches:
    """Batches gathered and normalized with numpy from the (possibly memory-mapped) arrays,
    then moved to ``device``.

    Parameters
    ----------
    abrdf : ndarray of shape (M, N, 3), raw texel ABRDFs (may be a memory map).
    sources : ndarray of shape (R, N, 3), raw encoder inputs.
    source_of_texel : ndarray of shape (M,), int, row of ``sources`` of each texel.
    norm : the eq. 1-6 normalization.
    sampling : what a batch holds.
    rng : draws each pass's order and the random queries.
    device : where the batch's tensors go.
    """

    def __init__(
        self,
        abrdf,
        sources,
        source_of_texel,
        norm: Normalization,
        sampling: Sampling,
        rng: np.random.Generator,
        device: torch.device,
    ):
        self.abrdf, self.sources, self.source_of_texel = abrdf, sources, source_of_texel
        self.norm, self.sampling, self.rng, self.device = norm, sampling, rng, device
        self.order = np.arange(abrdf.shape[0])
        b = sampling.batch_size
        self._all_dirs = torch.from_numpy(np.tile(sampling.train_dirs, (b, 1))).to(device)

    def new_pass(self) -> None:
        """Draw the next pass's order of the texels."""
        self.order = self.rng.permutation(self.abrdf.shape[0])

    def batch(self, first: int) -> StepBatch:
        """The batch of the texels at ``first``, ``first + 1``, ... of this pass's order."""
        s = self.sampling
        texels = np.sort(self.order[first : first + s.batch_size])
        inputs = self.norm.encoder_input(self.sources[self.source_of_texel[texels]])
        rows = self.source_of_texel[texels] if s.target_from_source else texels
        values = (self.sources if s.target_from_source else self.abrdf)[rows]
        if s.all_queries:
            target = self.norm.target(values if s.in_order else values[:, s.train_dirs])
            directions = self._all_dirs
        else:
            queries = s.train_dirs[
                self.rng.integers(0, len(s.train_dirs), size=(s.batch_size, s.queries))
            ]
            target = self.norm.target(np.take_along_axis(values, queries[:, :, None], 1))
            directions = torch.from_numpy(queries).to(self.device)
        return StepBatch(
            torch.from_numpy(inputs).permute(0, 2, 1).to(self.device),
            directions,
            torch.from_numpy(target).to(self.device),
        )


def resident_bytes(abrdf, sources, target_from_source: bool) -> int:
    """Bytes :class:`DeviceBatches` keeps on the device: the raw sources, and the texels'
    ABRDFs too where the targets are theirs and they are not the sources."""
    count = np.prod(sources.shape)
    if not target_from_source and abrdf is not sources:
        count += np.prod(abrdf.shape)
    return int(count) * 4


def fits_on_device(nbytes: int, device: torch.device) -> bool:
    """Whether ``nbytes`` fit in :data:`DEVICE_SHARE` of the CUDA device's free memory."""
    if device.type != "cuda":
        return False
    free, _ = torch.cuda.mem_get_info(device)
    return nbytes <= DEVICE_SHARE * free


class DeviceBatches:
    """The same batches as :class:`HostBatches` (up to the random queries, drawn on the
    device by a torch generator seeded with ``seed``, and float rounding), gathered and
    normalized on ``device`` from raw ABRDFs copied there once. Same parameters."""

    def __init__(
        self,
        abrdf,
        sources,
        source_of_texel,
        norm: Normalization,
        sampling: Sampling,
        rng: np.random.Generator,
        device: torch.device,
        seed: int,
    ):
        self.sampling, self.rng, self.device = sampling, rng, device
        self.m = abrdf.shape[0]
        self.sources = _upload(sources, device)
        shared = sampling.target_from_source or abrdf is sources  # the targets are the sources
        self.values = self.sources if shared else _upload(abrdf, device)
        self.source_of_texel = torch.from_numpy(np.asarray(source_of_texel, np.int64)).to(device)
        self.mean = torch.from_numpy(norm.mean).to(device)
        self.std = torch.from_numpy(norm.std).to(device)
        self.alpha = torch.tensor(norm.alpha, dtype=torch.float32, device=device)
        self.train_dirs = torch.from_numpy(np.asarray(sampling.train_dirs, np.int64)).to(device)
        self._all_dirs = self.train_dirs.expand(sampling.batch_size, -1)
        self.generator = torch.Generator(device).manual_seed(seed)
        self.order = torch.arange(self.m, device=device)

    def new_pass(self) -> None:
        self.order = torch.from_numpy(self.rng.permutation(self.m)).to(self.device)

    def batch(self, first: int) -> StepBatch:
        s = self.sampling
        texels = self.order[first : first + s.batch_size].sort().values
        source_rows = self.source_of_texel[texels]
        # Eq. 1-6 as Normalization.encoder_input and .target compute them.
        inputs = (torch.log1p(self.sources[source_rows]) - self.mean) / self.std
        rows = source_rows if s.target_from_source else texels
        if s.all_queries:
            directions = self._all_dirs
            values = self.values[rows]
            values = values if s.in_order else values[:, self.train_dirs]
        else:
            picks = torch.randint(
                0,
                len(self.train_dirs),
                (s.batch_size, s.queries),
                device=self.device,
                generator=self.generator,
            )
            directions = self.train_dirs[picks]
            values = self.values[rows[:, None], directions]
        return StepBatch(inputs.permute(0, 2, 1), directions, values / self.alpha)


def _upload(array, device: torch.device) -> torch.Tensor:
    """``array`` (..., float32 or not, possibly a memory map) as a float32 tensor on
    ``device``, copied a block of texels at a time."""
    out = torch.empty(array.shape, dtype=torch.float32, device=device)
    for start in range(0, array.shape[0], _UPLOAD_TEXELS):
        block = np.ascontiguousarray(array[start : start + _UPLOAD_TEXELS], dtype=np.float32)
        out[start : start + len(block)] = torch.from_numpy(block)
    return out
