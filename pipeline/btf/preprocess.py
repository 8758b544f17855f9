"""Preprocessing of ABRDFs (PAPERS.md A, eq. 1-6).

Encoder input: x2 = log(x1 + 1) element-wise, then standardized per dimension (each
direction and colour channel) with the mean and standard deviation over the M texels.
Decoder targets: the RGB values divided by alpha, the maximum over all target values, so
that they lie in [0, 1] (the space in which the paper reports RMSE, eq. 10).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.errors import DataError
from pipeline.core.progress import progress

# A dimension that is constant over all texels (sigma = 0) would divide by zero; such a
# dimension carries no information, so it is mapped to 0 instead.
_SIGMA_FLOOR = 1e-6


@dataclass(frozen=True)
class Normalization:
    """Statistics fitted on one ABRDF matrix.

    Attributes
    ----------
    mean, std : ndarray of shape (N, 3), float32
        Per-dimension statistics of log(x + 1) over the texels.
    alpha : float, maximum over all values of the matrix; targets are ``abrdf / alpha``
    """

    mean: np.ndarray
    std: np.ndarray
    alpha: float

    def encoder_input(self, abrdf: np.ndarray) -> np.ndarray:
        """Map raw ABRDFs of shape (..., N, 3) to standardized log values (float32)."""
        logged = np.log1p(np.asarray(abrdf, dtype=np.float32))
        return ((logged - self.mean) / self.std).astype(np.float32, copy=False)

    def targets(self, abrdf) -> Targets:
        """``abrdf``'s targets, normalized where indexed (a memory map or
        :class:`~pipeline.data.ubo2014_decode.FactorABRDFs` is not read whole)."""
        return Targets(abrdf, self)

    def target(self, abrdf: np.ndarray) -> np.ndarray:
        """Map raw values to the normalized [0, 1] space of the targets."""
        return (np.asarray(abrdf, dtype=np.float32) / np.float32(self.alpha)).astype(
            np.float32, copy=False
        )


class Targets:
    """``norm.target(abrdf[key])`` for ``targets[key]``; ``np.asarray`` gives all of them."""

    ndim = 3

    def __init__(self, abrdf, norm: Normalization):
        self.abrdf, self.norm, self.shape = abrdf, norm, abrdf.shape

    def __getitem__(self, key) -> np.ndarray:
        return self.norm.target(self.abrdf[key])

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        values = self.norm.target(self.abrdf)
        return values if dtype is None else values.astype(dtype, copy=False)


def fit_normalization(abrdf: np.ndarray, chunk: int = 1024) -> Normalization:
    """Fit the eq. 1-6 statistics on linear RGB ABRDFs ``abrdf`` (M, N, 3), read chunk by
    chunk so that a memory-mapped paper-size matrix is never duplicated in memory."""
    if abrdf.ndim != 3 or abrdf.shape[2] != 3:
        raise ValueError(f"abrdf must have shape (M, N, 3), got {abrdf.shape}")
    m = abrdf.shape[0]
    total = np.zeros(abrdf.shape[1:], dtype=np.float64)
    total_sq = np.zeros(abrdf.shape[1:], dtype=np.float64)
    alpha = 0.0
    for start in progress(range(0, m, chunk), "normalization", total=m, unit="texel", scale=chunk):
        block = np.asarray(abrdf[start : start + chunk], dtype=np.float32)
        if not np.all(np.isfinite(block)):
            raise DataError(f"the data hold NaN or Inf in texels {start}..{start + len(block)}")
        if (low := float(block.min())) <= -1.0:
            raise DataError(
                f"the data hold values down to {low:.3g} in texels {start}..{start + len(block)}:"
                " eq. 1's log(x + 1) needs x > -1 (radiance is not negative)"
            )
        logged = np.log1p(block, dtype=np.float64)
        total += logged.sum(axis=0)
        total_sq += np.square(logged).sum(axis=0)
        alpha = max(alpha, float(block.max()))
    mean = total / m
    var = np.maximum(total_sq / m - np.square(mean), 0.0)
    std = np.sqrt(var)
    std[std < _SIGMA_FLOOR] = 1.0
    if alpha <= 0:
        raise ValueError("abrdf is all zero: there is nothing to normalize the targets by")
    return Normalization(mean.astype(np.float32), std.astype(np.float32), alpha)


def encoder_inputs(abrdf: np.ndarray, norm: Normalization, chunk: int = 1024) -> np.ndarray:
    """All standardized inputs, flattened to shape (M, 3N), computed chunk by chunk."""
    m, n, _ = abrdf.shape
    out = np.empty((m, n * 3), dtype=np.float32)
    for start in progress(range(0, m, chunk), "encoder inputs", total=m, unit="texel", scale=chunk):
        block = norm.encoder_input(abrdf[start : start + chunk])
        out[start : start + len(block)] = block.reshape(len(block), -1)
    return out
