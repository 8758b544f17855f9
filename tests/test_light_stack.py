"""RTI light-stack reader and writer, and the built-in synthetic pot."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from pipeline.core.errors import ConfigError, DataError
from pipeline.data.light_stack import (
    load_btf_view,
    load_light_stack,
    load_normal_map,
    read_lp,
    srgb_to_linear,
    write_lp,
)
from pipeline.fourier.synthetic import (
    REGION_NAMES,
    SyntheticStackConfig,
    grid_light_dirs,
    load_synthetic_scene,
    write_synthetic_stack,
)

REAL_CAPTURE = Path(__file__).resolve().parents[2] / "shared/data/rti/neuralrti-example"

DIRS = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -0.6, 0.8]])


def _write_png(path: Path, value: int, size=(4, 5)) -> None:
    Image.fromarray(np.full((*size, 3), value, dtype=np.uint8)).save(path)


@pytest.fixture
def stack_dir(tmp_path):
    """Three 4x5 grey PNGs and a matching .lp file."""
    names = [f"im{i}.png" for i in range(3)]
    for i, name in enumerate(names):
        _write_png(tmp_path / name, 60 * (i + 1))
    write_lp(tmp_path / "lights.lp", names, DIRS)
    return tmp_path


def _write_text(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# --------------------------------------------------------------------------- reading


def test_reads_stack_in_lp_order(stack_dir):
    stack = load_light_stack(stack_dir)
    assert stack.images.shape == (3, 4, 5, 3) and stack.images.dtype == np.float32
    np.testing.assert_allclose(stack.light_dirs, DIRS, atol=1e-7)
    assert [p.name for p in stack.paths] == ["im0.png", "im1.png", "im2.png"]
    np.testing.assert_allclose(stack.images[1], srgb_to_linear(np.float32(120 / 255)), rtol=1e-6)


def test_srgb_eotf_reference_values():
    np.testing.assert_allclose(
        srgb_to_linear(np.array([0.0, 0.04045, 0.5, 1.0])),
        [0.0, 0.04045 / 12.92, 0.2140411, 1.0],
        rtol=1e-5,
    )


def test_blank_lines_and_non_unit_vectors(tmp_path):
    _write_png(tmp_path / "a.png", 10)
    _write_png(tmp_path / "b.png", 20)
    _write_text(tmp_path / "x.lp", "\n2\n\na.png 0 0 2\n\nb.png 3 0 4\n\n")
    paths, dirs = read_lp(tmp_path / "x.lp")
    np.testing.assert_allclose(dirs, [[0, 0, 1], [0.6, 0, 0.8]], atol=1e-7)
    assert [p.name for p in paths] == ["a.png", "b.png"]


def test_windows_absolute_names_fall_back_to_basename(tmp_path):
    _write_png(tmp_path / "a.png", 10)
    _write_text(tmp_path / "x.lp", "1\nC:\\capture\\a.png 0 0 1\n")
    assert load_light_stack(tmp_path).paths[0] == tmp_path / "a.png"


def test_write_lp_round_trip(tmp_path):
    for name in ("a.png", "b.png", "c.png"):
        _write_png(tmp_path / name, 10)
    write_lp(tmp_path / "r.lp", ["a.png", "b.png", "c.png"], DIRS)
    _, dirs = read_lp(tmp_path / "r.lp")
    np.testing.assert_allclose(dirs, DIRS, atol=1e-8)


def test_exr_images_are_read_linear(tmp_path):
    import OpenEXR

    pixels = np.linspace(0, 2, 20, dtype=np.float32).reshape(4, 5)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {c: pixels * (i + 1) for i, c in enumerate("RGB")}).write(
        str(tmp_path / "a.exr")
    )
    write_lp(tmp_path / "x.lp", ["a.exr"], DIRS[:1])
    stack = load_light_stack(tmp_path)
    np.testing.assert_allclose(stack.images[0, ..., 2], 3 * pixels)


def test_normal_maps_png_npy_and_array(stack_dir, tmp_path_factory):
    encoded = np.zeros((4, 5, 3), dtype=np.uint8)
    encoded[..., 2] = 255  # v = 255 -> n = (-1, -1, 1) before normalization
    Image.fromarray(encoded).save(stack_dir / "n.png")
    stack = load_light_stack(stack_dir, normals=stack_dir / "n.png")
    np.testing.assert_allclose(stack.normals[0, 0], np.array([-1, -1, 1]) / np.sqrt(3), atol=1e-6)
    other = tmp_path_factory.mktemp("normals") / "n.npy"
    np.save(other, np.tile([0.0, 0.0, 2.0], (4, 5, 1)))
    np.testing.assert_allclose(load_normal_map(other)[..., 2], 1.0)
    array_stack = load_light_stack(stack_dir, normals=np.tile([1.0, 0, 0], (4, 5, 1)))
    assert array_stack.normals.shape == (4, 5, 3)


def test_normal_map_exr(tmp_path):
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    planes = {
        "R": np.full((4, 5), 3.0, np.float32),
        "G": np.zeros((4, 5), np.float32),
        "B": np.full((4, 5), 4.0, np.float32),
    }
    OpenEXR.File(header, planes).write(str(tmp_path / "n.exr"))
    np.testing.assert_allclose(
        load_normal_map(tmp_path / "n.exr")[2, 3], [0.6, 0.0, 0.8], atol=1e-6
    )


# --------------------------------------------------------------------------- errors


def test_error_root_missing(tmp_path):
    with pytest.raises(DataError, match="nowhere"):
        load_light_stack(tmp_path / "nowhere")


def test_error_no_lp(tmp_path):
    _write_png(tmp_path / "a.png", 10)
    with pytest.raises(DataError, match="no .lp"):
        load_light_stack(tmp_path)


def test_error_several_lp(stack_dir):
    _write_text(stack_dir / "second.lp", "0\n")
    with pytest.raises(DataError, match="several .lp.*lights.lp.*second.lp"):
        load_light_stack(stack_dir)


def test_error_count_disagrees(stack_dir):
    _write_text(stack_dir / "lights.lp", "4\nim0.png 0 0 1\nim1.png 0 0 1\nim2.png 0 0 1\n")
    with pytest.raises(DataError, match=r"lights.lp, line 1: the count says 4 .* 3"):
        load_light_stack(stack_dir)


def test_error_count_not_a_number(stack_dir):
    _write_text(stack_dir / "lights.lp", "three\nim0.png 0 0 1\n")
    with pytest.raises(DataError, match=r"line 1: expected the number"):
        load_light_stack(stack_dir)


def test_error_line_does_not_parse(stack_dir):
    _write_text(stack_dir / "lights.lp", "3\nim0.png 0 0 1\n\nim1.png 0 zero 1\nim2.png 0 0 1\n")
    with pytest.raises(DataError, match=r"lights.lp, line 4: expected 'filename lx ly lz'"):
        load_light_stack(stack_dir)


def test_error_listed_file_missing(stack_dir):
    _write_text(stack_dir / "lights.lp", "2\nim0.png 0 0 1\nghost.png 0 0 1\n")
    with pytest.raises(DataError, match=r"line 3: listed image .*ghost.png does not exist"):
        load_light_stack(stack_dir)


def test_error_listed_file_corrupt(stack_dir):
    (stack_dir / "im1.png").write_bytes(b"not a png at all")
    with pytest.raises(DataError, match=r"lights.lp, line 3: cannot read image .*im1.png"):
        load_light_stack(stack_dir)


def test_error_zero_light_vector(stack_dir):
    _write_text(stack_dir / "lights.lp", "2\nim0.png 0 0 1\nim1.png 0 0 1e-9\n")
    with pytest.raises(DataError, match=r"lights.lp, line 3: light vector .* zero"):
        load_light_stack(stack_dir)


def test_error_inconsistent_image_sizes(stack_dir):
    _write_png(stack_dir / "im2.png", 10, size=(6, 5))
    with pytest.raises(DataError, match=r"im2.png is 5x6 \(WxH\) but .*im0.png is 5x4"):
        load_light_stack(stack_dir)


def test_error_normal_map_wrong_shape(stack_dir):
    np.save(stack_dir / "n.npy", np.ones((4, 6, 3)))
    with pytest.raises(DataError, match=r"n.npy has size \(4, 6\) but the images are \(4, 5\)"):
        load_light_stack(stack_dir, normals=stack_dir / "n.npy")


def test_error_normal_map_zero_normals(stack_dir):
    np.save(stack_dir / "n.npy", np.zeros((4, 5, 3)))
    with pytest.raises(DataError, match=r"n.npy has 20 zero"):
        load_light_stack(stack_dir, normals=stack_dir / "n.npy")


# --------------------------------------------------------------------------- real capture


@pytest.mark.skipif(
    not (REAL_CAPTURE / "dirs.lp").is_file(),
    reason=f"real RTI capture not present at {REAL_CAPTURE}",
)
def test_real_capture_reads():
    stack = load_light_stack(REAL_CAPTURE)
    assert stack.images.shape == (72, 395, 402, 3)
    np.testing.assert_allclose(np.linalg.norm(stack.light_dirs, axis=1), 1.0, atol=1e-6)
    assert stack.paths[0].name == "image01.jpg" and stack.paths[-1].name == "image72.jpg"
    assert 0.0 <= stack.images.min() and stack.images.max() <= 1.0
    assert np.all(stack.light_dirs[:, 2] > 0)  # every light in front of the object


# --------------------------------------------------------------------------- synthetic


SMALL = dict(n_elevations=2, n_azimuths=5, azimuth_step_deg=20.0, n_heldout=3)


def test_synthetic_stack_layout_and_ground_truth(tmp_path):
    root = tmp_path / "pot"
    scene = write_synthetic_stack(root, size=(32, 24), seed=3, noise_std=0.0, **SMALL)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging left
    stack = load_light_stack(root, normals=root / "normals.npy")
    heldout = load_light_stack(root / "heldout")
    assert stack.images.shape == (10, 32, 24, 3) and heldout.images.shape == (3, 32, 24, 3)
    np.testing.assert_allclose(stack.normals, scene.normals, atol=1e-6)
    regions = np.load(root / "regions.npy")
    assert set(np.unique(regions)) == set(range(len(REGION_NAMES)))
    rebuilt = load_synthetic_scene(root)
    np.testing.assert_array_equal(rebuilt.regions, regions)
    # The PNGs hold the ground truth up to 8-bit sRGB quantization.
    assert np.abs(heldout.images - rebuilt.render(heldout.light_dirs)).max() < 0.01
    assert np.abs(stack.images - rebuilt.render(stack.light_dirs)).max() < 0.01


def test_synthetic_stack_exr_and_overwrite(tmp_path):
    root = tmp_path / "pot"
    write_synthetic_stack(root, size=24, seed=0, image_format="exr", noise_std=0.0, **SMALL)
    with pytest.raises(ConfigError, match="already exists"):
        write_synthetic_stack(root, size=24, seed=0, **SMALL)
    scene = write_synthetic_stack(
        root, size=24, seed=1, overwrite=True, image_format="exr", noise_std=0.0, **SMALL
    )
    stack = load_light_stack(root)
    np.testing.assert_allclose(stack.images, scene.render(stack.light_dirs), atol=1e-6)


def test_paper_light_grid():
    dirs = grid_light_dirs(SyntheticStackConfig())
    assert dirs.shape == (330, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0)
    lateral = np.degrees(np.arctan2(dirs[:55, 0], dirs[:55, 2]))
    np.testing.assert_allclose(np.diff(lateral), 3.0, atol=1e-9)


def test_synthetic_settings_are_checked(tmp_path):
    with pytest.raises(ConfigError, match="n_azimuths=61"):
        write_synthetic_stack(tmp_path / "a", size=32, n_azimuths=61, azimuth_step_deg=3.0)
    with pytest.raises(ConfigError, match="unknown synthetic-stack settings"):
        write_synthetic_stack(tmp_path / "a", size=32, colour="red")


# --------------------------------------------------------------------------- BTF view


@pytest.fixture(scope="module")
def tiny_btf(tmp_path_factory):
    """An 8 x 8 synthetic BTF in the UBO2003 layout (lossless PNG), two view folders."""
    from pipeline.btf.synthetic_dataset import write_synthetic_btf

    root = tmp_path_factory.mktemp("btf") / "tiny"
    return write_synthetic_btf(root, size=8, format="ubo2003", ext="png", views=[(0, 0), (30, 90)])


def test_btf_view_reads_as_a_light_stack_with_its_view_direction(tiny_btf):
    from pipeline.data.btf import load_btf
    from pipeline.data.directions import grid_81

    stack = load_btf_view(tiny_btf, "ubo2003", (30, 90))
    assert stack.images.shape == (81, 8, 8, 3) and stack.lp_path is None
    np.testing.assert_allclose(stack.view_dir, [0.0, 0.5, np.sqrt(3) / 2], atol=1e-12)
    theta, phi = grid_81().T
    expected = np.stack(
        [np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1
    )
    np.testing.assert_allclose(stack.light_dirs, expected, atol=1e-6)
    btf = load_btf(tiny_btf, "ubo2003", views=[(30, 90)], progress=False)
    np.testing.assert_array_equal(stack.images, btf.images)
    assert all("tv030 pv090" in p.name for p in stack.paths)
    # The view from the top is the RTI stacks' (0, 0, 1).
    assert load_btf_view(tiny_btf, "ubo2003", (0, 0)).view_dir.tolist() == [0.0, 0.0, 1.0]
    subset = stack.subset([0, 1])
    assert subset.view_dir is stack.view_dir and len(subset.light_dirs) == 2


def test_btf_view_errors(tiny_btf):
    with pytest.raises(ConfigError, match=r"one \[theta_v, phi_v\] pair"):
        load_btf_view(tiny_btf, "ubo2003", [[0, 0], [30, 90]])
    with pytest.raises(ConfigError, match="not one of the 81 grid directions"):
        load_btf_view(tiny_btf, "ubo2003", (10, 0))
    with pytest.raises(DataError, match="requested view folder"):
        load_btf_view(tiny_btf, "ubo2003", (15, 0))
