"""Method A's materials for the renderer (:mod:`pipeline.render`): the measured BTF, the
PCA baseline, a compressed BTF file and the built-in material's generator.

Each is a :class:`pipeline.render.materials.Material`: batched queries
``evaluate(texels, directions)`` (the conventions are in that module).

- :class:`MeasuredMaterial`: the measured 81 x 81 directions, interpolated (the reference).
- :class:`LinearMaterial`: the PCA baseline's reconstruction, interpolated the same way.
- :class:`CompressedMaterial`: a compressed BTF file (``pipeline.btf.compressed``).
- :class:`AnalyticMaterial`: the built-in material's generator (``pipeline.btf.synthetic``),
  the truth at every direction.
- :class:`GridClamped`: any material queried at directions clamped onto the measured grid.
- :class:`BeyondGridIndicator`: 1 where a query lies beyond the grid, to measure how much of a
  render the grid does not cover.

Directions beyond the grid
--------------------------
The measured directions end at the theta = 75 degree ring. A query beyond the polygon of
that ring's 24 directions (:func:`beyond_grid`) has no measured neighbours: the measured
BTF and the PCA baseline, which store values at the grid only, answer it with their value
clamped onto the ring (:func:`clamp_to_grid`: theta lowered, phi kept), while a neural
decoder would extrapolate. Where a render has no truth (measured data), every material is
queried through the same clamp (:class:`GridClamped`), so that renders differ by their
reconstruction of the measured domain only, never by an extrapolation that nothing can
check; the share of samples beyond the grid is reported with each render. Where the
generator is at hand (the built-in material), the truth is evaluated unclamped and each
model as it is.
"""

from __future__ import annotations

import os

import numpy as np

from pipeline.btf.interpolation import ProductInterpolator
from pipeline.data.directions import RINGS_DEGREES, btf_directions
from pipeline.render.materials import Material, check_crop_size

# Queries answered at once by MeasuredMaterial and AnalyticMaterial (bounds their temporaries).
_MEASURED_CHUNK = 1 << 16
# A barycentric weight this close to 1 is a query on a grid direction: snap it to 1.
_SNAP = 1e-7


class CompressedMaterial(Material):
    """A compressed BTF (:func:`pipeline.btf.compressed.load_compressed`), queried as is.

    Parameters
    ----------
    compressed : :class:`pipeline.btf.compressed.CompressedBTF`, or anything with
        ``crop_size`` (rows, cols) and ``query_pairs(texels (n,), directions (n, 4)) ->
        (n, 3)``.

    Notes
    -----
    The decoder's output is not clamped here (it may be slightly negative); the renderer
    clamps radiance at 0.
    """

    def __init__(self, compressed):
        if not callable(getattr(compressed, "query_pairs", None)):
            raise ValueError(f"{compressed!r} has no query_pairs(texels, directions) method")
        self.crop_size = check_crop_size(compressed.crop_size)
        self.compressed = compressed

    @classmethod
    def from_file(cls, path: str | os.PathLike) -> CompressedMaterial:
        """Load a ``btf.safetensors`` file (imports torch)."""
        from pipeline.btf.compressed import load_compressed

        return cls(load_compressed(path))

    def _evaluate(self, texels, directions):
        return np.asarray(self.compressed.query_pairs(texels, directions), dtype=np.float32)


class AnalyticMaterial(Material):
    """The built-in material's analytic generator over the run's crop: the truth.

    The value of crop texel (row, col) at a direction pair is
    ``fabric.evaluate(directions)[:, offset[0] + row, offset[1] + col]``
    (:meth:`pipeline.btf.synthetic.SyntheticBTF.evaluate`) at any direction: no grid, no
    clamp. Units and directions are those of the measured crop (:class:`MeasuredMaterial`):
    the generator's values are the linear RGB that the built-in dataset encodes and the
    reader decodes again, and its phi runs from +x (texture columns, the tangent +u) to +y
    (rows, the bitangent +v), as the renderer's does. At grid directions it therefore
    equals the measured material up to the data's 8-bit (JPEG) rounding.

    Parameters
    ----------
    fabric : :class:`pipeline.btf.synthetic.SyntheticBTF`
    offset : (row, col)
        Top-left texel of the crop in the fabric's ``size x size`` texture
        (``btf.crop.offset``).
    crop_size : (rows, cols)

    Notes
    -----
    The generator evaluates every texel of its texture at each direction; a render asks
    for one texel per direction pair, so this class evaluates the generator's shading
    per pair (``SyntheticBTF.evaluate_pairs``), which the tests check equals ``evaluate``.
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
        out = np.empty((len(texels), 3), dtype=np.float32)
        for start in range(0, len(texels), _MEASURED_CHUNK):
            stop = start + _MEASURED_CHUNK
            out[start:stop] = self.fabric.evaluate_pairs(
                self._pixel[texels[start:stop]], directions[start:stop]
            )
        return out


class GridClamped(Material):
    """``material`` queried at directions clamped onto the measured grid
    (:func:`clamp_to_grid`, light and view alike): the rule for directions beyond the grid
    where a render has no truth (module docstring). The measured and PCA materials clamp
    already, so for them this changes nothing.

    Parameters
    ----------
    material : :class:`Material`
    """

    def __init__(self, material: Material):
        if not callable(getattr(material, "evaluate", None)):
            raise ValueError(f"{material!r} has no evaluate(texels, directions) method")
        self.crop_size = check_crop_size(material.crop_size)
        self.material = material

    def _evaluate(self, texels, directions):
        clamped = np.column_stack(
            [clamp_to_grid(directions[:, :2]), clamp_to_grid(directions[:, 2:])]
        )
        return np.asarray(self.material.evaluate(texels, clamped), dtype=np.float32)


class BeyondGridIndicator(Material):
    """Marks the queries beyond the measured grid: RGB = (light or view beyond, light
    beyond, 1) (:func:`beyond_grid`), whatever the texel.

    Rendered with the same samples as the models, channel 0 over channel 2 is, per pixel,
    the share of its (camera sample, light) pairs whose light or view lies beyond the grid,
    each pair weighted by the light's irradiance there (the renderer multiplies every
    material value by it; with one light the weights vary little across a pixel or crop);
    channel 1 over channel 2 the same for the light alone.
    """

    def __init__(self, crop_size):
        self.crop_size = check_crop_size(crop_size)

    def _evaluate(self, texels, directions):
        light = beyond_grid(directions[:, :2])
        either = light | beyond_grid(directions[:, 2:])
        return np.column_stack([either, light, np.ones(len(texels))]).astype(np.float32)


class MeasuredMaterial(Material):
    """The measured BTF, interpolated piecewise-linearly between its 81 x 81 directions.

    The interpolant is the "linear" one of :class:`pipeline.btf.interpolation.
    ProductInterpolator` (whose table of columns and :class:`~pipeline.btf.interpolation.
    Barycentric` weights it uses): barycentric weights in a Delaunay triangulation of the
    81 light directions (stereographic coordinates) times those of the 81 view directions,
    9 measured values per query. At a grid direction pair it returns the measured value
    exactly (weights within ``1e-7`` of a corner are snapped onto it).

    Directions beyond the grid's outermost ring (theta = 75 degrees) are clamped onto it:
    theta is lowered, phi kept, to the edge of the triangulation (the polygon of the 24
    directions of the 75-degree ring, which lies at most 75 degrees from the normal). Grazing
    light and view are therefore rendered as if they came from the 75-degree ring.

    Parameters
    ----------
    values : ndarray of shape (M, N, 3)
        Linear RGB of M = rows x cols texels (row-major) at N direction pairs; any float
        dtype, or a memory map.
    crop_size : (rows, cols)
    directions : ndarray of shape (N, 4), radians, or None
        The direction pair of each column of ``values``; None means
        :func:`pipeline.data.directions.btf_directions` (N = 6561). They must be the
        full 81 x 81 product grid.
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
        """The interpolation over ``directions`` (N, 4), the full 81 x 81 product grid."""
        try:
            self._interpolator = ProductInterpolator(directions, np.arange(len(directions)))
        except KeyError as error:
            raise ValueError(f"directions hold a pair off the 81-direction grid: {error}") from None
        if len(self._interpolator.lights) != 81 or len(self._interpolator.views) != 81:
            raise ValueError("directions must hold all 81 x 81 light and view grid directions")

    def _gather(self, texels: np.ndarray, columns: np.ndarray) -> np.ndarray:
        """Stored RGB of texel ``texels[i]`` at direction pair ``columns[i]``: (n, 3)."""
        return np.asarray(self.values[texels, columns], dtype=np.float32)

    def _evaluate(self, texels, directions):
        out = np.empty((len(texels), 3), dtype=np.float32)
        for start in range(0, len(texels), _MEASURED_CHUNK):
            stop = start + _MEASURED_CHUNK
            out[start:stop] = self._interpolate(texels[start:stop], directions[start:stop])
        return out

    def _interpolate(self, texels: np.ndarray, directions: np.ndarray) -> np.ndarray:
        interp = self._interpolator
        # The exhaustive search is much faster than scipy's walk for queries scattered
        # over the hemisphere, as a render's are.
        light_ids, light_w = interp.light_weights(
            clamp_to_grid(directions[:, :2]), bruteforce=True, snap=_SNAP
        )
        view_ids, view_w = interp.view_weights(
            clamp_to_grid(directions[:, 2:]), bruteforce=True, snap=_SNAP
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
    matrix is never formed).

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

    Notes
    -----
    A PCA value may be slightly negative; the renderer clamps radiance at 0.
    """

    def __init__(self, mean, basis, coefficients, crop_size, scale: float,
                 directions: np.ndarray | None = None):
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


_OUTER_THETA, _OUTER_COUNT = np.radians(RINGS_DEGREES[-1][0]), RINGS_DEGREES[-1][1]
# A direction this far (radians) outside the grid's polygon counts as beyond it: grid
# directions on the 75-degree ring itself are inside, whatever their rounding.
_BEYOND_TOLERANCE = 1e-9


def _edge_theta(phi: np.ndarray, shrink: float = 1.0) -> np.ndarray:
    """Theta of the grid's outer polygon at azimuth ``phi`` (its radius times ``shrink``).

    The 24 directions of the 75-degree ring span, in stereographic coordinates (radius
    tan(theta / 2)), a regular polygon; outside it the triangulation has no triangle.
    """
    step = 2.0 * np.pi / _OUTER_COUNT
    offset = np.mod(phi, step) - step / 2.0  # azimuth from the middle of the polygon's edge
    edge_radius = np.tan(_OUTER_THETA / 2.0) * np.cos(step / 2.0) / np.cos(offset)
    return 2.0 * np.arctan(edge_radius * shrink)


def beyond_grid(angles: np.ndarray) -> np.ndarray:
    """Whether each direction lies beyond the measured grid's outer polygon.

    Parameters
    ----------
    angles : ndarray of shape (n, 2), (theta, phi) in radians.

    Returns
    -------
    ndarray of shape (n,), bool: True where :func:`clamp_to_grid` moves the direction (by
    more than a rounding error), i.e. where no measured value surrounds it.

    Examples
    --------
    >>> beyond_grid(np.radians([[75.0, 0.0], [75.0, 7.5], [74.0, 7.5], [80.0, 30.0]]))
    array([False,  True, False,  True])
    """
    angles = np.asarray(angles, dtype=np.float64)
    return angles[:, 0] > _edge_theta(angles[:, 1]) + _BEYOND_TOLERANCE


def clamp_to_grid(angles: np.ndarray) -> np.ndarray:
    """Lower theta onto the grid's outer polygon where a direction lies beyond it.

    Parameters
    ----------
    angles : ndarray of shape (n, 2), (theta, phi) in radians.

    Returns
    -------
    ndarray of shape (n, 2): theta clamped to the polygon (slightly inside it), phi kept.
    """
    theta, phi = angles[:, 0], angles[:, 1]
    theta_max = _edge_theta(phi, shrink=1.0 - 1e-9)
    return np.column_stack([np.where(theta > theta_max, theta_max, theta), phi])
