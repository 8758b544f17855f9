"""Mitsuba 3 with the project's materials (``pipeline.render.mitsuba_bsdf``,
``pipeline.btf.render.mitsuba_scene``), checked against the project's own renderer.

Both renderers estimate the same pixel integrals (direct light, a box pixel filter), so a
tiny scene rendered by each agrees "within the noise". Each renders it :data:`REPEATS`
times at one sample per pixel with independent seeds: per pixel, that many samples, whose
spread gives the standard error of each renderer's mean. Three tests at a combined
significance :data:`ALPHA` (each at a third of it), every threshold derived from it and the
sample counts, none tuned (:func:`agreement`):

- every pixel and channel: Welch's t with a Bonferroni correction (a local difference: a
  wrong texel, a shadow);
- the channel sums of all pixels together: the sum of their squared z-scores against
  chi-square (a small difference spread over the image: a rotated tangent frame);
- the image mean: a z-test (a global difference: a missing cosine, a wrong light).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import WIRING_STEPS, pipeline_command

mi = pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install mitsuba)")

from pipeline.btf.render import mitsuba_scene  # noqa: E402
from pipeline.render import mitsuba_bsdf  # noqa: E402
from pipeline.render.engine import render as project_render  # noqa: E402
from pipeline.render.materials import LambertianTexture, Material  # noqa: E402

SIZE = 16  # pixels per side
REPEATS = 64  # renders per renderer, one sample per pixel each
ALPHA = 1e-3  # the chance that a check fails although both renderers agree
MESH_RESOLUTION = 24  # coarse: the vertex tangents differ most from Mitsuba's dP/du


def smoke_compressed_file(
    tmp_path: Path, empty_store: Path, data: Path, model: str = "clustered"
) -> Path:
    """Train the smoke experiment for a few steps (``python -m pipeline experiment=smoke
    paths.runs=<tmp_path>/runs train.max_steps=...``) and return the compressed
    file it exported, found in the stage cache (``cache/export/<key>/btf.safetensors``).
    ``empty_store``: an empty ``mlflow.db`` to start from (creating one takes seconds);
    ``data``: the folder of generated built-in BTFs (``paths.data``)."""
    runs = tmp_path / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    shutil.copy(empty_store, runs / "mlflow.db")
    done = pipeline_command(
        "experiment=smoke",
        f"model={model}",
        f"paths.runs={runs}",
        f"paths.data={data}",
        f"train.max_steps={WIRING_STEPS}",  # any model will do: it is the renderers compared
    )
    assert done.returncode == 0, done.stderr[-4000:]
    found = sorted((runs / "cache" / "export").glob("*/btf.safetensors"))
    assert len(found) == 1, f"expected one exported file under {runs / 'cache'}, got {found}"
    return found[0]


@pytest.fixture(scope="module")
def variant() -> str:
    """The variant the code chooses by default (llvm_ad_rgb where LLVM >= 19 is found)."""
    return mitsuba_bsdf.register(mitsuba_bsdf.choose_variant())


@pytest.fixture(scope="module", params=["clustered", "neural_btf"])
def compressed_file(request, tmp_path_factory, _empty_mlflow_db, shared_data) -> Path:
    """A smoke model of each trained kind (PCA: tests/test_mitsuba_pca.py)."""
    return smoke_compressed_file(
        tmp_path_factory.mktemp("smoke"), _empty_mlflow_db, shared_data, model=request.param
    )


@pytest.fixture(scope="module")
def scene():
    return mitsuba_scene.fig8_scene(SIZE, SIZE, floor=True, resolution=MESH_RESOLUTION)


def mitsuba_renders(description, variant: str) -> np.ndarray:
    """:data:`REPEATS` one-sample renders (R, H, W, 3) of a scene description or file."""
    mitsuba_bsdf.register(variant)
    loaded = (
        mi.load_file(str(description))
        if isinstance(description, Path)
        else mi.load_dict(mitsuba_scene.mitsuba_dict(description))
    )
    return np.stack([mitsuba_scene.render(loaded, 1, seed=seed) for seed in range(REPEATS)])


def project_renders(scene, material) -> np.ndarray:
    """:data:`REPEATS` one-sample renders (R, H, W, 3) by the project's renderer."""
    return np.stack([project_render(scene, material, 1, seed) for seed in range(REPEATS)])


class Directional(Material):
    """A closed form that depends on both azimuths: ``albedo / pi * cos(theta_light) *
    (1 + cos(phi_light)) / 2 * (2 + sin(phi_view)) / 3``, so that a rotated tangent frame
    (phi shifted) or a flipped bitangent (phi negated) changes it."""

    def __init__(self, albedo: np.ndarray):
        self.crop_size = albedo.shape[:2]
        self.albedo = albedo.reshape(-1, 3)

    def _evaluate(self, texels, directions):
        theta_l, phi_l, _, phi_v = directions.T
        lobe = np.cos(theta_l) / np.pi * (1 + np.cos(phi_l)) / 2 * (2 + np.sin(phi_v)) / 3
        return (self.albedo[texels] * lobe[:, None]).astype(np.float32)


def agreement(ours: np.ndarray, theirs: np.ndarray) -> dict:
    """Whether two stacks of one-sample renders (R, H, W, 3) estimate the same image.

    Returns the p-value of each check of the module docstring (``p_pixels`` Bonferroni-
    adjusted, ``p_spread``, ``p_mean``), whether pixels that vary in neither stack are
    equal to float32 rounding (``still_equal``), the median per-pixel tolerance of the
    first check in radiance (``tolerance``: its t limit times the pixel's standard error),
    and the RMSE and HDR-FLIP between the two means (``rmse_noise``: the RMSE the noise
    alone gives; ``mean``: the image's mean radiance).
    """
    from scipy import stats

    from pipeline.core.image_metrics import flip

    def welch(a, b):
        var_a, var_b = a.var(0, ddof=1) / len(a), b.var(0, ddof=1) / len(b)
        spread = var_a + var_b  # the squared standard error of the difference
        noisy = spread > 0
        dof = spread[noisy] ** 2 / (
            var_a[noisy] ** 2 / (len(a) - 1) + var_b[noisy] ** 2 / (len(b) - 1)
        )
        difference = a.mean(0) - b.mean(0)
        return difference, spread, noisy, np.abs(difference[noisy]) / np.sqrt(spread[noisy]), dof

    a, b = ours.astype(np.float64), theirs.astype(np.float64)
    difference, spread, noisy, t, dof = welch(a, b)
    tests = difference.size
    rounding = 4 * np.finfo(np.float32).eps * np.maximum(np.abs(a.mean(0)), np.abs(b.mean(0)))
    limit = stats.t.isf(ALPHA / 3 / (2 * tests), dof)
    sums, sum_spread, _, sum_t, sum_dof = welch(a.sum(-1), b.sum(-1))
    z = stats.norm.isf(stats.t.sf(sum_t, sum_dof))  # each pixel's |t| as a |z| (same p)
    mean_z = sums.sum() / np.sqrt(sum_spread.sum())
    return {
        "p_pixels": float(min(1.0, 2 * stats.t.sf(t, dof).min() * tests)) if t.size else 1.0,
        "p_spread": float(stats.chi2.sf(np.sum(z**2), z.size)),
        "p_mean": float(2 * stats.norm.sf(abs(mean_z))),
        "still_equal": bool(np.all(np.abs(difference[~noisy]) <= rounding[~noisy])),
        "tolerance": float(np.median(limit * np.sqrt(spread[noisy]))),
        "rmse": float(np.sqrt(np.mean(difference**2))),
        "rmse_noise": float(np.sqrt(np.mean(spread))),  # what the noise alone gives
        "mean": float(b.mean()),
        "flip": flip(b.mean(0), a.mean(0), dynamic_range="hdr"),
    }


def agrees(found: dict) -> bool:
    return (
        found["still_equal"]
        and min(found["p_pixels"], found["p_spread"], found["p_mean"]) >= ALPHA / 3
    )


def assert_agree(found: dict) -> None:
    print(
        {
            key: round(value, 5) if isinstance(value, float) else value
            for key, value in found.items()
        }
    )
    assert agrees(found), found


# --------------------------------------------------------------------- the conventions


def test_texels_follow_the_project_renderer_s_rule():
    uv = np.array([[0.0, 0.0], [0.26, 0.0], [0.0, 0.51], [1.26, 2.51], [-0.01, -0.01]])
    # (rows, cols) = (2, 4): col = floor(frac(u) * 4), row = floor(frac(v) * 2)
    assert mitsuba_bsdf.texels_of_uv(uv, (2, 4)).tolist() == [0, 1, 4, 5, 7]


def test_angles_are_measured_from_the_normal_and_the_tangent():
    local = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
    theta, phi = mitsuba_bsdf.spherical(local)
    np.testing.assert_allclose(theta, [0.0, np.pi / 2, np.pi / 2, np.pi / 2])
    np.testing.assert_allclose(phi[1:], [0.0, np.pi / 2, 3 * np.pi / 2])


def test_the_vertex_tangent_sets_phi_and_the_geometric_normal_hides_back_faces():
    """One shading point by hand, in Mitsuba's frame (s, t, n): with the vertex tangent
    along t (a turn of pi / 2), the bitangent n x t is -s, so a light leaning towards +s
    has phi = 3 pi / 2."""

    class Echo:  # returns (theta_light, phi_light, theta_view) as its colour
        crop_size = (1, 1)

        def evaluate(self, texels, directions):
            return directions[:, :3].astype(np.float32)

    light = np.array([[np.sqrt(0.5), 0.0, np.sqrt(0.5)]])
    view = np.array([[0.0, 0.0, 1.0]])
    up, uv = np.array([[0.0, 0.0, 1.0]]), np.zeros((1, 2))
    turned = mitsuba_bsdf.btf_query(Echo(), uv, view, light, up, np.array([np.pi / 2]))
    np.testing.assert_allclose(turned[0], [np.pi / 4, 3 * np.pi / 2, 0.0], atol=1e-6)
    plain = mitsuba_bsdf.btf_query(Echo(), uv, view, light, up)
    np.testing.assert_allclose(plain[0], [np.pi / 4, 0.0, 0.0], atol=1e-6)
    tilted = np.array([[-0.8, 0.0, 0.6]])  # the light is below this geometric normal
    assert not mitsuba_bsdf.btf_query(Echo(), uv, view, light, tilted).any()


def test_sampling_is_cosine_weighted_and_its_weight_is_eval_over_pdf(variant):
    """A Lambertian of albedo rho: eval = rho / pi cos, pdf = cos / pi, weight = rho."""
    albedo = np.array([[[0.2, 0.4, 0.6], [0.9, 0.5, 0.1]]])
    bsdf = mitsuba_bsdf.material_bsdf(LambertianTexture(albedo))
    ctx = mi.BSDFContext()
    rng = np.random.default_rng(0)
    for u, sample in zip(rng.random(8), rng.random((8, 2)), strict=True):
        si = mi.SurfaceInteraction3f()
        si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
        si.n = mi.Vector3f(0.0, 0.0, 1.0)
        si.wi = mi.Vector3f(0.6, 0.0, 0.8)
        si.uv = mi.Point2f(float(u), 0.5)
        bs, weight = bsdf.sample(ctx, si, 0.5, mi.Point2f(*map(float, sample)))
        wo = np.array(bs.wo).ravel()
        cosine = wo[2]
        assert float(np.ravel(bs.pdf)[0]) == pytest.approx(cosine / np.pi, rel=1e-5)
        assert float(np.ravel(bsdf.pdf(ctx, si, bs.wo))[0]) == pytest.approx(
            cosine / np.pi, rel=1e-5
        )
        np.testing.assert_allclose(np.ravel(weight), albedo[0, int(u * 2)], rtol=1e-5)
        value = np.ravel(bsdf.eval(ctx, si, bs.wo))
        np.testing.assert_allclose(value, albedo[0, int(u * 2)] / np.pi * cosine, rtol=1e-5)
        # Adjoint: the light is wi, the cosine still wo's (cos_i / cos_i cancels here).
        adjoint = np.ravel(bsdf.eval(mi.BSDFContext(mi.TransportMode.Importance), si, bs.wo))
        np.testing.assert_allclose(adjoint, value, rtol=1e-5)


def test_the_sphere_faces_outwards_with_v_along_the_bitangent():
    mesh = mitsuba_scene.sphere_mesh(resolution=6, tiles=2.0)
    corners = mesh.triangles
    normals = mesh.normals[corners].mean(1)
    assert np.all(np.einsum("ij,ij->i", mesh.face_normals(), normals) > 0)
    # dP/dv of each triangle points along n x t, as the renderers' frame assumes
    p, uv = mesh.vertices.astype(np.float64)[corners], mesh.uv[corners]
    dp1, dp2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    duv1, duv2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    det = duv1[:, 0] * duv2[:, 1] - duv1[:, 1] * duv2[:, 0]
    dp_dv = (duv1[:, 0, None] * dp2 - duv2[:, 0, None] * dp1) / det[:, None]
    bitangents = mesh.bitangents[corners].mean(1)
    assert np.all(np.einsum("ij,ij->i", dp_dv, bitangents) > 0)


# ------------------------------------------------------------------ against our renderer


def test_a_lambertian_texture_renders_as_in_the_project_renderer(scene, variant, tmp_path):
    material = LambertianTexture(np.random.default_rng(0).uniform(0.1, 0.9, (3, 5, 3)))
    description = mitsuba_scene.scene_description(
        scene, tmp_path, mitsuba_bsdf.material_bsdf(material), 1
    )
    ours, theirs = mitsuba_renders(description, variant), project_renders(scene, material)
    assert_agree(agreement(ours, theirs))
    assert not agrees(agreement(ours * 1.03, theirs))  # 3 % more light is caught


def test_a_material_that_depends_on_phi_renders_as_in_the_project_renderer(
    scene, variant, tmp_path
):
    material = Directional(np.random.default_rng(1).uniform(0.1, 0.9, (3, 5, 3)))
    description = mitsuba_scene.scene_description(
        scene, tmp_path, mitsuba_bsdf.material_bsdf(material), 1
    )
    ours = mitsuba_renders(description, variant)
    assert_agree(agreement(ours, project_renders(scene, material)))

    class Mirrored(Material):  # phi negated: the bitangent flipped
        crop_size = material.crop_size

        def _evaluate(self, texels, directions):
            return material.evaluate(texels, directions * [1, -1, 1, -1] % (2 * np.pi))

    assert not agrees(agreement(ours, project_renders(scene, Mirrored())))


@pytest.mark.parametrize("shape", ["sheet", "sphere"])
def test_the_built_in_analytic_btf_renders_as_in_the_project_renderer(shape, variant, tmp_path):
    from pipeline.btf.render.surfaces import AnalyticMaterial
    from pipeline.btf.synthetic import SyntheticBTF

    material = AnalyticMaterial(SyntheticBTF(size=8, seed=0), (0, 0), (8, 8))
    scene = mitsuba_scene.fig8_scene(SIZE, SIZE, shape, floor=True, resolution=MESH_RESOLUTION)
    description = mitsuba_scene.scene_description(
        scene, tmp_path, mitsuba_bsdf.material_bsdf(material), 1
    )
    assert_agree(agreement(mitsuba_renders(description, variant), project_renders(scene, material)))


@pytest.fixture(scope="module")
def written_folder(compressed_file, tmp_path_factory) -> Path:
    """The command's folder for the smoke model at the test's size."""
    out = tmp_path_factory.mktemp("mitsuba_scene")
    mitsuba_scene.main(
        [f"file={compressed_file}", f"out={out}", "spp=4", f"width={SIZE}", f"height={SIZE}"]
    )
    return out


def test_the_command_writes_a_self_contained_folder(written_folder, compressed_file):
    assert sorted(p.name for p in written_folder.iterdir()) == [
        "btf.safetensors",
        "cloth.ply",
        "floor.ply",
        "scene.xml",
    ]
    assert (written_folder / "btf.safetensors").read_bytes() == compressed_file.read_bytes()
    text = (written_folder / "scene.xml").read_text()
    assert 'value="btf.safetensors"' in text and str(written_folder) not in text


def test_a_compressed_model_renders_as_in_the_project_renderer(
    written_folder, compressed_file, variant
):
    """Through the written folder, as a user loads it (``mi.load_file``)."""
    scene = mitsuba_scene.fig8_scene(SIZE, SIZE, floor=True)  # the command's scene
    material = mitsuba_scene.material_from_file(compressed_file)
    ours = mitsuba_renders(written_folder / "scene.xml", variant)
    assert_agree(agreement(ours, project_renders(scene, material)))


def test_the_written_file_renders_like_the_description_it_came_from(
    written_folder, compressed_file, variant, tmp_path
):
    """write_xml loses nothing: the same seed gives the same image."""
    scene = mitsuba_scene.fig8_scene(SIZE, SIZE, floor=True)
    bsdf = mitsuba_bsdf.material_bsdf(mitsuba_scene.material_from_file(compressed_file))
    description = mitsuba_scene.scene_description(scene, tmp_path, bsdf, 4)
    from_file = mitsuba_scene.render(written_folder / "scene.xml", 4, seed=3)
    np.testing.assert_allclose(
        mitsuba_scene.render(description, 4, seed=3), from_file, rtol=1e-5, atol=1e-7
    )


def test_a_model_with_query_only_answers_as_with_query_pairs(compressed_file):
    """What a PCA file with ``query`` only would get: the same values."""
    from pipeline.btf.compressed import load_compressed

    btf = load_compressed(compressed_file)

    class QueryOnly:
        crop_size = btf.crop_size
        query = staticmethod(btf.query)

    rng = np.random.default_rng(0)
    texels = rng.integers(0, btf.n_texels, 50)
    directions = rng.uniform([0, 0, 0, 0], [1.4, 6.28, 1.4, 6.28], (50, 4))
    np.testing.assert_allclose(
        mitsuba_scene.as_material(QueryOnly()).evaluate(texels, directions),
        mitsuba_scene.as_material(btf).evaluate(texels, directions),
        rtol=1e-5,
        atol=1e-6,
    )


# ------------------------------------------------------------------------- error paths


def test_a_missing_model_file_is_named(tmp_path):
    with pytest.raises(SystemExit) as stop:
        mitsuba_scene.main([f"file={tmp_path / 'none.safetensors'}", f"out={tmp_path}"])
    assert stop.value.code == 2


def test_a_scene_without_an_output_folder_is_refused(tmp_path):
    from pipeline.core.errors import ConfigError

    (tmp_path / "btf.safetensors").write_bytes(b"")
    with pytest.raises(ConfigError, match="out=... is required"):
        mitsuba_scene.parse([f"file={tmp_path / 'btf.safetensors'}"])


def test_a_loader_that_cannot_be_imported_is_named():
    with pytest.raises(ValueError, match="loader='nowhere:load' cannot be imported"):
        mitsuba_bsdf.load_material("nowhere:load", "btf.safetensors")
    with pytest.raises(ValueError, match="must be 'package.module:function'"):
        mitsuba_bsdf.load_material("nowhere", "btf.safetensors")
