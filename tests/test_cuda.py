"""Method A's training on a CUDA device against the same training on the CPU.

Skipped where torch sees no CUDA device (CI, the 2-core machines). Self-contained (no
conftest fixture, no MLflow or Hydra) so that it runs on a bare GPU machine with
``pytest --noconftest tests/test_cuda.py``.

What must hold on the GPU:
- :class:`DeviceBatches` gathers the same texels and normalized values as
  :class:`HostBatches` for a seed (all queries, so that no random query differs);
- the autograd step on the GPU computes the CPU's losses and gradients in float32 (TF32
  off: cuDNN's convolutions would otherwise round their inputs to 10 bits);
- ``train()`` on the GPU (batches resident on the device) learns like the CPU's run, in
  float32 to rounding and in bfloat16 to bfloat16's rounding, and returns float32 CPU
  modules.
"""

import numpy as np
import pytest
import torch

from pipeline.btf.backends import AutogradStep
from pipeline.btf.batches import DeviceBatches, HostBatches, Sampling
from pipeline.btf.model import Decoder, Encoder
from pipeline.btf.preprocess import fit_normalization
from pipeline.btf.stereographic import stereographic
from pipeline.btf.train import train
from pipeline.btf.train_settings import TrainSettings

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")

CPU, CUDA = torch.device("cpu"), torch.device("cuda")
M, N = 10, 27


@pytest.fixture(autouse=True)
def _no_tf32():
    """Full float32 products on the GPU while a test runs (the defaults restored after)."""
    before = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = before


def _tiny_btf(m=M, n=N, seed=0):
    """Random ABRDFs and direction features (as ``tests/test_btf_model._tiny_btf``, which
    imports modules a bare GPU machine lacks)."""
    rng = np.random.default_rng(seed)
    abrdf = rng.random((m, n, 3), dtype=np.float32)
    theta, phi = rng.uniform(0, 1.2, (n, 2)), rng.uniform(0, 6.28, (n, 2))
    features = np.concatenate(
        [stereographic(theta[:, 0], phi[:, 0]), stereographic(theta[:, 1], phi[:, 1])], 1
    ).astype(np.float32)
    return abrdf, features


def _sampling(batch_size=5):
    return Sampling(batch_size, N, True, np.arange(N), N, False)


def test_device_batches_are_the_host_batches():
    abrdf, _ = _tiny_btf()
    norm = fit_normalization(abrdf)
    host = HostBatches(abrdf, abrdf, np.arange(M), norm, _sampling(), np.random.default_rng(0), CPU)
    device = DeviceBatches(
        abrdf, abrdf, np.arange(M), norm, _sampling(), np.random.default_rng(0), CUDA, seed=0
    )
    for batches in (host, device):
        batches.new_pass()
    for first in (0, 5):
        a, b = host.batch(first), device.batch(first)
        assert b.inputs.is_cuda and b.targets.is_cuda
        torch.testing.assert_close(b.directions.cpu(), a.directions)
        torch.testing.assert_close(b.inputs.cpu(), a.inputs, rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(b.targets.cpu(), a.targets, rtol=1e-6, atol=1e-6)


def _one_step(device):
    abrdf, features = _tiny_btf()
    norm = fit_normalization(abrdf)
    torch.manual_seed(0)
    encoder, decoder = Encoder(N, (4, 8)).to(device), Decoder().to(device)
    batches = HostBatches(
        abrdf, abrdf, np.arange(M), norm, _sampling(), np.random.default_rng(0), device
    )
    batches.new_pass()
    step = AutogradStep(encoder, decoder, torch.from_numpy(features).to(device))
    loss = float(step(batches.batch(0)))
    params = list(encoder.parameters()) + list(decoder.parameters())
    return loss, [p.grad.cpu() for p in params]


def test_the_autograd_step_on_the_gpu_is_the_cpu_step():
    cpu_loss, cpu_grads = _one_step(CPU)
    gpu_loss, gpu_grads = _one_step(CUDA)
    assert gpu_loss == pytest.approx(cpu_loss, rel=1e-5)
    for a, b in zip(cpu_grads, gpu_grads, strict=True):
        torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-6)
    assert any(float(g.abs().max()) > 0 for g in gpu_grads)  # a real comparison


@pytest.mark.parametrize("precision, rtol", [("float32", 1e-4), ("bfloat16", 0.05)])
def test_training_on_the_gpu_learns_as_on_the_cpu(precision, rtol):
    abrdf, features = _tiny_btf()
    norm = fit_normalization(abrdf)

    def run(device):
        settings = TrainSettings(
            epochs=4,
            lr=0.05,
            queries_per_abrdf=-1,
            device=device,
            threads=1,
            backend="autograd",
            precision=precision,
        )
        return train(
            abrdf,
            abrdf,
            np.arange(M),
            norm,
            features,
            np.arange(N),
            settings,
            seed=0,
            encoder_channels=(4, 8),
        )

    cpu, gpu = run("cpu"), run("cuda")
    assert gpu.steps == cpu.steps == 8
    np.testing.assert_allclose(gpu.pass_losses, cpu.pass_losses, rtol=rtol)
    assert gpu.pass_losses[-1] < gpu.pass_losses[0]
    for module in (gpu.encoder, gpu.decoder):
        assert all(p.device == CPU and p.dtype == torch.float32 for p in module.parameters())
