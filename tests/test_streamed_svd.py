"""The SVD read a block of rows at a time agrees with numpy's and scikit-learn's in-memory
ones, and the stages take it where the matrix would not fit."""

import numpy as np
import pytest
from sklearn.decomposition import PCA

from pipeline.btf import linear, streamed_svd
from pipeline.btf.clustering import pca_reduce, streamed_pca


def _matrix(m=300, d=80, rank=6, seed=0):
    rng = np.random.default_rng(seed)
    scales = np.geomspace(10, 1, rank)
    low = (rng.standard_normal((m, rank)) * scales) @ rng.standard_normal((rank, d))
    return (low + 0.01 * rng.standard_normal((m, d)) + 3.0).astype(np.float32)


def test_it_finds_numpys_singular_triplets_of_the_centred_matrix():
    a = _matrix()
    u, s, vt, mean, total = streamed_svd.streamed_svd(lambda i, j: a[i:j], *a.shape, 5, chunk=64)
    centred = a.astype(np.float64) - a.mean(axis=0)
    _, s_ref, vt_ref = np.linalg.svd(centred, full_matrices=False)
    np.testing.assert_allclose(mean, a.mean(axis=0, dtype=np.float64), rtol=1e-6)
    np.testing.assert_allclose(s, s_ref[:5], rtol=1e-4)
    np.testing.assert_allclose(np.abs(np.sum(vt * vt_ref[:5], axis=1)), 1.0, atol=1e-4)
    np.testing.assert_allclose((u * s) @ vt, centred @ vt_ref[:5].T @ vt_ref[:5], atol=2e-3)
    assert total == pytest.approx(np.square(centred).sum(), rel=1e-6)


def test_streamed_pca_explains_what_scikit_learns_pca_explains():
    a = _matrix(seed=1)
    scores, ratio = streamed_pca(lambda i, j: a[i:j], *a.shape, 4)
    reference = PCA(n_components=4, svd_solver="full").fit(a)
    np.testing.assert_allclose(ratio, reference.explained_variance_ratio_, rtol=1e-4)
    in_memory, _ = pca_reduce(a, 4)
    np.testing.assert_allclose(np.abs(scores), np.abs(in_memory), atol=1e-3 * np.abs(scores).max())


def test_the_linear_model_beyond_memory_scores_as_the_in_memory_one(monkeypatch):
    targets = (_matrix(m=200, d=90, seed=2) / 20.0).reshape(200, 30, 3)
    in_memory = linear.linear_error(linear.fit_linear(targets, 4, "float32"), targets)[0]
    monkeypatch.setattr(linear, "IN_MEMORY_BYTES", 0)
    streamed = linear.linear_error(linear.fit_linear(targets, 4, "float32"), targets)[0]
    assert streamed == pytest.approx(in_memory, rel=1e-3)
