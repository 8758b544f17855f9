"""Procedural fabric BTFs with an analytic ground truth, and a writer in real layouts.

A :class:`SyntheticBTF` renders one of the fabric presets of
:mod:`pipeline.btf.materials` seen from above (``material=``): ``plain_weave`` (the
default: a red-and-beige plain weave), ``knit`` (jersey: columns of V-shaped loops of
fuzzy wool), ``corduroy`` (dark cut-pile ridges with deep valleys) and ``satin`` (a
printed 5-harness satin with long glossy floats). The preset gives per texel:

- which yarn is visible (its label: :attr:`SyntheticBTF.material_labels`, named by
  :attr:`SyntheticBTF.label_names`), its albedo and a height field;
- the in-plane direction of the visible fibre.

From these the renderer derives, the same way for every preset, normals (from the
height), a *depth* (0 on the highest crest, 1 at the lowest floor), a tangent along the
fibre twisted by the yarn's twist angle about the normal, and an Ashikhmin–Shirley
anisotropic specular lobe aligned with that tangent.

Image value for light l and view v (both unit vectors, z = macro normal)::

    exposure · max(n·l, 0) · S(l) · M(v) · (albedo / π + k_s · AS(l, v))

with smooth self-shadowing ``S(l) = exp(-k · depth · tan θ_l · a(φ_l))``: deep texels
darken at grazing light, and ``a`` grows for light crossing the fibre's channel rather
than running along it; the same masking ``M(v)``, times a fade where the local surface
turns from the view. Values are clipped to [0, 1]; each preset's exposure keeps all but
the brightest highlights below 1.

Directions: θ from the macro normal, φ from +x (image columns, to the right) toward +y
(image rows, downward). The model accepts any direction, not only grid ones; directions
below the horizon give 0.

Written datasets (:func:`write_synthetic_btf`) sample light and view on a direction set
(:func:`synthetic_directions`): the UBO2003 81-grid (the default; the UBO2003 and UTIA
layouts hold no other), or a Fibonacci spiral of ``n_lights`` lights times one of
``n_views`` views, written as a UBO2014 ``.btf`` file that stores the values losslessly
(float32 factors of full rank, read back exactly by :mod:`pipeline.data.ubo2014`).
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from os import PathLike
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from pipeline.btf.materials import Material, get_material
from pipeline.core.errors import ConfigError, DataError
from pipeline.data.brdf_models import ashikhmin_shirley_lobe, ashikhmin_shirley_normalization
from pipeline.data.btf import encode_btf_image
from pipeline.data.directions import (
    N_DIRECTIONS,
    canonical_views,
    direction_index,
    fibonacci_hemisphere,
    grid_81,
    grid_81_degrees,
    product_directions,
    ubo2003_file_name,
    unit_vectors,
    utia_file_name,
    view_folder_name,
)
from pipeline.data.images import srgb_oetf

if TYPE_CHECKING:
    from matplotlib.figure import Figure

# Shadowing features of a direction: tan θ · (1, |sin(φ - β)| for each channel azimuth β).
# Light that crosses a channel running at β is shadowed by its walls, light along it is
# not. 0° and 90° (the plain weave's threads) come first; the diagonals serve fibres at
# other angles, whose weight is shared between the two nearest channels.
_CHANNEL_DEGREES = np.array([0.0, 90.0, 30.0, 60.0, 120.0, 150.0])
_CHANNEL_STEP = 30.0
_GEOMETRY_STREAM = 1  # the geometry's noise comes from default_rng([seed, 1])
_GENERATOR_VERSION = 1
_MARKER_NAME = "synthetic_btf.json"
UBO2014_FILE_NAME = "synthetic.btf"  # inside the dataset folder, beside the marker

# The direction sets of a written dataset (dataset.synthetic.directions), and how far from
# the normal a Fibonacci set reaches (about UBO2014's reach; below 90 degrees, where the
# shading of every texel fades out).
DIRECTION_SETS = ("ubo2003", "fibonacci")
FIBONACCI_MAX_THETA_DEGREES = 80.0
# The direction-set settings at their defaults. They came after datasets and cache entries
# existed: at these values they are left out of the dataset's folder name, its marker and
# the cache keys (generator_settings), so that those stay in use.
DEFAULT_DIRECTIONS = {"directions": "ubo2003", "n_lights": None, "n_views": None}


def generator_settings(gen: dict) -> dict:
    """``dataset.synthetic`` settings as folder names, markers and cache keys hold them:
    without the direction-set settings when those are all at their defaults
    (:data:`DEFAULT_DIRECTIONS`)."""
    if all(gen.get(key) == value for key, value in DEFAULT_DIRECTIONS.items()):
        return {key: value for key, value in gen.items() if key not in DEFAULT_DIRECTIONS}
    return dict(gen)


def synthetic_directions(
    directions: str = "ubo2003", n_lights: int | None = None, n_views: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The light and the view set of a written built-in BTF.

    Parameters
    ----------
    directions : {"ubo2003", "fibonacci"}
        ``ubo2003``: the 81-grid for both (``n_lights`` and ``n_views`` must be None);
        ``fibonacci``: :func:`pipeline.data.directions.fibonacci_hemisphere` spirals of
        ``n_lights`` and ``n_views`` directions up to
        :data:`FIBONACCI_MAX_THETA_DEGREES`.
    n_lights, n_views : int or None

    Returns
    -------
    lights : ndarray of shape (L, 2); views : ndarray of shape (V, 2)
        (θ, φ) radians.

    Raises
    ------
    ConfigError
        For an unknown set, or counts that do not go with it.
    """
    if directions not in DIRECTION_SETS:
        raise ConfigError(
            f"dataset.synthetic.directions={directions!r} is not one of {list(DIRECTION_SETS)}"
        )
    counts = {"n_lights": n_lights, "n_views": n_views}
    if directions == "ubo2003":
        given = [name for name, count in counts.items() if count is not None]
        if given:
            raise ConfigError(
                f"dataset.synthetic.{given[0]}={counts[given[0]]!r} goes with "
                f"directions=fibonacci only; directions=ubo2003 is the 81-grid (set it null)"
            )
        return grid_81(), grid_81()
    for name, count in counts.items():
        if count is None:
            raise ConfigError(f"dataset.synthetic.directions=fibonacci needs "
                              f"dataset.synthetic.{name} (an integer >= 3)")
    return (fibonacci_hemisphere(n_lights, FIBONACCI_MAX_THETA_DEGREES),
            fibonacci_hemisphere(n_views, FIBONACCI_MAX_THETA_DEGREES))


@dataclass(frozen=True)
class SyntheticBTF:
    """Procedural fabric, evaluable at any light and view direction.

    Parameters
    ----------
    size : int
        Texture is ``size × size`` texels.
    seed : int
        Seeds the per-thread colours, the fine noise and any random part of the geometry.
    material : str
        A preset of :data:`pipeline.btf.materials.MATERIALS`: ``"plain_weave"``,
        ``"knit"``, ``"corduroy"`` or ``"satin"``.
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

    # --- per-texel geometry and material (computed once, cached) -------------------------

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
        bitangent = np.cross(normal, tangent)

        depth = (height.max() - height) / max(np.ptp(height), 1e-12)
        return {
            "surface": surface,
            "normal": normal,
            "tangent": tangent,
            "bitangent": bitangent,
            "depth": depth,
        }

    @cached_property
    def albedo(self) -> np.ndarray:
        """Diffuse albedo per texel, ndarray of shape (size, size, 3), float32 in [0, 1]."""
        rng = np.random.default_rng(self.seed)
        albedo = self.preset.albedo(self._geometry["surface"], self.n_threads, rng)
        return np.clip(albedo, 0.0, 1.0).astype(np.float32)

    @property
    def material_labels(self) -> np.ndarray:
        """Visible yarn per texel, ndarray (size, size), int; for plain_weave 0 warp,
        1 weft, 2 gap; for every preset, label i is named ``label_names[i]``."""
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

    # --- evaluation ---------------------------------------------------------------------

    def evaluate(self, directions: np.ndarray) -> np.ndarray:
        """Image values at arbitrary light/view directions.

        Parameters
        ----------
        directions : array_like of shape (n, 4)
            (θ_light, φ_light, θ_view, φ_view) in radians; any values, not only grid ones.

        Returns
        -------
        ndarray of shape (n, size, size, 3), float32
            Linear RGB in [0, 1].
        """
        directions = np.asarray(directions, dtype=np.float64)
        if directions.ndim != 2 or directions.shape[1] != 4:
            raise ConfigError(f"directions must have shape (n, 4), got {directions.shape}")
        if not np.isfinite(directions).all():
            raise ConfigError("directions hold NaN or Inf values")
        size = self.size
        out = np.empty((len(directions), size, size, 3), dtype=np.float32)
        flat_out = out.reshape(len(directions), size * size, 3)
        # Bound the temporaries to a few tens of MB whatever n and size are.
        chunk = max(1, 2**20 // (size * size))
        for start in range(0, len(directions), chunk):
            flat_out[start : start + chunk] = self._evaluate_chunk(
                directions[start : start + chunk]
            )
        return out

    @cached_property
    def _flat_maps(self) -> dict[str, np.ndarray]:
        geometry, yarns = self._geometry, self.preset.yarns
        surface = geometry["surface"]
        labels = surface.labels.ravel()

        def per_texel(field):  # a Yarn field, looked up by each texel's label
            return np.array([getattr(yarn, field) for yarn in yarns])[labels]

        flat = {
            name: geometry[name].reshape(-1, 3).T.astype(np.float32)  # (3, P) for matmul
            for name in ("normal", "tangent", "bitangent")
        }
        # Occlusion exponent = features(direction) @ occlusion_weights (see
        # _CHANNEL_DEGREES): deep texels shadow more, and the walls of a fibre's channel
        # shadow light coming across the fibre more than light along it.
        weights = np.zeros((1 + len(_CHANNEL_DEGREES), labels.size))
        weights[0] = per_texel("shadow")
        weights[1:] = channel_weights(surface.fibre.reshape(-1, 2), per_texel("shadow_across"))
        flat["occlusion_weights"] = (
            self.preset.shadow_strength * geometry["depth"].ravel() * weights
        ).astype(np.float32)
        flat["albedo_over_pi"] = (self.albedo.reshape(-1, 3) / np.pi).astype(np.float32)
        along = per_texel("exponent_along")
        across = per_texel("exponent_across")
        flat["exponent_along"] = along.astype(np.float32)
        flat["exponent_across"] = across.astype(np.float32)
        # Ashikhmin–Shirley normalization times the yarn's specular weight.
        flat["specular_scale"] = (
            per_texel("specular") * ashikhmin_shirley_normalization(along, across)
        ).astype(np.float32)
        return flat

    def evaluate_pairs(self, texels: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Values of single texels, each at its own directions (what a renderer asks for).

        Parameters
        ----------
        texels : array_like of shape (n,), flat texel indices (row * size + col).
        directions : array_like of shape (n, 4), (θ_light, φ_light, θ_view, φ_view) in
            radians.

        Returns
        -------
        ndarray of shape (n, 3), float32: ``evaluate(directions)[i, row_i, col_i]``.
        """
        texels = np.asarray(texels, dtype=np.int64)
        directions = np.asarray(directions, dtype=np.float64)
        if directions.shape != (len(texels), 4):
            raise ConfigError(f"directions must have shape ({len(texels)}, 4), got "
                              f"{directions.shape}")
        if texels.size and (texels.min() < 0 or texels.max() >= self.size**2):
            raise ConfigError(f"texel indices must lie in [0, {self.size**2})")
        maps = {name: values[texels] if name == "albedo_over_pi" else values[..., texels]
                for name, values in self._flat_maps.items()}
        return self._shade(directions, maps, pairs=True)

    def _evaluate_chunk(self, directions: np.ndarray) -> np.ndarray:
        """(c, 4) directions to (c, P, 3) float32 values, P = size²."""
        return self._shade(directions, self._flat_maps, pairs=False)

    def _shade(self, directions: np.ndarray, maps: dict, pairs: bool) -> np.ndarray:
        """The shading of texels ``maps`` (texel axis last; ``albedo_over_pi`` first) at
        ``directions`` (c, 4): every direction at every texel, (c, P, 3), or with
        ``pairs`` the i-th direction at the i-th texel, (c, 3)."""
        def per_direction(values):  # (c,) -> broadcast against the texel axis
            return values if pairs else values[:, None]

        def dot(vectors, frames):  # (c, 3) with (3, P): (c, P), or (3, c) pairwise: (c,)
            return np.sum(vectors.T * frames, axis=0) if pairs else vectors @ frames

        theta_light = np.clip(directions[:, 0], 0.0, np.pi)
        theta_view = np.clip(directions[:, 2], 0.0, np.pi)
        light = unit_vectors(theta_light, directions[:, 1]).astype(np.float32)
        view = unit_vectors(theta_view, directions[:, 3]).astype(np.float32)
        halfway = light + view
        halfway /= np.maximum(np.linalg.norm(halfway, axis=1, keepdims=True), 1e-12)
        light_dot_half = per_direction(np.clip(np.sum(light * halfway, axis=1), 1e-4, 1.0))

        n_dot_l = dot(light, maps["normal"])  # (c, P), or (c,) for pairs
        n_dot_v = dot(view, maps["normal"])
        n_dot_h = dot(halfway, maps["normal"])
        t_dot_h = dot(halfway, maps["tangent"])
        b_dot_h = dot(halfway, maps["bitangent"])

        # The fibre tangent is the lobe's n_u axis; the normalization is in specular_scale.
        lobe = ashikhmin_shirley_lobe(
            n_dot_h, t_dot_h, b_dot_h, maps["exponent_along"], maps["exponent_across"]
        )
        fresnel_at_normal = self.preset.fresnel_at_normal
        fresnel = fresnel_at_normal + (1 - fresnel_at_normal) * (1 - light_dot_half) ** 5
        # The 0.1 floor keeps the lobe finite where a texel turns edge-on to both.
        specular = (
            maps["specular_scale"]
            * lobe
            * fresnel
            / (light_dot_half * np.maximum(np.maximum(n_dot_l, n_dot_v), 0.1))
        )

        def occlusion_features(theta, phi):  # (c,) -> (c, 1 + channels)
            tan_theta = np.tan(np.minimum(theta, np.deg2rad(89.0)))
            across = np.abs(np.sin(phi[:, None] - np.deg2rad(_CHANNEL_DEGREES)))
            return tan_theta[:, None] * np.concatenate([np.ones_like(phi)[:, None], across], 1)

        # Shadowing (light) times masking (view): exp(-a_l) exp(-a_v) = exp(-(a_l + a_v)).
        features = occlusion_features(theta_light, directions[:, 1]) + occlusion_features(
            theta_view, directions[:, 3]
        )
        occlusion = np.exp(-dot(features.astype(np.float32), maps["occlusion_weights"]))
        # Fade texels whose local surface turns away from the viewer (seen at a graze).
        facing = np.clip(n_dot_v / 0.2, 0.0, 1.0)
        facing = facing * facing * (3 - 2 * facing)
        above = per_direction((np.cos(theta_light) > 0) & (np.cos(theta_view) > 0))
        exposure = self.preset.exposure
        weight = np.where(above, exposure * np.maximum(n_dot_l, 0) * occlusion * facing, 0.0)
        values = weight[..., None] * (maps["albedo_over_pi"] + specular[..., None])
        return np.clip(values, 0.0, 1.0).astype(np.float32)


def channel_weights(fibre: np.ndarray, across: np.ndarray) -> np.ndarray:
    """Weights of the channel features for fibres at any azimuth.

    Parameters
    ----------
    fibre : ndarray of shape (P, 2)
        In-plane fibre directions (x, y), any length but zero.
    across : ndarray of shape (P,)
        How strongly each texel shadows light crossing its fibre.

    Returns
    -------
    ndarray of shape (len(_CHANNEL_DEGREES), P)
        ``across`` shared between the two channels nearest the fibre's azimuth, linearly
        in angle; all of it on one channel when the fibre runs along one.
    """
    azimuth = np.mod(np.degrees(np.arctan2(fibre[:, 1], fibre[:, 0])), 180.0)
    position = azimuth / _CHANNEL_STEP
    lower = np.floor(position)
    share = position - lower
    # The channels in order of azimuth (0°, 30°, …, 150°), as rows of the weights.
    row_of_step = np.argsort(np.round(_CHANNEL_DEGREES / _CHANNEL_STEP))
    below = row_of_step[lower.astype(int) % len(row_of_step)]
    above = row_of_step[(lower.astype(int) + 1) % len(row_of_step)]
    weights = np.zeros((len(_CHANNEL_DEGREES), len(across)))
    texels = np.arange(len(across))
    weights[below, texels] += across * (1 - share)
    weights[above, texels] += across * share
    return weights


def material_sheet(materials: Sequence[str], size: int = 64, seed: int = 0) -> Figure:
    """A figure of each material (rows) under three lights, viewed from overhead.

    Columns: light overhead, grazing (75°, the grid's lowest) from +x, grazing from +y;
    linear values are sRGB-encoded for display.

    Parameters
    ----------
    materials : sequence of str
        Preset names (:data:`pipeline.btf.materials.MATERIALS`).
    size, seed : int
        Passed to :class:`SyntheticBTF`.

    Returns
    -------
    matplotlib.figure.Figure
    """
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


# --- writer in the real layouts ----------------------------------------------------------

_WRITABLE = {"ubo2003": ("jpg", "png", "exr"), "utia": ("png", "exr"), "ubo2014": ("btf",)}


def _read_marker(root: Path) -> dict | None:
    try:
        marker = json.loads((root / _MARKER_NAME).read_text())
    except (OSError, ValueError):
        return None
    # Markers written before there were presets describe the same plain weave.
    if isinstance(marker, dict):
        marker.setdefault("material", "plain_weave")
    return marker


def write_synthetic_btf(
    root: str | PathLike,
    size: int = 64,
    seed: int = 0,
    format: str = "ubo2003",
    ext: str = "jpg",
    views=None,
    quality: int = 95,
    material: str = "plain_weave",
    directions: str = "ubo2003",
    n_lights: int | None = None,
    n_views: int | None = None,
) -> Path:
    """Write :class:`SyntheticBTF` images as a dataset in the UBO2003, UTIA or UBO2014 layout.

    The dataset is written into a hidden temporary sibling folder, one view at a time
    (memory stays at one view's 81 images), then renamed to ``root``; a killed run thus
    never leaves a half dataset under ``root``. A ``synthetic_btf.json`` marker in
    ``root`` records the parameters; when ``root`` already holds a dataset written with
    the same parameters, nothing is rewritten.

    UBO2003 running numbers are each image's index in the full view-major 6561-image
    order (``view_index * 81 + light_index``), so a written subset of views carries the
    same names as the full dataset's folders.

    The UBO2014 layout holds any direction set (:func:`synthetic_directions`): one file,
    ``root / UBO2014_FILE_NAME``, with every light under every view, the angles stored as
    float32 (the images are rendered at exactly those), colour model 0 (linear RGB), the
    incident cosine in the data, and float32 factors of full rank: one of U and SV is the
    identity, so that :mod:`pipeline.data.ubo2014` decodes every value exactly.

    Parameters
    ----------
    root : path-like
        Dataset folder to create.
    size, seed : int
        Passed to :class:`SyntheticBTF`.
    material : str
        The fabric preset, passed to :class:`SyntheticBTF` and recorded in the marker.
    format : {"ubo2003", "utia", "ubo2014"}
    ext : str
        ``ubo2003``: ``"jpg"`` (gamma 2.2, JPEG ``quality``), ``"png"`` (gamma 2.2, 8-bit)
        or ``"exr"`` (half linear RGB). ``utia``: ``"png"`` (8-bit sRGB) or ``"exr"``
        (half XYZ). ``ubo2014``: ``"btf"``.
    views : sequence of (θ_view, φ_view) in degrees, or None
        Write only these view folders; None writes all 81. The UBO2014 layout writes every
        view of its set (None only): its reader picks views.
    quality : int
        JPEG quality, 1..100.
    directions, n_lights, n_views
        The direction set (:func:`synthetic_directions`); other than the default
        ``ubo2003`` only in the ``ubo2014`` layout.

    Returns
    -------
    Path
        ``root``; for the UBO2014 layout the file ``root / UBO2014_FILE_NAME``.

    Raises
    ------
    ConfigError
        For an unknown format/extension pair or material, an off-grid view, a direction
        set the layout cannot hold, views given to the UBO2014 layout, or a bad quality.
    DataError
        If ``root`` exists, is not an empty folder, and is not this generator's output
        with these parameters.
    """
    if format not in _WRITABLE:
        raise ConfigError(f"format {format!r} is not one of {sorted(_WRITABLE)}")
    if ext not in _WRITABLE[format]:
        raise ConfigError(f"ext {ext!r} is not one of {_WRITABLE[format]} for format {format!r}")
    if not 1 <= int(quality) <= 100:
        raise ConfigError(f"JPEG quality={quality!r} must be in 1..100")
    fabric = SyntheticBTF(size=size, seed=seed, material=material)
    light_set, view_set = synthetic_directions(directions, n_lights, n_views)
    if format != "ubo2014" and directions != "ubo2003":
        raise ConfigError(
            f"dataset.synthetic.directions={directions!r} cannot be written in the {format} "
            f"layout, whose file names hold the 81-grid only: write it as UBO2014 "
            f"(dataset.format=ubo2014 dataset.synthetic.ext=btf)"
        )
    if format == "ubo2014" and views is not None:
        raise ConfigError(
            f"views={views!r}: the UBO2014 layout writes every view of the set; choose views "
            f"when reading it (dataset.views)"
        )
    view_list = canonical_views(views) if format != "ubo2014" else None
    root = Path(root)
    marker = {
        "generator": "pipeline.btf.synthetic.SyntheticBTF",
        "version": _GENERATOR_VERSION,
        "size": fabric.size,
        "seed": int(seed),
        "material": fabric.material,
        "n_threads": fabric.n_threads,
        "format": format,
        "ext": ext,
        "views": None if view_list is None else [list(view) for view in view_list],
        "quality": int(quality),
        # Only when not the default: markers written before the setting existed match.
        **generator_settings({"directions": directions, "n_lights": n_lights,
                              "n_views": n_views}),
    }
    written = root / UBO2014_FILE_NAME if format == "ubo2014" else root
    if root.exists() and not (root.is_dir() and not any(root.iterdir())):
        if _read_marker(root) == marker:
            return written
        raise DataError(
            f"{root} exists but is not a synthetic BTF written with {marker}; "
            f"remove it or choose another root"
        )
    root.parent.mkdir(parents=True, exist_ok=True)
    partial = root.parent / f".{root.name}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    partial.mkdir()
    try:
        if format == "ubo2014":
            _write_ubo2014(partial / UBO2014_FILE_NAME, fabric, light_set, view_set)
        else:
            _write_view_folders(partial, fabric, view_list, format, ext, quality, root.name)
        os.sync()  # every image on disk before the marker and the rename publish them
        # The marker goes in last: its presence means every image before it was written.
        (partial / _MARKER_NAME).write_text(json.dumps(marker, indent=1))
        try:
            partial.rename(root)
        except OSError:
            # Another process finished the same dataset first; keep theirs if it matches.
            if _read_marker(root) != marker:
                raise
            shutil.rmtree(partial, ignore_errors=True)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return written


def _write_view_folders(partial: Path, fabric: SyntheticBTF, view_list, format: str, ext: str,
                        quality: int, name: str) -> None:
    """The 81 lights of each view of ``view_list`` (degrees) as images in the UBO2003 or
    UTIA layout, one view folder at a time, under ``partial``."""
    lights = grid_81_degrees()
    light_radians = np.deg2rad(lights.astype(np.float64))
    show_bar = sys.stderr.isatty()
    for view in tqdm(view_list, desc=f"write {name}", leave=False, disable=not show_bar):
        view_index = direction_index(*view)
        folder = partial / view_folder_name(*view)
        folder.mkdir()
        view_radians = np.broadcast_to(
            np.deg2rad(np.array(view, dtype=np.float64)), (N_DIRECTIONS, 2)
        )
        images = fabric.evaluate(np.concatenate([light_radians, view_radians], axis=1))
        for light_index, (theta_light, phi_light) in enumerate(lights):
            if format == "ubo2003":
                number = view_index * N_DIRECTIONS + light_index
                file_name = ubo2003_file_name(number, theta_light, phi_light, *view, ext)
            else:
                file_name = utia_file_name(theta_light, phi_light, *view, ext)
            # Not synced one by one: one os.sync covers the whole folder.
            encode_btf_image(folder / file_name, images[light_index], format, quality,
                             sync=False)


def _write_ubo2014(path: Path, fabric: SyntheticBTF, lights: np.ndarray, views: np.ndarray):
    """The fabric at every light (L, 2) under every view (V, 2), as a lossless DFMF file."""
    from pipeline.data.ubo2014_write import write_dfmf

    # The file stores float32 angles: render at exactly those, so data and truth agree.
    lights, views = lights.astype(np.float32), views.astype(np.float32)
    images = fabric.evaluate(product_directions(lights, views))  # (N, size, size, 3)
    n, texels = len(images), fabric.size**2
    # The file's texel order: column y · width + x with y from the bottom (image row r is
    # the file's row size - 1 - r), as pipeline.data.ubo2014_write.encode_values lays out.
    matrices = images[:, ::-1].reshape(n, texels, 3)
    factors = []
    for channel in range(3):
        matrix = np.ascontiguousarray(matrices[..., channel])  # (N, texels)
        # Full rank K = min(N, texels) with one factor the identity: U · SVᵀ is the data,
        # each value a sum of one product by 1 and exact zeros.
        if n <= texels:
            u, sv = np.eye(n, dtype=np.float32), np.ascontiguousarray(matrix.T)
        else:
            u, sv = matrix, np.eye(texels, dtype=np.float32)
        factors.append((np.ones(len(u.T), dtype=np.float32), u, sv))
    write_dfmf(path, views, lights, fabric.size, fabric.size, factors=factors,
               color_model=0, dtype="float32", cosine_in_data=True, sync=False)
