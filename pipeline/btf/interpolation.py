"""Interpolation at directions training never saw, which the paper claims but could not test.

* held-out measured directions: ``btf.interpolation.holdout_lights`` of the data's light
  directions are removed from training for every view; the reference is the measured data;
* off-grid directions: ``btf.interpolation.offgrid`` random (light, view) pairs away from the
  measured directions; the reference is the synthetic generator's analytic ground truth.

The Neural BTF is compared with two interpolants of the measured training data: the
nearest measured (light, view) pair, and "linear": barycentric weights (:class:`Barycentric`,
which the renderer's measured material uses too) in a Delaunay triangulation of the light
directions times those of the view directions, both in stereographic coordinates.

The light and the view set are whatever the data's direction pairs hold
(:func:`pipeline.data.directions.direction_sets`), as long as every light was measured
under every view (a product L × V), not only the UBO2003 81-grid.
"""

from __future__ import annotations

from contextlib import suppress
from functools import cached_property

import numpy as np

from pipeline.btf.stereographic import direction_features, stereographic
from pipeline.core.errors import ConfigError, DataError
from pipeline.core.progress import progress
from pipeline.data.directions import direction_sets, unit_vectors

# Off-grid queries stay this close to the normal (and inside the data's directions, see
# offgrid_max_theta): within the UBO2003 grid's 75-degree ring, so inside its triangulation.
OFFGRID_MAX_THETA = np.radians(70.0)


def heldout_light_indices(cfg, lights: np.ndarray) -> np.ndarray:
    """Indices into the data's light set ``lights`` (L, 2) of the
    ``btf.interpolation.holdout_lights`` light directions held out of training: (count,)
    int, sorted. Never the light nearest the normal, which keeps the centre of the
    triangulation (for the 81-grid: index 0, the zenith). ConfigError if fewer than 2
    lights would be left to train on."""
    count = int(cfg.btf.interpolation.holdout_lights)
    if count <= 0:
        return np.zeros(0, dtype=int)
    if count > len(lights) - 2:
        raise ConfigError(
            f"btf.interpolation.holdout_lights={count} leaves too few of the data's "
            f"{len(lights)} light directions to train (at most {len(lights) - 2})"
        )
    rng = np.random.default_rng(cfg.btf.interpolation.seed)
    centre = int(np.argmin(lights[:, 0]))
    return np.sort(rng.choice(np.delete(np.arange(len(lights)), centre), size=count, replace=False))


def heldout_lights_of(cfg, entry) -> np.ndarray:
    """:func:`heldout_light_indices` of the light set of a load or crop stage's ``entry``."""
    lights = direction_sets(entry.array("directions", mmap=False)).lights
    return heldout_light_indices(cfg, lights)


def training_directions(directions: np.ndarray, heldout: np.ndarray) -> np.ndarray:
    """Column indices (into the ABRDF's N directions) whose light is not in ``heldout``
    (indices into the light set of ``directions``, :func:`heldout_light_indices`)."""
    light_of = direction_sets(directions).light_of
    return np.flatnonzero(~np.isin(light_of, heldout))


class NoPolygon(DataError):
    """A direction set that spans no polygon: fewer than 3 directions, or all on one line
    in stereographic coordinates (one view of a BTF)."""


class DirectionHull:
    """The region a direction set's triangulation covers, and the clamp onto its edge.

    In stereographic coordinates (radius tan(θ / 2)) the Delaunay triangulation of a set
    covers the convex polygon of its points; a direction beyond that polygon has no
    triangle around it. For the UBO2003 grid the polygon is the regular 24-gon of the
    75-degree ring; for any other set it is whatever the outermost directions span.

    Parameters
    ----------
    angles : ndarray of shape (P, 2)
        (θ, φ) radians of the set, P >= 3 not all on one line. The polygon must hold the
        normal (θ = 0) strictly inside, so that lowering θ at fixed φ reaches it: else
        DataError (NoPolygon where the set spans no polygon).
    """

    # A direction this far (radians) outside the polygon counts as beyond it: the set's own
    # outermost directions are inside, whatever their rounding.
    TOLERANCE = 1e-9

    def __init__(self, angles: np.ndarray):
        angles = np.asarray(angles, dtype=np.float64).reshape(-1, 2)
        points = stereographic(*angles.T)
        from scipy.spatial import ConvexHull, QhullError

        try:
            corners = points[ConvexHull(points).vertices]  # counterclockwise
        except (QhullError, ValueError):
            raise NoPolygon(
                f"{len(angles)} directions span no polygon (fewer than 3, or all on one "
                f"line in stereographic coordinates): nothing to interpolate in"
            ) from None
        edges = np.roll(corners, -1, axis=0) - corners
        normals = np.column_stack([edges[:, 1], -edges[:, 0]])  # outward, counterclockwise
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        distances = np.sum(normals * corners, axis=1)
        if distances.min() <= 1e-12:
            raise DataError(
                f"the {len(angles)} directions do not surround the normal (theta = 0): the "
                f"nearest edge of their polygon passes {distances.min():.3g} from it"
            )
        # Edge k runs from corner k to corner k + 1; a ray at azimuth phi leaves the polygon
        # through the edge whose corners' azimuths bracket phi.
        azimuths = np.mod(np.arctan2(corners[:, 1], corners[:, 0]), 2 * np.pi)
        first = int(np.argmin(azimuths))
        self._azimuths = np.roll(azimuths, -first)
        self._normals = np.roll(normals, -first, axis=0)
        self._distances = np.roll(distances, -first)

    @property
    def inscribed_theta(self) -> float:
        """The largest θ up to which every direction, whatever its φ, is inside."""
        return float(2.0 * np.arctan(self._distances.min()))

    def edge_theta(self, phi: np.ndarray, shrink: float = 1.0) -> np.ndarray:
        """θ of the polygon's edge at azimuth ``phi`` (any shape; its radius × ``shrink``)."""
        phi = np.asarray(phi, dtype=np.float64)
        edge = np.searchsorted(self._azimuths, np.mod(phi, 2 * np.pi), side="right") - 1
        edge = np.mod(edge, len(self._azimuths))
        facing = np.cos(phi) * self._normals[edge, 0] + np.sin(phi) * self._normals[edge, 1]
        return 2.0 * np.arctan(self._distances[edge] / facing * shrink)

    def beyond(self, angles: np.ndarray) -> np.ndarray:
        """Whether each of ``angles`` (n, 2) lies beyond the polygon: (n,) bool, True where
        :meth:`clamp` moves it by more than a rounding error."""
        angles = np.asarray(angles, dtype=np.float64)
        return angles[:, 0] > self.edge_theta(angles[:, 1]) + self.TOLERANCE

    def clamp(self, angles: np.ndarray) -> np.ndarray:
        """``angles`` (n, 2) with θ lowered onto the polygon (slightly inside it) where a
        direction lies beyond it; φ kept. Returns (n, 2)."""
        angles = np.asarray(angles, dtype=np.float64)
        theta, phi = angles[:, 0], angles[:, 1]
        theta_max = self.edge_theta(phi, shrink=1.0 - 1e-9)
        return np.column_stack([np.where(theta > theta_max, theta_max, theta), phi])


class Barycentric:
    """Barycentric weights in the Delaunay triangulation of a direction set (stereographic),
    built once.

    Parameters
    ----------
    grid_angles : ndarray of shape (P, 2)
        (theta, phi) in radians of the grid directions. With fewer than 3, or all on one
        line (stereographic), there is no triangulation and every query takes its nearest
        grid direction.
    """

    def __init__(self, grid_angles: np.ndarray):
        grid_angles = np.asarray(grid_angles, dtype=np.float64)
        if grid_angles.ndim != 2 or grid_angles.shape[1] != 2 or len(grid_angles) == 0:
            raise ValueError(f"grid_angles must have shape (P, 2), P >= 1, got {grid_angles.shape}")
        self.unit = unit_vectors(*grid_angles.T)
        self.triangulation = None
        if len(grid_angles) >= 3:
            from scipy.spatial import Delaunay, QhullError

            with suppress(QhullError):  # all on one line: no triangle, nearest only
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
        angles : ndarray of shape (n, 2), (theta, phi) in radians
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
            weights = np.where(corner.any(axis=1, keepdims=True), corner.astype(float), weights)
        return ids, weights


class ProductInterpolator:
    """Nearest and linear interpolation of measured ABRDFs over (light, view) pairs.

    Parameters
    ----------
    directions : ndarray of shape (N, 4)
        (θ_light, φ_light, θ_view, φ_view) radians of the data's columns.
    columns : ndarray of int
        The columns usable as samples; their lights and views must form a full product
        (every sampled light under every sampled view).

    Attributes
    ----------
    lights, views : ndarray of int
        The sampled lights (views): indices into the data's light (view) set
        (:func:`pipeline.data.directions.direction_sets`), increasing.
    light_dirs, view_dirs : ndarray of shape (len(lights), 2), (len(views), 2)
        Their (θ, φ) in radians.
    table : ndarray of shape (L, V), int
        The column of each (light, view) pair of the data's sets; -1 where not sampled.

    DataError if a sampled light was not measured under some sampled view.
    """

    def __init__(self, directions: np.ndarray, columns: np.ndarray):
        sets = direction_sets(directions)
        columns = np.asarray(columns, dtype=np.int64)
        light_ids, view_ids = sets.light_of[columns], sets.view_of[columns]
        self.lights = np.unique(light_ids)
        self.views = np.unique(view_ids)
        self.light_dirs, self.view_dirs = sets.lights[self.lights], sets.views[self.views]
        table = -np.ones((len(sets.lights), len(sets.views)), dtype=int)
        table[light_ids, view_ids] = columns
        missing = int((table[np.ix_(self.lights, self.views)] < 0).sum())
        if missing:
            raise DataError(
                f"{missing} of the {len(self.lights)} x {len(self.views)} (light, view) pairs "
                f"are not in the data: interpolating between directions needs every light "
                f"measured under every view"
            )
        self.table = table

    # Built when first needed: a grid that cannot be triangulated fails at predict only.
    @cached_property
    def light_weights(self) -> Barycentric:
        """:class:`Barycentric` weights over ``light_dirs``."""
        return Barycentric(self.light_dirs)

    @cached_property
    def view_weights(self) -> Barycentric:
        """:class:`Barycentric` weights over ``view_dirs``."""
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


def heldout_rmse(
    interp: ProductInterpolator,
    abrdf,
    queries: np.ndarray,
    columns: np.ndarray,
    alpha: np.float32,
    block_bytes: int = 1 << 26,
) -> tuple[float, float]:
    """RMSE (normalized by ``alpha``) of the nearest and the linear interpolation of the
    measured neighbours at the held-out ``queries`` (the data's ``columns``), a block of
    texels at a time (each read whole: about ``block_bytes`` of values), squares summed in
    float64: memory does not grow with the texels (a whole UBO2014 material has 160,000)."""
    n = abrdf.shape[1]
    step = max(1, block_bytes // (n * 3 * 4))
    sums, count = np.zeros(2), 0
    for start in progress(range(0, abrdf.shape[0], step), "held-out lights", unit="block"):
        block = np.asarray(abrdf[start : start + step], dtype=np.float32)
        target = block[:, columns] / alpha
        for i, pred in enumerate(interp.predict(block, queries)):
            sums[i] += float(np.square(pred / alpha - target, dtype=np.float64).sum())
        count += target.size
    nearest, linear = np.sqrt(sums / count)
    return float(nearest), float(linear)


def _rmse(pred: np.ndarray, target: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(pred - target, dtype=np.float64))))


def offgrid_directions(count: int, seed: int, max_theta: float = OFFGRID_MAX_THETA) -> np.ndarray:
    """(count, 4) random light/view directions, uniform in solid angle up to ``max_theta``
    radians (70 degrees by default; :func:`offgrid_max_theta` for a run's data)."""
    rng = np.random.default_rng(seed)
    cos_max = np.cos(max_theta)
    theta = np.arccos(1.0 - rng.random((count, 2)) * (1.0 - cos_max))
    phi = rng.random((count, 2)) * 2 * np.pi
    return np.column_stack([theta[:, 0], phi[:, 0], theta[:, 1], phi[:, 1]])


def offgrid_max_theta(directions: np.ndarray) -> float:
    """How far from the normal off-grid queries may go on data measured at ``directions``
    (N, 4): :data:`OFFGRID_MAX_THETA`, or less where the data's directions (lights and
    views together) surround a smaller region (:attr:`DirectionHull.inscribed_theta`; when
    they surround none, the largest θ among them). For the 81-grid: 70 degrees."""
    sets = direction_sets(directions)
    both = np.concatenate([sets.lights, sets.views])
    try:
        covered = DirectionHull(both).inscribed_theta
    except DataError:
        covered = float(both[:, 0].max())
    return min(float(OFFGRID_MAX_THETA), covered)


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

    ``heldout`` indexes the light set of the crop's directions (:func:`heldout_light_indices`);
    ``texel_scale`` (M,), when the clustered model stores one, multiplies its predictions.
    """
    from pipeline.btf.stages import abrdf as crop_abrdf
    from pipeline.btf.stages import truth_at_crop

    abrdf = crop_abrdf(cropped)
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
        nearest, linear = heldout_rmse(interp, abrdf, directions[test_cols], test_cols, alpha)
        metrics["rmse_heldout_nearest"], metrics["rmse_heldout_linear"] = nearest, linear
    settings = cfg.btf.interpolation
    if cfg.dataset.name == "synthetic" and int(settings.offgrid) > 0:
        from pipeline.btf.evaluate import decode_all

        queries = offgrid_directions(
            int(settings.offgrid), settings.seed, offgrid_max_theta(directions)
        )
        truth = truth_at_crop(cfg)(queries) / alpha
        model = decode_all(decoder, latents, direction_features(queries))[latent_of_texel]
        if texel_scale is not None:
            model = model * texel_scale[:, None, None]
        nearest, linear = interp.predict(abrdf, queries)
        metrics["rmse_offgrid_model"] = _rmse(model, truth)
        metrics["rmse_offgrid_nearest"] = _rmse(nearest / alpha, truth)
        metrics["rmse_offgrid_linear"] = _rmse(linear / alpha, truth)
    return metrics
