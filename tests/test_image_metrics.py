"""PSNR, per-image MSE, SSIM and FLIP: by hand on tiny inputs, and against the reference
implementations (scikit-image's SSIM, NVIDIA's flip-evaluator) where those are installed."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from pipeline.core.image_metrics import flip, per_image_mse, psnr, ssim


def _smooth_pair(rng, shape, noise=0.05):
    """A smooth random image in [0, 1] and a noisy copy of it, clipped to [0, 1]."""
    sigma = (2.0, 2.0, 0.0)[: len(shape)]
    reference = gaussian_filter(rng.random(shape), sigma)
    reference = (reference - reference.min()) / (reference.max() - reference.min())
    test = np.clip(reference + noise * rng.standard_normal(shape), 0.0, 1.0)
    return reference, test


# --- PSNR -------------------------------------------------------------------------------


def test_psnr_by_hand():
    reference = np.zeros((2, 3))
    assert psnr(reference, reference + 0.1) == pytest.approx(20.0)  # MSE 0.01
    assert psnr(reference, reference + 0.1, peak=2.0) == pytest.approx(10 * np.log10(400))
    # squared errors 0 and 0.04 -> MSE 0.02 -> 10 log10(50)
    assert psnr([0.0, 0.0], [0.0, 0.2]) == pytest.approx(16.989700043360188)


def test_psnr_identical_is_inf():
    assert psnr(np.ones(5), np.ones(5)) == float("inf")


# --- per-image MSE ----------------------------------------------------------------------


def test_per_image_mse_matches_hand_loop_for_images():
    rng = np.random.default_rng(0)
    reference, test = rng.random((2, 4, 5, 6, 3)), rng.random((2, 4, 5, 6, 3))
    image_mses = [np.mean((reference[i, j] - test[i, j]) ** 2) for i in range(2) for j in range(4)]
    assert per_image_mse(reference, test) == pytest.approx(np.mean(image_mses), rel=1e-12)


def test_per_image_mse_matches_hand_loop_for_btf():
    rng = np.random.default_rng(1)
    reference, test = rng.random((20, 7, 3)), rng.random((20, 7, 3))  # (M texels, N dirs, 3)
    direction_mses = [np.mean((reference[:, n] - test[:, n]) ** 2) for n in range(7)]
    measured = per_image_mse(reference, test, image_axes=(0, 2))
    assert measured == pytest.approx(np.mean(direction_mses), rel=1e-12)
    # Equal-sized images: the mean of their MSEs is the MSE over all values.
    assert measured == pytest.approx(np.mean((reference - test) ** 2), rel=1e-12)


@pytest.mark.parametrize(
    ("image_axes", "message"),
    [((0, 3), "out of range"), ((0, -3), "names an axis twice"), ((), "non-empty")],
)
def test_per_image_mse_rejects_bad_image_axes(image_axes, message):
    with pytest.raises(ValueError, match=message):
        per_image_mse(np.zeros((4, 2, 3)), np.zeros((4, 2, 3)), image_axes=image_axes)


# --- SSIM -------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(16, 16), (20, 24, 3)])
def test_ssim_of_identical_images_is_one(shape):
    reference, _ = _smooth_pair(np.random.default_rng(2), shape)
    assert ssim(reference, reference) == pytest.approx(1.0, abs=1e-12)


def test_ssim_of_constant_images_by_hand():
    # No variance: the structure term is C2 / C2 = 1, the luminance term is left.
    a, b = 0.3, 0.5
    c1 = (0.01 * 1.0) ** 2
    expected = (2 * a * b + c1) / (a**2 + b**2 + c1)
    assert ssim(np.full((12, 12), a), np.full((12, 12), b)) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize(
    ("shape", "data_range"), [((32, 40), 1.0), ((32, 40, 3), 1.0), ((24, 24, 3), 2.0)]
)
def test_ssim_matches_scikit_image(shape, data_range):
    metrics = pytest.importorskip("skimage.metrics", reason="scikit-image cross-checks ssim")
    reference, test = _smooth_pair(np.random.default_rng(3), shape, noise=0.1)
    expected = metrics.structural_similarity(
        reference,
        test,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=data_range,
        channel_axis=-1 if len(shape) == 3 else None,
    )
    assert ssim(reference, test, data_range=data_range) == pytest.approx(expected, abs=1e-10)


# --- FLIP -------------------------------------------------------------------------------

# Linear sRGB -> CIE XYZ (IEC 61966-2-1) and the D65 white, as FLIP uses them.
SRGB_TO_XYZ = np.array(
    [
        [0.4123908, 0.3575843, 0.1804808],
        [0.2126390, 0.7151687, 0.0721923],
        [0.0193308, 0.1191948, 0.9505322],
    ]
)
D65_WHITE = np.array([0.950428545, 1.0, 1.088900371])


def _hunt_lab(srgb):
    """Hunt-adjusted CIELab (L, 0.01 L a, 0.01 L b) of one sRGB-encoded colour, shape (3,)."""
    srgb = np.asarray(srgb, dtype=np.float64)
    linear = np.where(srgb > 0.04045, ((srgb + 0.055) / 1.055) ** 2.4, srgb / 12.92)
    xyz = SRGB_TO_XYZ @ linear / D65_WHITE
    f = np.where(xyz > (6 / 29) ** 3, np.cbrt(xyz), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    lightness = 116 * f[1] - 16
    return np.array([lightness, 5.0 * lightness * (f[0] - f[1]), 2.0 * lightness * (f[1] - f[2])])


def _uniform_ldr_flip(colour_a, colour_b):
    """LDR-FLIP of two single-colour images by hand: no edges or points, so the error is
    the colour term alone, HyAB**0.7 remapped by cmax (green vs blue), pc 0.4, pt 0.95."""

    def hyab(a, b):
        return abs(a[0] - b[0]) + np.hypot(a[1] - b[1], a[2] - b[2])

    cmax = hyab(_hunt_lab([0, 1, 0]), _hunt_lab([0, 0, 1])) ** 0.7  # 0 and 1 encode as-is
    error = hyab(_hunt_lab(colour_a), _hunt_lab(colour_b)) ** 0.7
    if error < 0.4 * cmax:
        return 0.95 * error / (0.4 * cmax)
    return 0.95 + 0.05 * (error - 0.4 * cmax) / (0.6 * cmax)


@pytest.mark.parametrize(
    ("colour_a", "colour_b"),
    [((0.2, 0.5, 0.8), (0.25, 0.45, 0.8)), ((0.9, 0.1, 0.1), (0.1, 0.9, 0.1))],
)
def test_ldr_flip_of_uniform_images_by_hand(colour_a, colour_b):
    pytest.importorskip("flip_evaluator", reason="flip() calls NVIDIA's flip-evaluator")
    reference = np.broadcast_to(colour_a, (16, 16, 3))
    test = np.broadcast_to(colour_b, (16, 16, 3))
    # The package works in float32: agreement to ~4e-5 is measured.
    assert flip(reference, test) == pytest.approx(_uniform_ldr_flip(colour_a, colour_b), abs=1e-4)


@pytest.mark.parametrize("pixels_per_degree", [67.0, 30.0])
def test_ldr_flip_matches_reference_package(pixels_per_degree):
    flip_evaluator = pytest.importorskip("flip_evaluator", reason="the reference FLIP")
    reference, test = _smooth_pair(np.random.default_rng(4), (32, 32, 3))
    _, expected, _ = flip_evaluator.evaluate(
        reference, test, "LDR", applyMagma=False, parameters={"ppd": pixels_per_degree}
    )
    measured = flip(reference, test, pixels_per_degree=pixels_per_degree)
    assert measured == pytest.approx(expected, abs=1e-6)
    assert 0.0 < measured < 1.0


@pytest.mark.parametrize("dynamic_range", ["ldr", "hdr"])
def test_flip_of_identical_images_is_zero(dynamic_range):
    pytest.importorskip("flip_evaluator", reason="flip() calls NVIDIA's flip-evaluator")
    reference, _ = _smooth_pair(np.random.default_rng(5), (32, 32, 3))
    assert flip(reference, reference, dynamic_range=dynamic_range) == 0.0


def test_hdr_flip_ignores_a_common_scale():
    # HDR-FLIP picks its exposures from the reference's luminance, so scaling both images
    # by 4 shifts the exposures by -2 stops and leaves the error unchanged; LDR-FLIP
    # sees the pair differently once values are scaled.
    pytest.importorskip("flip_evaluator", reason="flip() calls NVIDIA's flip-evaluator")
    reference, test = _smooth_pair(np.random.default_rng(6), (32, 32, 3))
    once = flip(reference, test, dynamic_range="hdr")
    assert flip(4 * reference, 4 * test, dynamic_range="hdr") == pytest.approx(once, rel=1e-4)
    assert flip(reference / 4, test / 4) != pytest.approx(flip(reference, test), rel=1e-2)


# --- input checks -----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: psnr(np.zeros((2, 3)), np.zeros((3, 2))), r"shape \(2, 3\) but test"),
        (lambda: psnr(np.zeros(3), [0.0, np.nan, 0.0]), "test .* 1 NaN or Inf"),
        (lambda: psnr(np.zeros(0), np.zeros(0)), "empty"),
        (lambda: psnr(np.zeros(3), np.zeros(3), peak=0.0), "peak must be"),
        (lambda: ssim(np.zeros((10, 20)), np.zeros((10, 20))), "at least 11x11"),
        (lambda: ssim(np.zeros((12, 12, 3, 1)), np.zeros((12, 12, 3, 1))), r"\(H, W\)"),
        (lambda: ssim(np.zeros((12, 12)), np.zeros((12, 12)), data_range=-1), "data_range"),
        (lambda: flip(np.zeros((8, 8)), np.zeros((8, 8))), r"\(H, W, 3\)"),
        (lambda: flip(np.zeros((8, 8, 3)), np.full((8, 8, 3), 1.5)), r"test .* \[0, 1\]"),
        (
            lambda: flip(np.full((8, 8, 3), -1.0), np.zeros((8, 8, 3)), dynamic_range="hdr"),
            "reference .* >= 0",
        ),
        (
            lambda: flip(np.zeros((8, 8, 3)), np.zeros((8, 8, 3)), dynamic_range="sdr"),
            "'ldr' or 'hdr'",
        ),
        (
            lambda: flip(np.zeros((8, 8, 3)), np.zeros((8, 8, 3)), pixels_per_degree=0),
            "pixels_per_degree",
        ),
    ],
)
def test_bad_inputs_are_named(call, message):
    with pytest.raises(ValueError, match=message):
        call()
