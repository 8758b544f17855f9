"""A truncated SVD of a matrix too large for memory, read a block of rows at a time.

The PCA before k-means and the linear baseline take the SVD of an (M, 3N) matrix: for a
whole UBO2014 material 160,000 x 68,403 float32 values, 43.8 GB. The randomized range
finder with power iterations (Halko, Martinsson & Tropp 2011, algorithms 4.3-4.4, as
scikit-learn's ``randomized_svd``) only multiplies it by thin matrices, one pass over its
rows each; scikit-learn's solvers need the whole matrix in memory (``IncrementalPCA`` a
full SVD of (batch + k) x 3N per batch). Below :data:`IN_MEMORY_BYTES` the stages keep
scikit-learn's in-memory solvers, so that results of crops that fit stay the same.

Cost: ``2 · n_iter + 3`` passes over the rows (the mean and the total variance, the range,
``n_iter`` power iterations of two products each, the projection).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from pipeline.core.progress import progress

# Matrices up to this size are decomposed in memory by scikit-learn.
IN_MEMORY_BYTES = 4 << 30


def streamed_svd(
    rows: Callable[[int, int], np.ndarray],
    m: int,
    d: int,
    k: int,
    *,
    n_iter: int = 4,
    oversamples: int = 10,
    seed: int = 0,
    chunk: int = 512,
    what: str = "SVD",
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """The ``k`` leading singular triplets of ``A − mean``, the column mean subtracted (PCA).

    Parameters
    ----------
    rows : callable, ``rows(start, stop)`` -> ndarray (stop − start, d), float32: rows of ``A``
    m, d : int, ``A``'s shape
    k : int, triplets kept; ``k + oversamples`` random directions are iterated
    n_iter : int
        Power iterations (each two passes); 4 is scikit-learn's choice for k ≥ 10 % of
        the smaller side, where the spectrum decays slowly.
    seed : int, of the random test matrix.
    chunk : int, rows read at a time.
    what : str, the name the progress lines show.

    Returns
    -------
    u : ndarray (m, k), float32
    s : ndarray (k,), float64
    vt : ndarray (k, d), float32
    mean : ndarray (d,), float64
    total : float
        The sum of squares of ``A − mean``: ``s² / total`` is the share each component
        explains.
    """
    width = min(k + oversamples, m, d)
    mean = np.zeros(d, dtype=np.float64)
    squares = 0.0
    for start in progress(range(0, m, chunk), f"{what}: mean", total=m, unit="row", scale=chunk):
        block = rows(start, min(start + chunk, m))
        mean += block.sum(axis=0, dtype=np.float64)
        squares += float(np.square(block, dtype=np.float64).sum())
    mean /= m
    total = squares - m * float(np.square(mean).sum())
    mean32 = mean.astype(np.float32)

    def times(matrix: np.ndarray, name: str) -> np.ndarray:
        """(A − mean) @ matrix, (m, width)."""
        out = np.empty((m, matrix.shape[1]), dtype=np.float64)
        shift = mean32 @ matrix
        for start in progress(range(0, m, chunk), name, total=m, unit="row", scale=chunk):
            stop = min(start + chunk, m)
            out[start:stop] = rows(start, stop) @ matrix - shift
        return out

    def times_transposed(q: np.ndarray, name: str) -> np.ndarray:
        """(A − mean)ᵀ @ q, (d, width)."""
        out = np.zeros((d, q.shape[1]), dtype=np.float64)
        q32 = q.astype(np.float32)
        for start in progress(range(0, m, chunk), name, total=m, unit="row", scale=chunk):
            stop = min(start + chunk, m)
            out += rows(start, stop).T @ q32[start:stop]
        return out - np.outer(mean, q.sum(axis=0))

    rng = np.random.default_rng(seed)
    omega = rng.standard_normal((d, width)).astype(np.float32)
    q, _ = np.linalg.qr(times(omega, f"{what}: range"))
    for i in range(n_iter):
        z, _ = np.linalg.qr(times_transposed(q, f"{what}: power {i + 1}/{n_iter} (Aᵀq)"))
        q, _ = np.linalg.qr(times(z.astype(np.float32), f"{what}: power {i + 1}/{n_iter} (Az)"))
    b = times_transposed(q, f"{what}: projection").T  # (width, d) = Qᵀ (A − mean)
    ub, s, vt = np.linalg.svd(b, full_matrices=False)
    u = (q @ ub[:, :k]).astype(np.float32)
    return u, s[:k], vt[:k].astype(np.float32), mean, total
