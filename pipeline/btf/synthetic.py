"""Procedural fabric BTFs with an analytic ground truth.

A :class:`SyntheticBTF` renders one of the fabric presets of :mod:`pipeline.btf.materials`
seen from above. From the preset's labels, albedo, height field and fibre directions it
derives, the same way for every preset, normals (from the height), a *depth* (0 on the
highest crest, 1 at the lowest floor), and a tangent along the fibre twisted by the yarn's
twist angle about the normal; :mod:`pipeline.btf.synthetic_shading` shades them. Each
preset's exposure keeps all but the brightest highlights below 1.

Directions: θ from the macro normal, φ from +x (image columns, to the right) toward +y
(image rows, downward). The model accepts any direction, not only grid ones; directions
below the horizon give 0. Datasets on disk are written by
:mod:`pipeline.btf.synthetic_dataset`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from pipeline.btf.materials import Material, get_material
from pipeline.btf.synthetic_shading import shade, texel_maps
from pipeline.core.errors import ConfigError
from pipeline.data.images import srgb_oetf

if TYPE_CHECKING:
    from matplotlib.figure import Figure

_GEOMETRY_STREAM = 1  # the geometry's noise comes from default_rng([seed, 1])


@dataclass(frozen=True)
class SyntheticBTF:
    """Procedural fabric, evaluable at any light and view direction.

    Parameters
    ----------
    size : int, the texture is ``size × size`` texels.
    seed : int, seeds the per-thread colours, the fine noise and any random geometry.
    material : str, a preset of :data:`pipeline.btf.materials.MATERIALS`.
    n_threads : int or None
        Repeats across the texture (threads, or wales for knit and corduroy); None takes
        the preset's own. plain_weave needs an even number, satin a multiple of 5.

    Examples
    --------
    >>> fabric = SyntheticBTF(size=16, seed=0)
    >>> fabric.evaluate(np.array([[0.3, 1.0, 0.2, 4.0]])).shape
    (1, 16, 16, 3)
    >>> SyntheticBTF(size=16, material="knit").label_names
    ('left leg', 'right leg', 'gap')
    """

    size: int = 64
    seed: int = 0
    material: str = "plain_weave"
    n_threads: int | None = None

    def __post_init__(self):
        if not isinstance(self.size, int | np.integer) or self.size < 2:
            raise ConfigError(f"synthetic BTF size={self.size!r} must be an integer >= 2")
        preset = get_material(self.material)
        if self.n_threads is None:
            object.__setattr__(self, "n_threads", preset.n_threads)
        preset.check_threads(self.n_threads)

    @property
    def preset(self) -> Material:
        """The material's constants and geometry (:mod:`pipeline.btf.materials`)."""
        return get_material(self.material)

    @cached_property
    def _geometry(self) -> dict:
        rng = np.random.default_rng([self.seed, _GEOMETRY_STREAM])
        surface = self.preset.surface(self.size, self.n_threads, rng)
        labels, height = surface.labels, surface.height
        slope_x = (np.roll(height, -1, axis=1) - np.roll(height, 1, axis=1)) / 2.0
        slope_y = (np.roll(height, -1, axis=0) - np.roll(height, 1, axis=0)) / 2.0
        normal = np.stack([-slope_x, -slope_y, np.ones_like(height)], axis=-1)
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)

        # Tangent: along the fibre, projected into the tangent plane, then twisted.
        along = np.zeros_like(normal)
        along[..., :2] = surface.fibre
        tangent = along - np.sum(along * normal, axis=-1, keepdims=True) * normal
        tangent /= np.linalg.norm(tangent, axis=-1, keepdims=True)
        twist_degrees = np.array([yarn.twist_degrees for yarn in self.preset.yarns])
        twist = np.deg2rad(twist_degrees[labels])[..., None]
        tangent = tangent * np.cos(twist) + np.cross(normal, tangent) * np.sin(twist)
        depth = (height.max() - height) / max(np.ptp(height), 1e-12)
        bitangent = np.cross(normal, tangent)
        frame = {"normal": normal, "tangent": tangent, "bitangent": bitangent}
        return {"surface": surface, **frame, "depth": depth}

    @cached_property
    def albedo(self) -> np.ndarray:
        """Diffuse albedo per texel, ndarray of shape (size, size, 3), float32 in [0, 1]."""
        rng = np.random.default_rng(self.seed)
        albedo = self.preset.albedo(self._geometry["surface"], self.n_threads, rng)
        return np.clip(albedo, 0.0, 1.0).astype(np.float32)

    @property
    def material_labels(self) -> np.ndarray:
        """Visible yarn per texel, ndarray (size, size), int, named by ``label_names``."""
        return self._geometry["surface"].labels

    @property
    def label_names(self) -> tuple[str, ...]:
        """Name of each label of :attr:`material_labels`, in label order."""
        return self.preset.label_names

    @property
    def height(self) -> np.ndarray:
        """Height field in texel units, ndarray of shape (size, size), float64."""
        return self._geometry["surface"].height

    @property
    def normals(self) -> np.ndarray:
        """Unit normals per texel, ndarray of shape (size, size, 3), float64."""
        return self._geometry["normal"]

    @property
    def tangents(self) -> np.ndarray:
        """Unit fibre tangents per texel (twisted), ndarray (size, size, 3), float64."""
        return self._geometry["tangent"]

    def evaluate(self, directions: np.ndarray) -> np.ndarray:
        """Image values, ndarray of shape (n, size, size, 3), float32, linear RGB in [0, 1],
        at ``directions`` (n, 4): (θ_light, φ_light, θ_view, φ_view) in radians, any values,
        not only grid ones."""
        directions = np.asarray(directions, dtype=np.float64)
        if directions.ndim != 2 or directions.shape[1] != 4:
            raise ConfigError(f"directions must have shape (n, 4), got {directions.shape}")
        if not np.isfinite(directions).all():
            raise ConfigError("directions hold NaN or Inf values")
        size = self.size
        out = np.empty((len(directions), size, size, 3), dtype=np.float32)
        flat = out.reshape(len(directions), size * size, 3)
        # Bound the temporaries to a few tens of MB whatever n and size are.
        chunk = max(1, 2**20 // (size * size))
        for start in range(0, len(directions), chunk):
            block = directions[start : start + chunk]
            flat[start : start + chunk] = shade(block, self._flat_maps, self.preset, pairs=False)
        return out

    @cached_property
    def _flat_maps(self) -> dict[str, np.ndarray]:
        """The shading's per-texel parameters, texels flattened
        (:func:`pipeline.btf.synthetic_shading.texel_maps`)."""
        return texel_maps(self.preset, **self._geometry, albedo=self.albedo)

    def evaluate_pairs(self, texels: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Values of single texels, each at its own directions (what a renderer asks for):
        ``texels`` (n,), flat indices (row * size + col), at ``directions`` (n, 4),
        (θ_light, φ_light, θ_view, φ_view) in radians -> ndarray of shape (n, 3), float32:
        ``evaluate(directions)[i, row_i, col_i]``."""
        texels = np.asarray(texels, dtype=np.int64)
        directions = np.asarray(directions, dtype=np.float64)
        if directions.shape != (len(texels), 4):
            raise ConfigError(
                f"directions must have shape ({len(texels)}, 4), got {directions.shape}"
            )
        if texels.size and (texels.min() < 0 or texels.max() >= self.size**2):
            raise ConfigError(f"texel indices must lie in [0, {self.size**2})")
        maps = {
            name: values[texels] if name == "albedo_over_pi" else values[..., texels]
            for name, values in self._flat_maps.items()
        }
        return shade(directions, maps, self.preset, pairs=True)


def material_sheet(materials: Sequence[str], size: int = 64, seed: int = 0) -> Figure:
    """A matplotlib figure of each of the presets ``materials`` (rows; ``size`` and ``seed``
    passed to :class:`SyntheticBTF`) under three lights, viewed from overhead. Columns:
    light overhead, grazing (75°, the grid's lowest) from +x, grazing from +y; linear values
    are sRGB-encoded for display."""
    from matplotlib.figure import Figure  # only this function draws

    if not materials:
        raise ConfigError("material_sheet needs at least one material")
    lights = [(0.0, 0.0, "light overhead"), (75.0, 0.0, "light from +x, 75°"),
              (75.0, 90.0, "light from +y, 75°")]  # fmt: skip
    directions = np.deg2rad([[theta, phi, 0.0, 0.0] for theta, phi, _ in lights])
    fig = Figure(figsize=(2.4 * len(lights), 2.5 * len(materials)), constrained_layout=True)
    axes = fig.subplots(len(materials), len(lights), squeeze=False)
    for row, name in zip(axes, materials, strict=True):
        images = SyntheticBTF(size=size, seed=seed, material=name).evaluate(directions)
        for ax, image in zip(row, images, strict=True):
            ax.imshow(srgb_oetf(image), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
        row[0].set_ylabel(name)
    for ax, (_, _, title) in zip(axes[0], lights, strict=True):
        ax.set_title(title, fontsize=9)
    return fig
