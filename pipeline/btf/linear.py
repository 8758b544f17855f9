"""The linear baseline of BTF compression: a truncated SVD (PCA) of the ABRDF matrix.

Stored: the mean ABRDF (3N values), ``c`` basis ABRDFs (c x 3N) and ``c`` coefficients per
texel (M x c), in float32 or float16. The reconstruction is measured after rounding them
to the stored dtype, so the RMSE is that of what would actually be kept, and exactly those
bytes are written into the run's compressed file (``pipeline.btf.compressed``, method
``pca``; :func:`pipeline.btf.export.export_linear_stage`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from sklearn.utils.extmath import randomized_svd

from pipeline.btf.evaluate import DTYPE_BYTES
from pipeline.btf.streamed_svd import IN_MEMORY_BYTES, streamed_svd
from pipeline.core.errors import ConfigError
from pipeline.core.progress import progress


@dataclass
class LinearModel:
    """mean : (3N,), basis : (c, 3N), coefficients : (M, c), all in normalized units."""

    mean: np.ndarray
    basis: np.ndarray
    coefficients: np.ndarray


def pca_bytes(n_components: int, n_texels: int, n_directions: int, dtype: str) -> int:
    return DTYPE_BYTES[dtype] * ((n_components + 1) * 3 * n_directions + n_texels * n_components)


def components_for_budget(budget: int, n_texels: int, n_directions: int, dtype: str) -> int:
    """The most components whose stored bytes stay within ``budget``; 0 when even one
    takes more (with many directions the basis alone outgrows a small clustered model)."""
    per_component = DTYPE_BYTES[dtype] * (3 * n_directions + n_texels)
    fixed = DTYPE_BYTES[dtype] * 3 * n_directions
    return max(int((budget - fixed) // per_component), 0)


def fit_linear(targets: np.ndarray, n_components: int, dtype: str, seed: int = 0) -> LinearModel:
    """Truncated SVD of normalized ABRDFs (M, N, 3), rounded to the stored dtype.

    ``targets`` may be any array that can be sliced by texels
    (:meth:`pipeline.btf.preprocess.Normalization.targets`); beyond
    :data:`~pipeline.btf.streamed_svd.IN_MEMORY_BYTES` it is read a block at a time."""
    m, d = targets.shape[0], int(np.prod(targets.shape[1:]))
    if not 1 <= n_components <= min(m, d):
        raise ConfigError(f"model.n_components={n_components} must be in 1..{min(m, d)}")
    if m * d * 4 <= IN_MEMORY_BYTES:
        flat = np.asarray(targets, dtype=np.float32).reshape(m, -1)
        mean = flat.mean(axis=0)
        u, s, vt = randomized_svd(flat - mean, n_components, random_state=seed)
    else:  # a block of texels at a time (a whole UBO2014 material: 43.8 GB of targets)

        def rows(start: int, stop: int) -> np.ndarray:
            return np.asarray(targets[start:stop], dtype=np.float32).reshape(stop - start, -1)

        u, s, vt, mean, _ = streamed_svd(rows, m, d, n_components, seed=seed, what="linear")
    store = np.float16 if dtype == "float16" else np.float32
    return LinearModel(mean.astype(store), vt.astype(store), (u * s).astype(store))


def linear_error(model: LinearModel, targets: np.ndarray, chunk: int = 256):
    """(rmse, rmse_per_direction (N,)) of the stored linear model against ``targets``."""
    m, n, _ = targets.shape
    sq_dir = np.zeros(n, dtype=np.float64)
    basis = model.basis.astype(np.float32)
    mean = model.mean.astype(np.float32)
    for start in progress(range(0, m, chunk), "evaluate", total=m, unit="texel", scale=chunk):
        coeffs = model.coefficients[start : start + chunk].astype(np.float32)
        pred = (coeffs @ basis + mean).reshape(len(coeffs), n, 3)
        diff = pred - np.asarray(targets[start : start + chunk], dtype=np.float32)
        sq_dir += np.square(diff, dtype=np.float64).sum(axis=(0, 2))
    return float(np.sqrt(sq_dir.sum() / (m * n * 3))), np.sqrt(sq_dir / (m * 3))
