"""The hand-written decoder gradient (pipeline/btf/fused.py) against autograd."""

import pytest
import torch

from pipeline.btf.fused import Batch, DecoderStep, split_rows
from pipeline.btf.model import Decoder


def _autograd(decoder, batch, features):
    latents = batch.latents.detach().clone().requires_grad_()
    b, q = batch.directions.shape
    pred = decoder(latents.repeat_interleave(q, 0), features[batch.directions.reshape(-1)])
    loss = torch.nn.functional.mse_loss(pred, batch.targets.reshape(-1, 3))
    decoder.zero_grad()
    loss.backward()
    grads = [p.grad.clone() for p in decoder.parameters()]
    return loss.item(), grads, latents.grad


@pytest.mark.parametrize("workers,chunk", [(1, 1000), (1, 7), (2, 5), (3, 64)])
def test_fused_gradient_equals_autograd(workers, chunk):
    torch.manual_seed(0)
    decoder = Decoder().double()
    features = torch.rand(50, 4, dtype=torch.float64) * 2 - 1
    batch = Batch(
        latents=torch.randn(4, 8, dtype=torch.float64),
        directions=torch.randint(0, 50, (4, 33)),
        targets=torch.rand(4, 33, 3, dtype=torch.float64),
    )
    loss, expected, expected_latents = _autograd(decoder, batch, features)
    step = DecoderStep(decoder, features, workers=workers, chunk=chunk)
    grads = step(batch)
    step.close()
    assert grads.loss == pytest.approx(loss, rel=1e-12)
    decoder.zero_grad(set_to_none=True)
    step.assign(grads)
    for param, want in zip(decoder.parameters(), expected, strict=True):
        torch.testing.assert_close(param.grad, want, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(grads.latents, expected_latents, rtol=1e-10, atol=1e-12)


def test_fused_step_is_deterministic_for_a_number_of_workers():
    torch.manual_seed(1)
    decoder = Decoder()
    features = torch.rand(300, 4)
    batch = Batch(torch.randn(5, 8), torch.randint(0, 300, (5, 300)), torch.rand(5, 300, 3))
    step = DecoderStep(decoder, features, workers=2, chunk=64)
    first, second = step(batch), step(batch)
    step.close()
    for a, b in zip(first.weights + first.biases, second.weights + second.biases, strict=True):
        assert torch.equal(a, b)


def _relative_error(got, want):
    return float((got.double() - want.double()).norm() / want.double().norm())


@pytest.mark.parametrize("workers,chunk", [(1, 1000), (2, 64), (3, 50)])
def test_bfloat16_gradient_is_autograds_to_bfloat16_rounding(workers, chunk):
    """bfloat16 keeps 8 significant bits (relative rounding 0.4 %): each gradient must be
    autograd's (float64) to within a few of those, and the loss to float32's accuracy of
    the residual; a wrong transpose, bias or layer would be off by order one."""
    torch.manual_seed(0)
    decoder = Decoder()
    features = torch.rand(300, 4) * 2 - 1
    batch = Batch(torch.randn(4, 8), torch.randint(0, 300, (4, 257)), torch.rand(4, 257, 3))
    loss, expected, expected_latents = _autograd(decoder.double(), Batch(
        batch.latents.double(), batch.directions, batch.targets.double()), features.double())
    decoder.float()
    step = DecoderStep(decoder, features, workers=workers, chunk=chunk, precision="bfloat16")
    grads = step(batch)
    step.close()
    assert grads.loss == pytest.approx(loss, rel=1e-3)
    decoder.zero_grad(set_to_none=True)
    step.assign(grads)
    errors = [_relative_error(p.grad, want) for p, want in zip(decoder.parameters(), expected,
                                                               strict=True)]
    errors.append(_relative_error(grads.latents, expected_latents))
    assert max(errors) < 0.03, errors
    assert all(p.grad.dtype == torch.float32 for p in decoder.parameters())


def test_bfloat16_step_is_deterministic_for_a_number_of_workers():
    torch.manual_seed(1)
    decoder = Decoder()
    features = torch.rand(300, 4)
    batch = Batch(torch.randn(5, 8), torch.randint(0, 300, (5, 301)), torch.rand(5, 301, 3))
    step = DecoderStep(decoder, features, workers=2, chunk=64, precision="bfloat16")
    first, second = step(batch), step(batch)
    step.close()
    for a, b in zip(first.weights + first.biases, second.weights + second.biases, strict=True):
        assert torch.equal(a, b)
    assert first.loss == second.loss


def test_rows_are_split_evenly_and_each_query_is_in_one_chunk():
    items = split_rows(rows=5 * 301, workers=2, chunk=64)
    assert [sum(stop - start for start, stop in work) for work in items] == [753, 752]
    rows = sorted(r for work in items for start, stop in work for r in range(start, stop))
    assert rows == list(range(5 * 301))
    assert max(stop - start for work in items for start, stop in work) == 64


def test_chunks_may_span_abrdfs():
    """One chunk holding the rows of several ABRDFs (each with its own latent) gives
    autograd's gradient, as chunks within one ABRDF do."""
    torch.manual_seed(2)
    decoder = Decoder().double()
    features = torch.rand(40, 4, dtype=torch.float64) * 2 - 1
    batch = Batch(torch.randn(3, 8, dtype=torch.float64), torch.randint(0, 40, (3, 10)),
                  torch.rand(3, 10, 3, dtype=torch.float64))
    loss, expected, expected_latents = _autograd(decoder, batch, features)
    for chunk in (30, 25, 4):  # one chunk; chunks across ABRDF boundaries
        step = DecoderStep(decoder, features, chunk=chunk)
        grads = step(batch)
        assert grads.loss == pytest.approx(loss, rel=1e-12)
        for got, want in zip(grads.weights + grads.biases, expected[0::2] + expected[1::2],
                             strict=True):
            torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(grads.latents, expected_latents, rtol=1e-10, atol=1e-12)


def test_unknown_precision_is_refused():
    with pytest.raises(ValueError, match="precision"):
        DecoderStep(Decoder(), torch.rand(10, 4), precision="float16")
