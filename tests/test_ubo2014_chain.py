"""Method A's chain on UBO2014 files: the training batches and the evaluation read the same
value for the same (texel, light, view), whatever order the file stores its directions in.

Two files hold one analytic material (the built-in generator's, evaluated at each file's
directions) with their views and lights in two different orders. For both, every value a
training batch hands the decoder as a target is checked against the generator at the
direction the batch pairs it with, and the evaluation of one fixed decoder gives the RMSE
computed here from the generator's values directly."""

import numpy as np
import pytest
import torch
from helpers import compose_config

from benchmarks.ubo2014_chain import direction_pairs
from benchmarks.ubo2014_load import hemisphere_angles
from pipeline.btf import stages
from pipeline.btf.batches import HostBatches, Sampling
from pipeline.btf.evaluate import reconstruction_error
from pipeline.btf.model import Decoder
from pipeline.btf.stereographic import direction_features
from pipeline.btf.synthetic import SyntheticBTF
from pipeline.core.stage import Context
from pipeline.data.ubo2014_write import write_dfmf

N_VIEWS, N_LIGHTS, SIZE, CROP, OFFSET = 12, 20, 12, 6, (2, 3)  # 240 directions
MATERIAL = SyntheticBTF(size=SIZE, seed=0, material="plain_weave")


def _write(path, order_seed: int | None):
    views, lights = hemisphere_angles(N_VIEWS), hemisphere_angles(N_LIGHTS)
    if order_seed is not None:
        rng = np.random.default_rng(order_seed)
        views, lights = views[rng.permutation(N_VIEWS)], lights[rng.permutation(N_LIGHTS)]
    values = MATERIAL.evaluate(direction_pairs(views, lights))
    write_dfmf(path, views, lights, SIZE, SIZE, values=values, dtype="float32", sync=False)
    return path


def _truth(texels: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """The generator's value of crop texel ``texels[i]`` at ``directions[i]``."""
    rows, cols = np.divmod(texels, CROP)
    flat = (rows + OFFSET[0]) * SIZE + cols + OFFSET[1]
    return MATERIAL.evaluate_pairs(flat, directions)


def _chain(tmp_path, path):
    cfg = compose_config(
        "experiment=smoke",
        f"paths.runs={tmp_path / 'runs'}",
        "dataset=ubo2014",
        f"dataset.root={path}",
        "dataset.views=null",
        f"btf.crop.size={CROP}",
        f"btf.crop.offset=[{OFFSET[0]},{OFFSET[1]}]",
    )
    ctx = Context.from_config(cfg)
    cropped = stages.crop(ctx, stages.load(ctx))
    return cropped, stages.normalization(stages.preprocess(ctx, cropped))


@pytest.mark.parametrize("order_seed", [None, 7])
def test_training_targets_are_the_files_values_at_the_directions_they_are_paired_with(
    tmp_path, order_seed
):
    cropped, norm = _chain(tmp_path, _write(tmp_path / "m.btf", order_seed))
    abrdf, directions = stages.abrdf(cropped), cropped.array("directions")
    m, n, _ = abrdf.shape
    assert (m, n) == (CROP * CROP, N_VIEWS * N_LIGHTS)
    sampling = Sampling(m, 16, False, np.arange(n), n, target_from_source=False)
    batches = HostBatches(
        abrdf, abrdf, np.arange(m), norm, sampling, np.random.default_rng(0), torch.device("cpu")
    )
    batch = batches.batch(0)  # the first pass's order is the texels' own: batch row = texel
    picked = batch.directions.numpy()
    texels = np.repeat(np.arange(m), picked.shape[1])
    expected = _truth(texels, directions[picked.ravel()]) / norm.alpha
    np.testing.assert_allclose(batch.targets.numpy().reshape(-1, 3), expected, atol=2e-5)
    # The encoder sees the same ABRDF in the file's direction order.
    np.testing.assert_allclose(
        batch.inputs.permute(0, 2, 1).numpy(), norm.encoder_input(abrdf), atol=1e-5
    )


def test_the_evaluation_scores_the_files_values_at_their_directions_in_any_order(tmp_path):
    torch.manual_seed(0)
    decoder = Decoder(latent=8).eval()
    latents = np.random.default_rng(1).standard_normal((CROP * CROP, 8)).astype(np.float32)
    scores = []
    for order_seed in (None, 7):
        folder = tmp_path / str(order_seed)
        cropped, norm = _chain(folder, _write(tmp_path / f"m{order_seed}.btf", order_seed))
        abrdf, directions = stages.abrdf(cropped), cropped.array("directions")
        m, n, _ = abrdf.shape
        recon = reconstruction_error(
            decoder, latents, np.arange(m), abrdf, norm.alpha, direction_features(directions)
        )
        # Directly: the decoder at each (texel, direction), the generator's value there.
        texels, columns = np.repeat(np.arange(m), n), np.tile(np.arange(n), m)
        with torch.no_grad():
            predicted = decoder(
                torch.from_numpy(latents[texels]),
                torch.from_numpy(direction_features(directions)[columns].astype(np.float32)),
            ).numpy()
        truth = _truth(texels, directions[columns]) / norm.alpha
        direct = float(np.sqrt(np.mean(np.square(predicted - truth, dtype=np.float64))))
        assert recon.rmse == pytest.approx(direct, rel=1e-4)
        scores.append(recon.rmse)
        # A decoder that predicts 0: the per-direction error is the data's own RMS there.
        silent = Decoder(latent=8).eval()
        torch.nn.init.zeros_(silent.net[-1].weight)
        torch.nn.init.zeros_(silent.net[-1].bias)
        zero = reconstruction_error(
            silent, latents, np.arange(m), abrdf, norm.alpha, direction_features(directions)
        )
        rms = np.sqrt(np.mean(np.square(truth.reshape(m, n, 3)), axis=(0, 2)))
        np.testing.assert_allclose(zero.rmse_per_direction, rms, rtol=1e-4)
    assert scores[0] == pytest.approx(scores[1], rel=1e-4)
