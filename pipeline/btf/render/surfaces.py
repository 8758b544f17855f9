"""Method A's materials for the renderer (:mod:`pipeline.render`), each a
:class:`pipeline.render.materials.Material` (batched ``evaluate(texels, directions)``): the
measured BTF (:class:`MeasuredMaterial`, the reference) and the PCA baseline
(:class:`LinearMaterial`) interpolated between the measured directions, a compressed BTF
file (:class:`CompressedMaterial`), the built-in material's generator
(:class:`AnalyticMaterial`, the truth at every direction), any material at directions
clamped onto the grid (:class:`GridClamped`), and :class:`BeyondGridIndicator`, 1 where a
query lies beyond the grid, to measure how much of a render the grid does not cover.

The "grid" is whatever light and view directions the data holds: the UBO2003 81 x 81, a
UBO2014 file's 151 x 151, or any other product of a light and a view set; each class takes
the data's direction pairs (N, 4), and None means the UBO2003 grid.

Directions beyond the grid
--------------------------
A query beyond the polygon that the outermost measured directions of a set span in
stereographic coordinates (:class:`pipeline.btf.interpolation.DirectionHull`; for UBO2003
the 24 directions of the theta = 75 degree ring) has no measured neighbours: the measured
BTF and the PCA baseline answer it with their value clamped onto that polygon
(:meth:`DirectionHull.clamp <pipeline.btf.interpolation.DirectionHull.clamp>`: theta
lowered, phi kept), while a neural decoder would extrapolate.
Where a render has no truth (measured data), every material is queried through the same
clamp (:class:`GridClamped`), so that renders differ by their reconstruction of the
measured domain only, never by an extrapolation that nothing can check; the share of
samples beyond the grid is reported with each render. Where the generator is at hand (the
built-in material), the truth is evaluated unclamped and each model as it is. Light and
view are clamped each onto its own set's polygon.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from pipeline.btf.interpolation import DirectionHull, NoPolygon, ProductInterpolator
from pipeline.data.directions import btf_directions, direction_sets, grid_81
from pipeline.render.materials import Material, check_crop_size

# Queries answered at once by MeasuredMaterial and AnalyticMaterial (bounds their temporaries).
_MEASURED_CHUNK = 1 << 16
# A barycentric weight this close to 1 is a query on a grid direction: snap it to 1.
_SNAP = 1e-7


def _in_chunks(evaluate, texels: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """``evaluate(texels, directions)`` over :data:`_MEASURED_CHUNK` queries at a time: (n, 3)."""
    out = np.empty((len(texels), 3), dtype=np.float32)
    for start in range(0, len(texels), _MEASURED_CHUNK):
        stop = start + _MEASURED_CHUNK
        out[start:stop] = evaluate(texels[start:stop], directions[start:stop])
    return out


class CompressedMaterial(Material):
    """A compressed BTF (:func:`pipeline.btf.compressed.load_compressed`), queried as is.

    Parameters
    ----------
    compressed : :class:`pipeline.btf.compressed.CompressedBTF`, or anything with
        ``crop_size`` (rows, cols) and ``query_pairs(texels (n,), directions (n, 4)) ->
        (n, 3)``. Its output may be slightly negative: the renderer clamps radiance at 0.
    """

    def __init__(self, compressed):
        if not callable(getattr(compressed, "query_pairs", None)):
            raise ValueError(f"{compressed!r} has no query_pairs(texels, directions) method")
        self.crop_size = check_crop_size(compressed.crop_size)
        self.compressed = compressed

    def _evaluate(self, texels, directions):
        return np.asarray(self.compressed.query_pairs(texels, directions), dtype=np.float32)


class AnalyticMaterial(Material):
    """The built-in material's analytic generator over the run's crop: the truth.

    The value of crop texel (row, col) at a direction pair is
    ``fabric.evaluate(directions)[:, offset[0] + row, offset[1] + col]`` at any direction,
    evaluated per pair (``SyntheticBTF.evaluate_pairs``, which the tests check equals
    ``evaluate``): no grid, no clamp. Its values are the linear RGB that the built-in
    dataset encodes and the reader decodes again, its phi runs from +x (texture columns, the
    tangent +u) to +y (rows, the bitangent +v) as the renderer's does, so at grid directions
    it equals the measured material up to the data's 8-bit (JPEG) rounding.

    Parameters
    ----------
    fabric : :class:`pipeline.btf.synthetic.SyntheticBTF`
    offset : (row, col)
        Top-left texel of the crop in the fabric's ``size x size`` texture
        (``btf.crop.offset``).
    crop_size : (rows, cols)
    """

    def __init__(self, fabric, offset, crop_size):
        self.crop_size = check_crop_size(crop_size)
        try:
            row0, col0 = (int(v) for v in offset)
        except (TypeError, ValueError):
            raise ValueError(f"offset={offset!r} must be (row, col)") from None
        rows, cols = self.crop_size
        if min(row0, col0) < 0 or row0 + rows > fabric.size or col0 + cols > fabric.size:
            raise ValueError(
                f"a crop of {rows}x{cols} texels at offset ({row0}, {col0}) does not fit the "
                f"generator's {fabric.size}x{fabric.size} texture"
            )
        self.fabric = fabric
        crop_rows, crop_cols = np.divmod(np.arange(self.n_texels), cols)
        # Crop texel -> the generator's flat texel index (row * size + col).
        self._pixel = (row0 + crop_rows) * fabric.size + col0 + crop_cols

    @classmethod
    def from_config(cls, cfg) -> AnalyticMaterial:
        """The truth of a run on the built-in dataset: the generator of
        ``dataset.synthetic`` (size, seed, material) over the crop ``btf.crop``."""
        from pipeline.btf.synthetic import SyntheticBTF

        gen = cfg.dataset.synthetic
        fabric = SyntheticBTF(size=int(gen.size), seed=int(gen.seed), material=str(gen.material))
        size = int(cfg.btf.crop.size)
        return cls(fabric, [int(v) for v in cfg.btf.crop.offset], (size, size))

    def _evaluate(self, texels, directions):
        return _in_chunks(self.fabric.evaluate_pairs, self._pixel[texels], directions)


def direction_hulls(directions: np.ndarray | None = None) -> tuple[DirectionHull, DirectionHull]:
    """The polygons (light hull, view hull) covered by the light and by the view directions
    of the measured pairs ``directions`` (N, 4), radians; None: the UBO2003 grid (both
    polygons the 75-degree ring's)."""
    if directions is None:
        return _ubo2003_hulls()
    sets = direction_sets(directions)
    return DirectionHull(sets.lights), DirectionHull(sets.views)


@lru_cache(maxsize=1)
def _ubo2003_hulls() -> tuple[DirectionHull, DirectionHull]:
    hull = DirectionHull(grid_81())
    return hull, hull


def _polygon_of(angles: np.ndarray) -> DirectionHull | None:
    """The polygon a direction set spans, None when it spans none (one view of a BTF)."""
    try:
        return DirectionHull(angles)
    except NoPolygon:
        return None


def _clamped(hull: DirectionHull | None, angles: np.ndarray) -> np.ndarray:
    return angles if hull is None else hull.clamp(angles)


class GridClamped(Material):
    """``material`` queried at directions clamped onto the measured grid, the light onto
    the light set's polygon and the view onto the view set's: the rule where a render has no
    truth (module docstring). The measured and PCA materials clamp already.

    Parameters
    ----------
    material : :class:`Material`
    directions : ndarray of shape (N, 4), radians, or None
        The measured direction pairs; None: the UBO2003 grid.
    """

    def __init__(self, material: Material, directions: np.ndarray | None = None):
        if not callable(getattr(material, "evaluate", None)):
            raise ValueError(f"{material!r} has no evaluate(texels, directions) method")
        self.crop_size = check_crop_size(material.crop_size)
        self.material = material
        self._light_hull, self._view_hull = direction_hulls(directions)

    def _evaluate(self, texels, directions):
        clamped = np.column_stack(
            [self._light_hull.clamp(directions[:, :2]), self._view_hull.clamp(directions[:, 2:])]
        )
        return np.asarray(self.material.evaluate(texels, clamped), dtype=np.float32)


class BeyondGridIndicator(Material):
    """Marks the queries beyond the measured grid: RGB = (light or view beyond, light
    beyond, 1) (``DirectionHull.beyond``, each against its own set), whatever the texel.

    Rendered with the same samples as the models, channel 0 over channel 2 is, per pixel,
    the share of its (camera sample, light) pairs whose light or view lies beyond the grid,
    each pair weighted by the light's irradiance there (the renderer multiplies every
    material value by it; with one light the weights vary little across a pixel or crop);
    channel 1 over channel 2 the same for the light alone.

    Parameters
    ----------
    crop_size : (rows, cols)
    directions : ndarray of shape (N, 4), radians, or None
        The measured direction pairs; None: the UBO2003 grid.
    """

    def __init__(self, crop_size, directions: np.ndarray | None = None):
        self.crop_size = check_crop_size(crop_size)
        self._light_hull, self._view_hull = direction_hulls(directions)

    def _evaluate(self, texels, directions):
        light = self._light_hull.beyond(directions[:, :2])
        either = light | self._view_hull.beyond(directions[:, 2:])
        return np.column_stack([either, light, np.ones(len(texels))]).astype(np.float32)


class MeasuredMaterial(Material):
    """The measured BTF, interpolated piecewise-linearly between its measured directions.

    The interpolant is the "linear" one of :class:`pipeline.btf.interpolation.
    ProductInterpolator`: barycentric weights in a Delaunay triangulation of the data's L
    light directions (stereographic coordinates) times those of its V view directions, 9
    measured values per query. At a measured direction pair it returns the measured value
    exactly (weights within ``1e-7`` of a corner are snapped onto it). Directions beyond the
    grid are clamped onto it (module docstring).

    Parameters
    ----------
    values : ndarray of shape (M, N, 3)
        Linear RGB of M = rows x cols texels (row-major) at N direction pairs; any float
        dtype, or a memory map.
    crop_size : (rows, cols)
    directions : ndarray of shape (N, 4), radians, or None
        The direction pair of each column of ``values``; None means
        :func:`pipeline.data.directions.btf_directions` (N = 6561). Any light and view
        sets, but every light under every view (N = L · V). A set of one direction, or
        of directions on one line, spans no polygon: every query takes its nearest
        direction of that set (as :class:`~pipeline.btf.interpolation.Barycentric` does),
        unclamped; a set that spans one must surround the normal
        (:class:`~pipeline.btf.interpolation.DirectionHull`).

    Raises
    ------
    ValueError
        For arrays of the wrong shapes; :class:`~pipeline.core.errors.DataError` (a
        ValueError) for directions that are not a full product or do not surround the normal.
    """

    def __init__(self, values: np.ndarray, crop_size, directions: np.ndarray | None = None):
        self.crop_size = check_crop_size(crop_size)
        directions = btf_directions() if directions is None else np.asarray(directions)
        if not isinstance(values, np.ndarray):
            values = np.asarray(values)
        if values.ndim != 3 or values.shape[2] != 3:
            raise ValueError(f"values must have shape (M, N, 3), got {values.shape}")
        if values.shape[0] != self.n_texels:
            raise ValueError(
                f"values has {values.shape[0]} texels but crop_size={self.crop_size} "
                f"has {self.n_texels}"
            )
        if directions.shape != (values.shape[1], 4):
            raise ValueError(
                f"directions must have shape ({values.shape[1]}, 4), got {directions.shape}"
            )
        self.values = values
        self._set_grid(directions)

    def _set_grid(self, directions: np.ndarray) -> None:
        """The interpolation over ``directions`` (N, 4), a full product of light and view
        sets, and the polygons each set covers."""
        self._interpolator = ProductInterpolator(directions, np.arange(len(directions)))
        self._light_hull = _polygon_of(self._interpolator.light_dirs)
        self._view_hull = _polygon_of(self._interpolator.view_dirs)

    def _gather(self, texels: np.ndarray, columns: np.ndarray) -> np.ndarray:
        """Stored RGB of texel ``texels[i]`` at direction pair ``columns[i]``: (n, 3)."""
        return np.asarray(self.values[texels, columns], dtype=np.float32)

    def _evaluate(self, texels, directions):
        return _in_chunks(self._interpolate, texels, directions)

    def _interpolate(self, texels: np.ndarray, directions: np.ndarray) -> np.ndarray:
        interp = self._interpolator
        # The exhaustive search is much faster than scipy's walk for queries scattered
        # over the hemisphere, as a render's are.
        light_ids, light_w = interp.light_weights(
            _clamped(self._light_hull, directions[:, :2]), bruteforce=True, snap=_SNAP
        )
        view_ids, view_w = interp.view_weights(
            _clamped(self._view_hull, directions[:, 2:]), bruteforce=True, snap=_SNAP
        )
        # Each query gathers its own texel's 9 values (ProductInterpolator.predict would
        # interpolate every texel at every query).
        out = np.zeros((len(texels), 3), dtype=np.float32)
        for a in range(3):
            for b in range(3):
                weight = light_w[:, a] * view_w[:, b]
                used = weight != 0.0
                columns = interp.table[
                    interp.lights[light_ids[used, a]], interp.views[view_ids[used, b]]
                ]
                value = self._gather(texels[used], columns)
                out[used] += weight[used, None].astype(np.float32) * value
        return out


class LinearMaterial(MeasuredMaterial):
    """The PCA baseline (:mod:`pipeline.btf.linear`), interpolated like the measured BTF.

    PCA stores the BTF at the measured direction pairs only, so a render interpolates its
    reconstruction between them exactly as :class:`MeasuredMaterial` does the measurement;
    each of the 9 values a query needs is reconstructed on the fly,
    ``scale * (mean + coefficients[texel] @ basis)`` at that direction pair (the 3N x M
    matrix is never formed). A value may be slightly negative: the renderer clamps at 0.

    Parameters
    ----------
    mean : ndarray of shape (3N,)
    basis : ndarray of shape (c, 3N)
    coefficients : ndarray of shape (M, c)
        As stored by the linear stage (normalized units, any float dtype).
    crop_size : (rows, cols), M = rows x cols
    scale : float
        Back to linear RGB: the normalization's ``alpha``.
    directions : ndarray of shape (N, 4), radians, or None (:func:`btf_directions`)
    """

    def __init__(
        self,
        mean,
        basis,
        coefficients,
        crop_size,
        scale: float,
        directions: np.ndarray | None = None,
    ):
        self.crop_size = check_crop_size(crop_size)
        directions = btf_directions() if directions is None else np.asarray(directions)
        n = len(directions)
        mean, basis = np.asarray(mean, np.float32), np.asarray(basis, np.float32)
        coefficients = np.asarray(coefficients, np.float32)
        if mean.shape != (3 * n,) or basis.ndim != 2 or basis.shape[1] != 3 * n:
            raise ValueError(
                f"mean {mean.shape} and basis {basis.shape} must be (3N,) and (c, 3N) "
                f"with N = {n} directions"
            )
        if coefficients.shape != (self.n_texels, basis.shape[0]):
            raise ValueError(
                f"coefficients have shape {coefficients.shape}, expected "
                f"({self.n_texels}, {basis.shape[0]}) for crop_size={self.crop_size}"
            )
        scale = np.float32(scale)
        # Scaled once here, and the basis laid out (N, 3, c) so that a query's column
        # gathers its (3, c) block contiguously.
        self._mean = scale * mean.reshape(n, 3)
        self._basis = np.ascontiguousarray((scale * basis).reshape(-1, n, 3).transpose(1, 2, 0))
        self._coefficients = coefficients
        self._set_grid(directions)

    def _gather(self, texels, columns):
        return self._mean[columns] + np.einsum(
            "nkc,nc->nk", self._basis[columns], self._coefficients[texels]
        )


def beyond_grid(angles: np.ndarray) -> np.ndarray:
    """Whether each direction (n, 2), (theta, phi) in radians, lies beyond the UBO2003 grid's
    polygon: True where :func:`clamp_to_grid` moves it by more than a rounding error, i.e.
    where no measured value surrounds it. Shape (n,), bool.

    >>> beyond_grid(np.radians([[75.0, 0.0], [75.0, 7.5], [74.0, 7.5], [80.0, 30.0]]))
    array([False,  True, False,  True])
    """
    return _ubo2003_hulls()[0].beyond(angles)


def clamp_to_grid(angles: np.ndarray) -> np.ndarray:
    """Directions (n, 2), (theta, phi) in radians, with theta lowered onto the UBO2003 grid's
    polygon (slightly inside it) where they lie beyond it; phi kept. Shape (n, 2)."""
    return _ubo2003_hulls()[0].clamp(angles)
