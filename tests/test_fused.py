"""The hand-written decoder gradient (pipeline/btf/fast/fused.py) against autograd, with torch
ops only and with the fused C++ kernels (pipeline/btf/fast/kernels.py)."""

import pytest
import torch

from pipeline.btf.fast import kernels
from pipeline.btf.fast.fused import Batch, DecoderStep, split_rows
from pipeline.btf.model import Decoder

# Both ways of computing the step: torch ops only, and the fused kernels.
KERNELS = pytest.mark.parametrize("fused_kernels", [False, True], ids=["torch", "kernels"])


@pytest.fixture(autouse=True)
def _skip_without_kernels(request):
    callspec = getattr(request.node, "callspec", None)
    if callspec and callspec.params.get("fused_kernels") and not kernels.available():
        pytest.skip("the fused kernels did not build here (see test_kernels_build)")


def _autograd(decoder, batch, features):
    latents = batch.latents.detach().clone().requires_grad_()
    b, q = batch.directions.shape
    pred = decoder(latents.repeat_interleave(q, 0), features[batch.directions.reshape(-1)])
    loss = torch.nn.functional.mse_loss(pred, batch.targets.reshape(-1, 3))
    decoder.zero_grad()
    loss.backward()
    grads = [p.grad.clone() for p in decoder.parameters()]
    return loss.item(), grads, latents.grad


@KERNELS
@pytest.mark.parametrize("workers,chunk", [(1, 1000), (1, 7), (2, 5), (3, 64)])
def test_fused_gradient_equals_autograd(workers, chunk, fused_kernels):
    torch.manual_seed(0)
    decoder = Decoder().double()
    features = torch.rand(50, 4, dtype=torch.float64) * 2 - 1
    batch = Batch(
        latents=torch.randn(4, 8, dtype=torch.float64),
        directions=torch.randint(0, 50, (4, 33)),
        targets=torch.rand(4, 33, 3, dtype=torch.float64),
    )
    loss, expected, expected_latents = _autograd(decoder, batch, features)
    step = DecoderStep(decoder, features, workers=workers, chunk=chunk, fused_kernels=fused_kernels)
    grads = step(batch)
    step.close()
    assert grads.loss == pytest.approx(loss, rel=1e-12)
    decoder.zero_grad(set_to_none=True)
    step.assign(grads)
    for param, want in zip(decoder.parameters(), expected, strict=True):
        torch.testing.assert_close(param.grad, want, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(grads.latents, expected_latents, rtol=1e-10, atol=1e-12)


@KERNELS
def test_fused_step_is_deterministic_for_a_number_of_workers(fused_kernels):
    torch.manual_seed(1)
    decoder = Decoder()
    features = torch.rand(300, 4)
    batch = Batch(torch.randn(5, 8), torch.randint(0, 300, (5, 300)), torch.rand(5, 300, 3))
    step = DecoderStep(decoder, features, workers=2, chunk=64, fused_kernels=fused_kernels)
    first, second = step(batch), step(batch)
    step.close()
    for a, b in zip(first.weights + first.biases, second.weights + second.biases, strict=True):
        assert torch.equal(a, b)


def _relative_error(got, want):
    return float((got.double() - want.double()).norm() / want.double().norm())


@KERNELS
@pytest.mark.parametrize("workers,chunk", [(1, 1000), (2, 64), (3, 50)])
def test_bfloat16_gradient_is_autograds_to_bfloat16_rounding(workers, chunk, fused_kernels):
    """bfloat16 keeps 8 significant bits (relative rounding 0.4 %): each gradient must be
    autograd's (float64) to within a few of those, and the loss to float32's accuracy of
    the residual; a wrong transpose, bias or layer would be off by order one."""
    torch.manual_seed(0)
    decoder = Decoder()
    features = torch.rand(300, 4) * 2 - 1
    batch = Batch(torch.randn(4, 8), torch.randint(0, 300, (4, 257)), torch.rand(4, 257, 3))
    loss, expected, expected_latents = _autograd(
        decoder.double(),
        Batch(batch.latents.double(), batch.directions, batch.targets.double()),
        features.double(),
    )
    decoder.float()
    step = DecoderStep(
        decoder,
        features,
        workers=workers,
        chunk=chunk,
        precision="bfloat16",
        fused_kernels=fused_kernels,
    )
    grads = step(batch)
    step.close()
    assert grads.loss == pytest.approx(loss, rel=1e-3)
    decoder.zero_grad(set_to_none=True)
    step.assign(grads)
    errors = [
        _relative_error(p.grad, want)
        for p, want in zip(decoder.parameters(), expected, strict=True)
    ]
    errors.append(_relative_error(grads.latents, expected_latents))
    assert max(errors) < 0.03, errors
    assert all(p.grad.dtype == torch.float32 for p in decoder.parameters())


@KERNELS
def test_bfloat16_step_is_deterministic_for_a_number_of_workers(fused_kernels):
    torch.manual_seed(1)
    decoder = Decoder()
    features = torch.rand(300, 4)
    batch = Batch(torch.randn(5, 8), torch.randint(0, 300, (5, 301)), torch.rand(5, 301, 3))
    step = DecoderStep(
        decoder, features, workers=2, chunk=64, precision="bfloat16", fused_kernels=fused_kernels
    )
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


@KERNELS
def test_chunks_may_span_abrdfs(fused_kernels):
    """One chunk holding the rows of several ABRDFs (each with its own latent) gives
    autograd's gradient, as chunks within one ABRDF do."""
    torch.manual_seed(2)
    decoder = Decoder().double()
    features = torch.rand(40, 4, dtype=torch.float64) * 2 - 1
    batch = Batch(
        torch.randn(3, 8, dtype=torch.float64),
        torch.randint(0, 40, (3, 10)),
        torch.rand(3, 10, 3, dtype=torch.float64),
    )
    loss, expected, expected_latents = _autograd(decoder, batch, features)
    for chunk in (30, 25, 4):  # one chunk; chunks across ABRDF boundaries
        step = DecoderStep(decoder, features, chunk=chunk, fused_kernels=fused_kernels)
        grads = step(batch)
        assert grads.loss == pytest.approx(loss, rel=1e-12)
        for got, want in zip(
            grads.weights + grads.biases, expected[0::2] + expected[1::2], strict=True
        ):
            torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(grads.latents, expected_latents, rtol=1e-10, atol=1e-12)


@KERNELS
@pytest.mark.parametrize("hidden", [106, 16, 33])
@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
def test_float32_and_bfloat16_storage_against_float64_autograd(hidden, precision, fused_kernels):
    """float32 and bfloat16 storage (the kernels' vector code: a row of ``hidden`` is
    whole 16-lane vectors and a masked rest) against autograd in float64, for hidden
    widths that are, are not, and are just over a multiple of 16."""
    torch.manual_seed(3)
    decoder = Decoder(hidden=hidden)
    features = torch.rand(200, 4) * 2 - 1
    batch = Batch(torch.randn(3, 8), torch.randint(0, 200, (3, 150)), torch.rand(3, 150, 3))
    loss, expected, expected_latents = _autograd(
        decoder.double(),
        Batch(batch.latents.double(), batch.directions, batch.targets.double()),
        features.double(),
    )
    decoder.float()
    step = DecoderStep(
        decoder, features, workers=2, chunk=100, precision=precision, fused_kernels=fused_kernels
    )
    grads = step(batch)
    step.close()
    tolerance = 1e-5 if precision == "float32" else 0.03
    assert grads.loss == pytest.approx(loss, rel=tolerance)
    errors = [
        _relative_error(got, want)
        for got, want in zip(
            grads.weights + grads.biases + [grads.latents],
            expected[0::2] + expected[1::2] + [expected_latents],
            strict=True,
        )
    ]
    assert max(errors) < tolerance, errors


def test_unknown_precision_is_refused():
    with pytest.raises(ValueError, match="precision"):
        DecoderStep(Decoder(), torch.rand(10, 4), precision="float16")
