"""Interpolation at directions training never saw, which the paper claims but could not test.

Two kinds of unseen directions:

* held-out measured directions: ``btf.interpolation.holdout_lights`` of the 81 light
  directions are removed from training for every view; the reference is the measured data;
* off-grid directions: ``btf.interpolation.offgrid`` random (light, view) pairs away from the
  81-direction grid; the reference is the synthetic generator's analytic ground truth.

The Neural BTF is compared with two interpolants of the measured training data: the
nearest measured (light, view) pair, and "linear": barycentric weights in a Delaunay
triangulation of the light directions times those of the view directions (both in
stereographic coordinates), i.e. piecewise-linear interpolation on the product mesh.
"""

from __future__ import annotations

import numpy as np

from pipeline.btf.stereographic import direction_features, stereographic
from pipeline.data.directions import direction_index, grid_81, unit_vectors

OFFGRID_MAX_THETA = np.radians(70.0)  # inside the 75-degree ring, so inside the triangulation


def heldout_light_indices(cfg) -> np.ndarray:
    """Indices into :func:`grid_81` of the light directions held out of training."""
    count = int(cfg.btf.interpolation.holdout_lights)
    if count <= 0:
        return np.zeros(0, dtype=int)
    if count >= 80:
        raise ValueError(f"btf.interpolation.holdout_lights={count} leaves too few lights to train")
    rng = np.random.default_rng(cfg.btf.interpolation.seed)
    # Never the zenith (index 0): keep the triangulation's centre so interpolation is fair.
    return np.sort(rng.choice(np.arange(1, 81), size=count, replace=False))


def _direction_ids(angles: np.ndarray) -> np.ndarray:
    """Grid index of each (theta, phi) in radians (exact grid directions only)."""
    degrees = np.round(np.degrees(angles)).astype(int)
    return np.array([direction_index(t, p % 360) for t, p in degrees])


def training_directions(directions: np.ndarray, heldout: np.ndarray) -> np.ndarray:
    """Column indices (into the ABRDF's N directions) whose light is not held out."""
    light_ids = _direction_ids(directions[:, :2])
    return np.flatnonzero(~np.isin(light_ids, heldout))


class ProductInterpolator:
    """Nearest and linear interpolation of measured ABRDFs over (light, view) pairs."""

    def __init__(self, directions: np.ndarray, columns: np.ndarray):
        """directions : (N, 4) of the measured data; columns : indices usable as samples."""
        light_ids = _direction_ids(directions[columns, :2])
        view_ids = _direction_ids(directions[columns, 2:])
        self.lights = np.unique(light_ids)
        self.views = np.unique(view_ids)
        grid = grid_81()
        self.light_dirs, self.view_dirs = grid[self.lights], grid[self.views]
        table = -np.ones((81, 81), dtype=int)
        table[light_ids, view_ids] = columns
        self.table = table

    @staticmethod
    def _weights(points: np.ndarray, queries: np.ndarray):
        """Barycentric (index, weight) triples; nearest point when outside the hull."""
        p2, q2 = stereographic(*points.T), stereographic(*queries.T)
        nearest = np.argmax(unit_vectors(*queries.T) @ unit_vectors(*points.T).T, axis=1)
        idx = np.repeat(nearest[:, None], 3, axis=1)
        w = np.tile([1.0, 0.0, 0.0], (len(queries), 1))
        if len(points) >= 3:
            from scipy.spatial import Delaunay

            tri = Delaunay(p2)
            simplex = tri.find_simplex(q2)
            inside = simplex >= 0
            t = tri.transform[simplex[inside]]
            b = np.einsum("qij,qj->qi", t[:, :2], q2[inside] - t[:, 2])
            idx[inside] = tri.simplices[simplex[inside]]
            w[inside] = np.column_stack([b, 1.0 - b.sum(1)])
        return idx, w, nearest

    def predict(self, abrdf: np.ndarray, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(nearest, linear) predictions of shape (M, q, 3) at (q, 4) query directions."""
        li, lw, ln = self._weights(self.light_dirs, queries[:, :2])
        vi, vw, vn = self._weights(self.view_dirs, queries[:, 2:])
        nearest_cols = self.table[self.lights[ln], self.views[vn]]
        nearest = np.asarray(abrdf[:, nearest_cols], dtype=np.float32)
        linear = np.zeros_like(nearest)
        for a in range(3):
            for b in range(3):
                cols = self.table[self.lights[li[:, a]], self.views[vi[:, b]]]
                weight = (lw[:, a] * vw[:, b]).astype(np.float32)
                linear += weight[None, :, None] * np.asarray(abrdf[:, cols], dtype=np.float32)
        return nearest, linear


def _rmse(pred: np.ndarray, target: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(pred - target, dtype=np.float64))))


def _model_predict(decoder, latents, latent_of_texel, queries) -> np.ndarray:
    from pipeline.btf.evaluate import decode_all

    return decode_all(decoder, latents, direction_features(queries))[latent_of_texel]


def offgrid_directions(count: int, seed: int) -> np.ndarray:
    """(count, 4) random light/view directions, uniform in solid angle up to 70 degrees."""
    rng = np.random.default_rng(seed)
    cos_max = np.cos(OFFGRID_MAX_THETA)
    theta = np.arccos(1.0 - rng.random((count, 2)) * (1.0 - cos_max))
    phi = rng.random((count, 2)) * 2 * np.pi
    return np.column_stack([theta[:, 0], phi[:, 0], theta[:, 1], phi[:, 1]])


def measure(
    cfg,
    cropped,
    norm,
    decoder,
    latents: np.ndarray,
    latent_of_texel: np.ndarray,
    rmse_per_direction: np.ndarray,
    heldout: np.ndarray,
    texel_scale: np.ndarray | None = None,
) -> dict[str, float]:
    """Interpolation metrics (all in the normalized [0, 1] space).

    ``texel_scale`` (M,), when the clustered model stores one, multiplies its predictions.
    """
    abrdf = cropped.array("abrdf")
    directions = cropped.array("directions", mmap=False)
    alpha = np.float32(norm.alpha)
    train_cols = training_directions(directions, heldout)
    interp = ProductInterpolator(directions, train_cols)
    metrics: dict[str, float] = {}
    if len(heldout):
        test_cols = np.setdiff1d(np.arange(len(directions)), train_cols)
        sq = np.square(rmse_per_direction)
        metrics["rmse_train_dirs"] = float(np.sqrt(sq[train_cols].mean()))
        metrics["rmse_heldout_model"] = float(np.sqrt(sq[test_cols].mean()))
        nearest, linear = interp.predict(abrdf, directions[test_cols])
        target = np.asarray(abrdf[:, test_cols], dtype=np.float32)
        metrics["rmse_heldout_nearest"] = _rmse(nearest / alpha, target / alpha)
        metrics["rmse_heldout_linear"] = _rmse(linear / alpha, target / alpha)
    if cfg.dataset.name == "synthetic" and int(cfg.btf.interpolation.offgrid) > 0:
        from pipeline.btf.synthetic import SyntheticBTF

        queries = offgrid_directions(int(cfg.btf.interpolation.offgrid), cfg.btf.interpolation.seed)
        gen = cfg.dataset.synthetic
        truth = SyntheticBTF(size=gen.size, seed=gen.seed, material=gen.material).evaluate(queries)
        size = int(cfg.btf.crop.size)
        y0, x0 = (int(v) for v in cfg.btf.crop.offset)
        truth = truth[:, y0 : y0 + size, x0 : x0 + size].reshape(len(queries), -1, 3)
        truth = truth.transpose(1, 0, 2) / alpha
        model = _model_predict(decoder, latents, latent_of_texel, queries)
        if texel_scale is not None:
            model = model * texel_scale[:, None, None]
        nearest, linear = interp.predict(abrdf, queries)
        metrics["rmse_offgrid_model"] = _rmse(model, truth)
        metrics["rmse_offgrid_nearest"] = _rmse(nearest / alpha, truth)
        metrics["rmse_offgrid_linear"] = _rmse(linear / alpha, truth)
    return metrics
