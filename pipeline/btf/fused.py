"""The decoder's training gradient by hand: forward and backward chunk by chunk, on threads.

Why not autograd: on a paper-size step (5 ABRDFs x 6561 directions = 32,805 queries)
autograd keeps every activation of the whole batch (14 MB a layer, far past the 1 MB L2
cache of a core), makes separate passes for bias, ReLU and their gradients, and runs the
thin 106-wide products on one intra-op thread pool that barely scales past one core
(``python -m pipeline.bench`` measures all three). Here

- each chunk of queries goes forward and straight back while its activations are in cache;
- biases are fused into ``addmm`` and the ReLU gradient is one ``threshold_backward``;
- the first layer is split into its latent part (once per ABRDF) and its direction part
  (once per direction and step), so no (latent, direction) input row is ever built;
- chunks run on ``workers`` threads, each op single-threaded, with private gradient buffers
  summed in a fixed order at the end (deterministic for a given number of workers);
- each worker's chunk loop is a TorchScript function, whose interpreter does not hold
  Python's GIL; in eager mode every one of a chunk's ~36 torch calls hands the GIL between
  the workers. A paper-size step (5 x 6561 queries, AMX Xeon, medians of 5 interleaved
  rounds) took 48.9 ms eager against 34.7 ms scripted in float32 with 2 workers (61.3
  against 51.7 ms with one), and 25.5 against 18.5 ms in bfloat16 (25.6 against 22.6 ms):
  two eager workers were no faster than one in bfloat16. The gradients are bit for bit
  those of the eager loops.

The result equals autograd's gradient of the mean squared error (``tests/test_fused.py``).

``precision="bfloat16"`` (``train.precision``) runs the products in bfloat16 with float32
master weights, what ``torch.autocast(dtype=torch.bfloat16)`` would do to the decoder:
weights, biases, directions and activations are rounded to bfloat16, each product sums in
float32 and rounds its output to bfloat16; the residual, the loss and the accumulated
gradients stay float32. Each layer and its ReLU is one oneDNN call. On a CPU with AMX the
step ran 1.9-2.1x as fast as float32's (``python -m pipeline.bench``); on a CPU without bfloat16
units oneDNN takes slower code paths (not measured: check with the bench). The gradient
differs from float32's by bfloat16's rounding (``tests/test_fused.py`` bounds it).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import torch

from pipeline.btf.model import Decoder
from pipeline.btf.train_settings import PRECISIONS

# Queries per chunk. float32 is fastest when a chunk's activations stay in a core's L2
# cache; bfloat16 products are so fast that each op's fixed cost dominates small chunks.
# The step at 5 x 6561 queries, 2 workers, scripted loops, medians of 5 interleaved rounds
# on an AMX Xeon, M queries/s: float32 0.95 / 0.94 / 0.79 / 0.78 at 512 / 1024 / 2048 /
# 4096; bfloat16 1.51 / 1.79 / 1.79 at 1024 / 2048 / 4096 (4096 means one chunk per
# worker's half of each ABRDF).
DEFAULT_CHUNK = {"float32": 1024, "bfloat16": 4096}


@dataclass
class Batch:
    """One step's queries, grouped by ABRDF.

    latents : (B, 8) latent of each ABRDF (no autograd graph needed).
    directions : (B, q) int64 direction indices into ``features`` queried per ABRDF.
    targets : (B, q, 3) target values.
    """

    latents: torch.Tensor
    directions: torch.Tensor
    targets: torch.Tensor


@dataclass
class Gradients:
    weights: list[torch.Tensor]  # per linear layer, shaped like its weight
    biases: list[torch.Tensor]
    latents: torch.Tensor  # (B, 8)
    loss: float  # mean squared error of the batch


def _layers(decoder: Decoder) -> list[torch.nn.Linear]:
    layers = [m for m in decoder.net if isinstance(m, torch.nn.Linear)]
    if len(layers) != 4:
        raise ValueError(f"the fused step expects 4 linear layers, the decoder has {len(layers)}")
    return layers


_SCRIPTED: dict = {}


def _script(function):
    """``torch.jit.script(function)``, compiled once per process."""
    if function not in _SCRIPTED:
        _SCRIPTED[function] = torch.jit.script(function)
    return _SCRIPTED[function]


class DecoderStep:
    """Computes :class:`Gradients` of a :class:`Batch`; reuse one instance across steps."""

    def __init__(self, decoder: Decoder, features: torch.Tensor, workers: int = 1,
                 chunk: int | None = None, precision: str = "float32"):
        if precision not in PRECISIONS:
            raise ValueError(f"precision={precision!r} must be one of {PRECISIONS}")
        self.decoder = decoder
        self.features = features
        self.workers = max(1, int(workers))
        self.chunk = max(1, int(chunk or DEFAULT_CHUNK[precision]))
        self.precision = precision
        self._features_bf16 = features.to(torch.bfloat16) if precision == "bfloat16" else None
        self._pool = ThreadPoolExecutor(self.workers - 1) if self.workers > 1 else None
        self._chunks = _script(_bfloat16_chunks if precision == "bfloat16" else _float32_chunks)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()

    def __call__(self, batch: Batch) -> Gradients:
        if self.precision == "bfloat16":
            return self._bfloat16(batch)
        weights, biases = self._parameters()
        n_latent = self.decoder.latent
        z = batch.latents.detach()
        # First layer: W1 [z; d] + b1 = (W1z z) + (W1d d + b1), each part computed once.
        direction_part = torch.addmm(biases[0], self.features, weights[0][:, n_latent:].T)
        latent_part = z @ weights[0][:, :n_latent].T
        b, q = batch.directions.shape
        items = [(i, s) for i in range(b) for s in range(0, q, self.chunk)]
        scale = 2.0 / (b * q * batch.targets.shape[-1])
        shared = (weights, biases, z, direction_part, latent_part, batch.directions,
                  batch.targets, self.features, scale, self.chunk)
        parts = self._run([items[w :: self.workers] for w in range(self.workers)], *shared)
        return _sum(parts, b * q * batch.targets.shape[-1])

    def _parameters(self) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        layers = _layers(self.decoder)
        return ([layer.weight.detach() for layer in layers],
                [layer.bias.detach() for layer in layers])

    def _run(self, items_of_worker: list[list], *shared) -> list[Gradients]:
        """Worker 0's chunks on the calling thread, each other worker's on a pool thread."""
        futures = [self._pool.submit(self._work, items, *shared)
                   for items in items_of_worker[1:]]
        threads = torch.get_num_threads()
        try:
            first = self._work(items_of_worker[0], *shared)
        finally:
            torch.set_num_threads(threads)
        return [first] + [f.result() for f in futures]

    def _work(self, items, *shared) -> Gradients:
        torch.set_num_threads(1)  # this thread's own setting (OpenMP's is per thread)
        g_w, g_b, g_z, loss = self._chunks(items, *shared)
        return Gradients(g_w, g_b, g_z, float(loss))

    def _bfloat16(self, batch: Batch) -> Gradients:
        bf16 = torch.bfloat16
        weights, biases = self._parameters()
        n_latent = self.decoder.latent
        z = batch.latents.detach()
        # The first layer as a product over the directions alone, its latent part folded
        # into a bias per ABRDF: W1 [z; d] + b1 = W1d d + (W1z z + b1).
        first_bias = torch.addmm(biases[0], z, weights[0][:, :n_latent].T).to(bf16)
        low = [weights[0][:, n_latent:].to(bf16)] + [w.to(bf16) for w in weights[1:]]
        low_biases = [bias.to(bf16) for bias in biases[1:]]
        b, q = batch.directions.shape
        items = split_rows(b, q, self.workers, self.chunk)
        scale = 2.0 / (b * q * batch.targets.shape[-1])
        onednn = first_bias.is_cpu and torch.backends.mkldnn.is_available()
        parts = self._run(items, batch.directions, batch.targets, low, low_biases, first_bias,
                          self._features_bf16, scale, n_latent, onednn)
        total = _sum(parts, b * q * batch.targets.shape[-1])
        # The workers summed dL/d(W1z z) per ABRDF in ``latents``; W1z's and z's gradients
        # follow from it in float32.
        hidden = total.latents
        total.weights[0][:, :n_latent] = hidden.T @ z.float()
        total.latents = hidden @ weights[0][:, :n_latent]
        return total

    def assign(self, grads: Gradients) -> None:
        """Store ``grads`` as the decoder parameters' ``.grad`` (adding to what is there)."""
        for layer, g_w, g_b in zip(_layers(self.decoder), grads.weights, grads.biases,
                                   strict=True):
            for param, grad in ((layer.weight, g_w), (layer.bias, g_b)):
                if param.grad is None:
                    param.grad = grad
                else:
                    param.grad += grad


def _float32_chunks(items: list[tuple[int, int]], weights: list[torch.Tensor],
                    biases: list[torch.Tensor], z: torch.Tensor, direction_part: torch.Tensor,
                    latent_part: torch.Tensor, directions: torch.Tensor, targets: torch.Tensor,
                    features: torch.Tensor, scale: float, chunk: int):
    """The float32 forward and backward of ``items`` ((ABRDF, first row) chunks of
    ``chunk`` rows). The first layer's ``direction_part`` (W1d d + b1, per direction) and
    ``latent_part`` (W1z z, per ABRDF) are precomputed. Returns (weight gradients, bias
    gradients, latent gradients, sum of squared residuals). Scripted like
    :func:`_bfloat16_chunks`, and for the same reason."""
    n_latent = z.shape[1]
    g_w = [torch.zeros_like(w) for w in weights]
    g_b = [torch.zeros_like(b) for b in biases]
    g_z = torch.zeros_like(z)
    loss = torch.zeros((), dtype=torch.float64, device=z.device)
    for item in items:
        i, start = item
        index = directions[i, start : start + chunk]
        a1 = direction_part.index_select(0, index).add_(latent_part[i]).relu_()
        a2 = torch.addmm(biases[1], a1, weights[1].t()).relu_()
        a3 = torch.addmm(biases[2], a2, weights[2].t()).relu_()
        residual = torch.addmm(biases[3], a3, weights[3].t()).sub_(
            targets[i, start : start + chunk])
        loss += residual.square().sum(dtype=torch.float64)
        g = residual.mul_(scale)  # d(mean squared error)/d(output)
        g_w[3].addmm_(g.t(), a3)
        g_b[3] += g.sum(0)
        g = torch.ops.aten.threshold_backward(g @ weights[3], a3, 0)
        g_w[2].addmm_(g.t(), a2)
        g_b[2] += g.sum(0)
        g = torch.ops.aten.threshold_backward(g @ weights[2], a2, 0)
        g_w[1].addmm_(g.t(), a1)
        g_b[1] += g.sum(0)
        g = torch.ops.aten.threshold_backward(g @ weights[1], a1, 0)
        g_sum = g.sum(0)
        g_w[0][:, n_latent:].addmm_(g.t(), features.index_select(0, index))
        g_w[0][:, :n_latent] += torch.outer(g_sum, z[i])
        g_b[0] += g_sum
        g_z[i] += g_sum @ weights[0][:, :n_latent]
    return g_w, g_b, g_z, loss


def _sum(parts: list[Gradients], count: int) -> Gradients:
    """The workers' gradients summed in a fixed order (deterministic for a number of
    workers); the loss becomes the mean over ``count`` values."""
    first, *rest = parts
    for part in rest:
        for total, add in zip(first.weights + first.biases, part.weights + part.biases,
                              strict=True):
            total += add
        first.latents += part.latents
        first.loss += part.loss
    first.loss /= count
    return first


def split_rows(b: int, q: int, workers: int, chunk: int) -> list[list[tuple]]:
    """Worker w takes the w-th of ``workers`` equal parts of every ABRDF's ``q`` queries, in
    chunks of at most ``chunk`` rows that never span two ABRDFs (a chunk's first-layer bias
    is its ABRDF's), so that all workers get the same number of rows. Returns each worker's
    (ABRDF, first row, end row) items."""
    part = -(-q // workers)
    return [[(i, s, min(s + chunk, p + part, q)) for i in range(b)
             for s in range(p, min(p + part, q), chunk)]
            for p in range(0, part * workers, part)]


def _bfloat16_chunks(items: list[tuple[int, int, int]], directions: torch.Tensor,
                     targets: torch.Tensor, weights: list[torch.Tensor],
                     biases: list[torch.Tensor], first_bias: torch.Tensor,
                     features: torch.Tensor, scale: float, n_latent: int, onednn: bool):
    """The bfloat16 forward and backward of ``items`` ((ABRDF, first row, end row) chunks of
    ``directions`` / ``targets``); ``weights`` in bfloat16, the first layer's restricted to
    the directions, ``biases`` those of layers 2-4 in bfloat16 and ``first_bias`` the first
    layer's per ABRDF. Returns (weight gradients, bias gradients, dL/d(W1z z) per ABRDF, sum
    of squared residuals).

    Runs as TorchScript (:func:`_script`; see the module's docstring for why).
    ``onednn``: each layer and its ReLU is one oneDNN call (a separate bfloat16 ReLU pass
    measured half to three quarters of the product's time), addmm elsewhere.
    """
    g_w = [torch.zeros(weights[0].shape[0], n_latent + weights[0].shape[1],
                       device=first_bias.device)]
    g_b = [torch.zeros(first_bias.shape[1], device=first_bias.device)]
    for k in range(1, len(weights)):  # (TorchScript has no zip(strict=))
        g_w.append(torch.zeros(weights[k].shape, device=first_bias.device))
        g_b.append(torch.zeros(biases[k - 1].shape, device=first_bias.device))
    g_hidden = torch.zeros(first_bias.shape, device=first_bias.device)  # (B, 106)
    loss = torch.zeros((), dtype=torch.float64, device=first_bias.device)
    for item in items:
        i, start, stop = item
        x = features.index_select(0, directions[i, start:stop])
        layer_biases = [first_bias[i]] + biases
        a = [x]
        for k in range(4):
            relu = k < 3
            if onednn:
                out = torch.ops.mkldnn._linear_pointwise(a[k], weights[k], layer_biases[k],
                                                         "relu" if relu else "none", [], "")
            else:
                out = torch.addmm(layer_biases[k], a[k], weights[k].t())
                if relu:
                    out = out.relu_()
            a.append(out)
        residual = a[4].float().sub_(targets[i, start:stop])
        loss += residual.square().sum(dtype=torch.float64)
        g = residual.mul_(scale).to(torch.bfloat16)  # d(mean squared error)/d(output)
        for k in range(3, 0, -1):
            g_w[k] += g.t() @ a[k]
            g_b[k] += g.sum(0)
            g = torch.ops.aten.threshold_backward(g @ weights[k], a[k], 0)
        g_sum = g.sum(0).float()  # sums in float32, rounds to bfloat16 (3x faster)
        g_w[0][:, n_latent:] += g.t() @ x
        g_b[0] += g_sum
        g_hidden[i] += g_sum
    return g_w, g_b, g_hidden, loss

