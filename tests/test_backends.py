"""train.backend: the fused step against the plain autograd one, and where batches come from.

The two backends compute the same gradients in float32, the sums in different orders
(the fused step's chunks and its first layer as one product over [direction, one-hot]
rows; autograd's separate ops), so they agree to float32 rounding, not bit for bit. The
tolerance, a relative 1e-5 (about 100 float32 epsilons), sits two orders above the
differences seen (under 1e-7 relative on the losses, 2e-8 on the parameters) and far
below what a real fault changes (a missing bias gradient, a wrong loss scale, another
batch: 1e-3 and more). Plain SGD only: Adam divides each gradient by its own size, so
that the rounding noise of a gradient that is zero in exact arithmetic (a convolution's
bias before batch-norm) becomes a step of the learning rate's size.
"""

import logging

import numpy as np
import pytest
import torch
from test_btf_model import _tiny_btf

from pipeline.btf import backends
from pipeline.btf.backends import AutogradStep, FusedStep, resolve_backend
from pipeline.btf.batches import DeviceBatches, HostBatches, Sampling
from pipeline.btf.model import Decoder, Encoder
from pipeline.btf.preprocess import fit_normalization
from pipeline.btf.train import train
from pipeline.btf.train_settings import TrainSettings
from pipeline.core.errors import ConfigError

RTOL, ATOL = 1e-5, 1e-7  # float32 rounding of differently ordered sums (module docstring)
CPU = torch.device("cpu")

# (queries per ABRDF, threads, chunk): random queries on one thread; all directions on
# two workers in chunks that span ABRDFs.
CASES = [(8, 1, None), (-1, 2, 16)]


def _steps(backend: str, queries: int, threads: int, chunk, steps: int = 4):
    """Per-step losses, the first step's gradients and the final parameters of ``steps``
    SGD steps of one backend from the seed-0 initial weights on the seed-0 batches."""
    abrdf, features = _tiny_btf(m=10)
    norm = fit_normalization(abrdf)
    torch.manual_seed(0)
    encoder, decoder = Encoder(27, (4, 8)), Decoder()
    model = torch.nn.ModuleList([encoder, decoder])
    optimizer = torch.optim.SGD(model.parameters(), lr=0.05)
    sampling = Sampling(5, 27 if queries < 0 else queries, queries < 0, np.arange(27), 27, False)
    batches = HostBatches(
        abrdf, abrdf, np.arange(10), norm, sampling, np.random.default_rng(0), CPU
    )
    features = torch.from_numpy(features)
    step = (
        FusedStep(encoder, decoder, features, workers=threads, chunk=chunk)
        if backend == "fused"
        else AutogradStep(encoder, decoder, features, workers=threads)
    )
    losses, first_grads = [], None
    threads_before = torch.get_num_threads()
    try:
        for index in range(steps):
            if index % 2 == 0:
                batches.new_pass()
            optimizer.zero_grad(set_to_none=True)
            losses.append(float(step(batches.batch(5 * (index % 2)))))
            if first_grads is None:
                first_grads = [p.grad.clone() for p in model.parameters()]
            optimizer.step()
    finally:
        step.close()
        torch.set_num_threads(threads_before)
    return losses, first_grads, [p.detach().clone() for p in model.parameters()]


@pytest.mark.parametrize("queries, threads, chunk", CASES)
def test_fused_and_autograd_take_the_same_steps(queries, threads, chunk):
    fused = _steps("fused", queries, threads, chunk)
    plain = _steps("autograd", queries, threads, chunk)
    np.testing.assert_allclose(fused[0], plain[0], rtol=RTOL)
    assert len(set(plain[0])) == len(plain[0])  # the steps differ: a real comparison
    for a, b in zip(fused[1], plain[1], strict=True):  # every parameter's gradient
        torch.testing.assert_close(a, b, rtol=RTOL, atol=ATOL)
    for a, b in zip(fused[2], plain[2], strict=True):
        torch.testing.assert_close(a, b, rtol=RTOL, atol=ATOL)


@pytest.mark.parametrize("queries, threads, chunk", CASES)
def test_training_with_either_backend_gives_the_same_model(queries, threads, chunk):
    abrdf, features = _tiny_btf(m=10)
    norm = fit_normalization(abrdf)

    def run(backend):
        settings = TrainSettings(
            epochs=3,
            lr=0.05,
            queries_per_abrdf=queries,
            device="cpu",
            threads=threads,
            chunk=chunk,
            backend=backend,
        )
        return train(
            abrdf,
            abrdf,
            np.arange(10),
            norm,
            features,
            np.arange(27),
            settings,
            seed=0,
            encoder_channels=(4, 8),
        )

    fused, plain = run("fused"), run("autograd")
    assert fused.steps == plain.steps == 6
    np.testing.assert_allclose(fused.pass_losses, plain.pass_losses, rtol=RTOL)
    for a, b in ((fused.encoder, plain.encoder), (fused.decoder, plain.decoder)):
        for (name, x), y in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
            torch.testing.assert_close(x, y, rtol=RTOL, atol=ATOL, msg=name)


def test_autograd_bfloat16_on_the_cpu_runs_the_decoder_under_autocast():
    """train.precision=bfloat16 with the autograd backend on the CPU: CPU autocast rounds
    the decoder's products (losses differ from float32's, by bfloat16's rounding only);
    weights stay float32."""
    abrdf, features = _tiny_btf(m=10)
    norm = fit_normalization(abrdf)

    def run(precision):
        settings = TrainSettings(
            epochs=3,
            lr=0.05,
            queries_per_abrdf=-1,
            device="cpu",
            threads=1,
            backend="autograd",
            precision=precision,
        )
        return train(
            abrdf,
            abrdf,
            np.arange(10),
            norm,
            features,
            np.arange(27),
            settings,
            seed=0,
            encoder_channels=(4, 8),
        )

    single, half = run("float32"), run("bfloat16")
    assert half.pass_losses != single.pass_losses
    np.testing.assert_allclose(half.pass_losses, single.pass_losses, rtol=0.02)
    assert all(p.dtype == torch.float32 for p in half.decoder.parameters())


def test_auto_is_fused_on_the_cpu_where_the_kernels_build_and_autograd_on_cuda(monkeypatch, caplog):
    monkeypatch.setattr(backends.kernels, "available", lambda: True)
    assert resolve_backend("auto", CPU) == "fused"
    assert resolve_backend("auto", torch.device("cuda")) == "autograd"
    assert resolve_backend("fused", torch.device("cuda")) == "fused"  # asked for: kept
    assert resolve_backend("autograd", CPU) == "autograd"
    monkeypatch.setattr(backends.kernels, "available", lambda: False)
    with caplog.at_level(logging.WARNING, logger="pipeline.btf.backends"):
        assert resolve_backend("auto", CPU) == "autograd"
    assert "did not build" in caplog.text and "train.backend=fused" in caplog.text


def test_an_unknown_backend_is_refused_naming_the_setting():
    with pytest.raises(ConfigError, match=r"train\.backend='gpu' must be one of auto, fused"):
        TrainSettings(backend="gpu")
    with pytest.raises(ConfigError, match=r"train\.backend='gpu'"):
        resolve_backend("gpu", CPU)


# All directions; every other one; the first 20 (in order, but not all of them).
@pytest.mark.parametrize("train_dirs", [np.arange(27), np.arange(0, 27, 2), np.arange(20)])
@pytest.mark.parametrize(
    "clustered, target_from_source", [(False, False), (True, False), (True, True)]
)
def test_batches_kept_on_the_device_equal_the_hosts(train_dirs, clustered, target_from_source):
    """DeviceBatches (the CUDA path, run here on the CPU) against HostBatches: the same
    texels, encoder inputs and targets for all directions; random queries drawn from the
    training directions, with their own targets."""
    abrdf, _ = _tiny_btf(m=12)
    norm = fit_normalization(abrdf)
    if clustered:
        sources, source_of_texel = abrdf[[0, 5, 7]] * 1.5, np.arange(12) % 3
    else:
        sources, source_of_texel = abrdf, np.arange(12)
    n = len(train_dirs)
    every = Sampling(4, n, True, train_dirs, 27, target_from_source)
    host = HostBatches(abrdf, sources, source_of_texel, norm, every, np.random.default_rng(3), CPU)
    device = DeviceBatches(
        abrdf, sources, source_of_texel, norm, every, np.random.default_rng(3), CPU, seed=3
    )
    for _ in range(2):
        host.new_pass()
        device.new_pass()
        for first in (0, 4, 8):
            a, b = host.batch(first), device.batch(first)
            torch.testing.assert_close(b.inputs, a.inputs, rtol=1e-6, atol=1e-6)
            assert b.inputs.shape == (4, 3, 27) and b.targets.shape == (4, n, 3)
            torch.testing.assert_close(b.directions, a.directions, rtol=0, atol=0)
            torch.testing.assert_close(b.targets, a.targets, rtol=0, atol=0)

    random = Sampling(4, 5, False, train_dirs, 27, target_from_source)
    device = DeviceBatches(
        abrdf, sources, source_of_texel, norm, random, np.random.default_rng(3), CPU, seed=3
    )
    device.new_pass()
    order = np.random.default_rng(3).permutation(12)
    values = norm.target(sources if target_from_source else abrdf)
    batch = device.batch(4)
    texels = np.sort(order[4:8])
    rows = source_of_texel[texels] if target_from_source else texels
    directions = batch.directions.numpy()
    assert directions.shape == (4, 5) and np.isin(directions, train_dirs).all()
    np.testing.assert_array_equal(batch.targets.numpy(), values[rows[:, None], directions])
