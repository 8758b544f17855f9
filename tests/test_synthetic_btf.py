"""The procedural woven-fabric BTF and its writer."""

import json

import numpy as np
import pytest

import pipeline.btf.synthetic_dataset as synthetic_dataset
from pipeline.btf.materials import GAP, MATERIALS, WARP, WEFT
from pipeline.btf.synthetic import SyntheticBTF, material_sheet
from pipeline.btf.synthetic_dataset import write_synthetic_btf
from pipeline.btf.synthetic_shading import channel_weights
from pipeline.core.errors import ConfigError, DataError
from pipeline.data.btf import load_btf
from pipeline.data.directions import btf_directions, grid_81_degrees, parse_ubo2003_file_name
from pipeline.data.images import (
    gamma_encode,
    linear_srgb_to_xyz,
    quantize_8bit,
    read_exr_channels,
    read_image_8bit,
    srgb_oetf,
)

SIZE = 8
VIEWS = [(0, 0), (45, 40)]


def random_directions(n, seed=0):
    """(n, 4) directions anywhere on the upper hemisphere, mostly off the grid."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0, np.deg2rad(85), size=(n, 2))
    phi = rng.uniform(0, 2 * np.pi, size=(n, 2))
    return np.stack([theta[:, 0], phi[:, 0], theta[:, 1], phi[:, 1]], axis=1)


def test_evaluate_returns_float32_images_in_unit_range():
    values = SyntheticBTF(size=16, seed=0).evaluate(btf_directions([(30, 30)]))
    assert values.shape == (81, 16, 16, 3)
    assert values.dtype == np.float32
    assert values.min() >= 0.0 and values.max() <= 1.0
    assert values.max() > 0.1  # not black


def test_evaluate_off_grid_is_finite_and_continuous():
    fabric = SyntheticBTF(size=16, seed=0)
    directions = random_directions(50)
    values = fabric.evaluate(directions)
    assert np.isfinite(values).all() and values.min() >= 0 and values.max() <= 1
    # A 0.1° nudge changes the image only a little: the model is smooth in direction.
    nudged = fabric.evaluate(directions + np.deg2rad(0.1))
    assert np.abs(nudged - values).max() < 0.05


def test_evaluate_matches_itself_across_chunks():
    """Many directions are evaluated in chunks; the chunking must not change values."""
    fabric = SyntheticBTF(size=8, seed=1)
    directions = random_directions(20000, seed=2)  # more than one chunk at 8 × 8
    values = fabric.evaluate(directions)
    np.testing.assert_array_equal(values[-5:], fabric.evaluate(directions[-5:]))


def test_below_the_horizon_is_black():
    directions = np.deg2rad([[100.0, 0.0, 30.0, 0.0], [30.0, 0.0, 95.0, 0.0]])
    assert (SyntheticBTF(size=8).evaluate(directions) == 0).all()


def test_same_seed_same_texture_other_seed_other_texture():
    directions = btf_directions([(0, 0)])
    first = SyntheticBTF(size=16, seed=4).evaluate(directions)
    np.testing.assert_array_equal(first, SyntheticBTF(size=16, seed=4).evaluate(directions))
    assert not np.array_equal(first, SyntheticBTF(size=16, seed=5).evaluate(directions))


def test_material_has_distinct_but_varied_families():
    fabric = SyntheticBTF(size=32, seed=0)
    labels = fabric.material_labels.ravel()
    assert set(np.unique(labels)) == {WARP, WEFT, GAP}
    abrdfs = fabric.evaluate(btf_directions([(0, 0), (60, 90)])).reshape(162, -1, 3)
    abrdfs = abrdfs.transpose(1, 0, 2).reshape(labels.size, -1)  # (texels, directions·3)
    means = {label: abrdfs[labels == label].mean(axis=0) for label in (WARP, WEFT, GAP)}
    spread = {label: abrdfs[labels == label].std(axis=0).mean() for label in (WARP, WEFT, GAP)}
    # Families differ from each other more than texels differ within a family …
    assert np.abs(means[WARP] - means[WEFT]).mean() > spread[WARP]
    # … yet no family is a single point (normals, twist, noise and per-thread colour).
    assert min(spread.values()) > 1e-3
    # Anisotropy: the warp's highlight depends on the azimuth, not only on elevation.
    turned = fabric.evaluate(np.deg2rad([[45, 0, 45, 180], [45, 90, 45, 270]]))
    assert np.abs(turned[0] - turned[1]).mean() > 0.01


def test_normals_and_tangents_are_orthonormal():
    fabric = SyntheticBTF(size=16, seed=0)
    np.testing.assert_allclose(np.linalg.norm(fabric.normals, axis=-1), 1, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(fabric.tangents, axis=-1), 1, atol=1e-12)
    np.testing.assert_allclose(np.sum(fabric.normals * fabric.tangents, axis=-1), 0, atol=1e-12)


@pytest.mark.parametrize("bad", [dict(size=1), dict(n_threads=3), dict(size=8.5)])
def test_bad_settings_are_config_errors_naming_the_value(bad):
    with pytest.raises(ConfigError, match=str(next(iter(bad.values())))):
        SyntheticBTF(**bad)


# --- materials -----------------------------------------------------------------------

# Values of the plain weave before the presets existed (SyntheticBTF(size=16, seed=0)),
# at texels (1, 2), (6, 9), (11, 5), (14, 13) of four directions in degrees.
PLAIN_WEAVE_DIRECTIONS = [[0, 0, 0, 0], [60, 0, 30, 180], [75, 90, 45, 200], [40, 130, 70, 10]]
PLAIN_WEAVE_TEXELS = ([1, 6, 11, 14], [2, 9, 5, 13])
PLAIN_WEAVE_VALUES = [
    [[0.594217420, 0.118713781, 0.100397170], [0.865667284, 0.784726679, 0.519678473],
     [0.665748358, 0.587123096, 0.409987092], [0.391067833, 0.086218819, 0.073572710]],
    [[0.437112331, 0.130169347, 0.118345760], [0.337735891, 0.305693418, 0.200767025],
     [0.199282482, 0.175261974, 0.121145830], [0.133594632, 0.025529087, 0.021046182]],
    [[0.082500242, 0.014653270, 0.012039775], [0.358858347, 0.324772984, 0.213157028],
     [0.061413560, 0.053996444, 0.037286311], [0.140626773, 0.026322531, 0.021580825]],
    [[0.368558735, 0.065463476, 0.053788118], [0.766401649, 0.693680108, 0.455545962],
     [0.302076846, 0.265651464, 0.183588207], [0.343785286, 0.071046181, 0.059732087]],
]  # fmt: skip


def test_plain_weave_is_the_default_and_unchanged():
    directions = np.deg2rad(PLAIN_WEAVE_DIRECTIONS)
    values = SyntheticBTF(size=16, seed=0).evaluate(directions)
    np.testing.assert_allclose(
        values[(slice(None), *PLAIN_WEAVE_TEXELS)], PLAIN_WEAVE_VALUES, rtol=1e-6, atol=1e-7
    )
    named = SyntheticBTF(size=16, seed=0, material="plain_weave").evaluate(directions)
    np.testing.assert_array_equal(values, named)


@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_every_material_is_finite_in_unit_range_and_black_below_the_horizon(material):
    fabric = SyntheticBTF(size=16, seed=0, material=material)
    values = fabric.evaluate(random_directions(40, seed=1))
    assert np.isfinite(values).all() and values.min() >= 0 and values.max() <= 1
    assert values.max() > 0.1  # not black
    below = np.deg2rad([[100.0, 0.0, 30.0, 0.0], [30.0, 60.0, 95.0, 0.0]])
    assert (fabric.evaluate(below) == 0).all()


@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_every_material_is_deterministic_per_seed(material):
    directions = random_directions(6, seed=3)
    first = SyntheticBTF(size=16, seed=4, material=material).evaluate(directions)
    again = SyntheticBTF(size=16, seed=4, material=material).evaluate(directions)
    np.testing.assert_array_equal(first, again)
    other = SyntheticBTF(size=16, seed=5, material=material).evaluate(directions)
    assert not np.array_equal(first, other)


@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_every_material_has_several_named_labels(material):
    fabric = SyntheticBTF(size=32, seed=0, material=material)
    labels = np.unique(fabric.material_labels)
    assert len(labels) > 1
    assert labels.min() >= 0 and labels.max() < len(fabric.label_names)


def test_materials_differ_clearly_from_each_other():
    directions = btf_directions([(0, 0)])[::4]
    means = {
        material: SyntheticBTF(size=16, seed=0, material=material)
        .evaluate(directions)
        .mean(axis=(1, 2))
        for material in MATERIALS
    }  # (directions, 3): the mean colour of each image
    names = sorted(means)
    for i, first in enumerate(names):
        for second in names[i + 1 :]:
            assert np.abs(means[first] - means[second]).mean() > 0.02, (first, second)


def mean_over(values, mask):
    """Mean of each image's texels where ``mask``: (n, S, S, 3), (S, S) -> (n,)."""
    return values.mean(axis=-1)[:, mask].mean(axis=1)


def test_knit_shadows_light_across_its_legs_more_than_along_them():
    knit = SyntheticBTF(size=32, seed=0, material="knit")
    left_leg = knit.material_labels == knit.label_names.index("left leg")  # runs at 60°
    # Grazing light from both ends of the leg, and from both sides across it; view overhead.
    along = mean_over(knit.evaluate(np.deg2rad([[75, 60, 0, 0], [75, 240, 0, 0]])), left_leg)
    across = mean_over(knit.evaluate(np.deg2rad([[75, 150, 0, 0], [75, 330, 0, 0]])), left_leg)
    assert across.sum() < 0.85 * along.sum()


def test_corduroy_darkens_more_for_light_across_the_ridges_than_along_them():
    corduroy = SyntheticBTF(size=32, seed=0, material="corduroy")  # ridges along +y
    everywhere = np.ones((32, 32), dtype=bool)
    for theta in (60, 75):
        across = corduroy.evaluate(np.deg2rad([[theta, 0, 0, 0], [theta, 180, 0, 0]]))
        along = corduroy.evaluate(np.deg2rad([[theta, 90, 0, 0], [theta, 270, 0, 0]]))
        assert mean_over(across, everywhere).sum() < 0.75 * mean_over(along, everywhere).sum()


def test_satin_highlight_peaks_higher_than_knit():
    mirror = np.deg2rad([[30, 90, 30, 270], [45, 90, 45, 270], [60, 90, 60, 270]])
    satin = SyntheticBTF(size=32, seed=0, material="satin").evaluate(mirror).max()
    knit = SyntheticBTF(size=32, seed=0, material="knit").evaluate(mirror).max()
    assert satin > knit + 0.2


def test_channel_weights_put_axis_fibres_on_one_channel_and_share_diagonals():
    fibre = np.array([[1.0, 0.0], [0.0, 1.0], [0.5, np.sqrt(3) / 2], [-1.0, 1.0]])
    fibre /= np.linalg.norm(fibre, axis=1, keepdims=True)
    weights = channel_weights(fibre, np.array([1.0, 2.0, 3.0, 4.0]))
    # Rows are the channels at 0°, 90°, 30°, 60°, 120°, 150°.
    np.testing.assert_allclose(weights[:, 0], [1, 0, 0, 0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(weights[:, 1], [0, 2, 0, 0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(weights[:, 2], [0, 0, 0, 3, 0, 0], atol=1e-12)
    np.testing.assert_allclose(weights[:, 3], [0, 0, 0, 0, 2, 2], atol=1e-12)  # 135°


def test_unknown_material_is_a_config_error_listing_the_known_ones(tmp_path):
    with pytest.raises(ConfigError, match=r"'tweed'.*'corduroy'.*'knit'"):
        SyntheticBTF(size=8, material="tweed")
    with pytest.raises(ConfigError, match="'tweed'"):
        write_synthetic_btf(tmp_path / "btf", SIZE, 0, views=VIEWS, material="tweed")
    assert not (tmp_path / "btf").exists()


def test_satin_needs_a_multiple_of_five_threads():
    with pytest.raises(ConfigError, match="n_threads=4"):
        SyntheticBTF(size=8, material="satin", n_threads=4)
    assert SyntheticBTF(size=8, material="satin").n_threads == 10


def test_material_sheet_has_a_row_per_material_and_a_column_per_light():
    fig = material_sheet(["knit", "satin"], size=8)
    assert len(fig.axes) == 6
    assert [ax.get_ylabel() for ax in fig.axes[::3]] == ["knit", "satin"]
    assert fig.axes[0].get_title() == "light overhead"


# --- writer --------------------------------------------------------------------------


def written_files(root, view):
    return sorted((root / f"tv{view[0]:03d}_pv{view[1]:03d}").iterdir())


@pytest.mark.parametrize(
    "format, ext", [("ubo2003", "png"), ("ubo2003", "exr"), ("utia", "png"), ("utia", "exr")]
)
def test_writer_stores_the_ground_truth_up_to_quantization(tmp_path, format, ext):
    root = write_synthetic_btf(tmp_path / "btf", SIZE, 0, format=format, ext=ext, views=VIEWS)
    truth = SyntheticBTF(size=SIZE, seed=0).evaluate(btf_directions([VIEWS[1]]))
    stored_paths = [
        root
        / "tv045_pv040"
        / (
            f"{81 * 21 + index:05d} tl{tl:03d} pl{pl:03d} tv045 pv040.{ext}"  # view 21
            if format == "ubo2003"
            else f"tl{tl:03d}_pl{pl:03d}_tv045_pv040.{ext}"
        )
        for index, (tl, pl) in enumerate(grid_81_degrees())
    ]
    if ext == "exr":
        names = ("R", "G", "B") if format == "ubo2003" else ("X", "Y", "Z")
        stored = np.stack([read_exr_channels(path, names) for path in stored_paths])
        expected = truth if format == "ubo2003" else linear_srgb_to_xyz(truth)
        np.testing.assert_array_equal(stored, expected.astype(np.float16).astype(np.float32))
    else:
        stored = np.stack([read_image_8bit(path) for path in stored_paths])
        encode = gamma_encode if format == "ubo2003" else srgb_oetf
        np.testing.assert_array_equal(np.rint(stored * 255), quantize_8bit(encode(truth)))


def test_ubo2003_running_numbers_follow_the_full_view_major_order(tmp_path):
    root = write_synthetic_btf(tmp_path / "btf", SIZE, 0, views=VIEWS)
    numbers = [parse_ubo2003_file_name(path).number for path in written_files(root, (0, 0))]
    assert numbers == list(range(81))
    numbers = [parse_ubo2003_file_name(path).number for path in written_files(root, (45, 40))]
    assert numbers == list(range(21 * 81, 22 * 81))  # (45°, 40°) is grid direction 1 + 6 + 12 + 2


def test_writer_skips_a_complete_dataset(tmp_path):
    root = write_synthetic_btf(tmp_path / "btf", SIZE, 0, views=VIEWS)
    stamp = written_files(root, (0, 0))[0].stat().st_mtime_ns
    assert write_synthetic_btf(tmp_path / "btf", SIZE, 0, views=VIEWS) == root
    assert written_files(root, (0, 0))[0].stat().st_mtime_ns == stamp
    marker = json.loads((root / "synthetic_btf.json").read_text())
    assert marker["size"] == SIZE and marker["views"] == [[0, 0], [45, 40]]


def test_writer_refuses_a_root_written_with_other_parameters(tmp_path):
    write_synthetic_btf(tmp_path / "btf", SIZE, 0, views=VIEWS)
    with pytest.raises(DataError, match=str(tmp_path / "btf")):
        write_synthetic_btf(tmp_path / "btf", SIZE, 1, views=VIEWS)


def test_killed_writer_leaves_no_dataset(tmp_path, monkeypatch):
    calls = []

    def failing_encode(*args, **kwargs):
        calls.append(args)
        if len(calls) == 100:  # part-way through the second view
            raise KeyboardInterrupt
        return encode(*args, **kwargs)

    encode = synthetic_dataset.encode_btf_image
    monkeypatch.setattr(synthetic_dataset, "encode_btf_image", failing_encode)
    with pytest.raises(KeyboardInterrupt):
        write_synthetic_btf(tmp_path / "btf", SIZE, 0, views=VIEWS)
    assert list(tmp_path.iterdir()) == []
    monkeypatch.undo()
    root = write_synthetic_btf(tmp_path / "btf", SIZE, 0, views=VIEWS)
    assert len(written_files(root, (45, 40))) == 81


@pytest.mark.parametrize("format, ext", [("utia", "jpg"), ("ubo2003", "tif"), ("bonn", "png")])
def test_writer_rejects_unknown_format_or_extension(tmp_path, format, ext):
    with pytest.raises(ConfigError, match=f"'{ext if format != 'bonn' else format}'"):
        write_synthetic_btf(tmp_path / "btf", SIZE, 0, format=format, ext=ext, views=VIEWS)


def test_writer_fills_an_existing_empty_folder(tmp_path):
    (tmp_path / "btf").mkdir()
    root = write_synthetic_btf(tmp_path / "btf", SIZE, 0, views=VIEWS[:1])
    assert len(written_files(root, (0, 0))) == 81


def test_writer_round_trips_a_material_through_the_reader(tmp_path):
    root = write_synthetic_btf(
        tmp_path / "btf", SIZE, 2, ext="exr", views=VIEWS[1:], material="corduroy"
    )
    btf = load_btf(root, "ubo2003")
    truth = SyntheticBTF(size=SIZE, seed=2, material="corduroy").evaluate(btf.directions)
    np.testing.assert_array_equal(btf.images, truth.astype(np.float16).astype(np.float32))
    assert json.loads((root / "synthetic_btf.json").read_text())["material"] == "corduroy"
    with pytest.raises(DataError, match="'material': 'plain_weave'"):  # same root, other material
        write_synthetic_btf(tmp_path / "btf", SIZE, 2, ext="exr", views=VIEWS[1:])


def test_writer_takes_a_marker_from_before_materials_as_plain_weave(tmp_path):
    root = write_synthetic_btf(tmp_path / "btf", SIZE, 0, views=VIEWS[:1])
    marker_path = root / "synthetic_btf.json"
    marker = json.loads(marker_path.read_text())
    del marker["material"]
    marker_path.write_text(json.dumps(marker))
    stamp = written_files(root, (0, 0))[0].stat().st_mtime_ns
    assert write_synthetic_btf(tmp_path / "btf", SIZE, 0, views=VIEWS[:1]) == root
    assert written_files(root, (0, 0))[0].stat().st_mtime_ns == stamp
    with pytest.raises(DataError):
        write_synthetic_btf(tmp_path / "btf", SIZE, 0, views=VIEWS[:1], material="knit")
