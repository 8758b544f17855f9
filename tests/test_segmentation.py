"""Reflectance-region segmentation: the paper's representatives and automatic k-means."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from pipeline.core.errors import ConfigError
from pipeline.fourier.segmentation import (
    mean_image,
    score_segmentation,
    segment_by_representatives,
    segment_kmeans,
    segmentation_accuracy,
)
from pipeline.fourier.series import fit_fourier
from pipeline.fourier.synthetic import (
    SyntheticStackConfig,
    grid_light_dirs,
    make_synthetic_scene,
)


@pytest.fixture(scope="module")
def pot():
    """A small noisy synthetic stack and its ground-truth regions."""
    config = SyntheticStackConfig(
        size=(64, 64), n_elevations=3, n_azimuths=12, azimuth_step_deg=12.0
    ).validated()
    scene = make_synthetic_scene(config)
    images = scene.render(grid_light_dirs(config))
    images += np.random.default_rng(0).normal(0, 0.005, images.shape).astype(np.float32)
    return images, scene


def _deepest_pixel(region):
    """The pixel farthest from the region's border: where a user would click."""
    depth = distance_transform_edt(region)
    return np.unravel_index(depth.argmax(), depth.shape)


def test_accuracy_ignores_label_names():
    truth = np.array([[0, 0, 1], [1, 2, 2]])
    assert segmentation_accuracy(np.array([[7, 7, 3], [3, 1, 1]]), truth) == 1.0
    assert segmentation_accuracy(np.array([[7, 7, 3], [3, 3, 1]]), truth) == pytest.approx(5 / 6)
    assert segmentation_accuracy(np.zeros((2, 3), int), truth) == pytest.approx(2 / 6)
    assert segmentation_accuracy(np.arange(6).reshape(2, 3), truth) == pytest.approx(3 / 6)
    with pytest.raises(ConfigError, match=r"pred \(2, 2\) and truth \(2, 3\)"):
        segmentation_accuracy(np.zeros((2, 2)), truth)


def test_representatives_segment_the_pot(pot):
    images, scene = pot
    points = [_deepest_pixel(scene.regions == label) for label in range(3)]
    labels = segment_by_representatives(mean_image(images), points, "chromaticity")
    assert segmentation_accuracy(labels, scene.regions) >= 0.95
    # The paper's plain-RGB variant is weaker: shading is left in the mean image.
    rgb = segment_by_representatives(mean_image(images), points, "rgb")
    assert segmentation_accuracy(rgb, scene.regions) >= 0.80


def test_kmeans_segments_the_pot(pot):
    images, scene = pot
    labels = segment_kmeans(mean_image(images), 3, seed=0, colour_space="chromaticity")
    assert segmentation_accuracy(labels, scene.regions) >= 0.95
    on_pot = segment_kmeans(
        mean_image(images), 2, seed=0, colour_space="chromaticity", mask=scene.mask
    )
    assert (on_pot[~scene.mask] == -1).all()
    assert segmentation_accuracy(on_pot, scene.regions, scene.mask) >= 0.95


def test_kmeans_on_fourier_coefficients_segments_the_pot(pot):
    images, scene = pot
    config = scene.config
    coeffs = fit_fourier(images, grid_light_dirs(config), scene.normals, M=10, lam=3.14)
    labels = segment_kmeans(coeffs, 3, seed=0)
    assert segmentation_accuracy(labels, scene.regions) >= 0.95


def test_segmentation_inputs_are_checked():
    image = np.zeros((4, 4, 3))
    with pytest.raises(ConfigError, match=r"point \(row=4, col=0\) is not a pixel"):
        segment_by_representatives(image, [(0, 0), (4, 0)])
    with pytest.raises(ConfigError, match="colour_space"):
        segment_by_representatives(image, [(0, 0)], "lab")
    with pytest.raises(ConfigError, match=r"k=17 must be an integer in \[1, 16\]"):
        segment_kmeans(image, 17)


def test_object_accuracy_leaves_the_backdrop_out():
    # 6 backdrop pixels all right, 4 object pixels half wrong: 8/10 overall, 2/4 on the object.
    truth = np.array([[0, 0, 0, 0, 0], [0, 1, 1, 2, 2]])
    pred = np.array([[5, 5, 5, 5, 5], [5, 1, 1, 1, 1]])
    assert score_segmentation(pred, truth) == {"all": 0.8, "object": 0.5}
    assert score_segmentation(pred, truth, backdrop=1)["object"] == 1.0  # labels 0, 2: right
    assert score_segmentation(np.zeros((2, 2), int), np.zeros((2, 2), int)) == {"all": 1.0}


def test_paper_method_in_rgb_scores_lower_on_the_pot_than_overall(pot):
    # Issue 18: the backdrop is large and easy, so it inflates the all-pixel accuracy.
    images, scene = pot
    points = [_deepest_pixel(scene.regions == label) for label in range(3)]
    scores = score_segmentation(
        segment_by_representatives(mean_image(images), points, "rgb"), scene.regions
    )
    assert scores["object"] < scores["all"] - 0.02, scores
    chroma = score_segmentation(
        segment_by_representatives(mean_image(images), points, "chromaticity"), scene.regions
    )
    assert chroma["object"] > scores["object"], (chroma, scores)
