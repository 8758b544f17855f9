"""What a surface point reflects: the interface the renderer queries, and a closed form.

A :class:`Material` answers batches of queries, ``evaluate(texels, directions)``, with
texels indices ``row * cols + col`` into its crop of ``crop_size = (rows, cols)`` texels
and directions ``(theta_light, phi_light, theta_view, phi_view)`` in radians in the
texel's tangent frame (theta from the normal, phi from the tangent towards the
bitangent). The value is a BTF value: reflected radiance per unit irradiance on a surface
perpendicular to the light, i.e. it already contains the cosine foreshortening
(:mod:`pipeline.render.engine`).

- :class:`Material`: the interface, with the checks of every query.
- :class:`LambertianTexture`: ``albedo / pi * cos(theta_light)``, a closed form for tests.
- :func:`texels_of_uv` and :func:`spherical`: the queries of a shading point, shared by
  the renderer and the Mitsuba plugin.

A method's own materials subclass :class:`Material` in the method's package (method A's
measured, PCA, compressed and analytic BTFs: :mod:`pipeline.btf.render.surfaces`); this
package imports no method.

Examples
--------
>>> albedo = np.full((2, 2, 3), 0.5)
>>> LambertianTexture(albedo).evaluate(np.array([3]), np.zeros((1, 4))).round(4)
array([[0.1592, 0.1592, 0.1592]], dtype=float32)
>>> texels_of_uv(np.array([[0.3, 0.6], [1.99, 0.1]]), crop_size=(2, 4))  # (row, col) (1, 1), (0, 3)
array([5, 3])
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np


class Material(ABC):
    """Batched RGB queries of a BTF-like material over a crop of ``crop_size`` texels.

    Subclasses set ``crop_size`` and implement :meth:`_evaluate`; :meth:`evaluate`
    checks the queries first.
    """

    crop_size: tuple[int, int]

    @property
    def n_texels(self) -> int:
        return self.crop_size[0] * self.crop_size[1]

    def evaluate(self, texels, directions) -> np.ndarray:
        """RGB of texel ``texels[i]`` at direction pair ``directions[i]``.

        Parameters
        ----------
        texels : array_like of ints of shape (n,), in [0, rows * cols).
        directions : array_like of shape (n, 4), (theta_light, phi_light, theta_view,
            phi_view) in radians.

        Returns
        -------
        ndarray of shape (n, 3), float32, linear RGB.
        """
        texels = np.asarray(texels)
        if texels.ndim != 1 or not (texels.size == 0 or np.issubdtype(texels.dtype, np.integer)):
            raise ValueError(
                f"texels must be a 1-D array of ints, got shape {texels.shape} of {texels.dtype}"
            )
        if texels.size and (texels.min() < 0 or texels.max() >= self.n_texels):
            bad = texels[(texels < 0) | (texels >= self.n_texels)][0]
            raise ValueError(f"texel {bad} is outside [0, {self.n_texels})")
        directions = np.asarray(directions, dtype=np.float64)
        if directions.shape != (len(texels), 4):
            raise ValueError(
                f"directions must have shape ({len(texels)}, 4), got {directions.shape}"
            )
        if len(texels) == 0:
            return np.zeros((0, 3), dtype=np.float32)
        return self._evaluate(texels.astype(np.int64), directions)

    @abstractmethod
    def _evaluate(self, texels: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Checked queries: texels (n,) int64, directions (n, 4) float64 -> (n, 3) float32."""


def check_crop_size(crop_size) -> tuple[int, int]:
    """``crop_size`` as (rows, cols), two integers >= 1; ValueError naming it otherwise."""
    try:
        rows, cols = (int(v) for v in crop_size)
    except (TypeError, ValueError):
        raise ValueError(f"crop_size={crop_size!r} must be (rows, cols)") from None
    if rows < 1 or cols < 1 or (rows, cols) != tuple(crop_size):
        raise ValueError(f"crop_size={tuple(crop_size)!r} must be two integers >= 1")
    return rows, cols


class LambertianTexture(Material):
    """A diffuse texture: value ``albedo[texel] / pi * max(cos(theta_light), 0)``.

    Parameters
    ----------
    albedo : ndarray of shape (rows, cols, 3), in [0, 1]
        Texel (row, col) has index ``row * cols + col``.
    """

    def __init__(self, albedo: np.ndarray):
        albedo = np.asarray(albedo, dtype=np.float64)
        if albedo.ndim != 3 or albedo.shape[2] != 3 or 0 in albedo.shape:
            raise ValueError(f"albedo must have shape (rows, cols, 3), got {albedo.shape}")
        if not np.all((albedo >= 0) & (albedo <= 1)):
            raise ValueError(
                f"albedo must lie in [0, 1], got values in "
                f"[{np.nanmin(albedo):g}, {np.nanmax(albedo):g}]"
            )
        self.crop_size = albedo.shape[:2]
        self.albedo = albedo.reshape(-1, 3)

    def _evaluate(self, texels, directions):
        cosine = np.maximum(np.cos(directions[:, 0]), 0.0)
        return (self.albedo[texels] * (cosine / np.pi)[:, None]).astype(np.float32)


def texels_of_uv(uv: np.ndarray, crop_size) -> np.ndarray:
    """Texel indices (n,) of uv coordinates (n, 2), the crop repeating every unit.

    ``col = floor(frac(u) * cols)``, ``row = floor(frac(v) * rows)``, texel ``row * cols +
    col``: uv (0, 0) is the corner of texel (row 0, col 0).
    """
    rows, cols = check_crop_size(crop_size)
    uv = np.asarray(uv, dtype=np.float64)
    col = np.minimum((np.mod(uv[:, 0], 1.0) * cols).astype(np.int64), cols - 1)
    row = np.minimum((np.mod(uv[:, 1], 1.0) * rows).astype(np.int64), rows - 1)
    return row * cols + col


def spherical(local: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(theta, phi) of unit local directions (n, 3) = (w.t, w.b, w.n): theta from +z (the
    normal), phi in [0, 2 pi) from +x (the tangent) towards +y (the bitangent)."""
    theta = np.arccos(np.clip(local[:, 2], -1.0, 1.0))
    phi = np.mod(np.arctan2(local[:, 1], local[:, 0]), 2.0 * np.pi)
    return theta, phi
