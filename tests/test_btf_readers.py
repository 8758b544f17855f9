"""BTF readers on tiny datasets written by the synthetic generator in the real layouts."""

import re
import shutil
import struct
import subprocess
import zipfile

import numpy as np
import OpenEXR
import pytest

from pipeline.btf.synthetic import SyntheticBTF
from pipeline.btf.synthetic_dataset import write_synthetic_btf
from pipeline.core.errors import ConfigError, DataError
from pipeline.core.stage import folder_fingerprint
from pipeline.data.btf import (
    archive_fingerprint,
    count_btf_images,
    decode_btf_image,
    list_btf_files,
    load_btf,
)
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
    np.testing.assert_array_equal(
        load_btf(root, format, linearize="gamma2.2").images, gamma_decode(codes)
    )
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


# --- zip archives, read as downloaded ---------------------------------------------------


def _zip_folder(folder, archive, prefix="", compression=zipfile.ZIP_DEFLATED):
    """Python's zipfile: DOS times only (no extended-timestamp field)."""
    with zipfile.ZipFile(archive, "w", compression) as opened:
        for path in sorted(folder.rglob("*")):
            if path.is_file():
                opened.write(path, prefix + path.relative_to(folder).as_posix())
    return archive


@pytest.mark.parametrize("format, ext, prefix", [("ubo2003", "jpg", "WOOL/"), ("utia", "exr", "")])
def test_a_zip_reads_bit_for_bit_as_its_folder(datasets, tmp_path, format, ext, prefix):
    folder = datasets[(format, ext)]
    archive = _zip_folder(folder, tmp_path / "m.zip", prefix)
    zipped, unpacked = load_btf(archive, format), load_btf(folder, format)
    np.testing.assert_array_equal(zipped.images, unpacked.images)
    np.testing.assert_array_equal(zipped.directions, unpacked.directions)
    relative = unpacked.paths[100].relative_to(folder).as_posix()
    assert str(zipped.paths[100]) == f"{archive}/{prefix}{relative}"
    assert count_btf_images(archive, format, views=[(30, 30)]) == (81, SIZE, SIZE)


@pytest.mark.skipif(
    shutil.which("unzip") is None or shutil.which("zip") is None,
    reason="needs Info-ZIP zip and unzip",
)
@pytest.mark.parametrize("maker", ["python", "info-zip"])
def test_a_zips_fingerprint_is_that_of_the_folder_unzip_makes(datasets, tmp_path, maker):
    """Python's zipfile records DOS times (local, 2 s steps); Info-ZIP's zip adds the
    Unix time in an extended-timestamp field, which unzip restores instead."""
    source = shutil.copytree(datasets[("ubo2003", "png")], tmp_path / "WOOL")
    archive = tmp_path / "m.zip"
    if maker == "python":
        _zip_folder(source, archive, "WOOL/")
    else:
        subprocess.run(["zip", "-q", "-r", str(archive), "WOOL"], cwd=tmp_path, check=True)
    subprocess.run(["unzip", "-q", str(archive), "-d", str(tmp_path / "out")], check=True)
    assert archive_fingerprint(archive) == folder_fingerprint(tmp_path / "out" / "WOOL")


def test_an_extended_timestamp_is_the_time_of_the_fingerprint(tmp_path):
    info = zipfile.ZipInfo("tv000_pv000/a.png", date_time=(2001, 2, 3, 4, 5, 6))
    info.extra = struct.pack("<HHBi", 0x5455, 5, 1, 1_600_000_000)  # "UT", flags, mtime
    with zipfile.ZipFile(tmp_path / "m.zip", "w") as opened:
        opened.writestr(info, b"12345")
    fingerprint = archive_fingerprint(tmp_path / "m.zip")
    assert fingerprint["mtime_ns"] == 1_600_000_000 * 10**9
    assert (fingerprint["files"], fingerprint["bytes"]) == (1, 5)


@pytest.mark.skipif(shutil.which("unzip") is None, reason="needs unzip")
def test_the_load_stage_shares_one_entry_between_a_zip_and_its_unzipped_folder(datasets, tmp_path):
    from helpers import compose_config

    from pipeline.btf import stages
    from pipeline.core.stage import Context

    archive = _zip_folder(datasets[("ubo2003", "jpg")], tmp_path / "m.zip", "WOOL/")
    subprocess.run(["unzip", "-q", str(archive), "-d", str(tmp_path / "out")], check=True)

    def load(root):
        cfg = compose_config(
            "experiment=smoke",
            f"paths.runs={tmp_path / 'runs'}",
            "dataset=ubo2003",
            f"dataset.root={root}",
            "dataset.views=null",
            "btf.crop.size=4",  # the crop must fit the 8 x 8 texture: checked as it loads
            "btf.crop.offset=[0,0]",
        )
        return stages.load(Context.from_config(cfg))

    from_folder = load(tmp_path / "out" / "WOOL")
    from_zip = load(archive)
    assert from_zip.key == from_folder.key
    np.testing.assert_array_equal(from_zip.array("images"), load_btf(archive).images)


def test_a_zip_missing_an_image_names_it(datasets, tmp_path):
    folder = datasets[("ubo2003", "jpg")]
    victim = sorted((folder / "tv030_pv030").iterdir())[5]
    archive = tmp_path / "m.zip"
    with zipfile.ZipFile(archive, "w") as opened:
        for path in sorted(folder.rglob("*.jpg")):
            if path != victim:
                opened.write(path, "WOOL/" + path.relative_to(folder).as_posix())
    with pytest.raises(DataError, match=re.escape(f"{archive}/WOOL/tv030_pv030/{victim.name}")):
        load_btf(archive)


def test_a_damaged_member_names_the_archive_and_member(datasets, tmp_path):
    archive = _zip_folder(
        datasets[("ubo2003", "png")], tmp_path / "m.zip", compression=zipfile.ZIP_STORED
    )
    with zipfile.ZipFile(archive) as opened:
        member = opened.getinfo(
            "tv030_pv030/"
            + sorted(
                name.rsplit("/", 1)[1] for name in opened.namelist() if name.startswith("tv030")
            )[9]
        )
    raw = bytearray(archive.read_bytes())
    data_start = member.header_offset + 30 + len(member.filename.encode()) + len(member.extra)
    raw[data_start + 40] ^= 0xFF  # the CRC no longer matches
    archive.write_bytes(bytes(raw))
    with pytest.raises(DataError, match=re.escape(f"{archive}/{member.filename}")):
        load_btf(archive)


def test_a_zip_with_view_folders_in_two_places(datasets, tmp_path):
    archive = _zip_folder(datasets[("utia", "png")], tmp_path / "m.zip", "a/")
    with zipfile.ZipFile(archive, "a") as opened:
        opened.writestr("b/tv000_pv000/tl000_pl000_tv000_pv000.png", b"")
    with pytest.raises(DataError, match=r"in 2 places \['a/', 'b/'\].*" + re.escape(str(archive))):
        list_btf_files(archive, "utia")


def test_a_zip_without_view_folders(tmp_path):
    with zipfile.ZipFile(tmp_path / "m.zip", "w") as opened:
        opened.writestr("readme.txt", b"hello")
    with pytest.raises(DataError, match="no view folders.*" + re.escape(str(tmp_path / "m.zip"))):
        load_btf(tmp_path / "m.zip")


def test_a_file_named_zip_that_is_not_one(tmp_path):
    (tmp_path / "m.zip").write_bytes(b"not a zip archive")
    with pytest.raises(DataError, match="cannot read zip archive " + re.escape(str(tmp_path))):
        load_btf(tmp_path / "m.zip")
