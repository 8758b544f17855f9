"""Direct tests of method A's core (PAPERS.md A, eq. 1-10): the normalisation, PCA,
k-means++, the cluster medians, and what the encoder is fed (issue 17, item 7).

Small inputs, each result checked by hand or against a second, independent computation.
"""

from __future__ import annotations

import inspect

import numpy as np
import pytest
from helpers import compose_config

from pipeline.btf import preprocess
from pipeline.btf.clustering import check_k, cluster_medians, kmeans_pp, pca_reduce
from pipeline.btf.preprocess import encoder_inputs, fit_normalization
from pipeline.core.errors import ConfigError


def _median_loop(abrdf: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """The reference: one np.median per cluster over its members, element-wise."""
    return np.stack([np.median(abrdf[labels == c], axis=0) for c in range(k)])


# --------------------------------------------------------------------------- medians


def test_cluster_medians_by_hand_are_element_wise_medians_not_means_or_medoids():
    """Catches a mean, a medoid, or a per-texel (not element-wise) median as representative."""
    # One direction, RGB: cluster 0 has 3 members (odd), cluster 1 has 4 (even), cluster 2
    # has 1. Channel by channel the median of cluster 0 mixes members: it is no medoid.
    abrdf = np.array(
        [
            [[0.0, 10.0, 5.0]],  # cluster 0
            [[7.0, 1.0, 1.0]],  # cluster 1
            [[1.0, 0.0, 9.0]],  # cluster 0
            [[3.0, 3.0, 3.0]],  # cluster 2 (alone)
            [[2.0, 5.0, 0.0]],  # cluster 0
            [[0.0, 2.0, 8.0]],  # cluster 1
            [[1.0, 4.0, 2.0]],  # cluster 1
            [[40.0, 3.0, 4.0]],  # cluster 1
        ],
        dtype=np.float32,
    )
    labels = np.array([0, 1, 0, 2, 0, 1, 1, 1])
    medians = cluster_medians(abrdf, labels, 3)
    expected = np.array(
        [
            [[1.0, 5.0, 5.0]],  # middle of (0, 1, 2), (10, 0, 5), (5, 9, 0)
            [[4.0, 2.5, 3.0]],  # mean of the two middle values of (0,1,7,40), (1,2,3,4), (1,2,4,8)
            [[3.0, 3.0, 3.0]],  # the single member
        ],
        dtype=np.float32,
    )
    np.testing.assert_array_equal(medians, expected)
    assert medians.shape == (3, 1, 3) and medians.dtype == np.float32
    # Not the mean (cluster 1's red channel mean is 12), and not any member of cluster 0.
    assert medians[1, 0, 0] != abrdf[labels == 1, 0, 0].mean()
    assert not any(np.array_equal(medians[0], abrdf[i]) for i in np.flatnonzero(labels == 0))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cluster_medians_match_a_per_cluster_np_median_loop(seed):
    """Catches a wrong gather (sorting, cluster bounds) on shuffled labels of odd, even and size-1 clusters."""
    rng = np.random.default_rng(seed)
    sizes = [5, 4, 1, 2, 7, 6]  # odd, even, single, even, odd, even
    labels = rng.permutation(np.repeat(np.arange(len(sizes)), sizes))
    abrdf = rng.gamma(2.0, size=(len(labels), 9, 3)).astype(np.float32)
    medians = cluster_medians(abrdf, labels, len(sizes))
    np.testing.assert_allclose(medians, _median_loop(abrdf, labels, len(sizes)), rtol=1e-6)
    # The size-1 cluster's representative is its texel's own ABRDF.
    np.testing.assert_array_equal(medians[2], abrdf[labels == 2][0])


def test_cluster_medians_reject_an_empty_cluster_and_mis_shaped_labels():
    """Catches an empty cluster silently given garbage (np.empty) as its representative."""
    abrdf = np.ones((4, 2, 3), dtype=np.float32)
    with pytest.raises(ValueError, match="cluster 1 of k=3 is empty"):
        cluster_medians(abrdf, np.array([0, 0, 2, 2]), 3)
    with pytest.raises(ValueError, match="labels has shape"):
        cluster_medians(abrdf, np.array([0, 1, 2]), 3)


# --------------------------------------------------------------------------- normalisation


def _one_shot(abrdf: np.ndarray):
    """eq. 1-6 in one numpy expression each: per-dimension statistics over the texels."""
    logged = np.log(np.asarray(abrdf, dtype=np.float32).astype(np.float64) + 1.0)
    return logged.mean(axis=0), logged.std(axis=0), float(abrdf.max())


def test_normalization_by_hand_uses_log_x_plus_1_and_sigma_over_texels():
    """Catches log without +1, a sample (n-1) or whole-matrix sigma, and sigma over the wrong axis."""
    e = np.e
    # Two texels, two directions. Direction 0: log-values 0 and 2 in every channel (mean 1,
    # std 1); direction 1: log-values 1 and 1 (mean 1, constant: std floored to 1) in red,
    # 0 and 4 (mean 2, std 2) in green and blue.
    abrdf = np.array(
        [
            [[0.0, 0.0, 0.0], [e - 1, 0.0, 0.0]],
            [[e**2 - 1] * 3, [e - 1, e**4 - 1, e**4 - 1]],
        ],
        dtype=np.float32,
    )
    norm = fit_normalization(abrdf)
    np.testing.assert_allclose(norm.mean, [[1, 1, 1], [1, 2, 2]], rtol=1e-5)
    np.testing.assert_allclose(norm.std, [[1, 1, 1], [1, 2, 2]], rtol=1e-5)
    assert norm.mean.shape == norm.std.shape == (2, 3)  # per dimension (N, 3), not per texel
    assert norm.alpha == pytest.approx(e**4 - 1, rel=1e-6)
    # Standardized inputs: texel 0 at -1 where the dimension varies, 0 where it is constant.
    np.testing.assert_allclose(norm.encoder_input(abrdf[0]), [[-1, -1, -1], [0, -1, -1]], atol=1e-5)
    np.testing.assert_allclose(norm.target(abrdf), abrdf / np.float32(e**4 - 1), rtol=1e-6)


@pytest.mark.parametrize("chunk", [1, 3, 7, 16, 17, 18, 4096])
def test_chunked_statistics_match_a_one_shot_computation(chunk):
    """Catches a chunked sum that drops, repeats or mis-weights texels at chunk boundaries."""
    rng = np.random.default_rng(chunk)
    # M = 17 texels: every chunk size above splits them unevenly, 16/17/18 sit at the edge.
    # Each dimension has its own scale so per-dimension statistics differ from global ones.
    scale = rng.uniform(0.1, 20.0, size=(5, 3))
    abrdf = (rng.gamma(1.5, size=(17, 5, 3)) * scale).astype(np.float32)
    abrdf[11, 2, 1] = 250.0  # the maximum, in the middle of a chunk for most sizes
    norm = fit_normalization(abrdf, chunk=chunk)
    mean, std, alpha = _one_shot(abrdf)
    np.testing.assert_allclose(norm.mean, mean, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(norm.std, std, rtol=1e-4, atol=1e-6)
    assert norm.alpha == pytest.approx(250.0)
    # And the chunked encoder inputs equal the one-shot standardization.
    expected = ((np.log1p(abrdf.astype(np.float64)) - mean) / std).reshape(17, -1)
    np.testing.assert_allclose(encoder_inputs(abrdf, norm, chunk=chunk), expected, atol=1e-4)


def test_chunked_statistics_across_the_default_chunk_size():
    """Catches a mistake that only shows once M passes the default chunk (the stages' setting)."""
    default = max(
        inspect.signature(fit_normalization).parameters["chunk"].default,
        inspect.signature(preprocess.encoder_inputs).parameters["chunk"].default,
    )
    rng = np.random.default_rng(7)
    for m in (default - 1, default, default + 1, 2 * default + 3):
        abrdf = rng.exponential(2.0, size=(m, 2, 3)).astype(np.float32)
        abrdf[-1] *= 10.0  # the last texel, in the last (partial) chunk, dominates
        norm = fit_normalization(abrdf)
        mean, std, alpha = _one_shot(abrdf)
        np.testing.assert_allclose(norm.mean, mean, rtol=1e-5)
        np.testing.assert_allclose(norm.std, std, rtol=1e-4)
        assert norm.alpha == pytest.approx(alpha)
        expected = ((np.log1p(abrdf.astype(np.float64)) - mean) / std).reshape(m, -1)
        np.testing.assert_allclose(encoder_inputs(abrdf, norm), expected, atol=1e-4)


def test_normalize_then_denormalize_round_trips():
    """Catches an encoder input or target that cannot be inverted with the stored mean, std and alpha."""
    rng = np.random.default_rng(3)
    abrdf = rng.gamma(2.0, 0.5, size=(23, 4, 3)).astype(np.float32)
    abrdf[:, 1, 2] = 0.25  # a constant dimension (std floored to 1)
    norm = fit_normalization(abrdf, chunk=5)
    z = encoder_inputs(abrdf, norm, chunk=4).reshape(abrdf.shape)
    back = np.expm1(z * norm.std + norm.mean)
    np.testing.assert_allclose(back, abrdf, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(norm.target(abrdf) * norm.alpha, abrdf, rtol=1e-6)
    assert norm.target(abrdf).max() == pytest.approx(1.0)
    # Standardized: each dimension has mean 0 and (where it varies) std 1 over the texels.
    np.testing.assert_allclose(z.mean(axis=0), 0.0, atol=1e-4)
    varying = np.ones((4, 3), dtype=bool)
    varying[1, 2] = False
    np.testing.assert_allclose(z.std(axis=0)[varying], 1.0, rtol=1e-3)


def test_normalization_rejects_bad_input():
    """Catches NaN data or an all-zero matrix passing into training unnoticed."""
    with pytest.raises(ValueError, match="NaN or Inf in texels 2..3"):
        fit_normalization(np.array([[[1, 1, 1]]] * 2 + [[[np.nan, 1, 1]]], np.float32), chunk=2)
    with pytest.raises(ValueError, match="all zero"):
        fit_normalization(np.zeros((3, 2, 3), np.float32))
    with pytest.raises(ValueError, match="shape"):
        fit_normalization(np.zeros((3, 2, 4), np.float32))


# --------------------------------------------------------------------------- k-means++


def _blobs(seed: int = 0, per_blob: int = 20):
    rng = np.random.default_rng(seed)
    centers = np.array([[0.0, 0.0, 0.0], [30.0, 0.0, 5.0], [0.0, -40.0, 20.0], [25, 25, 25]])
    truth = np.repeat(np.arange(len(centers)), per_blob)
    points = centers[truth] + rng.normal(scale=0.5, size=(len(truth), 3))
    order = rng.permutation(len(truth))
    return points[order].astype(np.float32), truth[order], centers


def _no_clusters():
    """Points without clear clusters, where the seeding decides the partition."""
    return np.random.default_rng(11).normal(size=(60, 4)).astype(np.float32)


@pytest.mark.parametrize("seed", [0, 1, 5])
@pytest.mark.parametrize("data", ["blobs", "no clusters"])
def test_kmeans_pp_returns_a_converged_partition_with_its_centers_and_inertia(seed, data):
    """Catches labels out of step with the texels or the centers (reordered, from another
    fit), centers that are not their members' means, an inertia of something else, or a fit
    stopped before it converged; checked in numpy, not against scikit-learn."""
    points, truth, _ = _blobs(seed) if data == "blobs" else (_no_clusters(), None, None)
    k = 4 if data == "blobs" else 5
    labels, centers, inertia = kmeans_pp(points, k, seed=seed)
    assert labels.shape == (len(points),) and labels.dtype == np.int32
    assert centers.shape == (k, points.shape[1]) and centers.dtype == np.float32
    assert isinstance(inertia, float)
    assert set(labels.tolist()) == set(range(k))  # no empty cluster
    points64 = points.astype(np.float64)
    squared = np.sum((points64[:, None, :] - centers[None].astype(np.float64)) ** 2, axis=2)
    # A converged Lloyd iteration: each texel in its nearest center's cluster, and each
    # center the mean of its cluster.
    np.testing.assert_array_equal(labels, squared.argmin(axis=1))
    for c in range(k):
        np.testing.assert_allclose(centers[c], points64[labels == c].mean(axis=0), atol=1e-5)
    assert inertia == pytest.approx(squared[np.arange(len(points)), labels].sum(), rel=1e-5)
    if truth is not None:  # well-separated blobs: the truth up to a renaming of clusters
        table = np.zeros((k, k), dtype=int)
        np.add.at(table, (truth, labels), 1)
        assert (table > 0).sum() == k, table


def test_kmeans_pp_takes_its_randomness_and_iterations_from_its_arguments():
    """Catches a seed that does not reach the seeding (or randomness not taken from it),
    and ``max_iter`` or ``n_init`` not passed on."""
    points = _no_clusters()
    seeds = range(6)
    fits = {seed: kmeans_pp(points, 5, seed=seed) for seed in seeds}
    again = kmeans_pp(points, 5, seed=3)  # the same seed, the same fit
    np.testing.assert_array_equal(again[0], fits[3][0])
    np.testing.assert_array_equal(again[1], fits[3][1])
    assert again[2] == fits[3][2]
    # Without clear clusters the seeding decides: different seeds, different partitions.
    assert len({fit[2] for fit in fits.values()}) > 1
    # Lloyd's iterations never raise the inertia from the same seeding: one iteration
    # leaves it higher than running to convergence, for some seed at least.
    one_step = {seed: kmeans_pp(points, 5, seed=seed, max_iter=1)[2] for seed in seeds}
    assert all(one_step[seed] >= fits[seed][2] * (1 - 1e-6) for seed in seeds)
    assert any(one_step[seed] > fits[seed][2] * (1 + 1e-3) for seed in seeds)
    # The best of 8 restarts is no worse than one, and better for some seed.
    restarts = {seed: kmeans_pp(points, 5, seed=seed, n_init=8)[2] for seed in seeds}
    assert all(restarts[seed] <= fits[seed][2] * (1 + 1e-6) for seed in seeds)
    assert any(restarts[seed] < fits[seed][2] * (1 - 1e-3) for seed in seeds)


@pytest.mark.parametrize(
    "k, match",
    [
        (0, r"model\.k=0 must be a positive integer"),
        (-3, r"model\.k=-3 must be a positive integer"),
        (2.5, r"model\.k=2\.5 must be a positive integer"),
        ("8", r"model\.k='8' must be a positive integer"),
        (6, r"model\.k=6 is larger than the number of texels M=5"),
    ],
)
def test_check_k_names_the_bad_value(k, match):
    """Catches a bad k accepted or reported without the value and the setting's name."""
    with pytest.raises(ConfigError, match=match):
        check_k(k, 5)


def test_check_k_accepts_the_edges_and_kmeans_pp_checks_k():
    """Catches k = 1 or k = M refused, or kmeans_pp running with a k it should refuse."""
    check_k(1, 5)
    check_k(5, 5)
    with pytest.raises(ConfigError, match=r"model\.k=4 is larger .* M=3"):
        kmeans_pp(np.zeros((3, 2), np.float32), 4, seed=0)


# --------------------------------------------------------------------------- PCA


@pytest.mark.parametrize("shape, bad", [((6, 4), 0), ((6, 4), 5), ((3, 8), 4), ((3, 8), -1)])
def test_pca_reduce_out_of_range_names_the_setting(shape, bad):
    """Catches n_components outside 1..min(M, D) accepted or reported without its setting's name."""
    features = np.random.default_rng(0).normal(size=shape).astype(np.float32)
    m, d = shape
    with pytest.raises(ConfigError, match=rf"btf\.pca\.n_components={bad} .*M={m}, D={d}"):
        pca_reduce(features, bad)


@pytest.mark.parametrize("shape, n_components", [((40, 6), 3), ((40, 6), 6), ((5, 12), 4)])
def test_pca_scores_match_an_svd_of_the_centred_features(shape, n_components):
    """Catches uncentred features, the wrong singular vectors, or wrong explained variance."""
    rng = np.random.default_rng(n_components)
    m, d = shape
    # Distinct singular values, and an offset that matters if the data are not centred.
    features = (rng.normal(size=shape) * np.linspace(3.0, 0.5, d) + 7.0).astype(np.float32)
    scores, ratio = pca_reduce(features, n_components)
    centred = features.astype(np.float64) - features.mean(axis=0, dtype=np.float64)
    u, s, _ = np.linalg.svd(centred, full_matrices=False)
    reference = u[:, :n_components] * s[:n_components]
    assert scores.shape == (m, n_components) and scores.dtype == np.float32
    signs = np.sign(np.sum(scores * reference, axis=0))
    assert np.all(signs != 0)
    np.testing.assert_allclose(scores * signs, reference, atol=2e-4 * s[0])
    np.testing.assert_allclose(ratio, (s**2 / np.sum(s**2))[:n_components], rtol=1e-4)


# --------------------------------------------------------------------------- the encoder's input


class _Captured(Exception):
    """Stops the chain once the train stage has handed its arguments over."""


@pytest.fixture(scope="module")
def smoke_runs(tmp_path_factory):
    """One runs folder per module: the built-in BTF is generated once for both methods."""
    return tmp_path_factory.mktemp("btf_core_runs")


def _train_arguments(monkeypatch, runs, method: str, run_training: bool = False):
    """Run the real chain up to (and, if asked, through) the train stage; return its inputs."""
    import pipeline.btf.train as train_module
    from pipeline.btf import runner, stages
    from pipeline.core.stage import Context

    # Two views (N = 2 x 81 directions) keep generating the built-in BTF quick.
    cfg = compose_config(
        "experiment=smoke",
        f"model={method}",
        f"paths.runs={runs}",
        "dataset.views=[[0,0],[15,0]]",
        "train.max_steps=3",
        "btf.network.encoder_channels=[8,16,32]",
        "train.curve_every=0",
    )
    ctx = Context.from_config(cfg)
    captured: dict = {}
    real_train = train_module.train

    def spy(abrdf, sources, source_of_texel, norm, *args, **kwargs):
        captured.update(
            abrdf=np.array(abrdf),
            sources=np.array(sources),
            source_of_texel=np.array(source_of_texel),
            norm=norm,
            kwargs=kwargs,
        )
        if not run_training:
            raise _Captured
        return real_train(abrdf, sources, source_of_texel, norm, *args, **kwargs)

    monkeypatch.setattr(train_module, "train", spy)
    cropped = stages.crop(ctx, stages.load(ctx))
    prep = stages.preprocess(ctx, cropped)
    clusters = reps = None
    if method == "clustered":
        clusters = stages.kmeans(ctx, stages.pca(ctx, cropped, prep))
        reps = stages.representatives(ctx, cropped, clusters)
    if run_training:
        runner.train_stage(ctx, cropped, prep, clusters, reps)
    else:
        with pytest.raises(_Captured):
            runner.train_stage(ctx, cropped, prep, clusters, reps)
    captured.update(
        cfg=cfg,
        crop=np.array(stages.abrdf(cropped)),
        labels=None if clusters is None else clusters.array("labels", mmap=False),
    )
    return captured


def test_clustered_train_stage_feeds_each_texel_its_cluster_median(smoke_runs, monkeypatch):
    """Catches the clustered model fed the texel's own ABRDF (or a mean/medoid) instead of its cluster's median."""
    got = _train_arguments(monkeypatch, smoke_runs, "clustered")
    abrdf, sources, of_texel = got["abrdf"], got["sources"], got["source_of_texel"]
    k = got["cfg"].model.k
    np.testing.assert_array_equal(abrdf, got["crop"])  # targets: the texels themselves
    assert sources.shape == (k,) + abrdf.shape[1:]
    np.testing.assert_array_equal(of_texel, got["labels"])  # the k-means list
    assert not got["kwargs"]["target_from_source"]  # model.target: texel (the default)
    fed = sources[of_texel]
    np.testing.assert_allclose(fed, _median_loop(abrdf, of_texel, k)[of_texel], rtol=1e-6)
    own = np.all(fed == abrdf, axis=(1, 2))
    sizes = np.bincount(of_texel, minlength=k)
    # Only a texel alone in its cluster is its own representative.
    assert not own[sizes[of_texel] > 1].any()
    assert (~own).sum() >= abrdf.shape[0] // 2


def test_neural_btf_train_stage_feeds_each_texel_its_own_abrdf(smoke_runs, monkeypatch):
    """Catches Neural BTF's encoder fed anything but the texel's own ABRDF."""
    got = _train_arguments(monkeypatch, smoke_runs, "neural_btf")
    abrdf, sources, of_texel = got["abrdf"], got["sources"], got["source_of_texel"]
    np.testing.assert_array_equal(abrdf, got["crop"])
    np.testing.assert_array_equal(of_texel, np.arange(abrdf.shape[0]))
    np.testing.assert_array_equal(sources[of_texel], abrdf)


def test_clustered_encoder_sees_only_normalized_medians_while_training(smoke_runs, monkeypatch):
    """Catches train() itself encoding the texel's own ABRDF although it was handed the medians."""
    from pipeline.btf.model import Encoder

    seen: list[np.ndarray] = []
    forward = Encoder.forward

    def spy(self, x):
        seen.append(x.detach().cpu().numpy().copy())
        return forward(self, x)

    monkeypatch.setattr(Encoder, "forward", spy)
    got = _train_arguments(monkeypatch, smoke_runs, "clustered", run_training=True)
    norm, abrdf = got["norm"], got["abrdf"]
    # The encoder takes (batch, 3, N): the permuted standardized log ABRDFs.
    medians = norm.encoder_input(_median_loop(abrdf, got["labels"], got["cfg"].model.k))
    medians = medians.transpose(0, 2, 1).reshape(len(medians), -1)
    own = norm.encoder_input(abrdf).transpose(0, 2, 1).reshape(len(abrdf), -1)
    rows = np.concatenate([s.reshape(len(s), -1) for s in seen])
    assert len(seen) >= 3 and len(rows) >= 3 * 2  # three steps, then the latents

    def nearest(rows, table):
        return np.min(np.abs(rows[:, None, :] - table[None, :, :]).max(axis=2), axis=1)

    assert np.all(nearest(rows, medians) < 1e-4)
    # Singletons aside, those rows are no texel's own input.
    assert np.mean(nearest(rows, own) > 1e-3) > 0.5


def test_k_beyond_the_distinct_abrdfs_is_refused_before_the_medians():
    """A tiled texture holds fewer distinct ABRDFs than texels: k-means leaves clusters
    empty, which is named at once, not in the medians' pass after it."""
    scores = np.repeat(np.eye(3, dtype=np.float32), 20, axis=0)  # 60 texels, 3 distinct
    with pytest.raises(ConfigError, match=r"model.k=5: k-means found only 3 non-empty"):
        kmeans_pp(scores, 5, seed=0)
