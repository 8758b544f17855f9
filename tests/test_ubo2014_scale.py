"""A UBO2014-shaped file through method A's chain: the structured file is what it says, the
README's command runs on it, and the cache holds the decoded crop once."""

from pathlib import Path

import numpy as np
import pytest
from helpers import pipeline_command

from benchmarks.ubo2014_chain import run_chain, write_structured
from pipeline.data.ubo2014 import load_ubo2014
from pipeline.data.ubo2014_header import read_dfmf

VIEWS, LIGHTS, TEXTURE, TILE, RANK = 6, 12, 40, 8, 5


@pytest.fixture(scope="module")
def structured(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("ubo") / "structured.btf"
    return write_structured(
        path, RANK, "float32", tile=TILE, n_views=VIEWS, n_lights=LIGHTS, size=TEXTURE
    )


def test_a_structured_file_repeats_its_patch_at_the_stated_rank(structured):
    dfmf = read_dfmf(structured)
    assert (dfmf.n_views, dfmf.n_lights, dfmf.height, dfmf.width) == (VIEWS, LIGHTS, 40, 40)
    images = load_ubo2014(structured).images  # (n, 40, 40, 3)
    # The patch repeats up to a per-texel gain: each texel's ABRDF is its twin's, scaled.
    a, b = images[:, :TILE, :TILE], images[:, TILE : 2 * TILE, -TILE:]
    ratio = (b * a).sum(axis=(0, 3)) / (a * a).sum(axis=(0, 3))
    np.testing.assert_allclose(b, a * ratio[None, :, :, None], rtol=1e-4, atol=1e-5)
    assert np.ptp(ratio) > 0.01  # the gain does not repeat with the patch
    assert images.min() > -0.05 and images.max() > 0.2  # a material's values, not noise
    for channel in range(3):
        singular = np.linalg.svd(images[..., channel].reshape(len(images), -1), compute_uv=False)
        assert singular[RANK] < 1e-5 * singular[0] and singular[RANK - 1] > 10 * singular[RANK]


@pytest.mark.slow
def test_the_chain_holds_no_copy_of_the_crop_and_pca_at_the_files_rank_is_exact(
    structured, tmp_path, mlflow_template
):
    """The main job's command (`python -m pipeline dataset=ubo2014 dataset.root=...
    btf.crop.size=...`, the default offset) with its PCA model, which the chain runs at the
    file's own rank (3 channels x RANK components). No data stage writes the
    decoded crop: load reads the header, crop records its texels and directions,
    preprocess its statistics; the ABRDFs are decoded from the file's factors where read."""
    size = 16
    mlflow_template(tmp_path / "runs")
    rows = run_chain(structured, tmp_path / "runs", size, models=("pca",), offset=None)
    written = {row["stage"]: row["cache_bytes"] for row in rows}
    decoded = size * size * VIEWS * LIGHTS * 3 * 4
    # The model's own stages (linear, export) hold the model, which is not counted here.
    assert written["load"] + written["crop"] + written["preprocess"] < 0.2 * decoded
    # Data of rank 3 x RANK: PCA with as many components reconstructs them up to rounding.
    assert rows[0]["rmse"] < 1e-4 * rows[0]["rmse_mean_abrdf"]


@pytest.mark.slow
def test_the_readmes_ubo2014_command_runs_its_three_models(structured, tmp_path, mlflow_template):
    """The README's UBO2014 line as written, on a small file, with a short training (the
    only override besides the file and the store): the main job's three arms finish."""
    import re

    from mlflow.tracking import MlflowClient

    from pipeline.core.store import tracking_uri

    root = Path(__file__).resolve().parents[1]
    line = next(
        line.strip()
        for line in (root / "README.md").read_text().splitlines()
        if line.strip().startswith("python -m pipeline dataset=ubo2014")
    )
    words = re.sub(r"dataset\.root=\S+", f"dataset.root={structured}", line).split()
    words = [w.replace("btf.crop.size=100", "btf.crop.size=16") for w in words[1:]]
    mlflow_template(tmp_path / "runs")
    short = ["train.epochs=1", "train.epoch_texels=64", f"paths.runs={tmp_path / 'runs'}"]
    assert words[:2] == ["-m", "pipeline"], words
    done = pipeline_command(*words[2:], *short, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    client = MlflowClient(tracking_uri(tmp_path / "runs"))
    experiment = client.get_experiment_by_name("btf")
    runs = client.search_runs([experiment.experiment_id], "attributes.status = 'FINISHED'")
    models = sorted(r.data.params["model.name"] for r in runs if "model.name" in r.data.params)
    assert models == ["clustered", "neural_btf", "pca"]
