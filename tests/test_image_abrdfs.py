"""A crop of decoded images served as ABRDFs (pipeline.data.image_abrdfs): in memory and
gathered where read, the same values as cutting the images by hand; the crop stage writes
no copy of them."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.data import image_abrdfs
from pipeline.data.image_abrdfs import ImageABRDFs, crop_abrdfs

N, H, W = 7, 9, 11
TEXELS = (2, 3, 4, 5)  # row, col, height, width


@pytest.fixture()
def images(tmp_path):
    values = np.random.default_rng(0).random((N, H, W, 3), dtype=np.float32)
    path = tmp_path / "images.npy"
    np.save(path, values)
    return path, values


def _by_hand(values: np.ndarray) -> np.ndarray:
    """(M, N, 3): texel r · width + c of the crop, every image."""
    row, col, height, width = TEXELS
    crop = values[:, row : row + height, col : col + width, :]  # (N, h, w, 3)
    return crop.reshape(N, height * width, 3).transpose(1, 0, 2)


def test_a_crop_that_fits_is_one_read_only_array(images):
    path, values = images
    served = crop_abrdfs(path, TEXELS)
    assert isinstance(served, np.ndarray) and not served.flags.writeable
    np.testing.assert_array_equal(served, _by_hand(values))
    assert crop_abrdfs(path, TEXELS) is served  # the stages of one job read it once


def test_a_rewritten_file_is_read_again(images):
    path, values = images
    first = crop_abrdfs(path, TEXELS)
    np.save(path, values + 1)
    np.testing.assert_array_equal(crop_abrdfs(path, TEXELS), first + 1)


def test_a_crop_too_large_to_hold_is_gathered_where_read(images, monkeypatch):
    path, values = images
    monkeypatch.setattr(image_abrdfs, "IN_MEMORY_BYTES", 0)
    served = crop_abrdfs(path, TEXELS)
    want = _by_hand(values)
    assert isinstance(served, ImageABRDFs) and served.shape == want.shape == (20, N, 3)
    np.testing.assert_array_equal(np.asarray(served), want)
    for key in (
        slice(3, 9),
        np.array([0, 7, 19]),
        5,
        (slice(None), 2),
        (np.array([1, 4]), slice(2, 5)),
        (slice(0, 20, 3), np.array([6, 0])),
        (4, 6),
        np.ix_([9, 2, 2], [5, 0]),
    ):
        np.testing.assert_array_equal(served[key], want[key], err_msg=str(key))
    with pytest.raises(IndexError, match="does not pair two index arrays"):
        served[np.array([0, 1]), np.array([0, 1])]
