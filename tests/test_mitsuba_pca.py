"""A PCA file (``pipeline.btf.compressed``, method ``pca``) in Mitsuba 3: the scene folder
of ``pipeline.btf.render.mitsuba_scene`` renders as the project's renderer renders the
file, with the checks of ``tests/test_mitsuba.py``, and the project's renderer renders
the file as it renders the linear stage's arrays."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install mitsuba)")

from test_mitsuba import (
    SIZE,
    agreement,
    assert_agree,
    mitsuba_renders,
    project_renders,
)

from pipeline.btf.compressed import FILE_NAME, load_compressed
from pipeline.btf.render import mitsuba_scene
from pipeline.render import mitsuba_bsdf


@pytest.fixture(scope="module")
def variant() -> str:
    """The variant the code chooses by default (as in tests/test_mitsuba.py)."""
    return mitsuba_bsdf.register(mitsuba_bsdf.choose_variant())


@pytest.fixture(scope="module")
def smoke_pca(tmp_path_factory):
    """A smoke PCA run through method A's chain (no MLflow): its context."""
    from helpers import compose_config

    from pipeline.btf import runner
    from pipeline.core.stage import Context

    runs = tmp_path_factory.mktemp("pca") / "runs"
    ctx = Context.from_config(compose_config("experiment=smoke", "model=pca", f"paths.runs={runs}"))
    runner.run(ctx)
    return ctx


def _entry(ctx, stage: str):
    return ctx.cache.lookup(stage, ctx.keys[stage])


def test_a_pca_file_renders_as_in_the_project_renderer(smoke_pca, variant, tmp_path):
    """Through the written folder, as a user loads it (``mi.load_file``)."""
    path = _entry(smoke_pca, "export").file(FILE_NAME)
    assert load_compressed(path).method == "pca"
    out = tmp_path / "scene"
    mitsuba_scene.main([f"file={path}", f"out={out}", "spp=1", f"width={SIZE}", f"height={SIZE}"])
    scene = mitsuba_scene.fig8_scene(SIZE, SIZE, floor=True)  # the command's scene
    ours = mitsuba_renders(out / "scene.xml", variant)
    assert_agree(agreement(ours, project_renders(scene, mitsuba_scene.material_from_file(path))))


def test_the_file_renders_as_the_linear_stage_s_arrays(smoke_pca):
    """The project's renderer: the file's material and the render stage's PCA material
    (``linear_material``, from the cache arrays) give the same image, and a wrapper that
    has ``query`` only (``QueryMaterial``) the same values."""
    from pipeline.btf.render.stage import linear_material
    from pipeline.render.engine import render

    ctx = smoke_pca
    path = _entry(ctx, "export").file(FILE_NAME)
    scene = mitsuba_scene.fig8_scene(SIZE, SIZE, floor=True)
    arrays = linear_material(*(_entry(ctx, s) for s in ("linear", "crop", "preprocess")))
    np.testing.assert_array_equal(
        render(scene, mitsuba_scene.material_from_file(path), 4, 0), render(scene, arrays, 4, 0)
    )

    pca = load_compressed(path)

    class QueryOnly:
        crop_size = pca.crop_size
        query = staticmethod(pca.query)

    rng = np.random.default_rng(0)
    texels = rng.integers(0, pca.n_texels, 200)
    directions = rng.uniform([0, 0, 0, 0], [1.5, 6.28, 1.5, 6.28], (200, 4))
    np.testing.assert_allclose(
        mitsuba_scene.as_material(QueryOnly()).evaluate(texels, directions),
        arrays.evaluate(texels, directions),
        rtol=1e-5,
        atol=1e-6,
    )
