"""The training loops ``python -m benchmarks.train`` times at the paper's batch (5 ABRDFs x
all 6561 directions), in its own process or in a child's (:mod:`benchmarks.train_child`).
Each function builds a loop and returns a callable that runs ``steps`` steps and returns
their seconds."""

from __future__ import annotations

import time

import numpy as np
import torch

from pipeline.btf.model import Decoder, Encoder

N_PAPER = 6561


def paper_channels() -> tuple[int, ...]:
    """The encoder's channels as btf.network declares them by default (the paper's)."""
    from pipeline.btf.data_settings import NetworkSettings

    return tuple(NetworkSettings().encoder_channels)


def naive_training(steps: int, channels):
    """A plain autograd loop at the paper's batch: each step encodes 5 ABRDFs, repeats each
    latent for all N directions, concatenates the direction inputs and backpropagates.
    Returns a callable that runs ``steps`` steps and returns their seconds."""
    torch.manual_seed(0)
    encoder, decoder = Encoder(N_PAPER, channels), Decoder()
    # The blocks as a plain implementation would write them, conv -> ReLU -> torch's
    # MaxPool1d -> batch-norm on (batch, C, L) tensors (Encoder.reference), not the
    # pipeline's faster equivalents (model.MaxPool3 first, the channels-last forward).
    for block in range(0, len(encoder.features), 4):
        encoder.features[block + 1] = torch.nn.ReLU()
        encoder.features[block + 2] = torch.nn.MaxPool1d(kernel_size=3, stride=3)
    params = list(encoder.parameters()) + list(decoder.parameters())
    optimizer = torch.optim.SGD(params, lr=0.05)
    abrdfs = torch.randn(5, 3, N_PAPER)
    directions = torch.rand(N_PAPER, 4)
    targets = torch.rand(5 * N_PAPER, 3)
    index = torch.arange(N_PAPER).repeat(5)

    def run() -> float:
        start = time.perf_counter()
        for _ in range(steps):
            latents = encoder.reference(abrdfs)
            pred = decoder(latents.repeat_interleave(N_PAPER, 0), directions[index])
            loss = torch.nn.functional.mse_loss(pred, targets)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        return time.perf_counter() - start

    return run


def decoder_training(fused: bool, steps: int, threads: int, precision: str = "float32"):
    """The decoder alone at the paper's batch (5 fixed latents x all N directions): autograd
    on the concatenated (latent, direction) rows, or the pipeline's fused step
    (``pipeline.btf.fast.fused.DecoderStep``) with its default chunk, in ``precision``. Both
    compute the latents' gradient and take an SGD step on the decoder, so the two differ only
    in how the decoder's forward and backward are computed. Both run as training does by
    default, without machine tuning. Returns a callable that runs ``steps`` steps and
    returns their seconds."""
    from pipeline.btf.fast.fused import Batch, DecoderStep

    torch.manual_seed(0)
    decoder = Decoder()
    optimizer = torch.optim.SGD(decoder.parameters(), lr=1e-3)
    latents = torch.randn(5, 8, requires_grad=True)
    features = torch.rand(N_PAPER, 4)
    targets = torch.rand(5, N_PAPER, 3)
    directions = torch.arange(N_PAPER).repeat(5, 1)
    step = DecoderStep(decoder, features, workers=threads, precision=precision) if fused else None

    def one_step() -> None:
        optimizer.zero_grad(set_to_none=True)
        if fused:
            torch.set_num_threads(1)  # as in training: one op per thread, chunks side by side
            step.assign(step(Batch(latents.detach(), directions, targets)))
            torch.set_num_threads(threads)
        else:
            pred = decoder(latents.repeat_interleave(N_PAPER, 0), features[directions.reshape(-1)])
            torch.nn.functional.mse_loss(pred, targets.reshape(-1, 3)).backward()
        optimizer.step()

    def run() -> float:
        one_step()  # untimed warm-up
        start = time.perf_counter()
        for _ in range(steps):
            one_step()
        return time.perf_counter() - start

    return run


def pipeline_training(
    batch: int,
    queries: int,
    steps: int,
    channels,
    threads: int,
    precision: str = "float32",
    optimizer: str = "sgd",
    lr: float = 0.05,
    tuning: dict | None = None,
    backend: str = "fused",
    device: str = "cpu",
):
    """The project's training loop (``pipeline.btf.train.train``) on random ABRDFs: data
    handling, normalization, encoder, the ``backend``'s step (``train.backend``; by
    default the fused decoder step) and optimizer (by default the paper's plain SGD, as in
    the naive loop), as in a real run on ``device``, with the opt-in machine tuning
    ``tuning`` asks for (``TrainSettings`` fields; ``omp_spin_count`` takes effect only
    where it was set before torch loaded: :mod:`benchmarks.train_child`).
    Returns a callable that runs ``steps`` steps and returns their training seconds."""
    from pipeline.btf.preprocess import fit_normalization
    from pipeline.btf.train import train
    from pipeline.btf.train_settings import TrainSettings

    rng = np.random.default_rng(0)
    m = max(2 * batch, 64)
    abrdf = rng.random((m, N_PAPER, 3), dtype=np.float32)
    norm = fit_normalization(abrdf)
    features = rng.random((N_PAPER, 4), dtype=np.float32) * 2 - 1
    settings = TrainSettings(
        epochs=10**6,
        batch_size=batch,
        queries_per_abrdf=queries,
        max_steps=steps,
        optimizer=optimizer,
        lr=lr,
        threads=threads,
        device=device,
        precision=precision,
        backend=backend,
        **(tuning or {}),
    )

    def run() -> float:
        return train(
            abrdf,
            abrdf,
            np.arange(m),
            norm,
            features,
            np.arange(N_PAPER),
            settings,
            seed=0,
            encoder_channels=channels,
        ).seconds

    return run
