"""Method A on any direction set: a product of light and view sets that is not the UBO2003
81-grid (here Fibonacci spirals), through the direction helpers, the interpolants, the
renderer's measured material and its grid edge, the built-in BTF's writer and the whole
chain (train, evaluate, held-out lights, Fig. 7, render, tables)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from helpers import WIRING_STEPS, compose_config
from mlflow.tracking import MlflowClient
from omegaconf import OmegaConf

from pipeline.btf.interpolation import (
    DirectionHull,
    ProductInterpolator,
    heldout_light_indices,
    offgrid_directions,
    offgrid_max_theta,
    training_directions,
)
from pipeline.btf.render.surfaces import (
    AnalyticMaterial,
    BeyondGridIndicator,
    GridClamped,
    MeasuredMaterial,
    direction_hulls,
)
from pipeline.btf.stereographic import stereographic
from pipeline.btf.synthetic import SyntheticBTF
from pipeline.btf.synthetic_dataset import write_synthetic_btf
from pipeline.core.errors import ConfigError, DataError
from pipeline.data.directions import (
    btf_directions,
    direction_sets,
    fibonacci_hemisphere,
    grid_81,
    product_directions,
)

N_LIGHTS, N_VIEWS = 37, 29
FIBONACCI = (
    "dataset.format=ubo2014",
    "dataset.synthetic.ext=btf",
    "dataset.views=null",
    "dataset.synthetic.directions=fibonacci",
    f"dataset.synthetic.n_lights={N_LIGHTS}",
    f"dataset.synthetic.n_views={N_VIEWS}",
)


def _fibonacci_pairs(n_lights: int = N_LIGHTS, n_views: int = N_VIEWS) -> np.ndarray:
    return product_directions(fibonacci_hemisphere(n_lights), fibonacci_hemisphere(n_views))


def _holdout(count: int, seed: int = 0):
    return OmegaConf.create({"btf": {"interpolation": {"holdout_lights": count, "seed": seed}}})


# ------------------------------------------------------------------- direction sets


def test_direction_sets_find_the_81_grid_in_canonical_order_whatever_the_pair_order():
    directions = btf_directions()
    shuffled = np.random.default_rng(0).permutation(len(directions))
    sets = direction_sets(directions[shuffled])
    np.testing.assert_array_equal(sets.lights, grid_81())
    np.testing.assert_array_equal(sets.views, grid_81())
    index = np.arange(6561)[shuffled]  # row v * 81 + l of the view-major order
    np.testing.assert_array_equal(sets.light_of, index % 81)
    np.testing.assert_array_equal(sets.view_of, index // 81)
    assert sets.is_product() and not direction_sets(directions[1:]).is_product()


def test_direction_sets_take_another_turn_of_phi_and_any_phi_at_the_normal_as_one():
    pairs = np.array(
        [
            [0.0, 0.0, 0.5, 1.0],
            [0.0, 2.0, 0.5, 1.0 + 2 * np.pi],  # the normal at another phi
            [0.3, 2 * np.pi - 1e-12, 0.5, 1.0],  # phi just below a whole turn
            [0.3, 0.0, 0.5, -2 * np.pi + 1.0],
        ]
    )
    sets = direction_sets(pairs)
    assert (len(sets.lights), len(sets.views)) == (2, 1)
    np.testing.assert_array_equal(sets.light_of, [0, 0, 1, 1])
    with pytest.raises(DataError, match="shape"):
        direction_sets(pairs[:, :3])


def test_fibonacci_sets_are_even_in_solid_angle_within_their_cap():
    angles = fibonacci_hemisphere(200, 80.0)
    cos_theta = np.cos(angles[:, 0])
    # Equal solid angle per point: cos(theta) steps evenly from 1 to cos(80 deg).
    np.testing.assert_allclose(np.diff(cos_theta), -(1 - np.cos(np.radians(80))) / 200)
    assert np.degrees(angles[:, 0]).max() < 80 and len(np.unique(angles, axis=0)) == 200
    with pytest.raises(ConfigError, match="count >= 3"):
        fibonacci_hemisphere(2)


# ------------------------------------------------------------------- held-out lights


@pytest.mark.parametrize("count, seed", [(4, 0), (10, 3), (79, 1)])
def test_heldout_lights_on_the_81_grid_are_the_ones_drawn_before(count, seed):
    """The rule for any set draws, on the 81-grid, the lights the grid-only rule drew (the
    train stage's key holds them: cached models stay valid)."""
    before = np.sort(
        np.random.default_rng(seed).choice(np.arange(1, 81), size=count, replace=False)
    )
    np.testing.assert_array_equal(heldout_light_indices(_holdout(count, seed), grid_81()), before)


def test_heldout_lights_of_any_set_spare_the_light_nearest_the_normal():
    sets = direction_sets(_fibonacci_pairs())
    heldout = heldout_light_indices(_holdout(30), sets.lights)
    assert len(np.unique(heldout)) == 30 and heldout.max() < N_LIGHTS
    assert int(np.argmin(sets.lights[:, 0])) not in heldout
    train = training_directions(_fibonacci_pairs(), heldout)
    assert len(train) == (N_LIGHTS - 30) * N_VIEWS
    assert not np.isin(sets.light_of[train], heldout).any()
    with pytest.raises(ConfigError, match="holdout_lights=36 leaves too few of the data's 37"):
        heldout_light_indices(_holdout(36), sets.lights)


# ------------------------------------------------------------------- the grid's edge


def test_the_81_grids_hull_is_the_polygon_of_its_75_degree_ring():
    """Cross-check: the hull computed from the points against the closed form of the
    regular 24-gon that the renderer used before any direction set was allowed."""
    phi = np.random.default_rng(0).uniform(-7.0, 7.0, 20000)
    step = 2 * np.pi / 24
    radius = np.tan(np.radians(75.0) / 2) * np.cos(step / 2) / np.cos(np.mod(phi, step) - step / 2)
    hull = DirectionHull(grid_81())
    np.testing.assert_allclose(hull.edge_theta(phi), 2 * np.arctan(radius), rtol=0, atol=1e-12)
    assert np.degrees(hull.inscribed_theta) == pytest.approx(
        np.degrees(2 * np.arctan(np.tan(np.radians(37.5)) * np.cos(step / 2)))
    )
    assert offgrid_max_theta(btf_directions()) == np.radians(70.0)  # as before


def test_a_fibonacci_sets_hull_clamps_every_direction_into_its_triangulation():
    from scipy.spatial import Delaunay

    lights = fibonacci_hemisphere(N_LIGHTS)
    hull = DirectionHull(lights)
    assert not hull.beyond(lights).any()  # the set's own directions are inside
    rng = np.random.default_rng(1)
    queries = np.column_stack([rng.uniform(0, np.radians(95), 5000), rng.uniform(-7, 7, 5000)])
    clamped = hull.clamp(queries)
    moved = np.abs(clamped[:, 0] - queries[:, 0]) > 1e-8
    np.testing.assert_array_equal(hull.beyond(queries), moved)
    assert 0.1 < moved.mean() < 0.9
    np.testing.assert_array_equal(clamped[:, 1], queries[:, 1])  # phi kept
    triangles = Delaunay(stereographic(*lights.T))
    assert (triangles.find_simplex(stereographic(*clamped.T)) >= 0).all()
    # Just beyond the clamp there is no triangle: the clamp goes no further than it must.
    outside = clamped[moved] + [1e-6, 0.0]
    assert (triangles.find_simplex(stereographic(*outside.T)) < 0).all()
    # Every direction up to the inscribed theta is inside, whatever its phi.
    ring = np.column_stack(
        [np.full(720, hull.inscribed_theta - 1e-9), np.linspace(0, 2 * np.pi, 720)]
    )
    assert not hull.beyond(ring).any()


def test_a_set_that_does_not_surround_the_normal_has_no_hull_to_clamp_onto():
    one_side = np.radians([[30.0, 0.0], [60.0, 20.0], [45.0, 40.0]])
    with pytest.raises(DataError, match="do not surround the normal"):
        DirectionHull(one_side)
    with pytest.raises(DataError, match="span no polygon"):
        DirectionHull(np.radians([[30.0, 0.0], [60.0, 0.0]]))


# ------------------------------------------------------------------- interpolation


def test_the_product_interpolator_refuses_pairs_that_are_not_a_product():
    pairs = _fibonacci_pairs(5, 4)
    with pytest.raises(DataError, match="1 of the 5 x 4 .* pairs are not in the data"):
        ProductInterpolator(pairs, np.arange(1, len(pairs)))


def test_linear_interpolation_is_exact_for_a_field_bilinear_in_light_and_view():
    """On any product set the linear interpolant holds every field a(l) b(v) + c(l) + d(v)
    with a, b, c, d linear in the stereographic coordinates (products of barycentric weights
    sum to 1 and reproduce each factor): a wrong triangle, weight or column breaks it."""
    pairs = _fibonacci_pairs()

    def field(directions):
        light = stereographic(directions[:, 0], directions[:, 1]) @ [0.4, -0.2]
        view = stereographic(directions[:, 2], directions[:, 3]) @ [-0.1, 0.3]
        value = (0.5 + light) * (0.7 + view) + 0.2 * light - 0.1 * view
        return np.repeat(value[None, :, None], 3, axis=2).astype(np.float32)

    inside = min(hull.inscribed_theta for hull in direction_hulls(pairs))  # of both sets
    queries = offgrid_directions(300, seed=2, max_theta=inside)
    nearest, linear = ProductInterpolator(pairs, np.arange(len(pairs))).predict(
        field(pairs), queries
    )
    np.testing.assert_allclose(linear, field(queries), atol=1e-5)
    assert np.abs(nearest - field(queries)).max() > 1e-2


def _measured_fabric(pairs: np.ndarray, fabric: SyntheticBTF) -> MeasuredMaterial:
    """The fabric's top-left 2 x 2 texels at ``pairs``, as a measured material."""
    values = fabric.evaluate(pairs)[:, :2, :2].reshape(len(pairs), 4, 3)
    return MeasuredMaterial(values.transpose(1, 0, 2).copy(), (2, 2), pairs)


def test_measured_interpolation_on_a_fibonacci_set_is_the_data_there_and_near_the_truth():
    """At the data's own directions the measured material returns the data bit for bit;
    between them it approaches the analytic truth as piecewise-linear interpolation does.

    The tolerances: (1) 81 x 81 Fibonacci directions interpolate the fabric within 1.5 x
    the error of the UBO2003 grid's 81 x 81 (the renders' accepted reference), the sets
    having as many samples over a similar cap; (2) halving the spacing (4 x the lights and
    4 x the views) divides the error by at least 2 (piecewise-linear interpolation of a
    smooth function: by 4; the fabric's highlights and its clip at 1 are not smooth);
    (3) interpolation beats the nearest sample."""
    fabric = SyntheticBTF(size=8, seed=0)
    pairs = _fibonacci_pairs()
    material = _measured_fabric(pairs, fabric)
    rng = np.random.default_rng(3)
    texels = rng.integers(0, 4, len(pairs))
    pixel = np.array([0, 1, 8, 9])  # the crop's texels in the 8 x 8 texture
    np.testing.assert_array_equal(
        material.evaluate(texels, pairs), material.values[texels, np.arange(len(pairs))]
    )

    queries = offgrid_directions(1500, seed=4, max_theta=np.radians(60.0))
    texels = rng.integers(0, 4, len(queries))
    truth = fabric.evaluate_pairs(pixel[texels], queries)

    def error(light_count, view_count):
        found = _measured_fabric(_fibonacci_pairs(light_count, view_count), fabric)
        return float(np.sqrt(np.mean(np.square(found.evaluate(texels, queries) - truth))))

    grid = float(
        np.sqrt(
            np.mean(
                np.square(
                    _measured_fabric(btf_directions(), fabric).evaluate(texels, queries) - truth
                )
            )
        )
    )
    assert error(81, 81) < 1.5 * grid
    coarse = error(N_LIGHTS, N_VIEWS)
    assert error(4 * N_LIGHTS, 4 * N_VIEWS) < coarse / 2
    nearest, _ = ProductInterpolator(pairs, np.arange(len(pairs))).predict(material.values, queries)
    nearest_error = np.sqrt(np.mean(np.square(nearest[texels, np.arange(len(queries))] - truth)))
    assert coarse < 0.6 * nearest_error


def test_one_view_is_interpolated_over_its_lights_and_takes_that_view_for_every_query():
    """One view of 37 lights (``dataset.views=[[0, 0]]``): the views span no polygon, so
    every query takes the one view, unclamped, as ProductInterpolator's baselines do; the
    lights are interpolated as on any set. Two computations of the same values agree."""
    lights = product_directions(fibonacci_hemisphere(N_LIGHTS), np.zeros((1, 2)))
    material = _measured_fabric(lights, SyntheticBTF(size=8, seed=0))
    inside = DirectionHull(lights[:, :2]).inscribed_theta
    queries = offgrid_directions(200, seed=5, max_theta=inside)  # views anywhere below it
    texels = np.random.default_rng(6).integers(0, 4, len(queries))
    _, linear = ProductInterpolator(lights, np.arange(len(lights))).predict(
        material.values, queries
    )
    np.testing.assert_allclose(
        material.evaluate(texels, queries), linear[texels, np.arange(len(queries))], atol=1e-6
    )
    at = texels[: len(lights)]
    np.testing.assert_array_equal(
        material.evaluate(at, lights), material.values[at, np.arange(len(lights))]
    )


def test_the_grid_edge_of_the_render_is_the_datas_own():
    """Clamp and indicator follow the data's sets, not the 75-degree ring: a view near the
    edge of a Fibonacci set that reaches 80 degrees is inside it, beyond the UBO2003 grid."""
    pairs = _fibonacci_pairs()
    light_hull, view_hull = direction_hulls(pairs)
    truth = AnalyticMaterial(SyntheticBTF(size=8), (0, 0), (8, 8))
    rng = np.random.default_rng(5)
    queries = np.column_stack(
        [rng.uniform(0, np.radians(95), (400, 2)), rng.uniform(-7, 7, (400, 2))]
    )[:, [0, 2, 1, 3]]
    texels = np.arange(400) % 64
    clamped = np.column_stack([light_hull.clamp(queries[:, :2]), view_hull.clamp(queries[:, 2:])])
    np.testing.assert_array_equal(
        GridClamped(truth, pairs).evaluate(texels, queries), truth.evaluate(texels, clamped)
    )
    phi = np.linspace(0, 2 * np.pi, 3600)
    widest = int(np.argmax(view_hull.edge_theta(phi)))
    steep = view_hull.edge_theta(phi[widest]) - np.radians(0.2)
    assert steep > np.radians(75.5)
    steep_view = np.array([[0.2, 1.0, steep, phi[widest]]])
    assert BeyondGridIndicator((8, 8), pairs).evaluate(np.array([0]), steep_view)[0, 0] == 0
    assert BeyondGridIndicator((8, 8)).evaluate(np.array([0]), steep_view)[0, 0] == 1
    # The measured material clamps onto the same edges by itself.
    measured = _measured_fabric(pairs, SyntheticBTF(size=8))
    np.testing.assert_array_equal(
        GridClamped(measured, pairs).evaluate(texels % 4, queries),
        measured.evaluate(texels % 4, queries),
    )


# ------------------------------------------------------------------- the built-in BTF


@pytest.mark.parametrize("size", [8, 4])  # 35 directions: fewer than 64 texels, more than 16
def test_a_fibonacci_built_in_btf_round_trips_the_ubo2014_reader_exactly(tmp_path, size):
    from pipeline.data.ubo2014 import load_ubo2014

    path = write_synthetic_btf(
        tmp_path / "btf",
        size=size,
        format="ubo2014",
        ext="btf",
        directions="fibonacci",
        n_lights=7,
        n_views=5,
    )
    assert path.name == "synthetic.btf" and path.parent == tmp_path / "btf"
    data = load_ubo2014(path)
    sets = direction_sets(data.directions)
    assert (len(sets.lights), len(sets.views), sets.is_product()) == (7, 5, True)
    # The angles as the file stores them (float32), and the fabric's values there exactly.
    np.testing.assert_array_equal(
        sets.lights, fibonacci_hemisphere(7).astype(np.float32).astype(np.float64)
    )
    np.testing.assert_array_equal(data.images, SyntheticBTF(size=size).evaluate(data.directions))
    mtime = path.stat().st_mtime_ns
    assert (
        write_synthetic_btf(
            tmp_path / "btf",
            size=size,
            format="ubo2014",
            ext="btf",
            directions="fibonacci",
            n_lights=7,
            n_views=5,
        )
        == path
    )
    assert path.stat().st_mtime_ns == mtime  # found, not written again


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (
            {"directions": "fibonacci", "n_lights": 7, "n_views": 5},
            "cannot be written in the ubo2003 layout",
        ),
        (
            {"format": "ubo2014", "ext": "btf", "directions": "fibonacci", "n_lights": 7},
            "needs dataset.synthetic.n_views",
        ),
        ({"n_views": 5}, "n_views=5 goes with directions=fibonacci only"),
        ({"directions": "spiral"}, "directions='spiral' is not one of"),
        ({"format": "ubo2014", "ext": "btf", "views": [[0, 0]]}, "writes every view"),
    ],
)
def test_the_writer_refuses_a_direction_set_its_layout_cannot_hold(tmp_path, kwargs, match):
    with pytest.raises(ConfigError, match=match):
        write_synthetic_btf(tmp_path / "btf", size=4, **kwargs)


def test_the_default_direction_set_keeps_the_dataset_folder_and_the_cache_keys():
    """Datasets and entries made before the setting existed stay in use: at its default
    the dataset folder is named as before, and the evaluate stage's key holds no trace."""
    from pipeline.btf.runner import evaluated_dataset
    from pipeline.btf.stages import synthetic_folder
    from pipeline.core.cache import canonical_json
    from pipeline.core.stage import plain_settings

    cfg = compose_config("experiment=smoke")
    gen = plain_settings(cfg.dataset.synthetic)
    old = {
        key: value for key, value in gen.items() if key not in ("directions", "n_lights", "n_views")
    }
    named = {"gen": old, "views": plain_settings(cfg.dataset.views)}
    tag = hashlib.sha256(canonical_json(named).encode()).hexdigest()[:10]
    assert synthetic_folder(cfg).name == f"synthetic_btf-ubo2003-jpg-{tag}"
    assert "directions" not in evaluated_dataset(cfg.dataset)["synthetic"]
    fibonacci = compose_config("experiment=smoke", *FIBONACCI)
    assert synthetic_folder(fibonacci).name.startswith("synthetic_btf-ubo2014-btf-")
    assert evaluated_dataset(fibonacci.dataset)["synthetic"]["n_lights"] == N_LIGHTS


# ------------------------------------------------------------------- the whole chain


def _only_run(runs_dir: Path, experiment: str):
    from pipeline.core.store import tracking_uri

    client = MlflowClient(tracking_uri(runs_dir))
    (run,) = client.search_runs([client.get_experiment_by_name(experiment).experiment_id])
    return client, run


def test_the_whole_chain_runs_on_a_fibonacci_set(tmp_path, mlflow_template):
    """Train, evaluate (Table 1's original bytes with N = 37 x 29), held-out lights,
    off-grid queries, Fig. 7 at the nearest measured pairs, the render and the tables, on
    the built-in BTF written as a lossless UBO2014 file."""
    from pipeline.app import run_job
    from pipeline.core.cache import StageCache
    from pipeline.tables import build_tables, default_settings

    runs_dir = tmp_path / "runs"
    mlflow_template(runs_dir)
    run_job(
        compose_config(
            "experiment=render_smoke",
            f"paths.runs={runs_dir}",
            "model=neural_btf",
            f"train.max_steps={WIRING_STEPS}",
            *FIBONACCI,
        )
    )
    client, run = _only_run(runs_dir, "render_smoke")
    metrics = run.data.metrics
    n, m = N_LIGHTS * N_VIEWS, 12 * 12
    assert (metrics["n_directions"], metrics["n_texels"]) == (n, m)
    assert metrics["bytes_original"] == m * n * 3 * 4
    assert metrics["rmse_data_vs_truth"] == 0  # the layout is lossless
    for name in (
        "rmse",
        "rmse_train_dirs",
        "rmse_heldout_model",
        "rmse_heldout_linear",
        "rmse_heldout_nearest",
        "rmse_offgrid_model",
        "rmse_offgrid_linear",
        "render_truth_rmse_cloth",
        "render_reference_truth_rmse_cloth",
    ):
        assert np.isfinite(metrics[name]), name
    # The reference interpolates lossless data: near the truth, unlike a model of a few steps.
    assert metrics["render_reference_truth_rmse_cloth"] < metrics["render_truth_rmse_cloth"]

    cache = StageCache(runs_dir / "cache")
    crop = cache.lookup("crop", run.data.tags["cache.crop"])
    sets = direction_sets(crop.array("directions", mmap=False))
    assert (len(sets.lights), len(sets.views), sets.is_product()) == (N_LIGHTS, N_VIEWS, True)
    trained = cache.lookup("train", run.data.tags["cache.train"])
    heldout = trained.manifest["settings"]["heldout_lights"]
    assert len(heldout) == 4 and max(heldout) < N_LIGHTS
    assert int(np.argmin(sets.lights[:, 0])) not in heldout

    # Fig. 7: each pair asked for is drawn at the measured pair nearest to it.
    figures = Path(client.download_artifacts(run.info.run_id, "figures", str(tmp_path)))
    (listing,) = figures.glob("fig7_*_pairs.json")
    for row in json.loads(listing.read_text()):
        asked, used = np.radians(row["asked"]), np.radians(row["used"])
        np.testing.assert_allclose(used, crop.array("directions", mmap=False)[row["column"]])
        light = np.argmax(
            np.cos(sets.lights[:, 0]) * np.cos(asked[0])
            + np.sin(sets.lights[:, 0]) * np.sin(asked[0]) * np.cos(sets.lights[:, 1] - asked[1])
        )
        np.testing.assert_array_equal(used[:2], sets.lights[light])
        assert not np.allclose(used, asked)  # the paper's pairs are not in a Fibonacci set

    settings = default_settings()
    settings.experiments = ["render_smoke"]
    out = build_tables(runs_dir, settings)
    interpolation = (out / "interpolation.md").read_text()
    assert f"12²×{n}" in interpolation and (out / "table3_render_dark.md").is_file()
    assert list(out.glob("fig7_*.png"))


def test_measured_data_on_a_fibonacci_set_renders_every_model_clamped_to_its_edge(
    tmp_path, mlflow_template
):
    """A UBO2014 file without a generator behind it (no truth): the PCA baseline and the
    reference interpolate the file's own directions, every model is clamped onto their
    edge, and the share of samples beyond it is reported."""
    from pipeline.app import run_job
    from pipeline.core.cache import StageCache

    runs_dir = tmp_path / "runs"
    mlflow_template(runs_dir)
    path = write_synthetic_btf(
        tmp_path / "carpet",
        size=16,
        format="ubo2014",
        ext="btf",
        directions="fibonacci",
        n_lights=N_LIGHTS,
        n_views=N_VIEWS,
    )
    run_job(
        compose_config(
            "experiment=render_smoke",
            f"paths.runs={runs_dir}",
            "dataset=ubo2014",
            f"dataset.root={path}",
            "model=pca",
            "model.n_components=2",
        )
    )
    _, run = _only_run(runs_dir, "render_smoke")
    metrics = run.data.metrics
    assert metrics["n_directions"] == N_LIGHTS * N_VIEWS
    assert np.isfinite(metrics["render_rmse_cloth"]) and "render_truth_rmse_cloth" not in metrics
    assert 0 <= metrics["render_beyond_grid_share"] <= 1
    entry = StageCache(runs_dir / "cache").lookup("render", run.data.tags["cache.render"])
    assert entry.manifest["summary"]["beyond_grid"] == "clamped to the grid"
