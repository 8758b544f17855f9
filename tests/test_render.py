"""The BTF renderer: closed-form images of a flat quad, shadows, seeds, batching, the
measured-BTF interpolant, the analytic truth and the grid's edge, the cloth's tangent
frames, and a small end-to-end render."""

import numpy as np
import pytest

from pipeline.btf.interpolation import ProductInterpolator, offgrid_directions
from pipeline.btf.render.surfaces import (
    AnalyticMaterial,
    BeyondGridIndicator,
    GridClamped,
    LinearMaterial,
    MeasuredMaterial,
    beyond_grid,
    clamp_to_grid,
)
from pipeline.data.directions import btf_directions
from pipeline.render.engine import render, render_with_stats, strata, subpixel_offsets
from pipeline.render.materials import LambertianTexture
from pipeline.render.scene import (
    Camera,
    DirectionalLight,
    PointLight,
    Scene,
    default_scene,
    folded_sheet,
    merge_meshes,
    quad,
)

BACKGROUND = np.array([0.1, 0.2, 0.3])
TEXELS = 4  # the checkerboard crop is TEXELS x TEXELS, tiled once over the quad
SUN = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
SUN_IRRADIANCE = np.array([1.0, 0.8, 0.6])


def _checkerboard(texels: int = TEXELS) -> np.ndarray:
    """(texels, texels, 3) albedo: two colours in a checkerboard."""
    rows, cols = np.indices((texels, texels))
    odd = ((rows + cols) % 2 == 1)[..., None]
    return np.where(odd, [0.9, 0.6, 0.3], [0.2, 0.4, 0.8])


def _floor_quad(tiles: float = 1.0):
    """The square y = 0, x and z in [-1, 1]; u = (x + 1) / 2 and v = (1 - z) / 2 (tiles=1)."""
    return quad([-1.0, 0.0, 1.0], [2.0, 0.0, 0.0], [0.0, 0.0, -2.0], tiles=tiles)


def _camera(size: int = 16) -> Camera:
    """Looking straight down at the quad from y = 3, seeing x in about [-1.4, 1.4]; the
    small shift keeps texel edges off pixel corners."""
    return Camera(
        position=[0.037, 3.0, -0.021],
        look_at=[0.037, 0.0, -0.021],
        up=[0.0, 0.0, -1.0],
        fov_y_degrees=50.0,
        width=size,
        height=size,
    )


def _footprints(camera: Camera, shrink: float = 1e-6) -> np.ndarray:
    """(H, W, 4, 3) points where rays through each pixel's corners meet the plane y = 0."""
    rows, cols = np.indices((camera.height, camera.width))
    corners = [
        (shrink, shrink),
        (1 - shrink, shrink),
        (shrink, 1 - shrink),
        (1 - shrink, 1 - shrink),
    ]
    x = np.stack([cols + dx for dx, _ in corners], axis=-1).ravel()
    y = np.stack([rows + dy for _, dy in corners], axis=-1).ravel()
    origins, directions = camera.rays(x, y)
    points = origins - (origins[:, 1] / directions[:, 1])[:, None] * directions
    return points.reshape(camera.height, camera.width, 4, 3)


def _texel_of(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(texel index, inside the quad) of points on the plane, for _floor_quad(tiles=1)."""
    u, v = (points[..., 0] + 1) / 2, (1 - points[..., 2]) / 2
    inside = (u > 0) & (u < 1) & (v > 0) & (v < 1)
    col = np.clip(np.floor(u * TEXELS), 0, TEXELS - 1)
    row = np.clip(np.floor(v * TEXELS), 0, TEXELS - 1)
    return (row * TEXELS + col).astype(int), inside


def _one_texel_pixels(points: np.ndarray):
    """Pixels wholly on one texel (H, W) bool, their texel (H, W), and pure misses."""
    texel, inside = _texel_of(points)
    whole = inside.all(-1) & (texel == texel[..., :1]).all(-1)
    return whole, texel[..., 0], (~inside).all(-1)


# ----------------------------------------------------------------------- closed forms


def test_lambertian_quad_under_a_directional_light_matches_the_closed_form():
    camera = _camera()
    scene = Scene(_floor_quad(), camera, [DirectionalLight(SUN, SUN_IRRADIANCE)])
    albedo = _checkerboard()
    image = render(scene, LambertianTexture(albedo), spp=4, seed=0, background=BACKGROUND)
    assert image.shape == (16, 16, 3) and image.dtype == np.float32

    whole, texel, missed = _one_texel_pixels(_footprints(camera))
    assert whole.sum() >= 40 and missed.sum() >= 10  # the test covers both cases
    cos_light = SUN[1]  # the quad's normal is +y
    expected = albedo.reshape(-1, 3)[texel[whole]] / np.pi * cos_light * SUN_IRRADIANCE
    np.testing.assert_allclose(image[whole], expected, rtol=1e-4)
    np.testing.assert_array_equal(
        image[missed], np.broadcast_to(BACKGROUND, (missed.sum(), 3)).astype(np.float32)
    )


def test_point_light_irradiance_falls_off_with_distance_squared():
    camera = _camera()
    light = PointLight([0.0, 2.0, 0.0], [4.0, 4.0, 4.0])
    scene = Scene(_floor_quad(), camera, [light])
    albedo = _checkerboard()
    image = render(scene, LambertianTexture(albedo), spp=16, seed=1)
    whole, texel, _ = _one_texel_pixels(_footprints(camera))
    # At the pixel centre: E_perp = I / r^2 and cos(theta_light) = h / r.
    rows, cols = np.indices(whole.shape)
    origins, directions = camera.rays(cols[whole] + 0.5, rows[whole] + 0.5)
    points = origins - (origins[:, 1] / directions[:, 1])[:, None] * directions
    r2 = np.sum((light.position - points) ** 2, axis=1)
    expected = albedo.reshape(-1, 3)[texel[whole]] / np.pi * (4.0 * 2.0 / r2**1.5)[:, None]
    np.testing.assert_allclose(image[whole], expected, rtol=1e-2)


def test_an_occluder_between_light_and_quad_casts_a_shadow():
    # A wall x = -1.6, y in [0, 1], outside the camera's view; light from -x at 45 degrees:
    # the plane is in its shadow for x < -1.6 + 1 = -0.6.
    camera = _camera()
    wall = quad([-1.6, 0.0, 3.0], [0.0, 0.0, -6.0], [0.0, 1.0, 0.0])
    light = DirectionalLight([-1.0, 1.0, 0.0], [1.0, 1.0, 1.0])
    scene = Scene(merge_meshes(_floor_quad(), wall), camera, [light])
    albedo = _checkerboard()
    image = render(scene, LambertianTexture(albedo), spp=4, seed=0)

    points = _footprints(camera)
    whole, texel, _ = _one_texel_pixels(points)
    shadowed = whole & (points[..., 0] < -0.6 - 1e-3).all(-1)
    lit = whole & (points[..., 0] > -0.6 + 1e-3).all(-1)
    assert shadowed.sum() >= 5 and lit.sum() >= 25
    np.testing.assert_array_equal(image[shadowed], 0.0)
    expected = albedo.reshape(-1, 3)[texel[lit]] / np.pi * np.sqrt(0.5)
    np.testing.assert_allclose(image[lit], expected, rtol=1e-4)


def test_coverage_is_one_on_lit_cloth_zero_in_shadow_and_partial_at_edges():
    camera = _camera()
    wall = quad([-1.6, 0.0, 3.0], [0.0, 0.0, -6.0], [0.0, 1.0, 0.0])
    light = DirectionalLight([-1.0, 1.0, 0.0], [1.0, 1.0, 1.0])
    scene = Scene(merge_meshes(_floor_quad(), wall), camera, [light])
    _, stats = render_with_stats(scene, LambertianTexture(_checkerboard()), spp=16, seed=0)
    coverage = stats.lit_cloth
    assert coverage.shape == (16, 16) and coverage.dtype == np.float32

    points = _footprints(camera)
    _, inside = _texel_of(points)
    lit = inside.all(-1) & (points[..., 0] > -0.6 + 1e-3).all(-1)
    dark = ~inside.any(-1) | (inside.all(-1) & (points[..., 0] < -0.6 - 1e-3).all(-1))
    assert lit.sum() >= 25 and dark.sum() >= 15
    np.testing.assert_array_equal(coverage[lit], 1.0)
    np.testing.assert_array_equal(coverage[dark], 0.0)
    # The quad's edge crosses pixels: some samples on it, some off it (16 per pixel).
    edge = inside.any(-1) & ~inside.all(-1) & (points[..., 0] > -0.6 + 1e-3).all(-1)
    assert edge.any()
    assert np.all((coverage[edge] > 0) & (coverage[edge] < 1))
    np.testing.assert_array_equal(coverage * 16, np.round(coverage * 16))


@pytest.mark.parametrize(
    "spp, grid", [(1, (1, 1)), (16, (4, 4)), (128, (16, 8)), (7, (7, 1)), (12, (4, 3))]
)
def test_every_spp_is_stratified_one_sample_per_stratum(spp, grid):
    assert strata(spp) == grid
    offsets = subpixel_offsets(np.arange(spp), spp, np.random.default_rng(0).random((spp, 2)))
    cells = np.floor(offsets * np.array(grid)).astype(int)
    assert len({tuple(c) for c in cells}) == spp  # each stratum holds exactly one sample


# ------------------------------------------------------------------ seeds and batches


def _fine_checker_scene(size: int = 16) -> tuple[Scene, LambertianTexture]:
    """Texels much smaller than pixels, so the jitter changes the image."""
    scene = Scene(_floor_quad(tiles=3.0), _camera(size), [DirectionalLight(SUN, [1, 1, 1])])
    return scene, LambertianTexture(_checkerboard(16))


@pytest.mark.parametrize("spp", [3, 4])  # strata 3 x 1 and 2 x 2
def test_same_seed_same_image_other_seed_other_image(spp):
    scene, material = _fine_checker_scene()
    first = render(scene, material, spp=spp, seed=7)
    np.testing.assert_array_equal(render(scene, material, spp=spp, seed=7), first)
    assert not np.array_equal(render(scene, material, spp=spp, seed=8), first)


def test_the_image_does_not_depend_on_the_batch_size():
    scene, material = _fine_checker_scene()
    whole = render(scene, material, spp=4, seed=3)
    np.testing.assert_allclose(
        render(scene, material, spp=4, seed=3, batch_rays=37), whole, rtol=1e-6, atol=1e-7
    )


class _CountingTexture(LambertianTexture):
    def __init__(self, albedo):
        super().__init__(albedo)
        self.batch_sizes = []

    def evaluate(self, texels, directions):
        self.batch_sizes.append(len(texels))
        return super().evaluate(texels, directions)


def test_the_material_is_queried_in_batches_not_per_pixel():
    scene, _ = _fine_checker_scene()
    material = _CountingTexture(_checkerboard(16))
    _, stats = render_with_stats(scene, material, spp=4, seed=0)
    assert material.batch_sizes == [stats.material_queries]  # one call for the whole image
    assert stats.material_calls == 1 and stats.material_queries > 16 * 16

    material = _CountingTexture(_checkerboard(16))
    _, stats = render_with_stats(scene, material, spp=4, seed=0, batch_rays=16 * 16)
    assert 1 <= len(material.batch_sizes) <= 4  # at most one call per sample pass
    assert sum(material.batch_sizes) == stats.material_queries
    assert stats.primary_rays == 16 * 16 * 4 and stats.shadow_rays > 0 and stats.seconds > 0


# ------------------------------------------------------------------------- materials


def _measured(texels: int = 4, seed: int = 0) -> tuple[np.ndarray, MeasuredMaterial]:
    values = np.random.default_rng(seed).random((texels, 6561, 3)).astype(np.float32)
    return values, MeasuredMaterial(values, (2, texels // 2))


def test_measured_material_returns_the_measured_values_at_grid_directions():
    values, material = _measured()
    rng = np.random.default_rng(1)
    texels, columns = rng.integers(0, 4, 300), rng.integers(0, 6561, 300)
    directions = btf_directions()[columns]
    np.testing.assert_array_equal(material.evaluate(texels, directions), values[texels, columns])
    directions[:, 1] += 2 * np.pi  # the same directions, another turn of phi
    np.testing.assert_array_equal(material.evaluate(texels, directions), values[texels, columns])


def test_measured_material_agrees_with_the_product_interpolator_off_the_grid():
    values, material = _measured()
    queries = offgrid_directions(100, seed=2)
    _, linear = ProductInterpolator(btf_directions(), np.arange(6561)).predict(values, queries)
    texels = np.random.default_rng(3).integers(0, 4, 100)
    np.testing.assert_allclose(
        material.evaluate(texels, queries), linear[texels, np.arange(100)], rtol=1e-5, atol=1e-6
    )


def test_measured_material_clamps_grazing_directions_to_the_outer_ring():
    values, material = _measured()
    directions = btf_directions()
    columns = np.flatnonzero(
        np.isclose(directions[:, 0], np.radians(75)) & np.isclose(directions[:, 2], np.radians(75))
    )[:50]
    grazing = directions[columns].copy()
    grazing[:, [0, 2]] = np.radians([85.0, 89.0])
    texels = np.arange(50) % 4
    np.testing.assert_array_equal(material.evaluate(texels, grazing), values[texels, columns])


def _queries(count: int, seed: int) -> np.ndarray:
    """(count, 4) directions over the whole hemisphere and a little below it, phi of any
    turn: grazing ones beyond the grid's 75-degree ring included."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0.0, np.radians(95.0), (count, 2))
    phi = rng.uniform(-7.0, 7.0, (count, 2))
    return np.column_stack([theta[:, 0], phi[:, 0], theta[:, 1], phi[:, 1]])


def test_analytic_material_is_the_generator_at_any_direction():
    from pipeline.btf.synthetic import SyntheticBTF

    fabric = SyntheticBTF(size=12, seed=3)
    truth = AnalyticMaterial(fabric, offset=(2, 3), crop_size=(4, 6))  # not square: rows, cols
    queries = _queries(60, seed=0)
    expected = fabric.evaluate(queries)[:, 2:6, 3:9].reshape(60, 24, 3)  # (q, texel, 3)
    texels = np.tile(np.arange(24), 60)
    found = truth.evaluate(texels, np.repeat(queries, 24, axis=0)).reshape(60, 24, 3)
    np.testing.assert_allclose(found, expected, rtol=1e-5, atol=1e-6)
    # No clamp: beyond the grid the truth is not its value on the 75-degree ring.
    grazing = np.radians([[85.0, 10.0, 20.0, 200.0]])
    clamped = np.column_stack([clamp_to_grid(grazing[:, :2]), grazing[:, 2:]])
    at_grazing = truth.evaluate(np.arange(24), np.repeat(grazing, 24, axis=0))
    np.testing.assert_allclose(
        at_grazing, fabric.evaluate(grazing)[0, 2:6, 3:9].reshape(24, 3), rtol=1e-5, atol=1e-6
    )
    assert not np.allclose(at_grazing, truth.evaluate(np.arange(24), np.repeat(clamped, 24, 0)))


@pytest.mark.parametrize("ext", ["png", "jpg"])
def test_analytic_material_agrees_with_the_measured_data_at_grid_directions(tmp_path, ext):
    """The truth and the reference interpolate the same thing: the generator's values, as
    the built-in dataset writes them (gamma 2.2, 8-bit: PNG, or JPEG q95) and the reader
    decodes them, cropped as the crop stage cuts, at every grid direction pair."""
    from pipeline.btf.synthetic import SyntheticBTF
    from pipeline.btf.synthetic_dataset import write_synthetic_btf
    from pipeline.data.btf import load_btf

    root = write_synthetic_btf(tmp_path / "btf", size=12, seed=1, ext=ext)
    data = load_btf(root)
    images, directions = np.asarray(data.images), np.asarray(data.directions)
    (y0, x0), size = (2, 5), 6
    abrdf = images[:, y0 : y0 + size, x0 : x0 + size].reshape(len(images), -1, 3)
    measured = MeasuredMaterial(abrdf.transpose(1, 0, 2).copy(), (size, size), directions)
    truth = AnalyticMaterial(SyntheticBTF(size=12, seed=1), (y0, x0), (size, size))
    texels = np.tile(np.arange(size * size), len(directions))
    pairs = np.repeat(directions, size * size, axis=0)
    error = truth.evaluate(texels, pairs) - measured.evaluate(texels, pairs)
    rounding = 2.2 * 0.5 / 255  # half an 8-bit step of gamma 2.2, at its steepest
    if ext == "png":  # lossless: only the 8-bit rounding of the encoded value
        assert np.abs(error).max() <= rounding + 1e-6
        # ... which a wrong direction convention (phi mirrored) is far from.
        mirrored = truth.evaluate(texels, pairs * [1, -1, 1, -1]) - measured.evaluate(texels, pairs)
        assert np.abs(mirrored).max() > 10 * rounding
    else:  # JPEG q95 adds its own rounding: the built-in data's distance from its truth
        assert np.sqrt(np.mean(np.square(error))) < 0.012


def test_analytic_material_rejects_a_crop_outside_the_texture():
    from pipeline.btf.synthetic import SyntheticBTF

    with pytest.raises(ValueError, match="does not fit the generator's 12x12"):
        AnalyticMaterial(SyntheticBTF(size=12), offset=(8, 0), crop_size=(6, 6))


def test_beyond_grid_marks_what_the_clamp_moves():
    grid = btf_directions()
    assert not beyond_grid(grid[:, :2]).any() and not beyond_grid(grid[:, 2:]).any()
    queries = _queries(2000, seed=1)[:, :2]
    moved = np.abs(clamp_to_grid(queries)[:, 0] - queries[:, 0]) > 1e-8
    np.testing.assert_array_equal(beyond_grid(queries), moved)
    assert 0 < moved.mean() < 1  # both cases occur


def test_grid_clamped_material_answers_at_the_clamped_directions():
    from pipeline.btf.synthetic import SyntheticBTF

    truth = AnalyticMaterial(SyntheticBTF(size=8), (0, 0), (8, 8))
    queries = _queries(300, seed=2)
    texels = np.arange(300) % 64
    clamped = np.column_stack([clamp_to_grid(queries[:, :2]), clamp_to_grid(queries[:, 2:])])
    np.testing.assert_array_equal(
        GridClamped(truth).evaluate(texels, queries), truth.evaluate(texels, clamped)
    )
    # The measured material clamps by itself: wrapping it changes nothing.
    _, measured = _measured()
    np.testing.assert_array_equal(
        GridClamped(measured).evaluate(texels % 4, queries), measured.evaluate(texels % 4, queries)
    )


def test_beyond_grid_share_is_zero_within_the_grid_and_counts_grazing_light():
    from pipeline.btf.render.stage import beyond_grid_shares

    camera = _camera()  # looking straight down: views within about 25 degrees of the normal
    grazing = np.array([np.sin(np.radians(85.0)), np.cos(np.radians(85.0)), 0.0])
    crops, size = {"dark": [6, 6], "bright": [5, 7]}, 4

    def shares(lights):
        scene = Scene(_floor_quad(), camera, lights)
        image, stats = render_with_stats(scene, BeyondGridIndicator((TEXELS, TEXELS)), 4, 0)
        assert stats.lit_cloth[6:10, 6:10].min() == 1  # the crops are wholly on lit cloth
        return beyond_grid_shares(image, stats.lit_cloth, crops, size)

    within = shares([DirectionalLight(SUN, [1.0, 1.0, 1.0])])
    assert within == {
        "beyond_grid_share": 0.0,
        "beyond_grid_share_dark": 0.0,
        "beyond_grid_share_bright": 0.0,
    }
    # One light within the grid and one grazing, of equal irradiance: half the pairs.
    both = shares(
        [DirectionalLight(SUN, [1.0, 1.0, 1.0]), DirectionalLight(grazing, [1.0, 1.0, 1.0])]
    )
    assert both == pytest.approx({name: 0.5 for name in within})


def _pca(texels: int = 6, components: int = 3, seed: int = 4):
    """A stored float16 PCA and, two ways, the measured values it stands for."""
    rng = np.random.default_rng(seed)
    mean = rng.random(3 * 6561).astype(np.float16)
    basis = (rng.standard_normal((components, 3 * 6561)) * 0.1).astype(np.float16)
    coefficients = rng.standard_normal((texels, components)).astype(np.float16)
    scale = 2.5
    dense = scale * (
        coefficients.astype(np.float64) @ basis.astype(np.float64) + mean.astype(np.float64)
    )
    linear = LinearMaterial(mean, basis, coefficients, (2, texels // 2), scale)
    measured = MeasuredMaterial(dense.reshape(texels, 6561, 3).astype(np.float32), (2, texels // 2))
    return linear, measured, dense.reshape(texels, 6561, 3)


def test_pca_material_is_the_measured_interpolation_of_its_reconstruction():
    linear, measured, dense = _pca()
    rng = np.random.default_rng(5)
    texels, columns = rng.integers(0, 6, 400), rng.integers(0, 6561, 400)
    at_grid = linear.evaluate(texels, btf_directions()[columns])
    np.testing.assert_allclose(at_grid, dense[texels, columns], rtol=1e-5, atol=1e-5)
    queries = offgrid_directions(200, seed=6)
    texels = rng.integers(0, 6, 200)
    np.testing.assert_allclose(
        linear.evaluate(texels, queries), measured.evaluate(texels, queries), rtol=1e-5, atol=1e-5
    )


def test_pca_material_rejects_arrays_that_do_not_fit():
    rng = np.random.default_rng(0)
    mean, basis = rng.random(3 * 6561), rng.random((2, 3 * 6561))
    with pytest.raises(ValueError, match="coefficients have shape"):
        LinearMaterial(mean, basis, rng.random((5, 2)), (2, 3), 1.0)
    with pytest.raises(ValueError, match="N = 6561"):
        LinearMaterial(mean[:-3], basis, rng.random((6, 2)), (2, 3), 1.0)


def test_lambertian_texture_value_is_albedo_over_pi_times_cosine():
    albedo = _checkerboard()
    directions = np.array([[np.pi / 3, 1.0, 0.2, 2.0], [2.0, 0.0, 0.0, 0.0]])
    values = LambertianTexture(albedo).evaluate(np.array([5, 6]), directions)
    np.testing.assert_allclose(values[0], albedo[1, 1] / np.pi * 0.5, rtol=1e-6)
    np.testing.assert_array_equal(values[1], 0.0)  # light below the surface


def test_compressed_material_answers_what_the_compressed_file_answers(tmp_path):
    torch = pytest.importorskip("torch")
    from pipeline.btf.compressed import load_compressed, write_compressed
    from pipeline.btf.model import Decoder
    from pipeline.btf.render.surfaces import CompressedMaterial

    torch.manual_seed(0)
    latents = np.random.default_rng(0).normal(size=(6, 8)).astype(np.float32)
    path = write_compressed(
        tmp_path / "btf.safetensors",
        Decoder(hidden=8, layers=1).eval(),
        latents,
        2.0,
        crop_size=(2, 3),
        method="neural_btf",
        dataset="synthetic",
    )
    material = CompressedMaterial(load_compressed(path))
    assert material.crop_size == (2, 3)
    texels, directions = np.arange(6), offgrid_directions(6, seed=4)
    np.testing.assert_array_equal(
        material.evaluate(texels, directions), load_compressed(path).query_pairs(texels, directions)
    )
    image, stats = render_with_stats(default_scene(12, 12, resolution=8), material, 1, seed=0)
    assert np.isfinite(image).all() and (image >= 0).all() and stats.material_calls == 1


# ---------------------------------------------------------------------------- scene


def test_folded_sheet_frames_are_orthonormal_and_follow_the_geometry_and_uv():
    mesh = folded_sheet(16, folds=3, amplitude=0.15, seed=4)
    n, t, b = mesh.normals, mesh.tangents, mesh.bitangents
    for vectors in (n, t, b):
        np.testing.assert_allclose(np.linalg.norm(vectors, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("ij,ij->i", n, t), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.cross(t, b), n, atol=1e-12)  # right-handed (t, b, n)

    face = mesh.face_normals()
    corner_normals = n[mesh.triangles]  # (F, 3, 3)
    assert (np.einsum("fkd,fd->fk", corner_normals, face) > 0).all()
    # Per triangle, dP/du and dP/dv from its uv: tangent along +u, bitangent along +v.
    p = mesh.vertices.astype(np.float64)[mesh.triangles]
    uv = mesh.uv[mesh.triangles]
    edges = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]], axis=1)  # (F, 2, 3)
    duv = np.stack([uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]], axis=1)  # (F, 2, 2)
    dp_duv = np.linalg.solve(duv, edges)  # rows dP/du, dP/dv
    centre_t, centre_b = t[mesh.triangles].mean(1), b[mesh.triangles].mean(1)
    assert (np.einsum("fd,fd->f", centre_t, dp_duv[:, 0]) > 0).all()
    assert (np.einsum("fd,fd->f", centre_b, dp_duv[:, 1]) > 0).all()


def test_folded_sheet_is_deterministic_and_spans_the_tiles():
    first, second = folded_sheet(8, seed=5), folded_sheet(8, seed=5)
    np.testing.assert_array_equal(first.vertices, second.vertices)
    assert not np.array_equal(folded_sheet(8, seed=6).vertices, first.vertices)
    np.testing.assert_allclose([first.uv.min(), first.uv.max()], [0.0, 4.0])


def test_default_scene_renders_a_finite_non_negative_image():
    scene = default_scene(24, 24, resolution=24)
    rows, cols = np.indices((8, 8))
    albedo = np.stack([0.3 + 0.05 * rows, 0.5 + 0.0 * cols, 0.2 + 0.05 * cols], axis=-1)
    image, stats = render_with_stats(scene, LambertianTexture(albedo), spp=2, seed=0)
    assert image.shape == (24, 24, 3)
    assert np.isfinite(image).all() and (image >= 0).all()
    assert (image.sum(-1) > 0).mean() > 0.5 and stats.material_queries > 0
    for lights in ("directional", "both"):
        image = render(
            default_scene(24, 24, lights=lights, resolution=24),
            LambertianTexture(albedo),
            spp=1,
            seed=0,
        )
        assert np.isfinite(image).all() and image.max() > 0


# ----------------------------------------------------------------------- bad inputs


def test_render_names_a_bad_sample_count():
    scene, material = _fine_checker_scene()
    with pytest.raises(ValueError, match="spp=0"):
        render(scene, material, spp=0, seed=0)


def test_render_names_a_bad_batch_size():
    scene, material = _fine_checker_scene()
    with pytest.raises(ValueError, match="batch_rays=0"):
        render(scene, material, spp=1, seed=0, batch_rays=0)


def test_material_rejects_a_texel_outside_its_crop():
    with pytest.raises(ValueError, match="texel 16 is outside"):
        LambertianTexture(_checkerboard()).evaluate(np.array([16]), np.zeros((1, 4)))


def test_measured_material_rejects_values_that_do_not_fit_the_crop():
    with pytest.raises(ValueError, match="values has 4 texels"):
        MeasuredMaterial(np.zeros((4, 6561, 3), dtype=np.float32), (3, 3))


def test_folded_sheet_rejects_a_bad_resolution():
    with pytest.raises(ValueError, match="resolution=0"):
        folded_sheet(0)


def test_default_scene_rejects_an_unknown_light_setting():
    with pytest.raises(ValueError, match="lights='spot'"):
        default_scene(8, 8, lights="spot")
