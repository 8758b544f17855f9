"""The encoder's training forward and backward by hand: block by block, a few ABRDFs at a time.

Why not autograd over the whole batch (``Encoder.forward_layers``): at
``experiment=paper_cpu``'s 32 ABRDFs x 6561 directions, each block's convolution output
(13 MB for the first) is far past a core's L2 cache, and autograd makes separate passes
over it for the max-pool, its indices, the ReLU, batch-norm and each of their gradients,
mostly into fresh memory that the kernel faults in page by page; the convolutions are a
minority of that step's time (docs/performance.md). Here, for each block (conv ->
max-pool -> ReLU -> batch-norm):

- forward, one chunk of ABRDFs at a time (about :data:`CHUNK_BYTES` of convolution output):
  the convolution (oneDNN, channels-last), torch's max-pool with its indices and the ReLU,
  then the chunk's batch-norm statistics, merged across chunks (Chan, Golub and LeVeque's
  pairwise update). Only the pooled output ``r`` (B, L/3, C) and the indices are kept; the
  next block recomputes the normalized output from ``r`` (one multiply-add) chunk by chunk;
- backward, one chunk at a time: batch-norm's gradient from its two per-channel sums (summed
  while the block above produced the chunk's gradient), the ReLU's, the max-pool's (torch's
  kernel, from the kept indices) and the convolution's (oneDNN).

Batch-norm uses, and updates the running statistics with, the whole batch's statistics as
``nn.BatchNorm1d`` in training mode does. The result is ``Encoder.reference``'s with its
gradients up to rounding (``tests/test_encoder_speed.py``): the same max-pool kernel (the
first maximum of a triple gets the gradient), other summation orders for the statistics.

Layouts: a block's input and output are (B, L, C) tensors, channel fastest: the memory of a
channels-last (B, C, 1, L) tensor, which oneDNN's convolution and torch's max-pool take as
they are. The fully connected layer reads the last block's output in that order, with its
weight's columns permuted to match (the plain layout's flatten is channel-major).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn
from torch.autograd.function import once_differentiable

# Bytes of convolution output per chunk of ABRDFs: a chunk's convolution output, pooled
# output and indices should stay in a core's L2 cache between the ops that read them.
CHUNK_BYTES = 2 << 20
_CL = torch.channels_last
# The (B, C, 1, L) max-pool's kernel, stride, padding, dilation and ceil_mode: 3 along L.
_POOL = ([1, 3], [1, 3], [0, 0], [1, 1], False)
# The convolution's stride, padding, dilation, transposed, output padding and groups.
_CONV = ([1, 1], [0, 1], [1, 1], False, [0, 0], 1)


def encode_for_training(
    convs: Sequence[nn.Conv1d],
    norms: Sequence[nn.BatchNorm1d],
    fc: nn.Linear,
    abrdf: torch.Tensor,
    chunk_bytes: int = CHUNK_BYTES,
) -> torch.Tensor:
    """Latents of ``abrdf`` with the blocks ``convs[i] -> max-pool 3 -> ReLU -> norms[i]``
    and ``fc``, batch-norm in training mode (its running statistics updated), and a
    gradient for backward.

    Parameters
    ----------
    convs : the blocks' ``Conv1d(kernel_size=3, padding=1)`` layers, with biases.
    norms : the blocks' affine ``BatchNorm1d`` layers.
    fc : the ``Linear`` layer from the flattened last block (channel-major) to the latent.
    abrdf : tensor of shape (B, 3, N), float; cheapest as a view of (B, N, 3) memory
        (``x.permute(0, 2, 1)``), which is not copied.
    chunk_bytes : convolution output per chunk of ABRDFs (speed only).

    Returns
    -------
    latents : tensor of shape (B, fc.out_features)
    """
    x = abrdf.permute(0, 2, 1).contiguous()  # (B, N, 3)
    params = [
        t
        for conv, norm in zip(convs, norms, strict=True)
        for t in (conv.weight, conv.bias, norm.weight, norm.bias)
    ]
    return _EncoderFunction.apply(x, list(norms), int(chunk_bytes), fc.weight, fc.bias, *params)


@dataclass
class _Block:
    """What a block's backward needs: its pooled output ``r`` (B, n, C) after the ReLU and
    before batch-norm, the max-pool's indices (B, C, 1, n) channels-last, the batch
    statistics of ``r`` per channel (mean, biased variance, 1 / std), the rows they cover,
    the chunks, and batch-norm as one multiply-add per channel (``scale``, ``shift``:
    gamma / std and beta - mean gamma / std)."""

    r: torch.Tensor
    indices: torch.Tensor
    mean: torch.Tensor
    var: torch.Tensor
    invstd: torch.Tensor
    count: int
    chunks: list[tuple[int, int]]
    length: int  # L, the block's input length
    scale: torch.Tensor | None = None
    shift: torch.Tensor | None = None


def _channels_last(h: torch.Tensor) -> torch.Tensor:
    """(c, L, C) contiguous -> the (c, C, 1, L) channels-last view of the same memory."""
    return h.permute(0, 2, 1).unsqueeze(2)


def _rows(t: torch.Tensor) -> torch.Tensor:
    """(c, C, 1, L) channels-last -> the (c, L, C) contiguous view of the same memory."""
    return t.squeeze(2).permute(0, 2, 1)


def _chunks(
    batch: int, length: int, channels: int, itemsize: int, chunk_bytes: int
) -> list[tuple[int, int]]:
    rows = max(1, chunk_bytes // (length * channels * itemsize))
    return [(s, min(s + rows, batch)) for s in range(0, batch, rows)]


def _block_input(x: torch.Tensor, blocks: list[_Block], i: int, s: int, e: int) -> torch.Tensor:
    """The ABRDFs s..e of block ``i``'s input, (c, L, C_in): ``x`` itself for the first
    block, else the batch-norm output of the block below, recomputed from its ``r``."""
    if i == 0:
        return x[s:e]
    below = blocks[i - 1]
    return torch.addcmul(below.shift, below.r[s:e], below.scale)


def _norm_sums(block: _Block, g_sum: torch.Tensor, gr_sum: torch.Tensor):
    """Batch-norm's per-channel sums of g and of g x-hat (x-hat = (r - mean) / std) from
    those of g and of g r."""
    return g_sum, (gr_sum - block.mean * g_sum) * block.invstd


def _fc_columns(weight: torch.Tensor, length: int, channels: int) -> torch.Tensor:
    """The fc weight (out, C L), columns channel-major, with its columns in (L, C) order."""
    return weight.view(-1, channels, length).transpose(1, 2).reshape(weight.shape[0], -1)


class _EncoderFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, norms, chunk_bytes, fc_weight, fc_bias, *params):
        batch = x.shape[0]
        blocks: list[_Block] = []
        for i, norm in enumerate(norms):
            length = x.shape[1] if i == 0 else blocks[-1].r.shape[1]
            weight, bias, gamma, beta = params[4 * i : 4 * i + 4]
            input_of = functools.partial(_block_input, x, blocks, i)
            block = _forward_block(input_of, weight, bias, norm.eps, length, batch, chunk_bytes)
            block.scale = gamma * block.invstd
            block.shift = beta - block.mean * block.scale
            _update_running_stats(norm, block)
            blocks.append(block)
        h = _block_input(x, blocks, len(blocks), 0, batch)  # the last block's output
        _, length, channels = h.shape
        columns = _fc_columns(fc_weight, length, channels)
        latents = torch.addmm(fc_bias, h.reshape(batch, -1), columns.T)
        ctx.blocks, ctx.h, ctx.columns = blocks, h, columns
        ctx.save_for_backward(x, fc_weight, *params)
        return latents

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_latents):
        x, fc_weight, *params = ctx.saved_tensors
        blocks, h = ctx.blocks, ctx.h
        batch, length, channels = h.shape
        g_fc_weight = (grad_latents.T @ h.reshape(batch, -1)).view(-1, length, channels)
        g_fc_weight = g_fc_weight.transpose(1, 2).reshape(fc_weight.shape)
        g = (grad_latents @ ctx.columns).view(batch, length, channels)
        g_rows = g.view(-1, channels)
        sums = _norm_sums(
            blocks[-1], g_rows.sum(0), (g_rows * blocks[-1].r.view(-1, channels)).sum(0)
        )
        grads: list = [None] * len(params)
        for i in range(len(blocks) - 1, -1, -1):
            need_input = i > 0 or ctx.needs_input_grad[0]
            g, g_weight, g_bias, below_sums = _backward_block(
                x, blocks, params, i, g, sums, need_input
            )
            grads[4 * i : 4 * i + 4] = [g_weight, g_bias, sums[1], sums[0]]
            sums = below_sums
        return (g, None, None, g_fc_weight, grad_latents.sum(0), *grads)


def _forward_block(input_of, weight, bias, eps, length, batch, chunk_bytes) -> _Block:
    """Convolution, max-pool and ReLU chunk by chunk, and the batch statistics."""
    channels = weight.shape[0]
    n = length // 3
    options = {"dtype": weight.dtype, "device": weight.device}
    r = torch.empty(batch, n, channels, **options)
    indices = torch.empty(
        batch, channels, 1, n, dtype=torch.int64, device=weight.device, memory_format=_CL
    )
    chunks = _chunks(batch, length, channels, weight.element_size(), chunk_bytes)
    kernel = weight.unsqueeze(2)
    mean = torch.zeros(channels, **options)
    squares = torch.zeros(channels, **options)  # sum of squared deviations from the mean
    count = 0
    for s, e in chunks:
        y = F.conv2d(_channels_last(input_of(s, e)), kernel, bias, padding=(0, 1))
        # Straight into r and the indices (both channels-last slices): no copies.
        torch.ops.aten.max_pool2d_with_indices.out(
            y, *_POOL, out=_channels_last(r[s:e]), indices=indices[s:e]
        )
        rows = r[s:e].clamp_min_(0).view(-1, channels)
        # Chan, Golub and LeVeque's update of (count, mean, squares) by this chunk's.
        k = rows.shape[0]
        chunk_mean = rows.sum(0) / k
        chunk_squares = (rows - chunk_mean).square_().sum(0)
        delta = chunk_mean - mean
        total = count + k
        mean = mean + delta * (k / total)
        squares = squares + chunk_squares + delta.square() * (count * k / total)
        count = total
    var = squares / count
    return _Block(r, indices, mean, var, torch.rsqrt(var + eps), count, chunks, length)


def _update_running_stats(norm: nn.BatchNorm1d, block: _Block) -> None:
    """What ``F.batch_norm`` does to ``norm``'s running statistics in training mode: the
    batch mean, and the unbiased batch variance, by the momentum (or cumulatively)."""
    if not norm.track_running_stats:
        return
    norm.num_batches_tracked.add_(1)
    if norm.momentum is None:  # a cumulative moving average
        factor = 1.0 / float(norm.num_batches_tracked)
    else:
        factor = norm.momentum
    unbiased = block.var * (block.count / max(block.count - 1, 1))
    norm.running_mean.mul_(1 - factor).add_(block.mean, alpha=factor)
    norm.running_var.mul_(1 - factor).add_(unbiased, alpha=factor)


def _backward_block(
    x, blocks: list[_Block], params, i: int, g: torch.Tensor, sums, need_input: bool
):
    """Block ``i``'s backward: ``g`` (B, n, C) is the gradient at its batch-norm's output
    and ``sums`` the per-channel sums of g and of g x-hat over the batch. Returns the
    gradient at the block's input (B, L, C_in) (None unless ``need_input``), the
    convolution's weight and bias gradients and, for the block below, its ``sums``."""
    block = blocks[i]
    weight, bias = params[4 * i : 4 * i + 2]
    channels, inputs = weight.shape[:2]
    # batch-norm: dL/dr = gamma / std (g - mean(g) - x-hat mean(g x-hat)), with
    # x-hat = (r - mean) / std, as scale g + slope r + offset per channel.
    scale = block.scale
    slope = -scale * block.invstd * (sums[1] / block.count)
    offset = -scale * (sums[0] / block.count) - slope * block.mean
    kernel = weight.unsqueeze(2)
    g_weight = torch.zeros_like(kernel)
    g_bias = torch.zeros_like(bias)
    options = {"dtype": g.dtype, "device": g.device}
    g_in = torch.empty(x.shape[0], block.length, inputs, **options) if need_input else None
    g_sum, gr_sum = torch.zeros(inputs, **options), torch.zeros(inputs, **options)
    for s, e in block.chunks:
        r = block.r[s:e]
        g_r = torch.addcmul(offset, g[s:e], scale).addcmul_(r, slope)
        g_pooled = torch.ops.aten.threshold_backward(g_r, r, 0)  # the ReLU
        template = torch.empty((e - s, channels, 1, block.length), memory_format=_CL, **options)
        g_y = torch.ops.aten.max_pool2d_with_indices_backward(
            _channels_last(g_pooled), template, *_POOL, block.indices[s:e]
        )
        h = _channels_last(_block_input(x, blocks, i, s, e)).contiguous(memory_format=_CL)
        g_h, g_w, g_b = torch.ops.aten.convolution_backward(
            g_y, h, kernel, [channels], *_CONV, [need_input, True, True]
        )
        g_weight += g_w
        g_bias += g_b
        if need_input:
            g_h = _rows(g_h)
            g_in[s:e] = g_h
            if i > 0:
                rows = g_h.reshape(-1, inputs)
                g_sum.add_(rows.sum(0))
                gr_sum.add_((rows * blocks[i - 1].r[s:e].view(rows.shape)).sum(0))
    below_sums = _norm_sums(blocks[i - 1], g_sum, gr_sum) if i > 0 else None
    return g_in, g_weight.squeeze(2), g_bias, below_sums
