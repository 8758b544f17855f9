"""A crop's ABRDFs (texels × directions × 3) served from the load stage's decoded images
(N, height, width, 3), never copied into the cache a second time.

A crop that fits in :data:`IN_MEMORY_BYTES` is read once into memory, as the (M, N, 3)
array the stages expect (the texel-major layout makes a training batch one contiguous
read); the last such crop is kept for the process, so the stages of one job read the
images once. A larger crop is an :class:`ImageABRDFs` that gathers what is indexed.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np

from pipeline.data.crop_abrdfs import CropABRDFs

# Crops up to this size are held in memory (a job's stages read every texel many times):
# 4 GiB, or an eighth of the machine's memory where that is less (each process of a sweep
# holds its own).
IN_MEMORY_BYTES = min(4 * 2**30, os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 8)


def crop_abrdfs(images_path: Path, texels) -> np.ndarray | ImageABRDFs:
    """The ``texels`` crop ``[row, col, height, width]`` (texel ``r · width + c``) of the
    images in ``images_path`` (a ``.npy`` of shape (N, H, W, 3)) as (M, N, 3) float32:
    a read-only array when it fits in :data:`IN_MEMORY_BYTES`, else an
    :class:`ImageABRDFs`."""
    images = np.load(images_path, mmap_mode="r")
    row, col, height, width = (int(v) for v in texels)
    if height * width * images.shape[0] * 3 * 4 > IN_MEMORY_BYTES:
        return ImageABRDFs(images, (row, col, height, width))
    stat = os.stat(images_path)
    return _in_memory(str(images_path), stat.st_size, stat.st_mtime_ns, row, col, height, width)


@functools.lru_cache(maxsize=1)
def _in_memory(path: str, size: int, mtime_ns: int, row: int, col: int, height: int, width: int):
    """The crop, texel-major, read once (keyed by the file's size and time as well, so a
    rewritten file is read again)."""
    images = np.load(path, mmap_mode="r")
    n = images.shape[0]
    crop = np.empty((height * width, n, 3), dtype=np.float32)
    for i in range(n):  # image by image: the crop of one image is one column of the ABRDFs
        crop[:, i, :] = images[i, row : row + height, col : col + width, :].reshape(-1, 3)
    crop.flags.writeable = False
    return crop


class ImageABRDFs(CropABRDFs):
    """A crop of decoded images (N, H, W, 3) as a
    :class:`~pipeline.data.crop_abrdfs.CropABRDFs`: each read gathers only the texels and
    images asked for."""

    def __init__(self, images: np.ndarray, texels: tuple[int, int, int, int]):
        self.images = images
        self.row, self.col, self.height, self.width = texels
        self.shape = (self.height * self.width, images.shape[0], 3)

    def _read(self, t: np.ndarray, d: np.ndarray) -> np.ndarray:
        rows, cols = self.row + t // self.width, self.col + t % self.width
        values = self.images[d[:, None], rows[None, :], cols[None, :], :]  # (D, T, 3)
        return np.ascontiguousarray(values.transpose(1, 0, 2), np.float32)
