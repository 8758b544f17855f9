"""The field's image error metrics beside RMSE: PSNR, per-image MSE, SSIM and FLIP.

Pure functions of two arrays of the same shape, ``reference`` first, taken as they come
(the BTF pipeline's linear normalised space), except LDR-FLIP, which models a display and
expects sRGB-encoded values in [0, 1].

Example
-------
>>> reference = np.zeros((4, 4))
>>> round(psnr(reference, reference + 0.1), 6)  # MSE 0.01
20.0
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

__all__ = ["psnr", "per_image_mse", "ssim", "flip"]

# Wang et al. 2004: an 11-tap Gaussian window (sigma 1.5, truncated at 3.5 sigma as
# scikit-image does), population (co)variances, and the stabilising constants K1, K2.
SSIM_SIGMA = 1.5
SSIM_TRUNCATE = 3.5
SSIM_RADIUS = int(SSIM_TRUNCATE * SSIM_SIGMA + 0.5)  # 5, the radius gaussian_filter uses
SSIM_K1, SSIM_K2 = 0.01, 0.03


def _check_pair(reference, test) -> tuple[np.ndarray, np.ndarray]:
    """Both arrays as float64, checked to match in shape and be finite."""
    reference = np.asarray(reference, dtype=np.float64)
    test = np.asarray(test, dtype=np.float64)
    if reference.shape != test.shape:
        raise ValueError(
            f"reference has shape {reference.shape} but test has shape {test.shape}; "
            "they must match"
        )
    if reference.size == 0:
        raise ValueError(f"reference and test are empty (shape {reference.shape})")
    for name, values in (("reference", reference), ("test", test)):
        bad = np.count_nonzero(~np.isfinite(values))
        if bad:
            raise ValueError(f"{name} (shape {values.shape}) holds {bad} NaN or Inf values")
    return reference, test


def _check_positive(name: str, value) -> float:
    value = float(value)
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {value}")
    return value


def psnr(reference, test, peak: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB over all values: ``10 log10(peak² / MSE)``.

    Parameters
    ----------
    reference, test : ndarray of any shape, the same for both
        Values in the linear normalised space, where ``peak = 1`` is the crop's maximum
        after normalisation.
    peak : float
        The largest value the signal can take.

    Returns
    -------
    float
        PSNR in dB; ``inf`` when the arrays are equal (MSE 0).
    """
    reference, test = _check_pair(reference, test)
    peak = _check_positive("peak", peak)
    mse = float(np.mean((reference - test) ** 2))
    return float("inf") if mse == 0.0 else float(10.0 * np.log10(peak**2 / mse))


def per_image_mse(reference, test, image_axes: tuple[int, ...] = (-3, -2, -1)) -> float:
    """The "per-image MSE" of NeuMIP and Neural Biplane: each image's MSE, averaged.

    Parameters
    ----------
    reference, test : ndarray of the same shape
        Images ``(..., H, W, 3)`` or a BTF ``(M texels, N directions, 3)``.
    image_axes : tuple of int
        The axes that one image spans, its channel axis included; every other axis indexes
        images. ``(-3, -2, -1)`` (the default) for ``(..., H, W, 3)``; ``(0, 2)`` for a BTF
        ``(M, N, 3)``, whose images are the directions, each seen over all texels.

    Returns
    -------
    float
        The mean over images of each image's MSE (over its pixels and channels, averaged,
        not summed). All images have as many values, so this is the MSE over all values.
    """
    reference, test = _check_pair(reference, test)
    axes = tuple(image_axes)
    if not axes or any(not isinstance(a, int | np.integer) for a in axes):
        raise ValueError(f"image_axes must be a non-empty tuple of ints, got {image_axes!r}")
    if any(not -reference.ndim <= a < reference.ndim for a in axes):
        raise ValueError(f"image_axes={axes} is out of range for arrays of shape {reference.shape}")
    if len({a % reference.ndim for a in axes}) != len(axes):
        raise ValueError(f"image_axes={axes} names an axis twice (shape {reference.shape})")
    image_mse = np.mean((reference - test) ** 2, axis=axes)
    return float(np.mean(image_mse))


def ssim(reference, test, data_range: float = 1.0) -> float:
    """Mean structural similarity (Wang et al. 2004) of two images, channels averaged.

    A Gaussian window (sigma 1.5, 11 taps), K1 = 0.01, K2 = 0.03, population (co)variances,
    the map's 5-pixel border left out of the mean: scikit-image's ``structural_similarity``
    with ``gaussian_weights=True, sigma=1.5, use_sample_covariance=False``.

    Parameters
    ----------
    reference, test : ndarray of shape (H, W) or (H, W, C), the same for both
        H and W at least 11, the window's width.
    data_range : float
        The range the values can span (max - min possible), which scales K1 and K2.

    Returns
    -------
    float
        The mean SSIM, 1 for identical images.
    """
    reference, test = _check_pair(reference, test)
    data_range = _check_positive("data_range", data_range)
    if reference.ndim not in (2, 3):
        raise ValueError(f"ssim needs images of shape (H, W) or (H, W, C), got {reference.shape}")
    width = 2 * SSIM_RADIUS + 1
    if min(reference.shape[:2]) < width:
        raise ValueError(
            f"ssim needs images at least {width}x{width} (its window), got {reference.shape}"
        )
    # sigma 0 on the channel axis: gaussian_filter leaves that axis unfiltered.
    sigma = (SSIM_SIGMA, SSIM_SIGMA, 0.0)[: reference.ndim]

    def window_mean(values: np.ndarray) -> np.ndarray:
        return gaussian_filter(values, sigma, mode="reflect", truncate=SSIM_TRUNCATE)

    mean_ref, mean_test = window_mean(reference), window_mean(test)
    var_ref = window_mean(reference * reference) - mean_ref**2
    var_test = window_mean(test * test) - mean_test**2
    covariance = window_mean(reference * test) - mean_ref * mean_test
    c1, c2 = (SSIM_K1 * data_range) ** 2, (SSIM_K2 * data_range) ** 2
    ssim_map = ((2 * mean_ref * mean_test + c1) * (2 * covariance + c2)) / (
        (mean_ref**2 + mean_test**2 + c1) * (var_ref + var_test + c2)
    )
    inner = ssim_map[SSIM_RADIUS:-SSIM_RADIUS, SSIM_RADIUS:-SSIM_RADIUS]
    return float(np.mean(inner))


def flip(reference, test, pixels_per_degree: float = 67.0, dynamic_range: str = "ldr") -> float:
    """Mean FLIP error (Andersson et al. 2020; HDR-FLIP, Andersson et al. 2021).

    Parameters
    ----------
    reference, test : ndarray of shape (H, W, 3), the same for both
        RGB images. For ``"ldr"``: sRGB-encoded values in [0, 1] (linear renders must be
        encoded first). For ``"hdr"``: linear RGB values >= 0; HDR-FLIP tone-maps them
        (ACES) at exposures chosen from the reference and keeps each pixel's worst
        LDR-FLIP error.
    pixels_per_degree : float
        The observer's pixels per degree of visual angle; 67 is a 0.7 m wide 4K display
        seen from 0.7 m (the package's own default is 67.02, from that geometry).
    dynamic_range : {"ldr", "hdr"}

    Returns
    -------
    float
        The mean of the per-pixel FLIP error map, in [0, 1]; 0 for identical images.
    """
    reference, test = _check_pair(reference, test)
    pixels_per_degree = _check_positive("pixels_per_degree", pixels_per_degree)
    if reference.ndim != 3 or reference.shape[2] != 3:
        raise ValueError(f"flip needs RGB images of shape (H, W, 3), got {reference.shape}")
    mode = str(dynamic_range).lower()
    if mode not in ("ldr", "hdr"):
        raise ValueError(f"dynamic_range must be 'ldr' or 'hdr', got {dynamic_range!r}")
    for name, values in (("reference", reference), ("test", test)):
        low, high = float(values.min()), float(values.max())
        if low < 0 or (mode == "ldr" and high > 1):
            allowed = "[0, 1] (sRGB-encoded)" if mode == "ldr" else ">= 0 (linear)"
            raise ValueError(
                f"{name} for {mode.upper()}-FLIP must hold values {allowed}, "
                f"got [{low:g}, {high:g}]"
            )
    # NVIDIA's own code (flip-evaluator), which gave the published values; imported here so
    # that the other metrics work without it.
    import flip_evaluator

    # It calls sys.exit on bad arguments (hence the checks above), and its default
    # `parameters` is a shared dict: pass a fresh one every time.
    _, mean_error, _ = flip_evaluator.evaluate(
        np.ascontiguousarray(reference, dtype=np.float32),
        np.ascontiguousarray(test, dtype=np.float32),
        mode.upper(),
        applyMagma=False,
        computeMeanError=True,
        parameters={"ppd": pixels_per_degree},
    )
    return float(mean_error)
