"""The Neural BTF model, its sizes at the paper's scale, training determinism, evaluation."""

import re

import numpy as np
import pytest
import torch

from pipeline.btf.evaluate import reconstruction_error, storage_sizes
from pipeline.btf.model import Decoder, Encoder, MaxPool3, parameter_count
from pipeline.btf.preprocess import fit_normalization
from pipeline.btf.stereographic import stereographic
from pipeline.btf.train import TrainSettings, encode, train
from pipeline.core.errors import ConfigError

M_PAPER, N_PAPER = 10_000, 6561


def test_stereographic_maps_zenith_to_origin_and_horizon_to_unit_circle():
    phi = np.linspace(0, 2 * np.pi, 7)
    np.testing.assert_allclose(stereographic(np.zeros(7), phi), 0.0, atol=1e-12)
    horizon = stereographic(np.full(7, np.pi / 2), phi)
    np.testing.assert_allclose(np.linalg.norm(horizon, axis=1), 1.0)
    np.testing.assert_allclose(horizon, np.column_stack([np.cos(phi), np.sin(phi)]), atol=1e-12)


def test_stereographic_matches_the_papers_formula():
    theta = np.radians([15.0, 30.0, 45.0, 60.0, 75.0])
    paper_radius = np.sin(np.pi - theta) / (1 - np.cos(np.pi - theta))  # eq. 7
    np.testing.assert_allclose(
        np.linalg.norm(stereographic(theta, 0 * theta), axis=1), paper_radius
    )


def test_decoder_has_the_papers_parameter_count():
    decoder = Decoder()
    assert parameter_count(decoder) == 24_383
    assert parameter_count(decoder) * 4 == 97_532  # 95.2 KB of Table 1


def test_encoder_blocks_follow_the_abrdf_length():
    encoder = Encoder(N_PAPER, (4, 4, 4))
    assert encoder(torch.zeros(2, 3, N_PAPER)).shape == (2, 8)
    assert encoder.fc.in_features == 4 * 243  # 6561 / 3^3
    with pytest.raises(ConfigError, match="N=20"):
        Encoder(20, (4, 4, 4))


@pytest.mark.parametrize("length", [6561, 730, 731])
def test_encoder_block_equals_the_papers_order_with_torchs_max_pool(length):
    """conv -> MaxPool3 -> ReLU gives the values and gradients of conv -> ReLU ->
    nn.MaxPool1d(3, 3), also where the length leaves a remainder and ReLU ties at zero."""
    torch.manual_seed(0)
    conv = torch.nn.Conv1d(3, 16, kernel_size=3, padding=1)
    x = torch.randn(4, 3, length)
    weights = torch.randn(4, 16, length // 3)
    grads = []
    for block in (
        torch.nn.Sequential(conv, torch.nn.ReLU(), torch.nn.MaxPool1d(3, 3)),
        torch.nn.Sequential(conv, MaxPool3(), torch.nn.ReLU()),
    ):
        conv.zero_grad()
        inputs = x.clone().requires_grad_()
        out = block(inputs)
        (out * weights).sum().backward()
        grads.append((out.detach(), inputs.grad, conv.weight.grad.clone()))
    assert (grads[0][0] == 0).float().mean() > 0.1  # many ReLU zeros, so ties are exercised
    for reference, ours in zip(grads[0], grads[1], strict=True):
        torch.testing.assert_close(ours, reference, rtol=0, atol=0)


@pytest.mark.parametrize(
    ("length", "dtype", "tol"),
    [(6561, torch.float64, 1e-9), (730, torch.float64, 1e-9), (6561, torch.float32, 1e-4)],
)
def test_channels_last_forward_equals_the_plain_layers(length, dtype, tol):
    """Encoder.forward (channels-last 2-D) against Encoder.reference (the Sequential on 1-D
    tensors) on two copies of one encoder: latents, every parameter's gradient, the
    batch-norm running statistics over three training steps (the third at a scale where
    torch's channels-last batch-norm was 1.8 % off), then eval mode. Relative Frobenius
    norms of the differences: float64 to rounding; float32 measured 3e-6."""

    def close(a, b, msg=""):
        assert float((a - b).norm()) <= tol * float(b.norm()) + 1e-12, msg

    torch.manual_seed(0)
    ours = Encoder(length, (16, 32, 64)).to(dtype)
    plain = Encoder(length, (16, 32, 64)).to(dtype)
    plain.load_state_dict(ours.state_dict())
    for step in range(3):
        x = torch.randn(5, 3, length, dtype=dtype) * (1 + step)
        weights = torch.randn(5, 8, dtype=dtype)
        outs = []
        for encoder, forward in ((ours, ours.forward), (plain, plain.reference)):
            encoder.zero_grad()
            out = forward(x)
            (out * weights).sum().backward()
            outs.append(out.detach())
        close(outs[0], outs[1])
        for (name, a), (_, b) in zip(
            ours.named_parameters(), plain.named_parameters(), strict=True
        ):
            close(a.grad, b.grad, name)
    for (name, a), (_, b) in zip(
        ours.state_dict().items(), plain.state_dict().items(), strict=True
    ):
        close(a.double(), b.double(), name)
    assert int(ours.state_dict()["features.3.num_batches_tracked"]) == 3
    ours.eval()
    plain.eval()
    x = torch.randn(7, 3, length, dtype=dtype)
    with torch.no_grad():
        close(ours(x), plain.reference(x))


@pytest.mark.parametrize(
    ("k", "latents", "total", "ratio"),
    [
        (None, 320_000, 417_532, 1885.6),
        (500, 16_000, 153_532, 5128.1),
        (1000, 32_000, 169_532, 4644.1),
        (2000, 64_000, 201_532, 3906.7),
    ],
)
def test_sizes_at_paper_scale_are_exact(k, latents, total, ratio):
    """Table 1 at M = 10000, N = 6561, int32 list: built models, no training."""
    decoder = Decoder()
    Encoder(N_PAPER)  # the encoder builds at this size; it is not stored
    sizes = storage_sizes(
        decoder,
        n_latents=k or M_PAPER,
        n_texels=M_PAPER,
        n_directions=N_PAPER,
        clustered=k is not None,
    )
    assert sizes["bytes_decoder"] == 97_532
    assert sizes["bytes_latents"] == latents
    assert sizes["bytes_list"] == (40_000 if k else 0)
    assert sizes["bytes_total"] == total
    assert sizes["bytes_original"] == 787_320_000
    assert sizes["compression_ratio"] == pytest.approx(ratio, abs=0.06)


def test_uint16_list_halves_the_list_and_refuses_large_k():
    sizes = storage_sizes(Decoder(), 1000, M_PAPER, N_PAPER, True, list_dtype="uint16")
    assert sizes["bytes_list"] == 20_000
    with pytest.raises(ValueError, match="k=70000"):
        storage_sizes(Decoder(), 70_000, 100_000, N_PAPER, True, list_dtype="uint16")


def test_decode_grid_equals_the_plain_forward_pass():
    torch.manual_seed(0)
    decoder = Decoder().eval()
    latents, dirs = torch.randn(4, 8), torch.randn(6, 4)
    pairs = decoder(latents.repeat_interleave(6, 0), dirs.repeat(4, 1)).reshape(4, 6, 3)
    torch.testing.assert_close(decoder.decode_grid(latents, dirs), pairs)


def _tiny_btf(m=30, n=27, seed=0):
    rng = np.random.default_rng(seed)
    abrdf = rng.random((m, n, 3), dtype=np.float32)
    theta = rng.uniform(0, 1.2, (n, 2))
    phi = rng.uniform(0, 6.28, (n, 2))
    features = np.concatenate(
        [stereographic(theta[:, 0], phi[:, 0]), stereographic(theta[:, 1], phi[:, 1])], 1
    ).astype(np.float32)
    return abrdf, features


def _train(seed, abrdf, features, sources=None, source_of_texel=None):
    settings = TrainSettings(epochs=1, lr=0.05, queries_per_abrdf=8, device="cpu")
    norm = fit_normalization(abrdf)
    sources = abrdf if sources is None else sources
    source_of_texel = np.arange(len(abrdf)) if source_of_texel is None else source_of_texel
    return train(
        abrdf,
        sources,
        source_of_texel,
        norm,
        features,
        np.arange(abrdf.shape[1]),
        settings,
        seed=seed,
        encoder_channels=(2, 2, 2),
    ), norm


def test_training_is_deterministic_for_a_seed():
    abrdf, features = _tiny_btf()
    a, _ = _train(3, abrdf, features)
    b, _ = _train(3, abrdf, features)
    c, _ = _train(4, abrdf, features)
    for pa, pb in zip(
        a.decoder.state_dict().values(), b.decoder.state_dict().values(), strict=True
    ):
        torch.testing.assert_close(pa, pb, rtol=0, atol=0)
    assert a.pass_losses == b.pass_losses and a.pass_losses != c.pass_losses


class CountingDecoder(Decoder):
    def __init__(self):
        super().__init__()
        self.decoded_latents = 0

    def decode_grid(self, latents, directions):
        self.decoded_latents += latents.shape[0]
        return super().decode_grid(latents, directions)


def test_clustered_path_decodes_k_by_n_not_m_by_n():
    abrdf, features = _tiny_btf(m=40)
    labels = np.arange(40) % 3
    decoder = CountingDecoder()
    latents = np.random.default_rng(0).standard_normal((3, 8)).astype(np.float32)
    recon = reconstruction_error(decoder, latents, labels, abrdf, 1.0, features)
    assert decoder.decoded_latents == 3
    # Cross-check against a direct computation over all texels.
    with torch.no_grad():
        full = decoder.decode_grid(torch.from_numpy(latents), torch.from_numpy(features))
    direct = np.sqrt(np.mean((full.numpy()[labels] - abrdf) ** 2))
    assert recon.rmse == pytest.approx(direct, rel=1e-5)
    assert recon.rmse_scaled <= recon.rmse_unscaled


def test_neural_btf_reconstruction_matches_a_direct_computation():
    abrdf, features = _tiny_btf(m=12)
    result, norm = _train(0, abrdf, features)
    latents = encode(result.encoder, abrdf, norm)
    recon = reconstruction_error(
        result.decoder, latents, np.arange(12), abrdf, norm.alpha, features
    )
    with torch.no_grad():
        pred = (
            result.decoder.eval()
            .decode_grid(torch.from_numpy(latents), torch.from_numpy(features))
            .numpy()
        )
    target = abrdf / norm.alpha
    assert recon.rmse == pytest.approx(np.sqrt(np.mean((pred - target) ** 2)), rel=1e-5)
    per_dir = np.sqrt(np.mean((pred - target) ** 2, axis=(0, 2)))
    np.testing.assert_allclose(recon.rmse_per_direction, per_dir, rtol=1e-5)


def test_linear_baseline_recovers_low_rank_data_and_counts_its_bytes():
    from pipeline.btf.linear import components_for_budget, fit_linear, linear_error, pca_bytes

    rng = np.random.default_rng(0)
    low_rank = rng.random((40, 2)) @ rng.random((2, 27 * 3)) + 0.1
    targets = low_rank.reshape(40, 27, 3).astype(np.float32)
    model = fit_linear(targets, 2, "float32")
    rmse, per_direction = linear_error(model, targets)
    assert rmse < 1e-5 and per_direction.shape == (27,)
    # One component: the best rank-1 fit of the centred data (Eckart-Young), whose error is
    # the second singular value, from numpy's SVD.
    one = fit_linear(targets, 1, "float32")
    assert (one.mean.shape, one.basis.shape, one.coefficients.shape) == ((81,), (1, 81), (40, 1))
    flat = targets.reshape(40, -1).astype(np.float64)
    singular = np.linalg.svd(flat - flat.mean(axis=0), compute_uv=False)
    assert singular[1] > 1e-2 * singular[0]  # the data really are rank 2
    assert linear_error(one, targets)[0] == pytest.approx(
        np.sqrt(np.sum(singular[1:] ** 2) / targets.size), rel=1e-4
    )
    stored = model.mean.nbytes + model.basis.nbytes + model.coefficients.nbytes
    assert stored == pca_bytes(2, 40, 27, "float32")
    # At the paper's size the bytes of clustered k = 1000 (169,532 B) hold two float16
    # components but not one float32 component.
    assert components_for_budget(169_532, 10_000, 6561, "float16") == 2
    assert pca_bytes(2, 10_000, 6561, "float16") <= 169_532 < pca_bytes(3, 10_000, 6561, "float16")
    assert components_for_budget(169_532, 10_000, 6561, "float32") == 0
    assert pca_bytes(1, 10_000, 6561, "float32") > 169_532


def test_texel_scale_is_in_every_figure_of_the_run():
    abrdf, features = _tiny_btf(m=40)
    labels = np.arange(40) % 3
    latents = np.random.default_rng(0).standard_normal((3, 8)).astype(np.float32)
    recon = reconstruction_error(
        Decoder(), latents, labels, abrdf, 1.0, features, texel_scale="lstsq"
    )
    assert recon.rmse == recon.rmse_scaled < recon.rmse_unscaled
    assert recon.texel_scale.shape == (40,)
    # The per-direction errors are those of the scaled reconstruction too.
    assert np.sqrt(np.mean(recon.rmse_per_direction**2)) == pytest.approx(recon.rmse)


def test_a_shorter_run_is_the_start_of_a_longer_one_with_its_curve():
    """The lr schedule does not depend on the run's length, so the RMSE-versus-time curve
    of one long run also gives every shorter run (checked against a separate short run)."""
    abrdf, features = _tiny_btf(m=40)
    norm = fit_normalization(abrdf)

    def run(steps):
        settings = TrainSettings(
            epochs=10,
            lr=0.01,
            optimizer="adam",
            queries_per_abrdf=-1,
            max_steps=steps,
            lr_half_life=0.5,
            curve_every=3,
            curve_texels=10,
            threads=2,
            chunk=16,
            device="cpu",
        )
        return train(
            abrdf,
            abrdf,
            np.arange(40),
            norm,
            features,
            np.arange(27),
            settings,
            seed=0,
            encoder_channels=(4, 8),
        )

    short, long = run(6), run(12)
    assert [p["step"] for p in long.curve] == [0, 3, 6, 9, 12]
    assert [p["rmse"] for p in short.curve] == [p["rmse"] for p in long.curve[:3]]
    assert long.curve[-1]["rmse"] < long.curve[0]["rmse"]
    assert long.curve[-1]["queries"] == 12 * 5 * 27
    # The curve's RMSE is eq. 10 on its texels: recompute the last point of the short run.
    rows = np.sort(np.random.default_rng(7919).choice(40, 10, replace=False))
    latents = encode(short.encoder, abrdf[rows], norm)
    with torch.no_grad():
        pred = short.decoder.decode_grid(torch.from_numpy(latents), torch.from_numpy(features))
    expected = np.sqrt(np.mean((pred.numpy() - norm.target(abrdf[rows])) ** 2))
    assert short.curve[-1]["rmse"] == pytest.approx(expected, rel=1e-5)


def _train_40(settings):
    """Train on 40 texels of :func:`_tiny_btf` (seed 0) with a small encoder."""
    abrdf, features = _tiny_btf(m=40)
    return train(
        abrdf,
        abrdf,
        np.arange(40),
        fit_normalization(abrdf),
        features,
        np.arange(27),
        settings,
        seed=0,
        encoder_channels=(4, 8),
    )


def test_learning_rate_halves_every_half_life(monkeypatch):
    settings = TrainSettings(
        epochs=2,
        lr=0.01,
        optimizer="sgd",
        queries_per_abrdf=4,
        lr_half_life=1.0,
        device="cpu",
        threads=1,
    )
    seen = []
    original = torch.optim.SGD.step

    def spy(self, *args, **kwargs):
        seen.append(self.param_groups[0]["lr"])
        return original(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.SGD, "step", spy)
    _train_40(settings)
    steps_per_epoch = 40 // 5
    assert seen[0] == pytest.approx(0.01)
    assert seen[steps_per_epoch] == pytest.approx(0.005)
    assert seen[-1] == pytest.approx(0.01 * 0.5 ** ((2 * steps_per_epoch - 1) / steps_per_epoch))


@pytest.mark.parametrize("backend", ["autograd", "fused"])
def test_clip_grad_norm_bounds_each_steps_gradient_and_a_loose_one_changes_nothing(
    monkeypatch, backend
):
    """The optimizer sees gradients of norm <= train.clip_grad_norm, on either backend
    (both leave every gradient in .grad); a bound no gradient reaches trains bit for bit as
    no bound (the code before the setting)."""
    norms = []
    original = torch.optim.Adam.step

    def spy(self, *args, **kwargs):
        grads = [p.grad for group in self.param_groups for p in group["params"]]
        norms.append(float(torch.linalg.vector_norm(torch.stack([g.norm() for g in grads]))))
        return original(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.Adam, "step", spy)

    def run(clip):
        norms.clear()
        settings = TrainSettings(
            epochs=2,
            lr=0.01,
            optimizer="adam",
            queries_per_abrdf=4,
            device="cpu",
            threads=1,
            backend=backend,
            clip_grad_norm=clip,
        )
        result = _train_40(settings)
        return result.decoder.state_dict(), list(norms)

    unclipped, free = run(None)
    bound = float(np.median(free))
    _, clipped = run(bound)
    assert max(free) > bound and max(clipped) <= bound * (1 + 1e-5)
    loose, _ = run(10 * max(free))
    for a, b in zip(unclipped.values(), loose.values(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_bfloat16_training_follows_float32_training():
    """train.precision=bfloat16 rounds the decoder's products, not its updates: on the same
    steps its RMSE-versus-time curve stays within 2 % of float32's (measured: under 1 %),
    and descends."""
    abrdf, features = _tiny_btf(m=40)
    norm = fit_normalization(abrdf)

    def run(precision):
        settings = TrainSettings(
            epochs=10,
            lr=0.01,
            optimizer="adam",
            queries_per_abrdf=-1,
            max_steps=24,
            curve_every=6,
            curve_texels=10,
            threads=2,
            chunk=16,
            device="cpu",
            precision=precision,
        )
        return train(
            abrdf,
            abrdf,
            np.arange(40),
            norm,
            features,
            np.arange(27),
            settings,
            seed=0,
            encoder_channels=(4, 8),
        )

    single, half = run("float32"), run("bfloat16")
    assert half.curve[0]["rmse"] == single.curve[0]["rmse"]  # same start, before any step
    assert half.curve[-1]["rmse"] < 0.8 * half.curve[0]["rmse"]
    for a, b in zip(single.curve[1:], half.curve[1:], strict=True):
        assert b["rmse"] == pytest.approx(a["rmse"], rel=0.02)
    assert all(p.dtype == torch.float32 for p in half.decoder.parameters())


@pytest.mark.parametrize(
    "m, epoch_texels, expected_steps",
    [
        (30, None, 2 * 6),  # one pass over 30 texels: 6 batches of 5, two epochs
        (30, 60, 2 * 12),  # epochs of 60 texels: two passes over 30 per epoch
        (60, 60, 2 * 12),  # the same number of steps on a crop twice as large
    ],
)
def test_epoch_texels_fixes_the_steps_whatever_the_crop(m, epoch_texels, expected_steps):
    abrdf, features = _tiny_btf(m=m)
    settings = TrainSettings(
        epochs=2,
        epoch_texels=epoch_texels,
        lr=0.01,
        batch_size=5,
        queries_per_abrdf=4,
        device="cpu",
    )
    result = train(
        abrdf,
        abrdf,
        np.arange(m),
        fit_normalization(abrdf),
        features,
        np.arange(abrdf.shape[1]),
        settings,
        seed=0,
        encoder_channels=(2, 2, 2),
    )
    assert result.steps == expected_steps
    assert len(result.pass_losses) == expected_steps // (m // 5)  # one loss per pass


def test_epoch_texels_below_the_batch_is_refused():
    with pytest.raises(ConfigError, match="train.epoch_texels=3"):
        TrainSettings(epoch_texels=3, batch_size=5)


@pytest.mark.parametrize(
    "bad, named",
    [
        ({"lr": float("nan")}, "train.lr=nan"),
        ({"lr": 0.0}, "train.lr=0.0"),
        ({"queries_per_abrdf": 0}, "train.queries_per_abrdf=0"),
        ({"max_steps": 0}, "train.max_steps=0"),
        ({"momentum": 1.5}, "train.momentum=1.5"),
        ({"lr_half_life": float("nan")}, "train.lr_half_life=nan"),
        ({"momentum": 1.0}, "train.momentum=1.0 must be a finite number >= 0 and < 1"),
        ({"max_steps": -2}, "train.max_steps=-2 must be one of -1 or an integer >= 1"),
        ({"optimizer": "lbfgs"}, "train.optimizer='lbfgs' must be one of sgd, adam"),
    ],
)
def test_bad_training_settings_are_refused_naming_the_setting(bad, named):
    with pytest.raises(ConfigError, match=re.escape(named)):
        TrainSettings(**bad)


def test_every_training_setting_declares_its_allowed_values():
    """One mechanism for A, B and C: train.*'s allowed values are declared on its fields
    and read by the shared validator (pipeline.core.settings.check_settings); only the
    switches, whose type says it all, declare none."""
    from pipeline.core.settings import constraints, roles

    switches = {"train.keep_awake", "train.reuse_freed_memory"}
    assert set(constraints(TrainSettings, "train")) == set(roles(TrainSettings, "train")) - switches
    assert TrainSettings(max_steps=-1, queries_per_abrdf=-1, momentum=0.99).momentum == 0.99


def test_training_settings_are_checked_without_hydra():
    """Training runs where Hydra and OmegaConf are not installed (a GPU machine): building
    and checking TrainSettings imports neither."""
    from helpers import fresh_python

    result = fresh_python(
        "import json, sys\n"
        "from pipeline.btf.train_settings import TrainSettings\n"
        "from pipeline.core.errors import ConfigError\n"
        "TrainSettings(max_steps=3)\n"
        "try:\n    TrainSettings(max_steps=0)\nexcept ConfigError as error:\n    refused = str(error)\n"
        "print(json.dumps({'refused': refused, 'loaded': sorted("
        "m for m in ('omegaconf', 'hydra') if m in sys.modules)}))\n"
    )
    assert result == {
        "refused": "train.max_steps=0 must be one of -1 or an integer >= 1",
        "loaded": [],
    }
