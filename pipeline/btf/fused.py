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
  summed in a fixed order at the end (deterministic for a given number of workers).

The result equals autograd's gradient of the mean squared error (``tests/test_fused.py``).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import torch

from pipeline.btf.model import Decoder


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


class DecoderStep:
    """Computes :class:`Gradients` of a :class:`Batch`; reuse one instance across steps."""

    def __init__(self, decoder: Decoder, features: torch.Tensor, workers: int = 1,
                 chunk: int = 2048):
        self.decoder = decoder
        self.features = features
        self.workers = max(1, int(workers))
        self.chunk = max(1, int(chunk))
        self._pool = ThreadPoolExecutor(self.workers) if self.workers > 1 else None

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()

    def __call__(self, batch: Batch) -> Gradients:
        layers = _layers(self.decoder)
        weights = [layer.weight.detach() for layer in layers]
        biases = [layer.bias.detach() for layer in layers]
        n_latent = self.decoder.latent
        z = batch.latents.detach()
        # First layer: W1 [z; d] + b1 = (W1z z) + (W1d d + b1), each part computed once.
        direction_part = torch.addmm(biases[0], self.features, weights[0][:, n_latent:].T)
        latent_part = z @ weights[0][:, :n_latent].T
        b, q = batch.directions.shape
        items = [(i, s) for i in range(b) for s in range(0, q, self.chunk)]
        scale = 2.0 / (b * q * batch.targets.shape[-1])
        shared = (weights, biases, z, direction_part, latent_part, batch, scale)
        if self._pool is None:
            parts = [self._work(items, *shared)]
        else:
            futures = [self._pool.submit(self._work, items[w :: self.workers], *shared)
                       for w in range(self.workers)]
            parts = [f.result() for f in futures]
        first, *rest = parts
        for part in rest:  # fixed order: deterministic for a given number of workers
            for total, add in zip(first.weights + first.biases, part.weights + part.biases,
                                  strict=True):
                total += add
            first.latents += part.latents
            first.loss += part.loss
        first.loss /= b * q * batch.targets.shape[-1]
        return first

    def _work(self, items, weights, biases, z, direction_part, latent_part, batch, scale):
        threshold_backward = torch.ops.aten.threshold_backward
        n_latent = self.decoder.latent
        g_w = [torch.zeros_like(w) for w in weights]
        g_b = [torch.zeros_like(b) for b in biases]
        g_z = torch.zeros_like(z)
        loss = torch.zeros((), dtype=torch.float64, device=z.device)
        for i, start in items:
            index = batch.directions[i, start : start + self.chunk]
            a1 = direction_part.index_select(0, index).add_(latent_part[i]).relu_()
            a2 = torch.addmm(biases[1], a1, weights[1].T).relu_()
            a3 = torch.addmm(biases[2], a2, weights[2].T).relu_()
            residual = torch.addmm(biases[3], a3, weights[3].T).sub_(
                batch.targets[i, start : start + self.chunk])
            loss += residual.square().sum(dtype=torch.float64)
            g = residual.mul_(scale)  # d(mean squared error)/d(output)
            g_w[3].addmm_(g.T, a3)
            g_b[3] += g.sum(0)
            g = threshold_backward(g @ weights[3], a3, 0)
            g_w[2].addmm_(g.T, a2)
            g_b[2] += g.sum(0)
            g = threshold_backward(g @ weights[2], a2, 0)
            g_w[1].addmm_(g.T, a1)
            g_b[1] += g.sum(0)
            g = threshold_backward(g @ weights[1], a1, 0)
            g_sum = g.sum(0)
            g_w[0][:, n_latent:].addmm_(g.T, self.features.index_select(0, index))
            g_w[0][:, :n_latent] += torch.outer(g_sum, z[i])
            g_b[0] += g_sum
            g_z[i] += g_sum @ weights[0][:, :n_latent]
        return Gradients(g_w, g_b, g_z, float(loss))

    def assign(self, grads: Gradients) -> None:
        """Store ``grads`` as the decoder parameters' ``.grad`` (adding to what is there)."""
        for layer, g_w, g_b in zip(_layers(self.decoder), grads.weights, grads.biases,
                                   strict=True):
            for param, grad in ((layer.weight, g_w), (layer.bias, g_b)):
                if param.grad is None:
                    param.grad = grad
                else:
                    param.grad += grad
