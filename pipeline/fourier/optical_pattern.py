"""Optical-pattern synthesis: blend per-region renders with weight maps (paper eq. 20).

Each reflectance region i has its own synthesized Fourier-coefficient map (from
:func:`pipeline.fourier.quilting.quilt`). For a light, a view and the target object's
normals, every map is rendered (:func:`pipeline.fourier.series.render_fourier`) and the
renders are combined per pixel::

    I_xy = Σ_i α_xyi I_xyi,   Σ_i α_xyi = 1                                  (eq. 20)

The weight maps α are where a user paints a new pattern. Generators for stripes and
blobs, and a loader for painted maps, are here.

Example
-------
>>> weights = stripe_weights((4, 6), n_regions=2, period=2)
>>> np.allclose(weights.sum(axis=0), 1.0)
True
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter

from pipeline.core.errors import ConfigError, DataError
from pipeline.fourier.series import VIEW, render_fourier

# Weight maps often come from 8-bit images; sums within this of 1 are accepted.
_SUM_TOLERANCE = 1e-3


def check_weights(weights, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Validate eq. 20's weights: shape (n, H, W), each >= 0, summing to 1 per pixel.

    Returns the weights as float64; ConfigError naming the worst pixel otherwise.
    """
    weights = np.asarray(weights, dtype=np.float64)
    if weights.ndim != 3 or weights.shape[0] < 1:
        raise ConfigError(f"weights must have shape (n_regions, H, W), got {weights.shape}")
    if shape is not None and weights.shape[1:] != tuple(shape):
        raise ConfigError(f"weights are {weights.shape[1:]} but the renders are {tuple(shape)}")
    if not np.all(np.isfinite(weights)) or weights.min() < -_SUM_TOLERANCE:
        raise ConfigError(f"weights must be finite and >= 0; minimum is {weights.min()}")
    deviation = np.abs(weights.sum(axis=0) - 1.0)
    if deviation.max() > _SUM_TOLERANCE:
        row, col = np.unravel_index(deviation.argmax(), deviation.shape)
        raise ConfigError(
            f"weights must sum to 1 at every pixel (eq. 20); at row {row}, column {col} "
            f"they sum to {weights[:, row, col].sum():.6g}"
        )
    return weights


def blend_renders(renders, weights) -> np.ndarray:
    """Eq. 20, Σ_i α_i I_i, of renders (n_regions, H, W, 3) and weights (n_regions, H, W):
    an (H, W, 3) float32 image."""
    renders = np.asarray(renders)
    if renders.ndim != 4:
        raise ConfigError(f"renders must have shape (n_regions, H, W, C), got {renders.shape}")
    weights = check_weights(weights, renders.shape[1:3])
    if weights.shape[0] != renders.shape[0]:
        raise ConfigError(f"{weights.shape[0]} weight maps for {renders.shape[0]} renders")
    return np.einsum("nhw,nhwc->hwc", weights, renders).astype(np.float32)


def render_optical_pattern(
    coeff_maps, weights, light_dir, normals, view=VIEW, clamp_diffuse: bool = False
) -> np.ndarray:
    """Render each region's coefficient map on the target and blend (eq. 20).

    Parameters
    ----------
    coeff_maps : sequence of ndarray of shape (H, W, 3, 2M + 2)
        One synthesized Fourier-coefficient map per region.
    weights : ndarray of shape (n_regions, H, W)
    light_dir : array_like of shape (3,)
        The virtual light.
    normals : ndarray of shape (H, W, 3)
        The target (screen) object's normals, seen from the projector.
    view : array_like of shape (3,)
    clamp_diffuse : bool
        As used when fitting the coefficients.

    Returns
    -------
    ndarray of shape (H, W, 3), float32
    """
    if len(coeff_maps) == 0:
        raise ConfigError("coeff_maps is empty: need one coefficient map per region")
    renders = np.stack(
        [render_fourier(coeffs, light_dir, normals, view, clamp_diffuse) for coeffs in coeff_maps]
    )
    if renders.ndim != 4:
        raise ConfigError(
            f"light_dir must be one direction of shape (3,), got {np.shape(light_dir)}"
        )
    return blend_renders(renders, weights)


def normalize_weights(raw, name: str = "weights") -> np.ndarray:
    """Divide non-negative maps (n, H, W) by their per-pixel sum; zero sums are errors."""
    raw = np.asarray(raw, dtype=np.float64)
    if raw.ndim != 3:
        raise DataError(f"{name} must have shape (n_regions, H, W), got {raw.shape}")
    if not np.all(np.isfinite(raw)) or raw.min() < 0:
        raise DataError(f"{name} must be finite and >= 0")
    total = raw.sum(axis=0)
    if np.any(total <= 0):
        row, col = np.argwhere(total <= 0)[0]
        raise DataError(
            f"{name}: every weight is zero at row {row}, column {col} "
            f"({int((total <= 0).sum())} such pixels)"
        )
    return raw / total


def _one_hot_blurred(labels: np.ndarray, n_regions: int, softness: float) -> np.ndarray:
    one_hot = (labels[None] == np.arange(n_regions)[:, None, None]).astype(np.float64)
    if softness > 0:
        # A linear filter that preserves constants keeps the per-pixel sum at 1.
        one_hot = gaussian_filter(one_hot, (0, softness, softness), mode="nearest")
    return one_hot / one_hot.sum(axis=0)


def _check_shape(shape) -> tuple[int, int]:
    shape = tuple(int(n) for n in shape)
    if len(shape) != 2 or min(shape) < 1:
        raise ConfigError(f"shape must be (H, W) with H, W >= 1, got {shape!r}")
    return shape


def stripe_weights(
    shape, n_regions: int = 2, period: float = 32.0, angle_deg: float = 0.0, softness: float = 0.0
) -> np.ndarray:
    """Parallel stripes cycling through the regions.

    Parameters
    ----------
    shape : (H, W)
    n_regions : int
    period : float
        Pixels per full cycle of all regions.
    angle_deg : float
        Direction across the stripes, counter-clockwise from the x axis.
    softness : float
        Gaussian blur (pixels) of the stripe edges.

    Returns
    -------
    ndarray of shape (n_regions, H, W), float64, summing to 1 per pixel
    """
    height, width = _check_shape(shape)
    if n_regions < 1 or period <= 0 or softness < 0:
        raise ConfigError(
            f"need n_regions >= 1, period > 0, softness >= 0; got {n_regions}, {period}, {softness}"
        )
    yy, xx = np.mgrid[:height, :width].astype(np.float64)
    angle = np.radians(angle_deg)
    phase = (xx * np.cos(angle) - yy * np.sin(angle)) / period
    labels = np.floor((phase % 1.0) * n_regions).astype(int) % n_regions
    return _one_hot_blurred(labels, n_regions, softness)


def blob_weights(
    shape,
    n_regions: int = 2,
    rng: np.random.Generator | None = None,
    n_blobs: int = 6,
    radius: float = 0.12,
    softness: float = 2.0,
) -> np.ndarray:
    """Round blobs of regions 1..n-1 on a region-0 ground.

    Parameters
    ----------
    shape : (H, W)
    n_regions : int, >= 2
    rng : numpy.random.Generator
        Blob centres, radii and regions.
    n_blobs : int
    radius : float
        Mean blob radius as a fraction of min(H, W).
    softness : float
        Gaussian blur (pixels) of the blob edges.

    Returns
    -------
    ndarray of shape (n_regions, H, W), float64, summing to 1 per pixel
    """
    height, width = _check_shape(shape)
    if not isinstance(rng, np.random.Generator):
        raise ConfigError(f"rng must be a numpy.random.Generator, got {rng!r}")
    if n_regions < 2 or n_blobs < 0 or radius <= 0 or softness < 0:
        raise ConfigError(
            f"need n_regions >= 2, n_blobs >= 0, radius > 0, softness >= 0; "
            f"got {n_regions}, {n_blobs}, {radius}, {softness}"
        )
    yy, xx = np.mgrid[:height, :width].astype(np.float64)
    labels = np.zeros((height, width), dtype=int)
    for _ in range(n_blobs):
        cy, cx = rng.uniform(0, height), rng.uniform(0, width)
        blob_radius = radius * min(height, width) * rng.uniform(0.5, 1.5)
        labels[(yy - cy) ** 2 + (xx - cx) ** 2 < blob_radius**2] = rng.integers(1, n_regions)
    return _one_hot_blurred(labels, n_regions, softness)


def load_weight_map(path: str | os.PathLike, n_regions: int | None = None) -> np.ndarray:
    """Read painted weight maps and normalize them to sum 1 per pixel.

    Parameters
    ----------
    path : path-like
        ``.npy`` of shape (n, H, W); or an image read as plain values in [0, 1] (no sRGB
        decoding: the pixels are weights, not colours). A grey-level image gives two
        regions (v, 1 - v); an RGB image gives one region per channel (the first
        ``n_regions``, default 3).
    n_regions : int, optional
        Expected number of regions; a mismatch is a DataError.

    Returns
    -------
    ndarray of shape (n_regions, H, W), float64, summing to 1 per pixel
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"weight map {path} does not exist")
    if path.suffix.lower() == ".npy":
        try:
            raw = np.load(path, allow_pickle=False).astype(np.float64)
        except (OSError, ValueError) as exc:
            raise DataError(f"cannot read weight map {path}: {exc}") from exc
    else:
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(path) as image:
                image.load()
                grey = image.mode in ("1", "L", "I", "I;16", "F", "LA")
                if image.mode.startswith("I") or image.mode == "F":
                    values = np.asarray(image, dtype=np.float64)
                    values = values / (65535.0 if values.max() > 255 else 255.0)
                else:
                    converted = image.convert("L" if grey else "RGB")
                    values = np.asarray(converted, dtype=np.float64) / 255.0
        except (OSError, UnidentifiedImageError, SyntaxError) as exc:
            raise DataError(f"cannot read weight map {path}: {exc}") from exc
        if values.ndim == 2:
            raw = np.stack([values, 1.0 - values])
        else:
            raw = np.moveaxis(values[..., : (n_regions or 3)], -1, 0)
    if raw.ndim != 3:
        raise DataError(f"weight map {path} must hold (n_regions, H, W), got {raw.shape}")
    if n_regions is not None and raw.shape[0] != n_regions:
        raise DataError(f"weight map {path} holds {raw.shape[0]} regions, expected {n_regions}")
    return normalize_weights(raw, f"weight map {path}")
