"""The encoder's hand-written training step (pipeline/btf/fast/encoder_step.py) against the
plain layers (Encoder.reference), and the step profiler (benchmarks/profile_step.py)."""

import pytest
import torch

from benchmarks import profile_step
from pipeline.btf import model
from pipeline.btf.fast.encoder_step import encode_for_training
from pipeline.btf.model import Encoder

CHANNELS = (16, 32, 64)


def _pair(length, dtype, channels=CHANNELS, momentum=0.1):
    """Two copies of one encoder."""
    torch.manual_seed(0)
    ours = Encoder(length, channels).to(dtype)
    plain = Encoder(length, channels).to(dtype)
    plain.load_state_dict(ours.state_dict())
    for encoder in (ours, plain):
        for module in encoder.features[3::4]:
            module.momentum = momentum
    return ours, plain


def _step(encoder, forward, x, weights):
    """Latents, input gradient and parameter gradients of sum(latents * weights)."""
    encoder.zero_grad()
    inputs = x.clone().requires_grad_()
    out = forward(inputs)
    (out * weights).sum().backward()
    return [out.detach(), inputs.grad] + [p.grad.clone() for p in encoder.parameters()]


def _relative(a, b):
    return float((a - b).norm()) / max(float(b.norm()), 1e-300)


@pytest.mark.parametrize(
    ("length", "batch", "chunk_bytes", "momentum"),
    [
        (6561, 5, 1, None),  # one ABRDF per chunk; a cumulative running average
        (6561, 7, 200_000, 0.1),  # chunks of 1, 2 and 4 ABRDFs by block, a short last one
        (730, 6, 1 << 30, 0.1),  # one chunk; lengths that leave a remainder to the pools
        (731, 3, 30_000, 0.3),
    ],
)
def test_training_step_equals_the_plain_layers_in_float64(length, batch, chunk_bytes, momentum):
    """Latents, the ABRDFs' gradient, every parameter's gradient and the batch-norm running
    statistics over three steps, to float64 rounding. Catches a wrong batch-norm gradient or
    statistic, a chunk boundary off by one, the fc columns in the wrong order, a pool
    remainder mishandled, a biased running variance."""
    ours, plain = _pair(length, torch.float64, momentum=momentum)
    blocks = list(ours.features)

    def fast(x):
        return encode_for_training(blocks[0::4], blocks[3::4], ours.fc, x, chunk_bytes)

    for step in range(3):
        x = torch.randn(batch, length, 3, dtype=torch.float64).permute(0, 2, 1) * (1 + step)
        weights = torch.randn(batch, 8, dtype=torch.float64)
        got, want = _step(ours, fast, x, weights), _step(plain, plain.reference, x, weights)
        for name, a, b in zip(
            ["latents", "abrdf"] + [n for n, _ in ours.named_parameters()], got, want, strict=True
        ):
            assert _relative(a, b) < 1e-10, name
    for (name, a), (_, b) in zip(
        ours.state_dict().items(), plain.state_dict().items(), strict=True
    ):
        assert _relative(a.double(), b.double()) < 1e-10, name
    assert int(ours.state_dict()["features.3.num_batches_tracked"]) == 3


def test_ties_in_a_pooled_triple_send_the_gradient_to_the_first():
    """ABRDFs constant over runs of 9 directions, and kernels with only their centre tap,
    make whole triples of convolution outputs equal; the gradient must reach the ABRDFs as
    through the autograd layers (torch's max-pool: the first maximum of a triple takes it;
    tests/test_btf_model.py checks that order against the paper's), which only the ABRDFs'
    gradient tells apart. (The 1-D reference's convolution rounds a few of these triples
    apart, so it is not the yardstick here.)"""
    ours, _ = _pair(243, torch.float64, channels=(4, 4))
    with torch.no_grad():
        for conv in ours.features[0::4]:
            conv.weight[:, :, 0::2] = 0
    torch.manual_seed(1)
    x = torch.randn(4, 3, 27, dtype=torch.float64).repeat_interleave(9, dim=2)
    weights = torch.randn(4, 8, dtype=torch.float64)
    with torch.no_grad():
        conv = ours.features[0]
        y = torch.nn.functional.conv2d(
            x.unsqueeze(2).contiguous(memory_format=torch.channels_last),
            conv.weight.unsqueeze(2),
            conv.bias,
            padding=(0, 1),
        ).view(4, 4, 81, 3)
    assert float((y == y[..., :1]).float().mean()) > 0.9  # the first block's triples tie
    want = _step(ours, ours.forward_layers, x, weights)
    got = _step(ours, ours.forward, x, weights)
    for a, b in zip(got, want, strict=True):
        assert _relative(a, b) < 1e-10


def test_paper_batch_in_float32_is_as_close_as_the_layers():
    """At experiment=paper_cpu's size (32 ABRDFs x 6561 directions, default chunks), float32
    against float64: the hand-written step is no further off than the autograd layers were
    (both about 1e-6 relative; 1e-4 allowed)."""
    ours, plain = _pair(6561, torch.float32)
    exact = Encoder(6561, CHANNELS).double()
    exact.load_state_dict(plain.state_dict())
    torch.manual_seed(2)
    x = torch.randn(32, 6561, 3).permute(0, 2, 1)
    weights = torch.randn(32, 8)
    want = _step(exact, exact.reference, x.double(), weights.double())
    for encoder, forward in ((ours, ours.forward), (plain, plain.forward_layers)):
        got = _step(encoder, forward, x, weights)
        for a, b in zip(got[:1] + got[2:], want[:1] + want[2:], strict=True):
            assert _relative(a.double(), b) < 1e-4


def test_forward_takes_the_hand_written_step_only_when_training_with_gradients(monkeypatch):
    """Catches the fast path silently unused in training, or used where it must not be (eval
    mode: running statistics; no gradients: encoding the texels)."""
    calls = []

    def spy(*args, **kwargs):
        calls.append(1)
        return encode_for_training(*args, **kwargs)

    monkeypatch.setattr(model, "encode_for_training", spy)
    encoder = Encoder(81, (4, 4))
    x = torch.randn(3, 3, 81)
    encoder(x)
    assert len(calls) == 1
    with torch.no_grad():
        encoder(x)
    encoder.eval()
    encoder(x)
    assert len(calls) == 1
    encoder.train()
    torch.testing.assert_close(encoder(x), encoder.reference(x), rtol=1e-5, atol=1e-6)


def test_flop_counts_by_hand():
    """One block of 2 channels on N = 9 directions, batch 1: conv 9 x 2 x 3 x 3 = 162
    multiply-adds, fc 3 x 2 x 8 = 48; backward twice that without the block's input
    gradient (162). Decoder: 3 x 2 x its multiply-adds per query."""
    forward, backward = profile_step.encoder_flops(1, channels=(2,), n=9)
    assert forward == 2 * (162 + 48)
    assert backward == 2 * (2 * (162 + 48) - 162)
    assert profile_step.decoder_flops(2, 3) == 6 * 6 * (12 * 106 + 2 * 106 * 106 + 106 * 3)


def test_profile_times_every_part_of_a_step(monkeypatch):
    monkeypatch.setattr(profile_step, "matmul_peak", lambda: 1.0)
    recipe = profile_step.SETUPS["after"]() | {"batch_size": 4, "queries_per_abrdf": 8}
    row = profile_step.time_steps(recipe, threads=1, steps=1, warmup=0, texels=8)
    assert set(profile_step.PARTS) <= set(row)
    assert all(row[part] > 0 for part in profile_step.PARTS)
    assert row["peak_gflops"] == 1.0


def test_the_after_setup_reads_the_cpu_recipe():
    """``after`` is conf/train/cpu.yaml's recipe, so the profile follows the config."""
    recipe = profile_step.cpu_recipe()
    assert recipe["batch_size"] >= 2 and recipe["queries_per_abrdf"] >= 1
    assert profile_step.steps_of(recipe) > 0
    assert profile_step.SETUPS["after"]()["encoder"] == "training"
