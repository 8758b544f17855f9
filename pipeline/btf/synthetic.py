"""A procedural woven-fabric BTF with an analytic ground truth, and a writer in real layouts.

The material is a plain weave seen from above. Warp threads run along the image rows'
direction (+y, down the image), weft threads along +x (across); at each crossing the
thread on top alternates. Per texel the model knows:

- a height field (threads as flattened cylinders arching over and under each other, a
  dark floor in the gaps), from which come normals and a *depth* (0 on the highest crest,
  1 at the lowest floor);
- which yarn is visible (warp, weft or gap: :attr:`SyntheticBTF.material_labels`), its
  albedo (two yarn colours, per-thread variation, fine noise), and its tangent (along the
  thread, twisted by the yarn's twist angle about the normal);
- an Ashikhmin–Shirley anisotropic specular lobe aligned with that tangent.

Image value for light l and view v (both unit vectors, z = macro normal)::

    exposure · max(n·l, 0) · S(l) · M(v) · (albedo / π + k_s · AS(l, v))

with smooth self-shadowing ``S(l) = exp(-k · depth · tan θ_l · a(φ_l))`` (deep texels
darken at grazing light; ``a`` is weaker along the gap channel between parallel threads)
and the same masking ``M(v)``, times a fade where the local surface turns from the view.
Values are clipped to [0, 1]; the exposure keeps all but the brightest highlights below 1.

Directions: θ from the macro normal, φ from +x (image columns, to the right) toward +y
(image rows, downward). The model accepts any direction, not only grid ones; directions
below the horizon give 0.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import uuid
from dataclasses import dataclass
from functools import cached_property
from os import PathLike
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter
from tqdm import tqdm

from pipeline.core.errors import ConfigError, DataError
from pipeline.data.btf import encode_btf_image
from pipeline.data.directions import (
    N_DIRECTIONS,
    canonical_views,
    direction_index,
    grid_81_degrees,
    ubo2003_file_name,
    unit_vectors,
    utia_file_name,
    view_folder_name,
)

WARP, WEFT, GAP = 0, 1, 2

# Look of the three materials (rows warp, weft, gap); per-thread variation comes from
# the seed. Warp: madder red; weft: undyed beige; gap: the dark floor between threads.
_YARN_ALBEDO = np.array([[0.55, 0.10, 0.08], [0.70, 0.62, 0.42], [0.05, 0.04, 0.035]])
_SPECULAR_WEIGHT = np.array([0.45, 0.30, 0.05])
# Ashikhmin–Shirley exponents along the tangent (n_u) and the bitangent (n_v): a fibre
# reflects a highlight narrow along its length and spread across it.
_EXPONENT_ALONG = np.array([90.0, 40.0, 5.0])
_EXPONENT_ACROSS = np.array([6.0, 3.0, 5.0])
_TWIST_DEGREES = np.array([25.0, -15.0, 0.0])  # S-twist warp, Z-twist weft
_FRESNEL_AT_NORMAL = 0.05
_THREAD_HALF_WIDTH = 0.4  # in thread periods; the rest of the period is gap
_THREAD_RADIUS = 0.3  # crest height above the thread's centre line, in periods
_UNDULATION = 0.15  # how far a thread dips under its crossing threads, in periods
_SHADOW_STRENGTH = 0.55
_EXPOSURE = 3.0  # about 3e-5 of the values at grid directions clip at 1
_GENERATOR_VERSION = 1
_MARKER_NAME = "synthetic_btf.json"


@dataclass(frozen=True)
class SyntheticBTF:
    """Procedural woven fabric, evaluable at any light and view direction.

    Parameters
    ----------
    size : int
        Texture is ``size × size`` texels.
    seed : int
        Seeds the per-thread colours and the fine noise (``np.random.default_rng(seed)``).
    n_threads : int
        Warp (and weft) threads across the texture; even, so the weave tiles.

    Examples
    --------
    >>> fabric = SyntheticBTF(size=16, seed=0)
    >>> fabric.evaluate(np.array([[0.3, 1.0, 0.2, 4.0]])).shape
    (1, 16, 16, 3)
    """

    size: int = 64
    seed: int = 0
    n_threads: int = 4

    def __post_init__(self):
        if not isinstance(self.size, int | np.integer) or self.size < 2:
            raise ConfigError(f"synthetic BTF size={self.size!r} must be an integer >= 2")
        if (
            not isinstance(self.n_threads, int | np.integer)
            or self.n_threads < 2
            or self.n_threads % 2
        ):
            raise ConfigError(f"n_threads={self.n_threads!r} must be an even integer >= 2")

    # --- per-texel geometry and material (computed once, cached) -------------------------

    @cached_property
    def _geometry(self) -> dict[str, np.ndarray]:
        size, periods = self.size, self.n_threads
        centres = (np.arange(size) + 0.5) * periods / size  # texel centres in thread periods
        y, x = np.meshgrid(centres, centres, indexing="ij")
        warp_index, weft_index = np.floor(x), np.floor(y)
        # Warp k is on top where (k + row of crossing) is even, weft on top elsewhere.
        warp_centre = _UNDULATION * np.cos(np.pi * (y - 0.5) + np.pi * warp_index)
        weft_centre = -_UNDULATION * np.cos(np.pi * (x - 0.5) + np.pi * weft_index)

        def thread_surface(centre_line, across):
            inside = np.abs(across) < _THREAD_HALF_WIDTH
            bulge = np.sqrt(np.clip(1.0 - (across / _THREAD_HALF_WIDTH) ** 2, 0.0, None))
            return np.where(inside, centre_line + _THREAD_RADIUS * bulge, -np.inf)

        floor = np.full_like(x, -_UNDULATION - _THREAD_RADIUS)
        surfaces = np.stack(
            [
                thread_surface(warp_centre, x - warp_index - 0.5),
                thread_surface(weft_centre, y - weft_index - 0.5),
                floor,
            ]
        )
        labels = np.argmax(surfaces, axis=0)
        # Heights in texels, so that their finite differences are slopes; a light blur
        # removes the vertical cliffs at thread edges.
        height = np.max(surfaces, axis=0) * size / periods
        height = gaussian_filter(height, sigma=0.7, mode="wrap")
        slope_x = (np.roll(height, -1, axis=1) - np.roll(height, 1, axis=1)) / 2.0
        slope_y = (np.roll(height, -1, axis=0) - np.roll(height, 1, axis=0)) / 2.0
        normal = np.stack([-slope_x, -slope_y, np.ones_like(height)], axis=-1)
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)

        # Tangent: along the thread, projected into the tangent plane, then twisted.
        along = np.zeros_like(normal)
        along[..., 0] = labels != WARP  # weft and floor: +x
        along[..., 1] = labels == WARP  # warp: +y
        tangent = along - np.sum(along * normal, axis=-1, keepdims=True) * normal
        tangent /= np.linalg.norm(tangent, axis=-1, keepdims=True)
        twist = np.deg2rad(_TWIST_DEGREES[labels])[..., None]
        tangent = tangent * np.cos(twist) + np.cross(normal, tangent) * np.sin(twist)
        bitangent = np.cross(normal, tangent)

        depth = (height.max() - height) / max(np.ptp(height), 1e-12)
        return {
            "labels": labels,
            "height": height,
            "normal": normal,
            "tangent": tangent,
            "bitangent": bitangent,
            "depth": depth,
            "warp_index": warp_index.astype(np.int64),
            "weft_index": weft_index.astype(np.int64),
        }

    @cached_property
    def albedo(self) -> np.ndarray:
        """Diffuse albedo per texel, ndarray of shape (size, size, 3), float32 in [0, 1]."""
        geometry = self._geometry
        rng = np.random.default_rng(self.seed)
        # Per-thread brightness and a little hue shift, so threads of one yarn differ.
        thread_gain = rng.uniform(0.8, 1.2, size=(2, self.n_threads, 1))
        thread_tint = 1.0 + rng.normal(0.0, 0.04, size=(2, self.n_threads, 3))
        labels = geometry["labels"]
        albedo = _YARN_ALBEDO[labels].copy()
        for yarn, index in ((WARP, geometry["warp_index"]), (WEFT, geometry["weft_index"])):
            on_yarn = labels == yarn
            albedo[on_yarn] *= (thread_gain[yarn] * thread_tint[yarn])[index[on_yarn]]
        # Fine fibre noise: multiplicative, slightly blurred so it is not pure pixel noise.
        noise = gaussian_filter(rng.normal(0.0, 1.0, size=labels.shape), 0.6, mode="wrap")
        albedo *= (1.0 + 0.12 * noise / max(noise.std(), 1e-12))[..., None]
        return np.clip(albedo, 0.0, 1.0).astype(np.float32)

    @property
    def material_labels(self) -> np.ndarray:
        """Visible yarn per texel: 0 warp, 1 weft, 2 gap; ndarray (size, size), int."""
        return self._geometry["labels"]

    @property
    def height(self) -> np.ndarray:
        """Height field in texel units, ndarray of shape (size, size), float64."""
        return self._geometry["height"]

    @property
    def normals(self) -> np.ndarray:
        """Unit normals per texel, ndarray of shape (size, size, 3), float64."""
        return self._geometry["normal"]

    @property
    def tangents(self) -> np.ndarray:
        """Unit thread tangents per texel (twisted), ndarray (size, size, 3), float64."""
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
        geometry = self._geometry
        labels = geometry["labels"].ravel()
        flat = {
            name: geometry[name].reshape(-1, 3).T.astype(np.float32)  # (3, P) for matmul
            for name in ("normal", "tangent", "bitangent")
        }
        # Occlusion exponent = features(direction) @ occlusion_weights, with features
        # tan θ·(1, |sin φ|, |cos φ|): deep texels shadow more, and the walls of a thread's
        # channel shadow light coming across the thread (|sin| of the angle to it) more
        # than light along it. Warp runs along +y, so across it is |cos φ|.
        weights = np.zeros((3, labels.size))
        weights[0] = np.where(labels == GAP, 1.0, 0.35)
        weights[1] = np.where(labels == WEFT, 0.65, 0.0)
        weights[2] = np.where(labels == WARP, 0.65, 0.0)
        flat["occlusion_weights"] = (_SHADOW_STRENGTH * geometry["depth"].ravel() * weights).astype(
            np.float32
        )
        flat["albedo_over_pi"] = (self.albedo.reshape(-1, 3) / np.pi).astype(np.float32)
        along = _EXPONENT_ALONG[labels]
        across = _EXPONENT_ACROSS[labels]
        flat["exponent_along"] = along.astype(np.float32)
        flat["exponent_across"] = across.astype(np.float32)
        # Ashikhmin–Shirley normalization times the yarn's specular weight.
        flat["specular_scale"] = (
            _SPECULAR_WEIGHT[labels] * np.sqrt((along + 1) * (across + 1)) / (8 * np.pi)
        ).astype(np.float32)
        return flat

    def _evaluate_chunk(self, directions: np.ndarray) -> np.ndarray:
        """(c, 4) directions to (c, P, 3) float32 values, P = size²."""
        maps = self._flat_maps
        theta_light = np.clip(directions[:, 0], 0.0, np.pi)
        theta_view = np.clip(directions[:, 2], 0.0, np.pi)
        light = unit_vectors(theta_light, directions[:, 1]).astype(np.float32)
        view = unit_vectors(theta_view, directions[:, 3]).astype(np.float32)
        halfway = light + view
        halfway /= np.maximum(np.linalg.norm(halfway, axis=1, keepdims=True), 1e-12)
        light_dot_half = np.clip(np.sum(light * halfway, axis=1), 1e-4, 1.0)[:, None]  # (c, 1)

        n_dot_l = light @ maps["normal"]  # (c, P)
        n_dot_v = view @ maps["normal"]
        n_dot_h = halfway @ maps["normal"]
        t_dot_h = halfway @ maps["tangent"]
        b_dot_h = halfway @ maps["bitangent"]

        # Ashikhmin–Shirley: (n·h)^((n_u (t·h)² + n_v (b·h)²) / (1 - (n·h)²)); in an
        # orthonormal frame 1 - (n·h)² = (t·h)² + (b·h)², which stays finite at n = h.
        along, across = maps["exponent_along"], maps["exponent_across"]
        tangential = t_dot_h**2 + b_dot_h**2
        exponent = (along * t_dot_h**2 + across * b_dot_h**2) / np.maximum(tangential, 1e-12)
        exponent = np.where(tangential > 1e-12, exponent, along)
        lobe = np.exp(exponent * np.log(np.maximum(n_dot_h, 1e-12)))
        lobe = np.where(n_dot_h > 0, lobe, 0.0)
        fresnel = _FRESNEL_AT_NORMAL + (1 - _FRESNEL_AT_NORMAL) * (1 - light_dot_half) ** 5
        # The 0.1 floor keeps the lobe finite where a texel turns edge-on to both.
        specular = (
            maps["specular_scale"]
            * lobe
            * fresnel
            / (light_dot_half * np.maximum(np.maximum(n_dot_l, n_dot_v), 0.1))
        )

        def occlusion_features(theta, phi):  # (c,) -> (c, 3)
            tan_theta = np.tan(np.minimum(theta, np.deg2rad(89.0)))
            return tan_theta[:, None] * np.stack(
                [np.ones_like(phi), np.abs(np.sin(phi)), np.abs(np.cos(phi))], axis=1
            )

        # Shadowing (light) times masking (view): exp(-a_l) exp(-a_v) = exp(-(a_l + a_v)).
        features = occlusion_features(theta_light, directions[:, 1]) + occlusion_features(
            theta_view, directions[:, 3]
        )
        occlusion = np.exp(-(features.astype(np.float32) @ maps["occlusion_weights"]))
        # Fade texels whose local surface turns away from the viewer (seen at a graze).
        facing = np.clip(n_dot_v / 0.2, 0.0, 1.0)
        facing = facing * facing * (3 - 2 * facing)
        above = ((np.cos(theta_light) > 0) & (np.cos(theta_view) > 0))[:, None]
        weight = np.where(above, _EXPOSURE * np.maximum(n_dot_l, 0) * occlusion * facing, 0.0)
        values = weight[..., None] * (maps["albedo_over_pi"] + specular[..., None])
        return np.clip(values, 0.0, 1.0).astype(np.float32)


# --- writer in the real layouts ----------------------------------------------------------

_WRITABLE = {"ubo2003": ("jpg", "png", "exr"), "utia": ("png", "exr")}


def _read_marker(root: Path) -> dict | None:
    try:
        return json.loads((root / _MARKER_NAME).read_text())
    except (OSError, ValueError):
        return None


def write_synthetic_btf(
    root: str | PathLike,
    size: int = 64,
    seed: int = 0,
    format: str = "ubo2003",
    ext: str = "jpg",
    views=None,
    quality: int = 95,
) -> Path:
    """Write :class:`SyntheticBTF` images as a dataset in the UBO2003 or UTIA layout.

    The dataset is written into a hidden temporary sibling folder, one view at a time
    (memory stays at one view's 81 images), then renamed to ``root``; a killed run thus
    never leaves a half dataset under ``root``. A ``synthetic_btf.json`` marker in
    ``root`` records the parameters; when ``root`` already holds a dataset written with
    the same parameters, nothing is rewritten.

    UBO2003 running numbers are each image's index in the full view-major 6561-image
    order (``view_index * 81 + light_index``), so a written subset of views carries the
    same names as the full dataset's folders.

    Parameters
    ----------
    root : path-like
        Dataset folder to create.
    size, seed : int
        Passed to :class:`SyntheticBTF`.
    format : {"ubo2003", "utia"}
    ext : str
        ``ubo2003``: ``"jpg"`` (gamma 2.2, JPEG ``quality``), ``"png"`` (gamma 2.2, 8-bit)
        or ``"exr"`` (half linear RGB). ``utia``: ``"png"`` (8-bit sRGB) or ``"exr"``
        (half XYZ).
    views : sequence of (θ_view, φ_view) in degrees, or None
        Write only these view folders; None writes all 81.
    quality : int
        JPEG quality, 1..100.

    Returns
    -------
    Path
        ``root``.

    Raises
    ------
    ConfigError
        For an unknown format/extension pair, an off-grid view, or a bad quality.
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
    fabric = SyntheticBTF(size=size, seed=seed)
    view_list = canonical_views(views)
    root = Path(root)
    marker = {
        "generator": "pipeline.btf.synthetic.SyntheticBTF",
        "version": _GENERATOR_VERSION,
        "size": fabric.size,
        "seed": int(seed),
        "n_threads": fabric.n_threads,
        "format": format,
        "ext": ext,
        "views": [list(view) for view in view_list],
        "quality": int(quality),
    }
    if root.exists() and not (root.is_dir() and not any(root.iterdir())):
        if _read_marker(root) == marker:
            return root
        raise DataError(
            f"{root} exists but is not a synthetic BTF written with {marker}; "
            f"remove it or choose another root"
        )
    root.parent.mkdir(parents=True, exist_ok=True)
    partial = root.parent / f".{root.name}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    partial.mkdir()
    try:
        lights = grid_81_degrees()
        light_radians = np.deg2rad(lights.astype(np.float64))
        show_bar = sys.stderr.isatty()
        for view in tqdm(view_list, desc=f"write {root.name}", leave=False, disable=not show_bar):
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
                    name = ubo2003_file_name(number, theta_light, phi_light, *view, ext)
                else:
                    name = utia_file_name(theta_light, phi_light, *view, ext)
                encode_btf_image(folder / name, images[light_index], format, quality)
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
    return root
