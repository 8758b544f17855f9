"""The compressed BTF file (pipeline.btf.compressed): round trip, queries against the
evaluation's decoding, bytes against Table 1, atomic writes, damaged files, MLflow, equal
runs logging equal bytes. The PCA's file: tests/test_compressed_pca.py."""

from __future__ import annotations

import errno
import json
import os
import re
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.btf import compressed, export, stages
from pipeline.btf.compressed import (
    FILE_NAME,
    header_bytes,
    load_compressed,
    payload_bytes,
    write_compressed,
)
from pipeline.btf.evaluate import decode_all, storage_sizes
from pipeline.btf.model import Decoder
from pipeline.btf.stereographic import direction_features
from pipeline.core.cache import Entry
from pipeline.core.errors import DataError

ROWS, COLS = 4, 6  # M = 24 texels
K = 5
ALPHA = 3.75


def _directions(n: int, seed: int = 0) -> np.ndarray:
    """n direction pairs (theta_l, phi_l, theta_v, phi_v) on the upper hemisphere."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0, np.radians(80), (n, 2))
    phi = rng.uniform(0, 2 * np.pi, (n, 2))
    return np.stack([theta[:, 0], phi[:, 0], theta[:, 1], phi[:, 1]], axis=1)


def _model(case: str, seed: int = 0) -> dict:
    """A hand-built model (random weights) and what write_compressed needs besides."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    m = ROWS * COLS
    decoder = Decoder(hidden=16, layers=2).eval()
    model = {
        "decoder": decoder,
        "alpha": ALPHA,
        "crop_size": (ROWS, COLS),
        "crop_offset": (2, 3),
        "dataset": "synthetic",
    }
    if case == "neural_btf":
        model.update(method="neural_btf", latents=rng.normal(size=(m, 8)).astype(np.float32))
    else:
        model.update(
            method="clustered",
            k=K,
            latents=rng.normal(size=(K, 8)).astype(np.float32),
            latent_of_texel=rng.permutation(np.arange(m) % K).astype(np.int32),
        )
    if case == "clustered_scaled":
        model.update(
            texel_scale=rng.uniform(0.5, 1.5, m).astype(np.float32), texel_scale_mode="lstsq"
        )
    return model


def _expected(model: dict, directions: np.ndarray, decoder: Decoder | None = None) -> np.ndarray:
    """RGB as the evaluate stage reconstructs it: decode_all, the list, the scale, x alpha."""
    pred = decode_all(decoder or model["decoder"], model["latents"], direction_features(directions))
    if "latent_of_texel" in model:
        pred = pred[model["latent_of_texel"]]
    if "texel_scale" in model:
        pred = pred * model["texel_scale"][:, None, None]
    return pred * np.float32(model["alpha"])


CASES = ["neural_btf", "clustered", "clustered_scaled"]


@pytest.mark.parametrize("case", CASES)
def test_round_trip_keeps_every_field(tmp_path, case):
    model = _model(case)
    path = write_compressed(tmp_path / FILE_NAME, **model)
    btf = load_compressed(path)
    assert btf.path == path
    for name, value in model["decoder"].state_dict().items():
        assert torch.equal(btf.decoder.state_dict()[name], value), name
    np.testing.assert_array_equal(btf.latents, model["latents"])
    assert btf.latents.dtype == np.float32
    if case == "neural_btf":
        assert btf.latent_of_texel is None and btf.k is None
    else:
        np.testing.assert_array_equal(btf.latent_of_texel, model["latent_of_texel"])
        assert btf.latent_of_texel.dtype == np.int32 and btf.k == K
    if case == "clustered_scaled":
        np.testing.assert_array_equal(btf.texel_scale, model["texel_scale"])
        assert btf.metadata["texel_scale"] == "lstsq"
    else:
        assert btf.texel_scale is None and btf.metadata["texel_scale"] == "none"
    assert btf.alpha == ALPHA and btf.crop_size == (ROWS, COLS) and btf.crop_offset == (2, 3)
    assert btf.method == model["method"] and "mlflow_run_id" not in btf.metadata
    meta = btf.metadata
    assert meta["format"] == "pipeline.btf.compressed" and meta["format_version"] == "1"
    assert meta["dataset"] == "synthetic" and meta["direction_encoding"] == "stereographic"
    assert (meta["decoder_latent"], meta["decoder_hidden"], meta["decoder_layers"]) == (
        "8",
        "16",
        "2",
    )
    assert (meta["weight_dtype"], meta["list_dtype"], meta["extra_dtype"]) == (
        "float32",
        "int32",
        "float32",
    )
    assert json.loads(meta["crop_size"]) == [ROWS, COLS]


def test_stored_dtypes_follow_the_sizes_settings(tmp_path):
    model = _model("clustered_scaled")
    path = write_compressed(
        tmp_path / FILE_NAME,
        **model,
        weight_dtype="float16",
        list_dtype="uint16",
        extra_dtype="float16",
    )
    btf = load_compressed(path)
    assert btf.latents.dtype == np.float16 and btf.texel_scale.dtype == np.float16
    assert btf.latent_of_texel.dtype == np.uint16
    np.testing.assert_array_equal(btf.latent_of_texel, model["latent_of_texel"])


@pytest.mark.parametrize("case", CASES)
def test_query_reproduces_the_evaluated_reconstruction(tmp_path, case):
    model = _model(case)
    btf = load_compressed(write_compressed(tmp_path / FILE_NAME, **model))
    directions = _directions(30)
    expected = _expected(model, directions)
    scale = float(np.abs(expected).max())
    np.testing.assert_allclose(btf.reconstruct(directions), expected, rtol=1e-6, atol=1e-6 * scale)
    texels = np.array([23, 0, 7, 7])
    got = btf.query(texels, directions)
    assert got.shape == (4, 30, 3) and got.dtype == np.float32
    np.testing.assert_allclose(got, expected[texels], rtol=1e-6, atol=1e-6 * scale)
    # Paired queries: texel i at direction i.
    pairs = btf.query_pairs(texels, directions[:4])
    np.testing.assert_allclose(pairs, expected[texels, np.arange(4)], rtol=1e-5, atol=1e-6 * scale)


def test_float16_weights_differ_by_their_rounding_only(tmp_path):
    model = _model("clustered_scaled")
    btf = load_compressed(
        write_compressed(
            tmp_path / FILE_NAME, **model, weight_dtype="float16", extra_dtype="float16"
        )
    )
    directions = _directions(20)
    # Exactly what the rounded model computes ...
    rounded = Decoder(hidden=16, layers=2).eval()
    rounded.load_state_dict(
        {name: value.half().float() for name, value in model["decoder"].state_dict().items()}
    )
    rounded_model = {
        **model,
        "latents": model["latents"].astype(np.float16).astype(np.float32),
        "texel_scale": model["texel_scale"].astype(np.float16).astype(np.float32),
    }
    expected = _expected(rounded_model, directions, rounded)
    scale = float(np.abs(expected).max())
    np.testing.assert_allclose(btf.reconstruct(directions), expected, rtol=1e-6, atol=1e-6 * scale)
    # ... and close to the float32 model: float16 keeps 11 significant bits.
    full = _expected(model, directions)
    assert np.abs(btf.reconstruct(directions) - full).max() < 1e-2 * scale


def test_the_plain_python_recipe_of_the_docstring_gives_the_same_values(tmp_path):
    """The module docstring's numpy-only ``btf_rgb`` and ``pca_rgb`` against query_pairs."""
    from test_compressed_pca import _measured
    from test_compressed_pca import _model as _pca_model

    recipe = compressed.__doc__.split("numpy and safetensors only", 1)[1].split("::\n", 1)[1]
    namespace: dict = {}
    exec(textwrap.dedent(recipe), namespace)
    for case in CASES:
        model = _model(case, seed=1)
        path = write_compressed(tmp_path / f"{case}.safetensors", **model)
        texels, directions = np.arange(ROWS * COLS), _directions(ROWS * COLS, seed=2)
        expected = load_compressed(path).query_pairs(texels, directions)
        np.testing.assert_allclose(
            namespace["btf_rgb"](str(path), texels, directions), expected, rtol=1e-5, atol=1e-6
        )
    for dtype in ("float32", "float16"):
        path = compressed.write_compressed_pca(
            tmp_path / f"pca_{dtype}.safetensors", **_pca_model(dtype, seed=1)
        )
        pca = load_compressed(path)
        texels = np.repeat(np.arange(pca.n_texels), 5)
        pairs = np.random.default_rng(3).integers(0, len(_measured()), len(texels))
        expected = pca.query_pairs(texels, _measured()[pairs])
        np.testing.assert_allclose(
            namespace["pca_rgb"](str(path), texels, pairs), expected, rtol=1e-5, atol=1e-6
        )


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize(
    "dtypes", [("float32", "int32", "float32"), ("float16", "uint16", "float16")]
)
def test_payload_is_table1s_bytes_total(tmp_path, case, dtypes):
    weight_dtype, list_dtype, extra_dtype = dtypes
    model = _model(case)
    path = write_compressed(
        tmp_path / FILE_NAME,
        **model,
        weight_dtype=weight_dtype,
        list_dtype=list_dtype,
        extra_dtype=extra_dtype,
    )
    sizes = storage_sizes(
        model["decoder"],
        n_latents=len(model["latents"]),
        n_texels=ROWS * COLS,
        n_directions=81,
        clustered=case != "neural_btf",
        weight_dtype=weight_dtype,
        list_dtype=list_dtype,
        extra_dtype=extra_dtype if case == "clustered_scaled" else None,
    )
    assert payload_bytes(path) == sizes["bytes_total"]
    assert payload_bytes(path) + header_bytes(path) == path.stat().st_size
    assert header_bytes(path) % 8 == 0  # safetensors pads its header to 8 bytes


def test_a_failed_write_leaves_no_file(tmp_path, monkeypatch):
    model = _model("clustered")
    target = tmp_path / FILE_NAME

    def fail(fd):
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", fail)
    with pytest.raises(OSError, match="disk full"):
        write_compressed(target, **model)
    assert list(tmp_path.iterdir()) == []
    # A file already there stays as it was.
    monkeypatch.undo()
    write_compressed(target, **model)
    before = target.read_bytes()
    monkeypatch.setattr(os, "fsync", fail)
    with pytest.raises(OSError):
        write_compressed(target, **_model("neural_btf"))
    assert list(tmp_path.iterdir()) == [target] and target.read_bytes() == before


@pytest.mark.parametrize("case", CASES)
def test_the_same_model_gives_the_same_bytes(tmp_path, case):
    """safetensors' own save orders the metadata by a hash map seeded anew on each call."""
    first = write_compressed(tmp_path / "a.safetensors", **_model(case))
    second = write_compressed(tmp_path / "b.safetensors", **_model(case))
    assert first.read_bytes() == second.read_bytes()
    _, header = compressed.read_header(first)
    assert list(header)[0] == "__metadata__"
    assert list(header["__metadata__"]) == sorted(header["__metadata__"])


def test_a_full_disk_is_a_data_error_naming_the_file(tmp_path, monkeypatch):
    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    target = tmp_path / FILE_NAME
    with pytest.raises(
        DataError,
        match=rf"no space left for {re.escape(str(target))}: it "
        rf"needs \d+ bytes, .* free in {re.escape(str(tmp_path))}",
    ):
        write_compressed(target, **_model("clustered"))
    assert list(tmp_path.iterdir()) == []


def test_a_missing_file_is_a_data_error_naming_it(tmp_path):
    path = tmp_path / "nowhere.safetensors"
    with pytest.raises(DataError, match=re.escape(str(path))):
        load_compressed(path)


@pytest.mark.parametrize("keep", [0, 5, 100, -1])
def test_a_truncated_file_is_a_data_error_naming_it(tmp_path, keep):
    path = write_compressed(tmp_path / FILE_NAME, **_model("clustered"))
    data = path.read_bytes()
    path.write_bytes(data[:keep] if keep >= 0 else data[:-1])
    for read in (load_compressed, payload_bytes, header_bytes):
        with pytest.raises(DataError, match=re.escape(str(path))):
            read(path)


def test_a_damaged_header_is_a_data_error_naming_it(tmp_path):
    path = write_compressed(tmp_path / FILE_NAME, **_model("clustered"))
    data = bytearray(path.read_bytes())
    data[8:12] = b"\xff\xfe{["
    path.write_bytes(bytes(data))
    with pytest.raises(DataError, match=re.escape(str(path))):
        load_compressed(path)


def test_another_format_version_is_a_data_error_naming_it(tmp_path):
    from safetensors.numpy import save_file

    model = _model("neural_btf")
    path = write_compressed(tmp_path / FILE_NAME, **model)
    btf = load_compressed(path)
    tensors = {"latents": btf.latents}
    save_file(tensors, str(path), metadata={**btf.metadata, "format_version": "2"})
    with pytest.raises(DataError, match=rf"{re.escape(str(path))}.*version '2'"):
        load_compressed(path)
    save_file(tensors, str(path), metadata={"format": "something else"})
    with pytest.raises(DataError, match="not a compressed BTF"):
        load_compressed(path)
    save_file(tensors, str(path), metadata={**btf.metadata})  # no decoder weights
    with pytest.raises(DataError, match=rf"{re.escape(str(path))}.*decoder\.0\.weight"):
        load_compressed(path)


def test_inconsistent_inputs_are_refused_before_writing(tmp_path):
    model = _model("clustered")
    with pytest.raises(ValueError, match="neural_btf stores no list"):
        write_compressed(tmp_path / FILE_NAME, **{**model, "method": "neural_btf", "k": None})
    with pytest.raises(ValueError, match="k=7 but there are 5 latents"):
        write_compressed(tmp_path / FILE_NAME, **{**model, "k": 7})
    with pytest.raises(ValueError, match="texel_scale_mode='lstsq' but texel_scale is absent"):
        write_compressed(tmp_path / FILE_NAME, **model, texel_scale_mode="lstsq")
    with pytest.raises(ValueError, match="weight_dtype='bfloat16'"):
        write_compressed(tmp_path / FILE_NAME, **model, weight_dtype="bfloat16")
    assert list(tmp_path.iterdir()) == []
    btf = load_compressed(write_compressed(tmp_path / FILE_NAME, **model))
    with pytest.raises(ValueError, match=r"texel 24 is outside \[0, 24\)"):
        btf.query([0, 24], _directions(2))
    with pytest.raises(ValueError, match=r"shape \(n, 4\)"):
        btf.query([0], np.zeros((2, 3)))
    assert btf.texel_index(1, 2) == 1 * COLS + 2


def test_the_logged_pyfunc_model_answers_like_query(tmp_path, mlflow_template, monkeypatch):
    import time

    import mlflow
    import pandas as pd

    from pipeline.core.run_log import RunLog
    from pipeline.core.store import init_store

    # init_store points MLflow at the store (MLFLOW_TRACKING_URI too): restored afterwards.
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.delenv("PIPELINE_TRACKING_URI_SET_BY_PIPELINE", raising=False)
    mlflow_template(tmp_path / "runs")
    experiment = init_store(tmp_path / "runs", "compressed")
    folder = tmp_path / "entry"
    folder.mkdir()
    write_compressed(folder / FILE_NAME, **_model("clustered_scaled"))
    with mlflow.start_run(experiment_id=experiment) as run:
        start = time.perf_counter()
        export.log_compressed(RunLog(on=True), Entry("export", "key", folder))
        seconds = time.perf_counter() - start
    print(f"log_compressed took {seconds:.2f} s")
    run_id = run.info.run_id
    logged = mlflow.artifacts.download_artifacts(
        run_id=run_id, artifact_path=f"compressed/{FILE_NAME}", dst_path=str(tmp_path / "download")
    )
    btf = load_compressed(logged)
    # The cached file as it is: the run knows its file, the file names no run.
    assert Path(logged).read_bytes() == (folder / FILE_NAME).read_bytes()
    assert "mlflow_run_id" not in btf.metadata

    texels, directions = np.array([0, 5, 23, 5]), _directions(4)
    frame = pd.DataFrame(
        {
            "texel": texels,
            "theta_light": directions[:, 0],
            "phi_light": directions[:, 1],
            "theta_view": directions[:, 2],
            "phi_view": directions[:, 3],
        }
    )
    model = mlflow.pyfunc.load_model(f"runs:/{run_id}/compressed_btf")
    rgb = model.predict(frame)
    assert list(rgb.columns) == ["R", "G", "B"]
    np.testing.assert_array_equal(rgb.to_numpy(), btf.query_pairs(texels, directions))


def test_the_export_stage_holds_what_the_run_evaluated(tmp_path):
    """Through method A's chain (without MLflow): the cached file's reconstruction gives the
    evaluate stage's RMSE over all directions, and its tensors are the run's bytes_total."""
    from helpers import compose_config

    from pipeline.btf import runner
    from pipeline.core.stage import Context

    cfg = compose_config(
        "experiment=smoke",
        f"paths.runs={tmp_path / 'runs'}",
        "model.texel_scale=lstsq",
        "btf.crop.size=8",
    )
    ctx = Context.from_config(cfg)
    metrics = runner.run(ctx)
    cache = Path(cfg.paths.cache)
    path = cache / "export" / ctx.keys["export"] / FILE_NAME
    crop = cache / "crop" / ctx.keys["crop"]
    btf = load_compressed(path)
    assert btf.crop_size == (8, 8) and btf.k == 8 and btf.metadata["texel_scale"] == "lstsq"
    assert payload_bytes(path) == metrics["bytes_total"]
    abrdf = np.asarray(stages.abrdf(ctx.cache.lookup("crop", ctx.keys["crop"])))
    recon = btf.reconstruct(np.load(crop / "directions.npy"))
    rmse = float(
        np.sqrt(
            np.mean(np.square(recon / np.float32(btf.alpha) - abrdf / btf.alpha, dtype=np.float64))
        )
    )
    assert rmse == pytest.approx(metrics["rmse"], rel=1e-5)


@pytest.mark.parametrize("model", ["clustered", "pca"])
def test_two_equal_runs_log_the_same_bytes(tmp_path, mlflow_template, model):
    """Two smoke jobs with equal settings, each in its own runs folder (its own cache and
    store, so the second computes everything again): their logged
    ``compressed/btf.safetensors`` are byte for byte equal."""
    import mlflow
    from helpers import WIRING_STEPS, compose_config
    from mlflow.tracking import MlflowClient

    from pipeline.app import run_job
    from pipeline.core.store import tracking_uri

    logged = []
    for name in ("first", "second"):
        runs = tmp_path / name
        mlflow_template(runs)
        cfg = compose_config(
            "experiment=smoke",
            f"model={model}",
            f"paths.runs={runs}",
            f"train.max_steps={WIRING_STEPS}",
        )
        run_job(cfg)
        client = MlflowClient(tracking_uri(runs))
        experiment = client.get_experiment_by_name(cfg.tracking.experiment)
        (run,) = client.search_runs([experiment.experiment_id])
        path = client.download_artifacts(
            run.info.run_id, f"compressed/{FILE_NAME}", str(tmp_path / f"{name}_download")
        )
        logged.append(Path(path).read_bytes())
    assert logged[0] == logged[1]
    assert load_compressed(path).method == model
    if model == "pca":  # the pyfunc model answers for a PCA file too
        import pandas as pd

        texels, directions = np.array([0, 5, 143]), _directions(3)
        frame = pd.DataFrame(
            {
                "texel": texels,
                **{name: directions[:, i] for i, name in enumerate(compressed.QUERY_COLUMNS[1:])},
            }
        )
        model_dir = client.download_artifacts(
            run.info.run_id, "compressed_btf", str(tmp_path / "model")
        )
        rgb = mlflow.pyfunc.load_model(model_dir).predict(frame)
        np.testing.assert_array_equal(
            rgb.to_numpy(), load_compressed(path).query_pairs(texels, directions)
        )
