"""The procedural woven-fabric BTF and its writer."""

import json

import numpy as np
import pytest

import pipeline.btf.synthetic as synthetic_btf
from pipeline.btf.synthetic import GAP, WARP, WEFT, SyntheticBTF, write_synthetic_btf
from pipeline.core.errors import ConfigError, DataError
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

    encode = synthetic_btf.encode_btf_image
    monkeypatch.setattr(synthetic_btf, "encode_btf_image", failing_encode)
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
