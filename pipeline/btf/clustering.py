"""The clustering step of the clustered Neural BTF (PAPERS.md A, steps 1-4).

PCA of the preprocessed ABRDFs, k-means++ on the reduced vectors, and the element-wise
median ABRDF of every cluster as its representative.
"""

from __future__ import annotations

import warnings

import numpy as np
from sklearn.cluster import KMeans
from sklearn.decomposition import PCA
from sklearn.exceptions import ConvergenceWarning

from pipeline.core.errors import ConfigError
from pipeline.core.progress import progress


def pca_reduce(
    features: np.ndarray, n_components: int, random_state: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Project ABRDFs on their first principal components: scores (M, n_components)
    float32, and the explained variance ratio (n_components,).

    Parameters
    ----------
    features : ndarray of shape (M, D), float32, preprocessed ABRDFs (D = 3N).
    n_components : int, components kept.
    random_state : int
        Seed of the randomized SVD. It is a PCA setting, not the run's seed, so that runs
        with different seeds share one cached PCA.
    """
    m, d = features.shape
    _check_components(n_components, m, d)
    # Randomized SVD keeps float32 input as float32 and is far cheaper than a full SVD
    # when n_components << D (paper size: D = 19683).
    pca = PCA(n_components=n_components, svd_solver="randomized", random_state=random_state)
    scores = pca.fit_transform(features).astype(np.float32, copy=False)
    return scores, pca.explained_variance_ratio_.astype(np.float64)


def streamed_pca(
    rows, m: int, d: int, n_components: int, random_state: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`pca_reduce` of a matrix read a block of rows at a time (``rows(start, stop)``
    -> (stop − start, d) float32), for features that do not fit in memory
    (:func:`pipeline.btf.streamed_svd.streamed_svd`)."""
    from pipeline.btf.streamed_svd import streamed_svd

    _check_components(n_components, m, d)
    u, s, _, _, total = streamed_svd(rows, m, d, n_components, seed=random_state, what="PCA")
    return (u * s.astype(np.float32)), (np.square(s) / total).astype(np.float64)


def _check_components(n_components: int, m: int, d: int) -> None:
    if not 1 <= n_components <= min(m, d):
        raise ConfigError(
            f"btf.pca.n_components={n_components} must be between 1 and min(M={m}, D={d})"
        )


def check_k(k: int, n_texels: int) -> None:
    """Refuse a ``model.k`` that is not a positive integer or exceeds the M texels."""
    if not isinstance(k, int) or k < 1:
        raise ConfigError(f"model.k={k!r} must be a positive integer")
    if k > n_texels:
        raise ConfigError(
            f"model.k={k} is larger than the number of texels M={n_texels}: "
            "lower k or enlarge btf.crop.size"
        )


def kmeans_pp(
    scores: np.ndarray, k: int, seed: int, n_init: int = 1, max_iter: int = 300
) -> tuple[np.ndarray, np.ndarray, float]:
    """k-means with k-means++ seeding (Arthur & Vassilvitskii 2007) via scikit-learn:
    labels (M,) int32 (the paper's "list"), centers (k, n_components) float32, inertia."""
    check_k(k, scores.shape[0])
    kmeans = KMeans(
        n_clusters=k, init="k-means++", n_init=n_init, max_iter=max_iter, random_state=seed
    )
    with warnings.catch_warnings():  # the case is refused below, naming the setting
        warnings.filterwarnings("ignore", "Number of distinct clusters", ConvergenceWarning)
        labels = kmeans.fit_predict(scores).astype(np.int32)
    found = len(np.unique(labels))
    if found < k:
        # Fewer distinct texels than k (a tiled or flat texture): some clusters stay empty
        # and would have no representative. Said here, before the medians' pass.
        raise ConfigError(
            f"model.k={k}: k-means found only {found} non-empty clusters (the crop holds "
            f"about that many distinct ABRDFs); lower model.k to at most {found}"
        )
    return labels, kmeans.cluster_centers_.astype(np.float32), float(kmeans.inertia_)


def cluster_medians(abrdf: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """Element-wise median ABRDF of each cluster: ``abrdf`` (M, N, 3) and ``labels`` (M,)
    in [0, k) -> representatives (k, N, 3), float32."""
    if labels.shape != (abrdf.shape[0],):
        raise ValueError(f"labels has shape {labels.shape}, expected ({abrdf.shape[0]},)")
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(k + 1))
    representatives = np.empty((k,) + abrdf.shape[1:], dtype=np.float32)
    for cluster in progress(range(k), "cluster medians", unit="cluster"):
        members = order[bounds[cluster] : bounds[cluster + 1]]
        if len(members) == 0:
            raise ValueError(f"cluster {cluster} of k={k} is empty")
        # Sorted indices make the gather from a memory map sequential.
        representatives[cluster] = np.median(abrdf[np.sort(members)], axis=0)
    return representatives
