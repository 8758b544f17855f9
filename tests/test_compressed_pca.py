"""The PCA baseline's compressed file (pipeline.btf.compressed, method ``pca``): round
trip, bytes against Table 1, values at the measured directions against the stored arrays,
queries anywhere against the renderer's PCA material, refused files."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from pipeline.btf.compressed import (
    FILE_NAME,
    CompressedPCA,
    header_bytes,
    load_compressed,
    payload_bytes,
    stored_parts,
    support_bytes,
    write_compressed_pca,
)
from pipeline.btf.linear import pca_bytes
from pipeline.core.errors import DataError
from pipeline.data.directions import grid_81

ROWS, COLS = 2, 3  # M = 6 texels
COMPONENTS = 2
ALPHA = 2.5


def _measured() -> np.ndarray:
    """7 lights x 7 views (the normal and the 15-degree ring of the 81-grid), view-major:
    (49, 4) radians."""
    ring = grid_81()[:7]
    return np.array([[*light, *view] for view in ring for light in ring])


def _model(dtype: str = "float32", seed: int = 0) -> dict:
    """A hand-made PCA and what write_compressed_pca needs besides."""
    rng = np.random.default_rng(seed)
    n = len(_measured())
    return {
        "mean": rng.uniform(0.2, 0.6, 3 * n).astype(dtype),
        "basis": rng.normal(0, 0.1, (COMPONENTS, 3 * n)).astype(dtype),
        "coefficients": rng.normal(0, 1, (ROWS * COLS, COMPONENTS)).astype(dtype),
        "alpha": ALPHA,
        "measured_directions": _measured(),
        "crop_size": (ROWS, COLS),
        "crop_offset": (1, 4),
        "dataset": "synthetic",
        "weight_dtype": dtype,
    }


def _stored_values(model: dict) -> np.ndarray:
    """alpha * (mean + coefficients @ basis) in float64, from the arrays as stored: (M, N, 3)."""
    mean, basis, coefficients = (
        np.asarray(model[k], np.float64) for k in ("mean", "basis", "coefficients")
    )
    values = mean + coefficients @ basis
    return model["alpha"] * values.reshape(len(coefficients), -1, 3)


def _queries(n: int, seed: int = 1, max_theta: float = np.radians(85)) -> np.ndarray:
    """n direction pairs up to ``max_theta``, beyond the measured ones too: (n, 4)."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0, max_theta, (n, 2))
    phi = rng.uniform(0, 2 * np.pi, (n, 2))
    return np.column_stack([theta[:, 0], phi[:, 0], theta[:, 1], phi[:, 1]])


@pytest.mark.parametrize("dtype", ["float32", "float16"])
def test_round_trip_and_bytes(tmp_path, dtype):
    model = _model(dtype)
    path = write_compressed_pca(tmp_path / FILE_NAME, **model)
    pca = load_compressed(path)
    assert isinstance(pca, CompressedPCA) and pca.path == path
    for name in ("mean", "basis", "coefficients"):
        np.testing.assert_array_equal(getattr(pca, name), model[name])
        assert getattr(pca, name).dtype == dtype, name
    np.testing.assert_array_equal(pca.measured_directions, _measured())
    assert pca.measured_directions.dtype == np.float64
    assert (pca.alpha, pca.crop_size, pca.crop_offset) == (ALPHA, (ROWS, COLS), (1, 4))
    assert (pca.method, pca.k, pca.n_components, pca.n_texels) == ("pca", None, COMPONENTS, 6)
    meta = pca.metadata
    assert (meta["format"], meta["format_version"], meta["weight_dtype"]) == (
        "pipeline.btf.compressed",
        "1",
        dtype,
    )
    assert (meta["n_components"], meta["n_directions"], meta["value_layout"]) == (
        "2",
        "49",
        "direction,channel",
    )
    assert json.loads(meta["crop_size"]) == [ROWS, COLS] and "mlflow_run_id" not in meta
    # Table 1's bytes: the model only; the measured directions are the file's support.
    assert payload_bytes(path) == pca_bytes(COMPONENTS, ROWS * COLS, 49, dtype)
    assert support_bytes(path) == 49 * 4 * 8
    assert payload_bytes(path) + support_bytes(path) + header_bytes(path) == path.stat().st_size
    size = 2 if dtype == "float16" else 4
    assert stored_parts(path) == {
        "decoder": {"dtype": dtype, "bytes": size * 3 * 49 * (COMPONENTS + 1)},
        "latents": {"dtype": dtype, "bytes": size * ROWS * COLS * COMPONENTS},
    }
    # The same model, the same bytes.
    again = write_compressed_pca(tmp_path / "again.safetensors", **_model(dtype))
    assert again.read_bytes() == path.read_bytes()


@pytest.mark.parametrize("dtype", ["float32", "float16"])
def test_at_the_measured_directions_it_is_mean_plus_coefficients_times_basis(tmp_path, dtype):
    model = _model(dtype)
    pca = load_compressed(write_compressed_pca(tmp_path / FILE_NAME, **model))
    expected = _stored_values(model)
    scale = float(np.abs(expected).max())
    got = pca.reconstruct(_measured())
    assert got.shape == (ROWS * COLS, 49, 3) and got.dtype == np.float32
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-6 * scale)
    texels = np.repeat(np.arange(ROWS * COLS), 49)
    pairs = np.tile(np.arange(49), ROWS * COLS)
    np.testing.assert_allclose(
        pca.query_pairs(texels, _measured()[pairs]),
        expected[texels, pairs],
        rtol=1e-6,
        atol=1e-6 * scale,
    )


def test_query_interpolates_as_the_renderer_s_pca_material(tmp_path):
    from pipeline.btf.render.surfaces import LinearMaterial

    model = _model()
    pca = load_compressed(write_compressed_pca(tmp_path / FILE_NAME, **model))
    material = LinearMaterial(
        model["mean"], model["basis"], model["coefficients"], (ROWS, COLS), ALPHA, _measured()
    )
    rng = np.random.default_rng(2)
    texels, directions = rng.integers(0, ROWS * COLS, 500), _queries(500)
    pairs = pca.query_pairs(texels, directions)
    np.testing.assert_array_equal(pairs, material.evaluate(texels, directions))
    # Every texel at every direction: the basis interpolated once per direction.
    grid = pca.query(np.arange(ROWS * COLS), directions)
    assert grid.shape == (ROWS * COLS, 500, 3)
    np.testing.assert_allclose(
        grid[texels, np.arange(500)], pairs, rtol=1e-5, atol=1e-6 * float(np.abs(pairs).max())
    )
    # Between directions the values are not those of the nearest one: it interpolates.
    nearest = _stored_values(model)[:, 0]  # the normal
    assert not np.allclose(pca.query([0], [[0.05, 0.0, 0.05, 0.0]])[0, 0], nearest[0])


def test_inconsistent_inputs_are_refused_before_writing(tmp_path):
    model = _model()
    target = tmp_path / FILE_NAME
    with pytest.raises(ValueError, match=r"mean \(147,\) and basis \(2, 150\) must be"):
        write_compressed_pca(target, **{**model, "basis": np.zeros((2, 150), np.float32)})
    with pytest.raises(ValueError, match=r"coefficients have shape \(5, 2\), expected \(6, 2\)"):
        write_compressed_pca(target, **{**model, "coefficients": np.zeros((5, 2), np.float32)})
    with pytest.raises(ValueError, match=r"measured_directions must have shape \(N, 4\)"):
        write_compressed_pca(target, **{**model, "measured_directions": _measured()[:, :3]})
    with pytest.raises(ValueError, match="weight_dtype='bfloat16'"):
        write_compressed_pca(target, **{**model, "weight_dtype": "bfloat16"})
    with pytest.raises(ValueError, match="alpha=0.0 must be a positive finite number"):
        write_compressed_pca(target, **{**model, "alpha": 0.0})
    # Not every light under every view: nothing to interpolate between.
    n = 48
    with pytest.raises(DataError, match="every light measured under every view"):
        write_compressed_pca(
            target,
            **{
                **model,
                "measured_directions": _measured()[:n],
                "mean": model["mean"][: 3 * n],
                "basis": model["basis"][:, : 3 * n],
            },
        )
    assert list(tmp_path.iterdir()) == []


def _rewrite(path: Path, tensors: dict | None = None, **metadata) -> None:
    """The file at ``path`` with tensors replaced or removed (None) and metadata changed."""
    from safetensors import safe_open
    from safetensors.numpy import save_file

    with safe_open(path, framework="numpy") as f:
        meta = {**f.metadata(), **metadata}
        found = {name: f.get_tensor(name) for name in f.keys()}
    for name, value in (tensors or {}).items():
        if value is None:
            found.pop(name)
        else:
            found[name] = value
    save_file(found, str(path), metadata=meta)


@pytest.mark.parametrize(
    "damage, match",
    [
        ({"tensors": {"measured_directions": None}}, "without 'measured_directions'"),
        ({"tensors": {"coefficients": np.zeros((4, 2), np.float32)}}, r"inconsistent .*\(4, 2\)"),
        ({"crop_size": "[3, 3]"}, r"inconsistent .*crop_size=\(3, 3\)"),
        ({"interpolation": "nearest"}, "interpolation='nearest'"),
        ({"format": "someone.else"}, "not a compressed BTF"),
        ({"format_version": "2"}, "version '2'"),
    ],
)
def test_a_damaged_or_foreign_file_is_refused_naming_it(tmp_path, damage, match):
    path = write_compressed_pca(tmp_path / FILE_NAME, **_model())
    _rewrite(path, **damage)
    with pytest.raises(DataError, match=rf"{re.escape(str(path))}.*{match}"):
        load_compressed(path)


def test_a_truncated_file_is_refused_naming_it(tmp_path):
    path = write_compressed_pca(tmp_path / FILE_NAME, **_model())
    path.write_bytes(path.read_bytes()[:-8])
    for read in (load_compressed, payload_bytes, support_bytes):
        with pytest.raises(DataError, match=re.escape(str(path))):
            read(path)


def test_query_checks_its_arguments(tmp_path):
    pca = load_compressed(write_compressed_pca(tmp_path / FILE_NAME, **_model()))
    with pytest.raises(
        ValueError, match=rf"texel 6 is outside \[0, 6\) \({re.escape(str(pca.path))}"
    ):
        pca.query([0, 6], _queries(2))
    with pytest.raises(ValueError, match=r"shape \(n, 4\)"):
        pca.query_pairs([0], np.zeros((1, 3)))
    with pytest.raises(ValueError, match="2 texels but 3 direction pairs"):
        pca.query_pairs([0, 1], _queries(3))


# ------------------------------------------------------------------- through the chain


@pytest.fixture(scope="module")
def smoke_pca(tmp_path_factory):
    """A smoke PCA run through method A's chain (no MLflow): its config, context, metrics."""
    from helpers import compose_config

    from pipeline.btf import runner
    from pipeline.core.stage import Context

    runs = tmp_path_factory.mktemp("pca") / "runs"
    cfg = compose_config("experiment=smoke", "model=pca", f"paths.runs={runs}")
    ctx = Context.from_config(cfg)
    return cfg, ctx, runner.run(ctx)


def test_the_exported_file_holds_the_linear_stage_s_bytes(smoke_pca):
    cfg, ctx, metrics = smoke_pca
    exported = ctx.cache.lookup("export", ctx.keys["export"])
    path = exported.file(FILE_NAME)
    assert payload_bytes(path) == metrics["bytes_total"]
    parts = stored_parts(path)
    assert parts["decoder"]["bytes"] == metrics["bytes_decoder"]
    assert parts["latents"]["bytes"] == metrics["bytes_latents"]
    summary = exported.manifest["summary"]
    assert summary["bytes_payload"] == metrics["bytes_total"]
    assert summary["stored_as"] == {"decoder": cfg.model.dtype, "latents": cfg.model.dtype}
    assert summary["bytes_support"] == metrics["n_directions"] * 4 * 8
    assert exported.manifest["inputs"]["linear"] == ctx.keys["linear"]


def test_the_file_answers_as_the_renderer_s_linear_material(smoke_pca):
    """The file's query against pipeline.btf.render.stage.linear_material (the linear
    stage's cache arrays), at random texels and directions, beyond the grid too; at the
    measured directions, mean + coefficients @ basis x alpha."""
    from pipeline.btf.render.stage import linear_material
    from pipeline.btf.stages import normalization

    _, ctx, _ = smoke_pca
    cropped, prep, fitted, exported = (
        ctx.cache.lookup(name, ctx.keys[name])
        for name in ("crop", "preprocess", "linear", "export")
    )
    pca = load_compressed(exported.file(FILE_NAME))
    material = linear_material(fitted, cropped, prep)
    rng = np.random.default_rng(0)
    texels, directions = rng.integers(0, pca.n_texels, 2000), _queries(2000)
    ours, theirs = pca.query_pairs(texels, directions), material.evaluate(texels, directions)
    grid = pca.query(texels[:50], directions)[np.arange(50), np.arange(50)]
    print(
        f"query_pairs - linear_material: max |diff| {np.abs(ours - theirs).max():.3g}; "
        f"query (grid) - linear_material: {np.abs(grid - theirs[:50]).max():.3g} "
        f"(values up to {np.abs(theirs).max():.3g})"
    )
    np.testing.assert_array_equal(ours, theirs)
    np.testing.assert_allclose(grid, theirs[:50], rtol=1e-5, atol=1e-6 * np.abs(theirs).max())

    measured = cropped.array("directions", mmap=False)
    mean, basis, coefficients = (
        fitted.array(n, mmap=False).astype(np.float64) for n in ("mean", "basis", "coefficients")
    )
    expected = normalization(prep).alpha * (mean + coefficients @ basis).reshape(
        pca.n_texels, len(measured), 3
    )
    got = pca.reconstruct(measured)
    print(
        f"reconstruct at the measured directions - stored values: max |diff| "
        f"{np.abs(got - expected).max():.3g} (values up to {np.abs(expected).max():.3g})"
    )
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6 * np.abs(expected).max())
