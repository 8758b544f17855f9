"""UBO2014 (DFMF) reader: small files written by the project's writer, decoded against the
formula written out here in plain numpy, parsed by pysmtb where installed, and each bad
file named in a DataError."""

import re
import struct
from pathlib import Path

import numpy as np
import pytest
from helpers import compose_config

from pipeline.core.errors import ConfigError, DataError
from pipeline.data.ubo2014 import load_ubo2014, select_rows
from pipeline.data.ubo2014_decode import channel_factors, decode_dfmf
from pipeline.data.ubo2014_header import read_dfmf
from pipeline.data.ubo2014_write import write_dfmf

# 3 views × 4 lights, 5 wide × 4 high (not square: a swapped width and height shows).
VIEWS_DEG = np.array([[0.0, 0.0], [30.0, 90.0], [60.0, 200.0]])
LIGHTS_DEG = np.array([[10.0, 0.0], [40.0, 45.0], [55.0, 300.0], [70.0, 120.0]])
N_VIEWS, N_LIGHTS, WIDTH, HEIGHT, K = 3, 4, 5, 4, 3
ROWS, COLUMNS = N_VIEWS * N_LIGHTS, WIDTH * HEIGHT


def random_factors(color_model: int, seed: int = 0):
    """One (S, U, SV) per channel; for colour model 11, channel 0 near log(0.3) and small
    chroma ratios, so that most values land inside [0, 1] and a few are clipped."""
    rng = np.random.default_rng(seed)
    factors = []
    for channel in range(3):
        u = rng.uniform(0.2, 1.0, (ROWS, K))
        sv = rng.uniform(0.0, 0.4, (COLUMNS, K))
        if color_model == 11:
            sv = sv - (0.6 if channel == 0 else 0.2)
        factors.append((rng.uniform(1.0, 2.0, K), u, sv))
    return factors


def write(path, color_model=0, dtype="float32", seed=0, **options):
    factors = options.pop("factors", None) or random_factors(color_model, seed)
    write_dfmf(
        path,
        np.radians(VIEWS_DEG),
        np.radians(LIGHTS_DEG),
        WIDTH,
        HEIGHT,
        factors=factors,
        color_model=color_model,
        dtype=dtype,
        **options,
    )
    return factors


def expected_images(factors, dtype, color_model):
    """The decoding written out from the format's description, in float64."""
    channels = []
    for _, u, sv in factors:
        u = u.astype(dtype).astype(np.float64)  # what the file holds
        sv = sv.astype(dtype).astype(np.float64)
        channels.append(u @ sv.T)  # (rows, columns): value = U[row] · SV[column]
    c0, c1, c2 = channels
    if color_model == 0:
        rgb = np.stack(channels, axis=-1)
    else:
        y = np.exp(c0) - 1e-5
        u_chroma, v_chroma = c1 * y + 1e-5, c2 * y + 1e-5
        rgb = np.stack(
            [
                y + 1.13983 * v_chroma,
                y - 0.39465 * u_chroma - 0.5806 * v_chroma,
                y + 2.03211 * u_chroma,
            ],
            axis=-1,
        )
        rgb = np.clip(rgb, 0.0, 1.0)
    # Column y * width + x with y from the bottom: image row r is file row height - 1 - r.
    return rgb.reshape(ROWS, HEIGHT, WIDTH, 3)[:, ::-1]


# --- decoding ---------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", ["float16", "float32"])
@pytest.mark.parametrize("color_model", [0, 11])
def test_decoding_follows_the_formula(tmp_path, color_model, dtype):
    factors = write(tmp_path / "m.btf", color_model, dtype)
    dfmf = read_dfmf(tmp_path / "m.btf")
    assert (dfmf.color_model, dfmf.channels[0].dtype.name) == (color_model, dtype)
    images = decode_dfmf(dfmf)
    assert images.shape == (ROWS, HEIGHT, WIDTH, 3) and images.dtype == np.float32
    expected = expected_images(factors, dtype, color_model)
    if color_model == 11:
        assert 0 < (expected == 1.0).mean() < 0.5  # some values clipped, most not
    np.testing.assert_allclose(images, expected, rtol=2e-6, atol=2e-6)


def test_directions_are_the_files_view_major(tmp_path):
    write(tmp_path / "m.btf")
    directions = read_dfmf(tmp_path / "m.btf").directions()
    lights = np.tile(LIGHTS_DEG, (N_VIEWS, 1))
    views = np.repeat(VIEWS_DEG, N_LIGHTS, axis=0)
    np.testing.assert_allclose(np.degrees(directions), np.hstack([lights, views]), atol=1e-4)


@pytest.mark.parametrize("color_model", [0, 11])
def test_values_written_by_the_writer_read_back(tmp_path, color_model):
    rng = np.random.default_rng(1)
    values = rng.uniform(0.05, 0.95, (ROWS, HEIGHT, WIDTH, 3))
    write_dfmf(
        tmp_path / "v.btf",
        np.radians(VIEWS_DEG),
        np.radians(LIGHTS_DEG),
        WIDTH,
        HEIGHT,
        values=values,
        color_model=color_model,
        dtype="float64",
    )
    np.testing.assert_allclose(decode_dfmf(read_dfmf(tmp_path / "v.btf")), values, atol=1e-6)


def test_a_crop_of_some_directions_equals_that_part_of_the_full_decode(tmp_path):
    write(tmp_path / "m.btf", color_model=11, dtype="float16")
    dfmf = read_dfmf(tmp_path / "m.btf")
    rows = select_rows(dfmf, views=[2, 0], lights=[[40, 45], 3])
    np.testing.assert_array_equal(rows, [1, 3, 9, 11])  # view-major, file order
    part = decode_dfmf(dfmf, rows, crop=[1, 2, 2, 3])
    np.testing.assert_allclose(part, decode_dfmf(dfmf)[rows][:, 1:3, 2:5], rtol=1e-6, atol=1e-7)


def test_the_cosine_is_multiplied_in_when_the_file_says_it_is_not_in_the_data(tmp_path):
    factors = write(tmp_path / "with.btf", cosine_in_data=True)
    write(tmp_path / "without.btf", factors=factors, cosine_in_data=False)
    write(tmp_path / "v1.btf", factors=factors, version=1)  # no flag: not in the data
    stored = decode_dfmf(read_dfmf(tmp_path / "with.btf"))
    cosine = np.cos(np.radians(np.tile(LIGHTS_DEG[:, 0], N_VIEWS)))[:, None, None, None]
    for name in ("without.btf", "v1.btf"):
        dfmf = read_dfmf(tmp_path / name)
        assert not dfmf.cosine_in_data
        np.testing.assert_allclose(decode_dfmf(dfmf), stored * cosine, rtol=1e-6)
        np.testing.assert_array_equal(decode_dfmf(dfmf, include_cosine=False), stored)


@pytest.mark.parametrize("version", [1, 2, 3, 4])
def test_every_header_version_parses(tmp_path, version):
    rotations = np.arange(18, dtype=np.float32).reshape(2, 3, 3)
    names = ("R", "G", "B") if version <= 3 else ("red", "green", "blue")
    factors = write(
        tmp_path / "m.btf",
        version=version,
        xml="<btf a='1'/>",
        channel_names=names,
        rotations=rotations,
        measurement_setup="dome II",
        light_source="LED",
        ppmm=12.5,
        rgb_scale=(0.5, 1.0, 2.0),
    )
    dfmf = read_dfmf(tmp_path / "m.btf")
    assert dfmf.version == version
    assert dfmf.xml == ("<btf a='1'/>" if version > 2 else "")
    assert dfmf.channel_names == names
    assert (dfmf.measurement_setup, dfmf.light_source, dfmf.ppmm) == ("dome II", "LED", 12.5)
    assert dfmf.rgb_scale == (0.5, 1.0, 2.0)
    np.testing.assert_array_equal(dfmf.rotations, rotations)
    np.testing.assert_array_equal(channel_factors(dfmf, 1)[2], factors[1][2].astype(np.float32))


def test_a_file_without_the_rotations_block(tmp_path):
    factors = write(tmp_path / "m.btf", with_rotations=False)
    dfmf = read_dfmf(tmp_path / "m.btf")
    assert not dfmf.has_rotations and dfmf.rotations.shape == (0, 3, 3)
    np.testing.assert_allclose(decode_dfmf(dfmf), expected_images(factors, "float32", 0), rtol=2e-6)


def test_direction_entries_off_the_file_or_out_of_range(tmp_path):
    write(tmp_path / "m.btf")
    dfmf = read_dfmf(tmp_path / "m.btf")
    with pytest.raises(ConfigError, match=r"\[31, 90\] degrees is 1\.00 degrees from"):
        select_rows(dfmf, views=[[31, 90]])
    with pytest.raises(ConfigError, match="entry 4 is not an index of the file's 4 lights"):
        select_rows(dfmf, lights=[4])
    with pytest.raises(ConfigError, match=r"crop \[0, 0, 5, 5\] does not fit"):
        decode_dfmf(dfmf, crop=[0, 0, 5, 5])


# --- an independent parser ----------------------------------------------------------------


@pytest.mark.parametrize("dtype", ["float16", "float32"])
def test_pysmtb_reads_the_same_factors_and_header(tmp_path, dtype):
    """pysmtb's read_ubo_btf_dfmf parses the writer's file the same way (it reads only
    files with the "R" mark; it reads n x 3 floats of rotations, so write none)."""
    iio = pytest.importorskip("pysmtb.btf")
    factors = write(
        tmp_path / "m.btf",
        color_model=11,
        dtype=dtype,
        cosine_in_data=False,
        xml="<x/>",
        channel_names=("Y", "U", "V"),
    )
    meta, data = iio.read_ubo_btf_dfmf(str(tmp_path / "m.btf"))
    dfmf = read_dfmf(tmp_path / "m.btf")
    assert (meta.num_views, meta.num_lights, meta.width, meta.height) == (
        N_VIEWS,
        N_LIGHTS,
        WIDTH,
        HEIGHT,
    )
    assert (meta.color_model, bool(meta.cosine_in_data), meta.xml) == (11, False, b"<x/>")
    assert meta.channel_names == [b"Y", b"U", b"V"]
    assert list(dfmf.channel_names) == ["Y", "U", "V"]
    for channel, (s, u, sv) in enumerate(factors):
        ours = channel_factors(dfmf, channel)
        for theirs, mine, given in zip((data.S, data.U, data.SxV), ours, (s, u, sv), strict=True):
            np.testing.assert_array_equal(theirs[channel], given.astype(dtype))
            np.testing.assert_array_equal(mine, given.astype(dtype))
    # Their factors through the formula give our decoding.
    theirs = [(None, data.U[c], data.SxV[c]) for c in range(3)]
    np.testing.assert_allclose(
        decode_dfmf(dfmf, include_cosine=False),
        expected_images(theirs, dtype, 11),
        rtol=2e-6,
        atol=2e-6,
    )


# --- bad files ----------------------------------------------------------------------------


def _patched(path: Path, offset: int, data: bytes) -> Path:
    raw = bytearray(path.read_bytes())
    raw[offset : offset + len(data)] = data
    path.write_bytes(bytes(raw))
    return path


@pytest.fixture
def good(tmp_path):
    write(tmp_path / "m.btf", dtype="float16")
    return tmp_path / "m.btf"


def test_wrong_signature(good):
    _patched(good, 0, b"!FMF1")
    with pytest.raises(DataError, match=f"not a UBO2014 DFMF file.*{re.escape(str(good))}"):
        read_dfmf(good)


def test_unknown_version(good):
    _patched(good, 10 + 4, struct.pack("<I", 9))  # after "!DFMF08FCR" and the block size
    with pytest.raises(DataError, match=f"version 9 is not one.*{re.escape(str(good))}"):
        read_dfmf(good)


def test_unknown_colour_model(tmp_path):
    write(tmp_path / "m.btf", color_model=7)
    with pytest.raises(DataError, match="colour model 7 is not one"):
        read_dfmf(tmp_path / "m.btf")


def test_header_block_size_disagreeing_with_its_fields(good):
    _patched(good, 10, struct.pack("<I", 999))
    with pytest.raises(DataError, match="header block says it is 999 bytes"):
        read_dfmf(good)


@pytest.mark.parametrize("cut", [200, 1])  # inside the header; inside the last channel
def test_truncated_file_names_expected_and_actual_size(good, cut):
    size = good.stat().st_size
    good.write_bytes(good.read_bytes()[: cut if cut > 1 else size - cut])
    actual = cut if cut > 1 else size - 1
    expected = "needs bytes" if cut > 1 else f"ends at byte {size}"
    with pytest.raises(DataError, match=f"truncated: .*{expected}.*the file has {actual} bytes"):
        read_dfmf(good)


def test_bytes_after_the_last_channel(good):
    size = good.stat().st_size
    good.write_bytes(good.read_bytes() + b"\0\0")
    with pytest.raises(DataError, match=f"2 bytes after.*expected {size} bytes, actual {size + 2}"):
        read_dfmf(good)


@pytest.mark.parametrize("field, offset", [("rows", 5), ("columns", 9)])
def test_factor_shapes_disagreeing_with_the_header(good, field, offset):
    header_start = read_dfmf(good).channels[1].offset - 13  # uint8 scalar size, 3 × uint32
    _patched(good, header_start + offset, struct.pack("<I", 7))
    shape = "7 rows × 20 columns" if field == "rows" else "12 rows × 7 columns"
    with pytest.raises(DataError, match=f"channel 'G'.*{shape}.*make 12 × 20"):
        read_dfmf(good)


def test_unknown_scalar_size(good):
    _patched(good, read_dfmf(good).channels[0].offset - 13, bytes([3]))
    with pytest.raises(DataError, match="scalars of 3 bytes"):
        read_dfmf(good)


def test_a_file_of_two_channels_is_not_decoded(tmp_path):
    write(tmp_path / "m.btf", factors=random_factors(0)[:2], channel_names=("L", "a"))
    with pytest.raises(DataError, match=r"2 channels \['L', 'a'\]; the decoder needs 3"):
        decode_dfmf(read_dfmf(tmp_path / "m.btf"))


# --- the load stage -----------------------------------------------------------------------


def _load_config(tmp_path, root, *overrides):
    return compose_config(
        "experiment=smoke",
        f"paths.runs={tmp_path / 'runs'}",
        "dataset=ubo2014",
        f"dataset.root={root}",
        "dataset.views=null",
        "btf.crop.size=3",
        "btf.crop.offset=[0,1]",
        *overrides,
    )


def test_the_crop_stage_decodes_the_crop_from_the_factors_as_abrdfs(tmp_path):
    from pipeline.btf import stages
    from pipeline.core.stage import Context

    factors = write(tmp_path / "m.btf", color_model=11, dtype="float16")
    cfg = _load_config(tmp_path, tmp_path / "m.btf", "dataset.lights=[0,2]")
    ctx = Context.from_config(cfg)
    loaded = stages.load(ctx)
    assert not loaded.file("images.npy").exists()  # the header only: nothing decoded
    rows = np.array([0, 2, 4, 6, 8, 10])
    np.testing.assert_array_equal(
        loaded.array("directions"), read_dfmf(tmp_path / "m.btf").directions()[rows]
    )
    cropped = stages.crop(ctx, loaded)
    images = expected_images(factors, "float16", 11)[rows, 0:3, 1:4]  # (n, 3, 3, 3)
    np.testing.assert_allclose(
        np.asarray(stages.abrdf(cropped)),
        images.reshape(len(rows), 9, 3).transpose(1, 0, 2),
        rtol=2e-6,
        atol=2e-6,
    )
    np.testing.assert_array_equal(cropped.array("directions"), loaded.array("directions"))
    assert stages.load(Context.from_config(cfg)).key == loaded.key  # a rerun is a hit
    assert (
        not list(Path(cfg.paths.cache).glob("*/*/*.npy.*"))
        and not cropped.file("abrdf.npy").exists()
    )  # the crop is served from the factors, never written
    # Indexing as the stages do: texels, texels x directions, single entries (the same
    # values up to the last bit, which depends on the block's shape in the product).
    served = stages.abrdf(cropped)
    whole = np.asarray(served)
    for key in ([1, 4], (slice(2, 5), [0, 3]), (slice(None), 2), 3, np.ix_([4, 1], [3, 0, 3])):
        assert served[key].shape == whole[key].shape
        np.testing.assert_allclose(served[key], whole[key], rtol=1e-6)
    with pytest.raises(IndexError, match="pair"):
        served[[0, 1], [0, 1]]
    # The latent texture reads its batches so (np.ix_ of the drawn texels and directions):
    # trained on the served crop it follows the same path as on the decoded one.
    from pipeline.btf.latent_texture import train_latent_texture
    from pipeline.btf.stereographic import direction_features

    norm = stages.normalization(stages.preprocess(ctx, cropped))
    size = int(cfg.btf.crop.size)
    features = direction_features(cropped.array("directions", mmap=False)).astype(np.float32)
    runs = [
        train_latent_texture(
            targets,
            features,
            np.arange(whole.shape[1]),
            (size, size),
            latent=2,
            levels=1,
            hidden=8,
            layers=1,
            steps=4,
            batch_texels=2,
            queries_per_texel=3,
            lr=1e-2,
            seed=0,
        ).curve
        for targets in (norm.targets(served), norm.target(whole))
    ]
    np.testing.assert_allclose(
        [point["loss"] for point in runs[0]], [point["loss"] for point in runs[1]], rtol=1e-5
    )


def test_a_cached_crop_whose_file_changed_is_refused_naming_it(tmp_path):
    from pipeline.btf import stages
    from pipeline.core.stage import Context

    write(tmp_path / "m.btf")
    cfg = _load_config(tmp_path, tmp_path / "m.btf")
    ctx = Context.from_config(cfg)
    cropped = stages.crop(ctx, stages.load(ctx))
    write(tmp_path / "m.btf", seed=1)  # another file under the same name
    with pytest.raises(DataError, match="has changed since.*m.btf"):
        stages.abrdf(cropped)


def test_a_crop_that_does_not_fit_is_refused_from_the_header_naming_a_fitting_offset(tmp_path):
    from pipeline.btf import stages
    from pipeline.core.stage import Context

    write(tmp_path / "m.btf")  # 4 x 5 texels
    cfg = _load_config(tmp_path, tmp_path / "m.btf", "btf.crop.offset=[2,2]")
    ctx = Context.from_config(cfg)
    loaded = stages.load(ctx)
    with pytest.raises(
        ConfigError, match=r"btf.crop.offset=\[2, 2\].*give btf.crop.offset=\[1, 2\]"
    ):
        stages.crop(ctx, loaded)
    assert not list(Path(cfg.paths.cache).glob("crop/*/*"))


def test_a_bad_file_fails_the_load_stage_naming_it_and_caches_nothing(tmp_path):
    from pipeline.btf import stages
    from pipeline.core.stage import Context

    write(tmp_path / "m.btf")
    path = tmp_path / "m.btf"
    path.write_bytes(path.read_bytes()[:-8])
    cfg = _load_config(tmp_path, path)
    with pytest.raises(DataError, match=f"truncated.*{re.escape(str(path))}"):
        stages.load(Context.from_config(cfg))
    cache = Path(cfg.paths.cache)
    assert not [p for p in cache.glob("*/*") if not p.name.startswith(".")]


def test_load_ubo2014_returns_a_btf(tmp_path):
    write(tmp_path / "m.btf")
    btf = load_ubo2014(tmp_path / "m.btf", views=[[30, 90]], crop=[0, 0, 2, 2])
    assert btf.images.shape == (N_LIGHTS, 2, 2, 3) and btf.root == tmp_path / "m.btf"
    np.testing.assert_allclose(np.degrees(btf.directions[:, 2:]), [[30, 90]] * N_LIGHTS, atol=1e-4)


# --- memory ---------------------------------------------------------------------------------


@pytest.mark.slow
def test_loading_a_crop_of_a_paper_shaped_file_keeps_the_heap_below_the_decoded_crop(tmp_path):
    """151 × 151 directions, 400 × 400 texels: loading a 100 × 100 crop of 24 views into a
    memory map holds a block of directions at a time, not the decoded crop (let alone the
    whole texture's 22801 × 400 × 400 values)."""
    from benchmarks.ubo2014_load import bench_crop_load, write_paper_shaped

    path = write_paper_shaped(tmp_path / "paper.btf", components=8)
    result = bench_crop_load(path, tmp_path, crop=(100, 200, 100, 100), views=list(range(24)))
    assert result["n_images"] == 24 * 151
    assert result["heap_peak_bytes"] < result["out_bytes"] / 4


def test_factors_that_give_nan_are_refused_naming_the_file(tmp_path):
    from pipeline.data.ubo2014_decode import FactorABRDFs

    factors = random_factors(0)
    factors[1][1][5, 0] = np.nan  # one U entry of channel G: direction row 5
    write(tmp_path / "m.btf", factors=factors)
    served = FactorABRDFs(read_dfmf(tmp_path / "m.btf"), np.arange(ROWS), [0, 0, 2, 2])
    served[:, :5]  # the rows before it decode
    with pytest.raises(DataError, match=r"NaN or Inf at 1 direction rows \(first 5\).*m\.btf"):
        served[:2]


def test_values_below_minus_one_are_refused_naming_the_dataset(tmp_path):
    """Eq. 1 takes log(x + 1): a file of noise factors (half its values negative) is not
    radiance, and preprocessing says so instead of training on NaN."""
    from pipeline.btf import stages
    from pipeline.core.stage import Context

    factors = [(s, u - 1.5, sv) for s, u, sv in random_factors(0)]  # values well below 0
    write(tmp_path / "m.btf", factors=factors)
    cfg = _load_config(tmp_path, tmp_path / "m.btf")
    ctx = Context.from_config(cfg)
    cropped = stages.crop(ctx, stages.load(ctx))
    with pytest.raises(DataError, match=r"values down to .* x > -1.*m\.btf"):
        stages.preprocess(ctx, cropped)
