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
:class:`Barycentric` computes those weights; the renderer's measured material
(:mod:`pipeline.btf.render.surfaces`) uses the same ones.
"""

from __future__ import annotations

from functools import cached_property

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


class Barycentric:
    """Barycentric weights in the Delaunay triangulation of grid directions (stereographic).

    The triangulation is built once, when the object is made.

    Parameters
    ----------
    grid_angles : ndarray of shape (P, 2)
        (theta, phi) in radians of the grid directions. With fewer than 3 there is no
        triangulation and every query takes its nearest grid direction.
    """

    def __init__(self, grid_angles: np.ndarray):
        grid_angles = np.asarray(grid_angles, dtype=np.float64)
        if grid_angles.ndim != 2 or grid_angles.shape[1] != 2 or len(grid_angles) == 0:
            raise ValueError(f"grid_angles must have shape (P, 2), P >= 1, got {grid_angles.shape}")
        self.unit = unit_vectors(*grid_angles.T)
        self.triangulation = None
        if len(grid_angles) >= 3:
            from scipy.spatial import Delaunay

            self.triangulation = Delaunay(stereographic(*grid_angles.T))

    def nearest(self, angles: np.ndarray) -> np.ndarray:
        """Index (n,) of the grid direction closest (largest cosine) to each of ``angles``
        (n, 2)."""
        return np.argmax(unit_vectors(*angles.T) @ self.unit.T, axis=1)

    def __call__(
        self,
        angles: np.ndarray,
        *,
        nearest: np.ndarray | None = None,
        bruteforce: bool = False,
        snap: float = 0.0,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Grid indices and weights of each direction.

        Parameters
        ----------
        angles : ndarray of shape (n, 2)
            (theta, phi) in radians.
        nearest : ndarray of shape (n,), optional
            :meth:`nearest` of ``angles`` when the caller has it already; otherwise it is
            computed for the queries outside the triangulation only.
        bruteforce : bool
            scipy's exhaustive simplex search instead of its walk: much faster for queries
            scattered over the hemisphere (a render's). Both find the triangle that holds
            a query; on a shared edge they may pick different ones (same point, weights
            that differ by rounding).
        snap : float
            A weight above ``1 - snap`` marks a query on a grid direction: its weights
            become exactly (1, 0, 0) in that corner's place. 0 leaves weights as computed.

        Returns
        -------
        ids : ndarray of shape (n, 3), int
            Grid indices of the triangle's corners; outside the triangulation, the nearest
            grid direction three times.
        weights : ndarray of shape (n, 3), float64
            Summing to 1; outside the triangulation (1, 0, 0).
        """
        angles = np.asarray(angles, dtype=np.float64)
        inside = np.zeros(len(angles), dtype=bool)
        ids = np.zeros((len(angles), 3), dtype=np.int64)
        weights = np.zeros((len(angles), 3))
        tri = self.triangulation
        if tri is not None:
            points = stereographic(*angles.T)
            simplex = tri.find_simplex(points, bruteforce=bruteforce)
            inside = simplex >= 0
            transform = tri.transform[simplex[inside]]
            b = np.einsum("qij,qj->qi", transform[:, :2], points[inside] - transform[:, 2])
            ids[inside] = tri.simplices[simplex[inside]]
            weights[inside] = np.column_stack([b, 1.0 - b.sum(1)])
        if not inside.all():
            outside = self.nearest(angles[~inside]) if nearest is None else nearest[~inside]
            ids[~inside] = outside[:, None]
            weights[~inside, 0] = 1.0
        if snap > 0:
            corner = weights > 1.0 - snap
            weights = np.where(corner.any(axis=1, keepdims=True), corner.astype(np.float64),
                               weights)
        return ids, weights


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

    # Built when first needed: a grid that cannot be triangulated fails at predict only.
    @cached_property
    def light_weights(self) -> Barycentric:
        """:class:`Barycentric` weights over the sampled light directions ``light_dirs``."""
        return Barycentric(self.light_dirs)

    @cached_property
    def view_weights(self) -> Barycentric:
        """:class:`Barycentric` weights over the sampled view directions ``view_dirs``."""
        return Barycentric(self.view_dirs)

    def predict(self, abrdf: np.ndarray, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(nearest, linear) predictions of shape (M, q, 3) at (q, 4) query directions."""
        ln = self.light_weights.nearest(queries[:, :2])
        vn = self.view_weights.nearest(queries[:, 2:])
        li, lw = self.light_weights(queries[:, :2], nearest=ln)
        vi, vw = self.view_weights(queries[:, 2:], nearest=vn)
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
