"""The interpolants the Neural BTF is compared with at unseen directions."""

import numpy as np
from omegaconf import OmegaConf

from pipeline.btf.interpolation import (
    ProductInterpolator,
    heldout_light_indices,
    offgrid_directions,
    training_directions,
)
from pipeline.btf.stereographic import stereographic
from pipeline.data.directions import btf_directions, grid_81


def _linear_field(directions):
    """A field linear in the stereographic coordinates of light and view: (1, n, 3)."""
    light = stereographic(directions[:, 0], directions[:, 1])
    view = stereographic(directions[:, 2], directions[:, 3])
    value = 0.3 + light @ [0.2, -0.1] + view @ [0.05, 0.15]
    return np.repeat(value[None, :, None], 3, axis=2).astype(np.float32)


def test_linear_interpolation_is_exact_for_a_field_linear_in_each_direction():
    directions = btf_directions(
        views=[
            (0, 0),
            (15, 0),
            (15, 60),
            (15, 120),
            (15, 180),
            (15, 240),
            (15, 300),
            (30, 0),
            (30, 30),
        ]
    )
    columns = np.arange(len(directions))
    interp = ProductInterpolator(directions, columns)
    queries = offgrid_directions(50, seed=1)
    queries[:, 2] = np.minimum(
        queries[:, 2], np.radians(12.0)
    )  # inside the hexagon of 15-degree views
    nearest, linear = interp.predict(_linear_field(directions), queries)
    np.testing.assert_allclose(linear, _linear_field(queries), atol=1e-5)
    assert np.abs(nearest - _linear_field(queries)).max() > 1e-3  # nearest is not exact


def test_interpolants_return_the_measured_values_at_measured_directions():
    directions = btf_directions(views=[(0, 0), (15, 0), (15, 60), (15, 120)])
    abrdf = np.random.default_rng(0).random((5, len(directions), 3)).astype(np.float32)
    interp = ProductInterpolator(directions, np.arange(len(directions)))
    nearest, linear = interp.predict(abrdf, directions[::7])
    np.testing.assert_allclose(nearest, abrdf[:, ::7], atol=1e-6)
    np.testing.assert_allclose(linear, abrdf[:, ::7], atol=1e-5)


def test_heldout_lights_are_removed_from_training_for_every_view():
    cfg = OmegaConf.create({"btf": {"interpolation": {"holdout_lights": 5, "seed": 0}}})
    heldout = heldout_light_indices(cfg, grid_81())
    assert len(heldout) == 5 and 0 not in heldout
    directions = btf_directions(views=[(0, 0), (30, 90)])
    train = training_directions(directions, heldout)
    assert len(train) == 2 * (81 - 5)


def test_the_held_out_rmse_in_blocks_equals_the_rmse_at_once():
    """A block of texels at a time (the memory of a whole UBO2014 material's evaluation)
    gives the RMSE of all texels at once."""
    from pipeline.btf.interpolation import ProductInterpolator, heldout_rmse, training_directions

    rng = np.random.default_rng(0)
    angles = np.radians([[0, 0], [30, 0], [30, 120], [30, 240], [60, 60], [60, 180], [60, 300]])
    directions = np.array([[*light, *view] for view in angles for light in angles])
    abrdf = rng.random((37, len(directions), 3)).astype(np.float32)
    heldout = np.array([2])
    train = training_directions(directions, heldout)
    test = np.setdiff1d(np.arange(len(directions)), train)
    interp = ProductInterpolator(directions, train)
    alpha = np.float32(0.7)
    nearest, linear = interp.predict(abrdf, directions[test])
    target = abrdf[:, test] / alpha
    want = [
        np.sqrt(np.mean(np.square(p / alpha - target, dtype=np.float64))) for p in (nearest, linear)
    ]
    for block_bytes in (1, 5 * len(directions) * 12, 1 << 30):  # 1 texel, 5 texels, all
        got = heldout_rmse(interp, abrdf, directions[test], test, alpha, block_bytes=block_bytes)
        np.testing.assert_allclose(got, want, rtol=1e-12)
