"""The decoder's training gradient by hand: forward and backward chunk by chunk, on threads.

Why not autograd: on a paper-size step (5 ABRDFs x 6561 directions = 32,805 queries)
autograd keeps every activation of the whole batch (14 MB a layer, far past a core's L2
cache), makes separate passes for bias, ReLU and their gradients, and runs the thin
106-wide products on an intra-op thread pool that barely scales past one core
(``python -m benchmarks.train`` compares the two; figures in docs/performance.md). Here

- each chunk of queries goes forward and straight back while its activations are in cache;
- biases are fused into the products; where the C++ kernels of :mod:`pipeline.btf.fast.kernels`
  build (:func:`_chunks_fused`), the last layer's forward, residual, loss and backward into
  the last hidden layer are one pass over its activations (seven torch calls otherwise),
  and each ReLU's gradient is one pass with its bias gradient or the first layer's weight
  gradient (two calls otherwise);
- no (latent, direction) input row is built: the first layer's latent part is computed
  once per ABRDF and enters as a weight column picked by a one-hot input
  (:meth:`DecoderStep.__call__`), so a chunk may span ABRDFs and its size is free of the
  batch's shape (chunks that ended with each ABRDF were small, and slow, at
  ``experiment=paper_cpu``'s 256 queries per ABRDF). The one-hot input costs B
  multiply-adds per hidden unit and query, few at the batches used (5, 32);
- chunks run on ``workers`` threads, each op single-threaded, with private gradient buffers
  summed in a fixed order at the end (deterministic for a given number of workers);
- each worker's chunk loop is a TorchScript function, whose interpreter does not hold
  Python's GIL: in eager mode each of a chunk's ~36 torch calls hands the GIL between the
  workers, and two eager workers were no faster than one in bfloat16. The gradients are
  bit for bit those of the eager loops.

The result equals autograd's gradient of the mean squared error (``tests/test_fused.py``).

``precision="bfloat16"`` (``train.precision``) runs the products in bfloat16 with float32
master weights, as ``torch.autocast(dtype=torch.bfloat16)`` would: weights, biases,
directions and activations are rounded to bfloat16, each product sums in float32 and
rounds its output to bfloat16; the residual, the loss and the accumulated gradients stay
float32. Where the CPU supports bfloat16, each hidden layer and its ReLU is one oneDNN
call. It pays on a CPU with AMX or AVX512-BF16, elsewhere the products take slower paths
(docs/performance.md). The gradient differs from float32's by bfloat16's rounding
(``tests/test_fused.py`` bounds it).
"""

from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import torch

from pipeline.btf.fast import kernels
from pipeline.btf.model import Decoder
from pipeline.btf.train_settings import PRECISIONS

# Queries per chunk. float32 is fastest when a chunk's activations stay in a core's L2
# cache; bfloat16 products are so fast that each op's fixed cost dominates small chunks
# (the sizes compared: docs/performance.md).
DEFAULT_CHUNK = {"float32": 1024, "bfloat16": 8192}


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


@functools.cache
def _script(function):
    """``torch.jit.script(function)``, compiled once per process."""
    return torch.jit.script(function)


class DecoderStep:
    """Computes :class:`Gradients` of a :class:`Batch`; reuse one instance across steps."""

    def __init__(
        self,
        decoder: Decoder,
        features: torch.Tensor,
        workers: int = 1,
        chunk: int | None = None,
        precision: str = "float32",
        fused_kernels: bool | None = None,
    ):
        """``fused_kernels``: use :mod:`pipeline.btf.fast.kernels` (None: where they build, on
        the CPU; False: torch ops only)."""
        if precision not in PRECISIONS:
            raise ValueError(f"precision={precision!r} must be one of {PRECISIONS}")
        self.decoder = decoder
        self.workers = max(1, int(workers))
        self.chunk = max(1, int(chunk or DEFAULT_CHUNK[precision]))
        self.precision = precision
        # The products' type: bfloat16, or the decoder's own (float64 in the tests).
        dtype = torch.bfloat16 if precision == "bfloat16" else features.dtype
        self.features = features.to(dtype)
        self._inputs = torch.empty(0, dtype=dtype, device=features.device)
        self._pool = ThreadPoolExecutor(self.workers - 1) if self.workers > 1 else None
        on_cpu = features.device.type == "cpu"
        if fused_kernels is None:
            fused_kernels = on_cpu and kernels.available()
        elif fused_kernels and not (on_cpu and kernels.available()):
            raise ValueError(
                "fused_kernels=True needs the C++ kernels (pipeline.btf.fast.kernels) "
                f"and a CPU device; features are on {features.device}, kernels "
                f"{'built' if kernels.available() else 'not built'}"
            )
        self.fused_kernels = bool(fused_kernels)
        self._chunks = _script(_chunks_fused if self.fused_kernels else _chunks)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()

    def __call__(self, batch: Batch) -> Gradients:
        layers = _layers(self.decoder)
        weights = [layer.weight.detach() for layer in layers]
        biases = [layer.bias.detach() for layer in layers]
        n_latent, n_direction = self.decoder.latent, self.features.shape[1]
        z = batch.latents.detach()
        dtype = self.features.dtype
        # The first layer, W1 [z; d] + b1 = W1d d + (W1z z + b1), as one product over input
        # rows [d, e_i]: a query's direction features, then the one-hot e_i of its ABRDF i,
        # against [W1d, (W1z z_j + b1) for each ABRDF j]. Each ABRDF's latent part is one
        # weight column, so a chunk may span ABRDFs.
        first = torch.cat(
            [weights[0][:, n_latent:], torch.addmm(biases[0], z, weights[0][:, :n_latent].T).T], 1
        )
        inputs = self._rows(batch.directions)
        low = [first.to(dtype)] + [w.to(dtype) for w in weights[1:]]
        low_biases = [bias.to(dtype) for bias in biases[1:]]
        rows = batch.directions.numel()
        targets = batch.targets.reshape(rows, -1).contiguous()
        # oneDNN's fused bfloat16 layer has no primitive on CPUs without bfloat16 support
        # (AVX-512 BF16 or AMX; an AVX2-only CPU refuses it): plain products there.
        onednn = (
            inputs.is_cpu
            and dtype == torch.bfloat16
            and torch.backends.mkldnn.is_available()
            and torch.ops.mkldnn._is_mkldnn_bf16_supported()
        )
        items = split_rows(rows, self.workers, self.chunk)
        scale = 2.0 / targets.numel()  # d(mean squared error)/d(residual) = scale x residual
        g_w, g_b, loss = _sum(self._run(items, inputs, targets, low, low_biases, scale, onednn))
        # The one-hot columns' gradient is dL/d(W1z z_i + b1) per ABRDF i; W1z's, b1's and
        # z's gradients follow from it.
        hidden = g_w[0][:, n_direction:].T  # (B, 106)
        g_first = torch.empty_like(weights[0])
        g_first[:, n_latent:] = g_w[0][:, :n_direction]
        g_first[:, :n_latent] = hidden.T @ z
        return Gradients(
            [g_first] + g_w[1:],
            [hidden.sum(0)] + g_b,
            hidden @ weights[0][:, :n_latent],
            loss / targets.numel(),
        )

    def _rows(self, directions: torch.Tensor) -> torch.Tensor:
        """The first layer's (B q, n_direction + B) input rows [d, e_i] (see __call__); the
        one-hot part is built once per batch shape and kept."""
        b, q = directions.shape
        n = self.features.shape[1]
        options = {"dtype": self.features.dtype, "device": self.features.device}
        if self._inputs.shape != (b * q, n + b):
            self._inputs = torch.zeros(b * q, n + b, **options)
            self._inputs.view(b, q, n + b)[:, :, n:] = torch.eye(b, **options)[:, None, :]
        self._inputs[:, :n] = self.features.index_select(0, directions.reshape(-1))
        return self._inputs

    def _run(self, items_of_worker: list[list], *shared) -> list[tuple]:
        """Worker 0's chunks on the calling thread, each other worker's on a pool thread."""
        futures = [self._pool.submit(self._work, items, *shared) for items in items_of_worker[1:]]
        threads = torch.get_num_threads()
        try:
            first = self._work(items_of_worker[0], *shared)
        finally:
            torch.set_num_threads(threads)
        return [first] + [f.result() for f in futures]

    def _work(self, items, *shared) -> tuple[list[torch.Tensor], list[torch.Tensor], float]:
        torch.set_num_threads(1)  # this thread's own setting (OpenMP's is per thread)
        g_w, g_b, loss = self._chunks(items, *shared)
        return g_w, g_b, float(loss)

    def assign(self, grads: Gradients) -> None:
        """Store ``grads`` as the decoder parameters' ``.grad`` (adding to what is there)."""
        for layer, g_w, g_b in zip(_layers(self.decoder), grads.weights, grads.biases, strict=True):
            for param, grad in ((layer.weight, g_w), (layer.bias, g_b)):
                if param.grad is None:
                    param.grad = grad
                else:
                    param.grad += grad


def split_rows(rows: int, workers: int, chunk: int) -> list[list[tuple[int, int]]]:
    """Worker w takes the w-th of ``workers`` equal parts of the ``rows`` query rows, in
    chunks of at most ``chunk`` rows. Returns each worker's (first row, end row) items."""
    part = -(-rows // workers)
    return [
        [(s, min(s + chunk, p + part, rows)) for s in range(p, min(p + part, rows), chunk)]
        for p in range(0, part * workers, part)
    ]


def _chunks(
    items: list[tuple[int, int]],
    inputs: torch.Tensor,
    targets: torch.Tensor,
    weights: list[torch.Tensor],
    biases: list[torch.Tensor],
    scale: float,
    onednn: bool,
):
    """The forward and backward of ``items`` ((first row, end row) chunks of ``inputs`` and
    ``targets``): the first layer a product over the rows [d, e_i] without a bias
    (:meth:`DecoderStep.__call__`), ``biases`` those of layers 2-4. Products, activations
    and the output gradient are in ``weights``' type; the residual, the loss and the
    accumulated gradients in ``targets``' (float32, or float64 in the tests): in bfloat16
    each product sums in float32 and rounds its output, as ``torch.autocast`` would.
    Returns (weight gradients, bias gradients of layers 2-4, sum of squared residuals).

    Runs as TorchScript (:func:`_script`; see the module's docstring for why), with torch
    ops only; :func:`_chunks_fused` is the same with the fused kernels.
    """
    g_w = [torch.zeros(w.shape, dtype=targets.dtype, device=targets.device) for w in weights]
    g_b = [torch.zeros(b.shape, dtype=targets.dtype, device=targets.device) for b in biases]
    loss = torch.zeros((), dtype=torch.float64, device=targets.device)
    for item in items:
        start, stop = item
        a = _forward(inputs[start:stop], weights, biases, 4, onednn)
        residual = a[4].to(targets.dtype).sub_(targets[start:stop])
        loss += residual.square().sum(dtype=torch.float64)
        g = residual.mul_(scale).to(weights[0].dtype)  # d(mean squared error)/d(output)
        for k in range(3, -1, -1):
            _accumulate(g_w[k], g, a[k])
            if k > 0:
                g_b[k - 1] += g.sum(0)
                g = torch.ops.aten.threshold_backward(g @ weights[k], a[k], 0)
    return g_w, g_b, loss


def _chunks_fused(
    items: list[tuple[int, int]],
    inputs: torch.Tensor,
    targets: torch.Tensor,
    weights: list[torch.Tensor],
    biases: list[torch.Tensor],
    scale: float,
    onednn: bool,
):
    """:func:`_chunks` with the fused kernels of :mod:`pipeline.btf.fast.kernels`. In
    bfloat16 the first and last layers' weight gradients and all bias gradients sum in
    ``targets``' type with no rounding to bfloat16 in between (``_chunks`` rounds each
    chunk's product and column sum); layers 2-3's weight gradients are ``_accumulate``'s,
    as there. The first layer's weight gradient is returned as a transposed view. Runs as
    TorchScript."""
    g_w = [torch.zeros(w.shape, dtype=targets.dtype, device=targets.device) for w in weights]
    g_b = [torch.zeros(b.shape, dtype=targets.dtype, device=targets.device) for b in biases]
    # The first layer's weight gradient, transposed: (inputs, hidden), so that the kernel
    # adds each input column's contribution to one contiguous row of vectors.
    g_first = torch.zeros(
        (weights[0].shape[1], weights[0].shape[0]), dtype=targets.dtype, device=targets.device
    )
    loss = torch.zeros((), dtype=torch.float64, device=targets.device)
    for item in items:
        start, stop = item
        a = _forward(inputs[start:stop], weights, biases, 3, onednn)
        g = torch.ops.neural_btf.output_layer(
            a[3], weights[3], biases[2], targets[start:stop], scale, g_w[3], g_b[2], g_b[1], loss
        )
        # g: the gradient at layer 3's output (before its ReLU); on through layers 3 and 2.
        _accumulate(g_w[2], g, a[2])
        g_2 = g @ weights[2]
        torch.ops.neural_btf.relu_backward_(g_2, a[2], g_b[0], None, None)  # + layer 2's bias
        _accumulate(g_w[1], g_2, a[1])
        g_1 = g_2 @ weights[1]
        torch.ops.neural_btf.relu_backward_(g_1, a[1], None, a[0], g_first)  # + layer 1's W
    g_w[0] = g_first.t()
    return g_w, g_b, loss


def _forward(
    rows: torch.Tensor,
    weights: list[torch.Tensor],
    biases: list[torch.Tensor],
    layers: int,
    onednn: bool,
) -> list[torch.Tensor]:
    """[rows, then the outputs of the first ``layers`` layers] (see :func:`_chunks`).
    ``onednn``: each layer and its ReLU is one oneDNN call (a separate bfloat16 ReLU pass
    costs a large share of the product's time: docs/performance.md), addmm elsewhere."""
    a = [rows]
    for k in range(layers):
        bias: torch.Tensor | None = None
        if k > 0:
            bias = biases[k - 1]
        if onednn:
            out = torch.ops.mkldnn._linear_pointwise(
                a[k], weights[k], bias, "relu" if k < 3 else "none", [], ""
            )
        else:
            out = a[k] @ weights[k].t() if bias is None else torch.addmm(bias, a[k], weights[k].t())
            if k < 3:
                out = out.relu_()
        a.append(out)
    return a


def _accumulate(total: torch.Tensor, g: torch.Tensor, a: torch.Tensor) -> None:
    """total += g.t() @ a, the product in ``g``'s type (bfloat16 products into float32
    sums round the product first)."""
    if g.dtype == total.dtype:
        total.addmm_(g.t(), a)
    else:
        total += g.t() @ a


def _sum(parts: list[tuple]) -> tuple[list[torch.Tensor], list[torch.Tensor], float]:
    """The workers' (weight gradients, bias gradients, loss) summed in a fixed order
    (deterministic for a number of workers)."""
    (g_w, g_b, loss), *rest = parts
    for weights, biases, part_loss in rest:
        for total, add in zip(g_w + g_b, weights + biases, strict=True):
            total += add
        loss += part_loss
    return g_w, g_b, loss
