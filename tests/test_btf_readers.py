"""BTF readers on tiny datasets written by the synthetic generator in the real layouts."""

import re
import shutil

import numpy as np
import OpenEXR
import pytest

from pipeline.btf.synthetic import SyntheticBTF, write_synthetic_btf
from pipeline.core.errors import ConfigError, DataError
from pipeline.data.btf import count_btf_images, decode_btf_image, list_btf_files, load_btf
from pipeline.data.directions import btf_directions, parse_ubo2003_file_name, ubo2003_file_name
from pipeline.data.images import (
    gamma_decode,
    gamma_encode,
    linear_srgb_to_xyz,
    quantize_8bit,
    srgb_eotf,
    srgb_oetf,
    write_exr,
    write_image_8bit,
    xyz_to_linear_srgb,
)

SIZE, SEED = 8, 3
VIEWS = [(0, 0), (30, 30)]  # two views = 162 images of 8 × 8: fast to write and read


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    """One small dataset per (format, ext), written once for the module."""
    base = tmp_path_factory.mktemp("btf")
    return {
        (format, ext): write_synthetic_btf(
            base / f"{format}_{ext}", SIZE, SEED, format=format, ext=ext, views=VIEWS
        )
        for format, ext in [
            ("ubo2003", "jpg"),
            ("ubo2003", "png"),
            ("ubo2003", "exr"),
            ("utia", "png"),
            ("utia", "exr"),
        ]
    }


@pytest.fixture
def damaged_copy(datasets, tmp_path):
    """A fresh copy of a dataset that a test may damage."""

    def copy(format="ubo2003", ext="jpg"):
        return shutil.copytree(datasets[(format, ext)], tmp_path / "copy")

    return copy


def ground_truth(directions):
    return SyntheticBTF(size=SIZE, seed=SEED).evaluate(directions)


# --- round trips ------------------------------------------------------------------------


def test_ubo2003_jpeg_round_trip_within_jpeg_error(datasets):
    btf = load_btf(datasets[("ubo2003", "jpg")], "ubo2003")
    np.testing.assert_allclose(btf.directions, btf_directions(VIEWS), atol=1e-12)
    # Compared in 8-bit code values of the gamma-2.2 encoding, where JPEG works. At
    # quality 95 with 4:4:4 chroma the generator's 8 × 8 textures (sharp thread edges,
    # per-texel noise) measure ~2 codes mean and ~15 codes worst error; the bounds leave
    # a margin while still catching a wrong gamma, order or channel (errors of 30+).
    code_error = 255 * np.abs(gamma_encode(btf.images) - gamma_encode(ground_truth(btf.directions)))
    assert code_error.mean() < 4.0
    assert code_error.max() < 32.0


def test_ubo2003_png_equals_the_quantized_gamma_encoding(datasets):
    btf = load_btf(datasets[("ubo2003", "png")], "ubo2003")
    codes = quantize_8bit(gamma_encode(ground_truth(btf.directions)))
    expected = gamma_decode(codes.astype(np.float32) / np.float32(255.0))
    np.testing.assert_array_equal(btf.images, expected)


def test_ubo2003_exr_equals_the_half_float_values(datasets):
    btf = load_btf(datasets[("ubo2003", "exr")], "ubo2003")
    expected = ground_truth(btf.directions).astype(np.float16).astype(np.float32)
    np.testing.assert_array_equal(btf.images, expected)


def test_utia_png_equals_the_quantized_srgb_encoding(datasets):
    btf = load_btf(datasets[("utia", "png")], "utia")
    codes = quantize_8bit(srgb_oetf(ground_truth(btf.directions)))
    expected = srgb_eotf(codes.astype(np.float32) / np.float32(255.0))
    np.testing.assert_array_equal(btf.images, expected)


def test_utia_exr_xyz_round_trip(datasets):
    btf = load_btf(datasets[("utia", "exr")], "utia")
    truth = ground_truth(btf.directions)
    half_xyz = linear_srgb_to_xyz(truth).astype(np.float16).astype(np.float32)
    np.testing.assert_array_equal(btf.images, xyz_to_linear_srgb(half_xyz))
    # Half floats carry 11 significant bits; the XYZ->RGB matrix amplifies by up to ~3.
    np.testing.assert_allclose(btf.images, truth, atol=3e-3)


@pytest.mark.parametrize("format", ["ubo2003", "utia"])
def test_linearize_chooses_the_decoding_of_8bit_images(datasets, format):
    root = datasets[(format, "png")]
    codes = load_btf(root, format, linearize="none").images
    # "none" keeps the encoded values: the 8-bit codes / 255, whatever the layout.
    np.testing.assert_array_equal(codes * np.float32(255.0), np.rint(codes * np.float32(255.0)))
    np.testing.assert_array_equal(load_btf(root, format, linearize="gamma2.2").images, gamma_decode(codes))
    np.testing.assert_array_equal(load_btf(root, format, linearize="srgb").images, srgb_eotf(codes))
    own = {"ubo2003": gamma_decode, "utia": srgb_eotf}[format]
    np.testing.assert_array_equal(load_btf(root, format).images, own(codes))


def test_linearize_leaves_exr_linear(datasets):
    root = datasets[("ubo2003", "exr")]
    np.testing.assert_array_equal(
        load_btf(root, "ubo2003", linearize="none").images, load_btf(root, "ubo2003").images
    )


def test_unknown_linearize_names_the_setting(datasets):
    with pytest.raises(ConfigError, match=r"dataset\.linearize='gamma' .*srgb"):
        load_btf(datasets[("ubo2003", "png")], "ubo2003", linearize="gamma")


def test_utia_exr_with_rgb_labels_is_read_as_xyz(tmp_path):
    xyz = np.random.default_rng(0).uniform(0.1, 0.9, size=(4, 5, 3)).astype(np.float16)
    path = tmp_path / "tl000_pl000_tv000_pv000.exr"
    write_exr(path, xyz, names=("R", "G", "B"))
    np.testing.assert_array_equal(
        decode_btf_image(path, "utia"), xyz_to_linear_srgb(xyz.astype(np.float32))
    )


def test_angles_come_from_names_not_file_order(damaged_copy):
    """Scramble the running numbers: the order on disk changes, the result must not."""
    root = damaged_copy("ubo2003", "png")
    for folder in sorted(root.glob("tv*")):
        paths = sorted(folder.iterdir())
        for path, number in zip(paths, reversed(range(len(paths))), strict=True):
            name = parse_ubo2003_file_name(path)
            path.rename(folder / ("new-" + ubo2003_file_name(number, *name[1:5], "png")))
        for path in folder.iterdir():
            path.rename(folder / path.name.removeprefix("new-"))
    btf = load_btf(root, "ubo2003")
    np.testing.assert_allclose(btf.directions, btf_directions(VIEWS), atol=1e-12)
    codes = quantize_8bit(gamma_encode(ground_truth(btf.directions)))
    np.testing.assert_array_equal(btf.images, gamma_decode(codes / np.float32(255.0)))


def test_view_subset_loads_only_those_views(datasets):
    btf = load_btf(datasets[("ubo2003", "png")], "ubo2003", views=[(30, 30)])
    assert btf.images.shape == (81, SIZE, SIZE, 3)
    np.testing.assert_allclose(np.rad2deg(btf.directions[:, 2:]), np.tile([30, 30], (81, 1)))
    assert [folder.name for folder in btf.view_folders] == ["tv030_pv030"]
    assert all(path.parent.name == "tv030_pv030" for path in btf.paths)


def test_count_btf_images_and_decoding_into_a_memmap(datasets, tmp_path):
    root = datasets[("utia", "png")]
    n_images, height, width = count_btf_images(root, "utia")
    assert (n_images, height, width) == (162, SIZE, SIZE)
    out = np.lib.format.open_memmap(
        tmp_path / "images.npy", mode="w+", dtype=np.float32, shape=(n_images, height, width, 3)
    )
    btf = load_btf(root, "utia", out=out)
    assert btf.images is out
    np.testing.assert_array_equal(np.load(tmp_path / "images.npy"), load_btf(root, "utia").images)


def test_out_of_the_wrong_shape_is_a_config_error(datasets):
    with pytest.raises(ConfigError, match=r"\(161, 8, 8, 3\)"):
        load_btf(datasets[("utia", "png")], "utia", out=np.empty((161, 8, 8, 3), np.float32))


# --- each bad input names its path ------------------------------------------------------


def test_missing_root(tmp_path):
    with pytest.raises(DataError, match=re.escape(str(tmp_path / "nowhere"))):
        load_btf(tmp_path / "nowhere")


def test_root_without_view_folders(tmp_path):
    with pytest.raises(DataError, match=re.escape(str(tmp_path))):
        load_btf(tmp_path)


def test_unknown_format_is_a_config_error(datasets):
    with pytest.raises(ConfigError, match="'bonn'"):
        load_btf(datasets[("utia", "png")], format="bonn")


def test_requested_view_absent_on_disk(datasets):
    root = datasets[("ubo2003", "jpg")]
    with pytest.raises(DataError, match=re.escape(str(root / "tv075_pv015"))):
        load_btf(root, views=[(75, 15)])


def test_missing_image(damaged_copy):
    root = damaged_copy("ubo2003", "jpg")
    victim = sorted((root / "tv030_pv030").iterdir())[5]
    victim.unlink()
    with pytest.raises(DataError, match=re.escape(str(victim))):
        load_btf(root)


def test_missing_utia_image(damaged_copy):
    root = damaged_copy("utia", "png")
    victim = root / "tv000_pv000" / "tl045_pl040_tv000_pv000.png"
    victim.unlink()
    with pytest.raises(DataError, match=re.escape(str(victim))):
        list_btf_files(root, "utia")


@pytest.mark.parametrize("ext", ["jpg", "png", "exr"])
def test_truncated_image(damaged_copy, ext):
    root = damaged_copy("ubo2003", ext)
    victim = sorted((root / "tv000_pv000").iterdir())[10]
    data = victim.read_bytes()
    victim.write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match=re.escape(str(victim))):
        load_btf(root)


def test_unparseable_folder_name(damaged_copy):
    root = damaged_copy()
    (root / "tv030_pv030").rename(root / "view30")
    with pytest.raises(DataError, match=re.escape(str(root / "view30"))):
        load_btf(root)


def test_off_grid_folder_name(damaged_copy):
    root = damaged_copy()
    (root / "tv030_pv030").rename(root / "tv030_pv031")
    with pytest.raises(DataError, match=re.escape(str(root / "tv030_pv031"))):
        load_btf(root)


def test_unparseable_file_name(damaged_copy):
    root = damaged_copy()
    victim = sorted((root / "tv030_pv030").iterdir())[3]
    renamed = victim.rename(victim.parent / "photo 3.jpg")
    with pytest.raises(DataError, match=re.escape(str(renamed))):
        load_btf(root)


def test_file_whose_view_disagrees_with_its_folder(damaged_copy):
    root = damaged_copy()
    victim = sorted((root / "tv030_pv030").iterdir())[3]
    moved = victim.rename(root / "tv000_pv000" / victim.name)
    with pytest.raises(DataError, match=re.escape(str(moved))):
        load_btf(root)


def test_image_of_another_size(damaged_copy):
    root = damaged_copy("ubo2003", "png")
    victim = sorted((root / "tv030_pv030").iterdir())[7]
    write_image_8bit(victim, np.zeros((SIZE + 1, SIZE, 3)))
    with pytest.raises(DataError, match=re.escape(str(victim))):
        load_btf(root)


def test_nan_in_exr(damaged_copy):
    root = damaged_copy("utia", "exr")
    victim = root / "tv030_pv030" / "tl060_pl018_tv030_pv030.exr"
    with OpenEXR.File(str(victim), separate_channels=True) as exr_file:
        channels = {name: channel.pixels.copy() for name, channel in exr_file.channels().items()}
    channels["Y"][2, 3] = np.nan
    write_exr(victim, np.stack([channels[name] for name in "XYZ"], axis=-1), names="XYZ")
    with pytest.raises(DataError, match=re.escape(str(victim))):
        load_btf(root, "utia")
