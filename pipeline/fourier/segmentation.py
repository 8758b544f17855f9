"""Reflectance-region segmentation of a light stack (PAPERS.md C, step 1; paper §4.2.2).

Two ways to label each pixel with a reflectance region:

- :func:`segment_by_representatives` -- the paper's: average the images over all lights
  (which evens out the shading that a single light leaves), take the colour of one
  representative pixel per region (picked by the user), and give every pixel the label
  of the nearest representative colour.
- :func:`segment_kmeans` -- automatic (the paper's future work): k-means (scikit-learn,
  k-means++ initialization, seeded) on any per-pixel feature: the mean colour, or the
  fitted Fourier coefficients.

Colours are compared in ``colour_space="rgb"`` by default, as in the paper ("colour
information"); ``"chromaticity"`` divides each colour by its channel sum first, which
removes the brightness left over from foreshortening on a curved object (an option,
not in the paper).

:func:`segmentation_accuracy` scores a labelling against ground truth up to a
renaming of the labels (Hungarian assignment on the confusion matrix);
:func:`score_segmentation` does so over all pixels and over the object's pixels only
(ground-truth label != the backdrop's), since a large, easy backdrop inflates the
all-pixel score.

Example
-------
>>> truth = np.array([[0, 0, 1], [1, 2, 2]])
>>> segmentation_accuracy(np.array([[5, 5, 3], [3, 4, 4]]), truth)
1.0
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from pipeline.core.errors import ConfigError
from pipeline.fourier.settings import COLOUR_SPACES  # declared with method.segmentation.*


def mean_image(images) -> np.ndarray:
    """Average over lights: (n, H, W, C) -> (H, W, C), float32."""
    images = np.asarray(images)
    if images.ndim != 4:
        raise ConfigError(f"images must have shape (n, H, W, C), got {images.shape}")
    return images.mean(axis=0, dtype=np.float64).astype(np.float32)


def _to_colour_space(image: np.ndarray, colour_space: str) -> np.ndarray:
    if colour_space not in COLOUR_SPACES:
        raise ConfigError(f"colour_space must be one of {COLOUR_SPACES}, got {colour_space!r}")
    image = image.astype(np.float64)
    if colour_space == "chromaticity":
        total = image.sum(axis=-1, keepdims=True)
        return image / np.maximum(total, 1e-8)
    return image


def segment_by_representatives(image, points, colour_space: str = "rgb") -> np.ndarray:
    """Nearest-representative-colour labelling (the paper's method).

    Parameters
    ----------
    image : ndarray of shape (H, W, C)
        Usually :func:`mean_image` of the stack.
    points : sequence of (row, col)
        One representative pixel per region; label i is the region of ``points[i]``.
    colour_space : {"rgb", "chromaticity"}

    Returns
    -------
    labels : ndarray of shape (H, W), int
    """
    image = np.asarray(image)
    if image.ndim != 3:
        raise ConfigError(f"image must have shape (H, W, C), got {image.shape}")
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 2 or len(points) < 1:
        raise ConfigError(f"points must be a sequence of (row, col), got {points.tolist()}")
    height, width = image.shape[:2]
    for row, col in points:
        if not (0 <= row < height and 0 <= col < width) or row != int(row) or col != int(col):
            raise ConfigError(
                f"point (row={row}, col={col}) is not a pixel of a {height}x{width} image"
            )
    features = _to_colour_space(image, colour_space)
    centres = features[points[:, 0].astype(int), points[:, 1].astype(int)]  # (k, C)
    distances = ((features[:, :, None, :] - centres[None, None]) ** 2).sum(axis=-1)
    return distances.argmin(axis=-1)


def segment_kmeans(
    features,
    k: int,
    seed: int = 0,
    colour_space: str | None = None,
    mask=None,
    n_init: int = 4,
) -> np.ndarray:
    """Automatic segmentation: k-means on per-pixel features.

    Parameters
    ----------
    features : ndarray of shape (H, W, C) or (H, W, 3, K)
        Mean colour, or fitted coefficients (flattened to C = 3K per pixel).
    k : int
        Number of regions.
    seed : int
        ``random_state`` of scikit-learn's KMeans.
    colour_space : {"rgb", "chromaticity"}, optional
        Applied to (H, W, 3) colour features; None leaves features as they are.
    mask : ndarray of shape (H, W), bool, optional
        Only these pixels are clustered; the rest get label -1.
    n_init : int
        k-means restarts.

    Returns
    -------
    labels : ndarray of shape (H, W), int
    """
    from sklearn.cluster import KMeans

    features = np.asarray(features)
    if features.ndim == 4:
        features = features.reshape(*features.shape[:2], -1)
    if features.ndim != 3:
        raise ConfigError(
            f"features must have shape (H, W, C) or (H, W, 3, K), got {features.shape}"
        )
    if colour_space is not None:
        features = _to_colour_space(features, colour_space)
    height, width, _ = features.shape
    if mask is None:
        mask = np.ones((height, width), dtype=bool)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != (height, width):
        raise ConfigError(f"mask {mask.shape} does not match the image {(height, width)}")
    # Not standardized: Fourier coefficients share the units of intensity, and unit
    # variance lets the noisy high harmonics outweigh the terms that separate materials
    # (on a synthetic pot it lowered the accuracy: docs/performance.md).
    samples = features[mask].astype(np.float64)
    if isinstance(k, bool) or int(k) != k or k < 1 or k > len(samples):
        raise ConfigError(
            f"k={k!r} must be an integer in [1, {len(samples)}] (the number of pixels clustered)"
        )
    model = KMeans(n_clusters=int(k), n_init=n_init, random_state=seed).fit(samples)
    labels = np.full((height, width), -1, dtype=int)
    labels[mask] = model.labels_
    return labels


def segmentation_accuracy(pred, truth, mask=None) -> float:
    """Fraction of pixels labelled correctly under the best one-to-one renaming.

    Parameters
    ----------
    pred, truth : ndarray of shape (H, W), int
        Any label values; their sets may differ in size (unmatched labels count wrong).
    mask : ndarray of shape (H, W), bool, optional
        Pixels to score.

    Returns
    -------
    float in [0, 1]
    """
    pred, truth = np.asarray(pred), np.asarray(truth)
    if pred.shape != truth.shape:
        raise ConfigError(f"pred {pred.shape} and truth {truth.shape} differ in shape")
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != truth.shape:
            raise ConfigError(f"mask {mask.shape} does not match {truth.shape}")
        pred, truth = pred[mask], truth[mask]
    pred, truth = pred.ravel(), truth.ravel()
    if pred.size == 0:
        raise ConfigError("no pixels to score")
    pred_values, pred_index = np.unique(pred, return_inverse=True)
    truth_values, truth_index = np.unique(truth, return_inverse=True)
    confusion = np.zeros((len(pred_values), len(truth_values)), dtype=np.int64)
    np.add.at(confusion, (pred_index, truth_index), 1)
    rows, cols = linear_sum_assignment(confusion, maximize=True)
    return float(confusion[rows, cols].sum() / pred.size)


def score_segmentation(pred, truth, backdrop: int = 0) -> dict[str, float]:
    """Accuracy over all pixels and over the object's pixels (truth != ``backdrop``).

    Each is :func:`segmentation_accuracy` with its own best renaming of the labels.

    Parameters
    ----------
    pred, truth : ndarray of shape (H, W), int
    backdrop : int
        The ground-truth label of the background (0 in the synthetic stack's
        ``regions.npy``).

    Returns
    -------
    dict
        ``{"all": float, "object": float}``; no ``"object"`` when every pixel is backdrop.

    Example
    -------
    >>> truth = np.array([[0, 0, 0, 0], [0, 0, 1, 2]])
    >>> score_segmentation(np.array([[0, 0, 0, 0], [0, 0, 1, 1]]), truth)
    {'all': 0.875, 'object': 0.5}
    """
    truth = np.asarray(truth)
    scores = {"all": segmentation_accuracy(pred, truth)}
    on_object = truth != backdrop
    if on_object.any():
        scores["object"] = segmentation_accuracy(pred, truth, mask=on_object)
    return scores
