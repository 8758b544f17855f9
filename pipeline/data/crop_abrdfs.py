"""The (M, N, 3) float32 array-like of a crop's ABRDFs that method A's stages read when the
values are not one array in memory: :class:`CropABRDFs` does the indexing, a subclass the
reading (:class:`~pipeline.data.ubo2014_decode.FactorABRDFs` decodes from a DFMF file's
factors, :class:`~pipeline.data.image_abrdfs.ImageABRDFs` gathers from decoded images)."""

from __future__ import annotations

import numpy as np


class CropABRDFs:
    """``shape``, ``len``, ``abrdf[texels]`` and ``abrdf[texels, directions]`` with ints,
    slices or index arrays (one array at most: numpy's paired indexing of two arrays is
    refused, but ``np.ix_(texels, directions)``, every texel at every direction, is
    served), and ``np.asarray(abrdf)`` (everything: only for crops that fit in memory).
    A subclass sets ``shape`` and reads a block with :meth:`_read`."""

    dtype = np.dtype(np.float32)
    ndim = 3
    shape: tuple[int, int, int]

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def __len__(self) -> int:
        return self.shape[0]

    def _read(self, texels: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(len(texels), len(directions), 3) float32: those texels at those directions."""
        raise NotImplementedError

    def __getitem__(self, key) -> np.ndarray:
        texels, directions = _texels_and_directions(key)
        t = np.arange(self.shape[0])[texels]
        d = np.arange(self.shape[1])[directions]
        # np.ix_'s (B, 1) and (1, D): every texel at every direction, read as one block.
        if t.ndim == 2 and d.ndim == 2 and t.shape[1] == 1 and d.shape[0] == 1:
            return self._read(t[:, 0], d[0])
        if t.ndim > 1 or d.ndim > 1 or (_is_array(texels) and _is_array(directions)):
            raise IndexError(
                f"{type(self).__name__} does not pair two index arrays: read a block first, "
                "or index with np.ix_(texels, directions)"
            )
        values = self._read(np.atleast_1d(t), np.atleast_1d(d))
        if d.ndim == 0:
            values = values[:, 0]
        if t.ndim == 0:
            values = values[0]
        return values

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        values = self[:]
        return values if dtype is None else values.astype(dtype, copy=False)


def _texels_and_directions(key):
    """``abrdf[key]``'s texel and direction indices (the colour axis only as ``:``)."""
    if not isinstance(key, tuple):
        return key, slice(None)
    if len(key) == 1:
        return key[0], slice(None)
    if len(key) == 2 or (len(key) == 3 and key[2] == slice(None)):
        return key[0], key[1]
    raise IndexError("a crop's ABRDFs take [texels] or [texels, directions]")


def _is_array(index) -> bool:
    return not isinstance(index, (slice, int, np.integer)) and np.ndim(index) > 0
