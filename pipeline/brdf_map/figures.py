"""Figures of method B (PAPERS.md, B): distributions, slices and rendered spheres.

* :func:`plot_distribution_heatmaps` -- the observed distribution d and the fitted f over
  (theta_h, phi_h), side by side (the paper's Figs. 3-5, drawn as heat maps);
* :func:`plot_distribution_slices` -- 1-D slices at fixed phi_h and at fixed theta_h
  (Figs. 6-7);
* :func:`render_sphere` and :func:`plot_sphere_pair` -- a sphere lit by one distant light
  near and far from the view, from raw data with holes (flagged colour where no value
  exists, Fig. 2) and from a reconstruction (Fig. 8).

Every plotting function takes arrays or callables and an output folder and returns the
paths it wrote. Matplotlib runs on the Agg backend (no display needed).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.colors import PowerNorm
from matplotlib.figure import Figure

from pipeline.core.errors import ConfigError, DataError
from pipeline.core.report import save_figure
from pipeline.data.brdf import to_angles, to_unit_vectors

MISSING_RGB = (1.0, 0.0, 1.0)  # magenta: no value can be computed there
BACKGROUND_RGB = (0.35, 0.35, 0.35)

BRDFFunction = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _scalar_map(values: np.ndarray, name: str, shape: tuple[int, int]) -> np.ndarray:
    """(n_theta, n_phi) map; an RGB map (n_theta, n_phi, 3) is summed over channels."""
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 3 and values.shape[-1] == 3:
        values = values.sum(axis=-1)
    if values.shape != shape:
        raise DataError(f"{name} has shape {values.shape}, expected {shape} (or {shape + (3,)})")
    return values


def _prepare(theta_h, phi_h, observed, fitted, observed_mask):
    theta_h = np.asarray(theta_h, dtype=np.float64)
    phi_h = np.asarray(phi_h, dtype=np.float64)
    shape = (theta_h.size, phi_h.size)
    d = _scalar_map(observed, "observed", shape)
    f = _scalar_map(fitted, "fitted", shape)
    mask = np.ones(shape, bool) if observed_mask is None else np.asarray(observed_mask, bool)
    if mask.shape != shape:
        raise DataError(f"observed_mask has shape {mask.shape}, expected {shape}")
    return theta_h, phi_h, np.where(mask, d, np.nan), f


def plot_distribution_heatmaps(
    theta_h: np.ndarray,
    phi_h: np.ndarray,
    observed: np.ndarray,
    fitted: np.ndarray,
    out_dir: str | os.PathLike,
    observed_mask: np.ndarray | None = None,
    name: str = "distribution",
    gamma: float = 0.5,
) -> list[Path]:
    """Heat maps of the observed d and the fitted f over (theta_h, phi_h).

    Parameters
    ----------
    theta_h : ndarray of shape (n_theta,)
        Cell-centre polar angles (radians).
    phi_h : ndarray of shape (n_phi,)
        Cell-centre azimuths (radians).
    observed, fitted : ndarray of shape (n_theta, n_phi) or (n_theta, n_phi, 3)
        d and f (RGB maps are summed over channels).
    out_dir : path-like
        Folder to write ``name``.png into (created if needed); the path is returned in a list.
    observed_mask : ndarray of shape (n_theta, n_phi), bool, optional
        Cells holding a measurement; the others are drawn grey ("no data").
    gamma : float
        Power-law colour scale exponent (< 1 shows the tails of a peaked lobe).
    """
    theta_h, phi_h, d, f = _prepare(theta_h, phi_h, observed, fitted, observed_mask)
    finite = d[np.isfinite(d)]
    vmax = max(float(np.max(f)), float(np.max(finite)) if finite.size else 0.0, 1e-12)
    norm = PowerNorm(gamma=gamma, vmin=0.0, vmax=vmax)
    cmap = matplotlib.colormaps["viridis"].with_extremes(bad=(0.6, 0.6, 0.6))
    fig = Figure(figsize=(10, 4), constrained_layout=True)
    axes = fig.subplots(1, 2)
    for ax, values, title in ((axes[0], d, "(a) observed d"), (axes[1], f, "(b) reconstructed f")):
        mesh = ax.pcolormesh(
            np.rad2deg(phi_h),
            np.rad2deg(theta_h),
            np.ma.masked_invalid(values),
            shading="nearest",
            cmap=cmap,
            norm=norm,
        )
        ax.set_xlabel("phi_h (deg)")
        ax.set_ylabel("theta_h (deg)")
        ax.set_title(title)
    fig.colorbar(mesh, ax=axes, shrink=0.9)
    return [_save(fig, Path(out_dir) / f"{name}.png")]


def plot_distribution_slices(
    theta_h: np.ndarray,
    phi_h: np.ndarray,
    observed: np.ndarray,
    fitted: np.ndarray,
    out_dir: str | os.PathLike,
    phi_values_deg: Sequence[float] = (0.0, 45.0, 90.0),
    theta_values_deg: Sequence[float] = (5.0, 15.0, 30.0),
    observed_mask: np.ndarray | None = None,
    name: str = "slices",
) -> list[Path]:
    """1-D slices of d (markers) and f (lines): along theta_h at fixed phi_h, and vice versa.

    Arguments as :func:`plot_distribution_heatmaps`; ``phi_values_deg`` and
    ``theta_values_deg`` are the slice positions (degrees): the nearest grid column / row
    is drawn.
    """
    theta_h, phi_h, d, f = _prepare(theta_h, phi_h, observed, fitted, observed_mask)
    fig = Figure(figsize=(10, 4), constrained_layout=True)
    (ax_t, ax_p) = fig.subplots(1, 2)
    colours = matplotlib.colormaps["tab10"]
    for k, phi_deg in enumerate(phi_values_deg):
        j = int(np.argmin(np.abs(np.rad2deg(phi_h) - phi_deg)))
        label = f"phi={np.rad2deg(phi_h[j]):.1f}"
        ax_t.plot(np.rad2deg(theta_h), d[:, j], "o", ms=3, color=colours(k), label=f"d {label}")
        ax_t.plot(np.rad2deg(theta_h), f[:, j], "-", color=colours(k), label=f"f {label}")
    for k, theta_deg in enumerate(theta_values_deg):
        i = int(np.argmin(np.abs(np.rad2deg(theta_h) - theta_deg)))
        label = f"theta={np.rad2deg(theta_h[i]):.1f}"
        ax_p.plot(np.rad2deg(phi_h), d[i], "o", ms=3, color=colours(k), label=f"d {label}")
        ax_p.plot(np.rad2deg(phi_h), f[i], "-", color=colours(k), label=f"f {label}")
    ax_t.set_xlabel("theta_h (deg)")
    ax_t.set_title("(a) fixed phi_h")
    ax_p.set_xlabel("phi_h (deg)")
    ax_p.set_title("(b) fixed theta_h")
    for ax in (ax_t, ax_p):
        ax.legend(fontsize=7)
    return [_save(fig, Path(out_dir) / f"{name}.png")]


def render_sphere(
    brdf: BRDFFunction, light: tuple[float, float], size: int = 64
) -> tuple[np.ndarray, np.ndarray]:
    """Render a sphere seen orthographically along +z, lit by one distant light (eq. 22-23).

    Each visible point has normal n = (x, y, sqrt(1 - x^2 - y^2)) and tangent along the
    projection of the image x axis, so an anisotropic BRDF shows horizontal "brushing".
    Pixel = brdf(k1, k2) cos(theta_1) (a light of unit L_i omega_i); points facing away from
    the light are 0.

    Parameters
    ----------
    brdf : callable
        ``brdf(light (n, 2), view (n, 2)) -> (n, 3)``; NaN means "no value" (a hole).
    light : (float, float)
        Light direction (theta, phi) in radians in the camera frame (theta from the
        view direction, phi from the image x axis towards image up).
    size : int
        Image side in pixels.

    Returns
    -------
    image : ndarray of shape (size, size, 3)
        Linear radiance; NaN at holes, 0 outside the sphere.
    inside : ndarray of shape (size, size), bool
        Pixels covered by the sphere.
    """
    if size < 2:
        raise ConfigError(f"size={size} must be >= 2")
    coords = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    x, y = np.meshgrid(coords, -coords)  # row 0 is the top of the image
    inside = x**2 + y**2 < 1.0
    normal = np.stack([x[inside], y[inside], np.sqrt(1.0 - x[inside] ** 2 - y[inside] ** 2)], -1)
    tangent = np.array([1.0, 0.0, 0.0]) - normal[:, :1] * normal
    tangent /= np.maximum(np.linalg.norm(tangent, axis=-1, keepdims=True), 1e-12)
    bitangent = np.cross(normal, tangent)
    k_light, k_view = to_unit_vectors(light), np.array([0.0, 0.0, 1.0])

    def local(k):
        return np.stack([tangent @ k, bitangent @ k, normal @ k], axis=-1)

    light_local, view_local = local(k_light), local(k_view)
    lit = light_local[:, 2] > 1e-6
    values = np.zeros((normal.shape[0], 3))
    if np.any(lit):
        rho = np.asarray(
            brdf(to_angles(light_local[lit]), to_angles(view_local[lit])), dtype=np.float64
        )
        values[lit] = rho * light_local[lit, 2:3]
    image = np.zeros((size, size, 3))
    image[inside] = values
    return image, inside


def plot_sphere_pair(
    brdf: BRDFFunction,
    out_dir: str | os.PathLike,
    name: str,
    near_light: tuple[float, float] = (np.deg2rad(10.0), 0.0),
    far_light: tuple[float, float] = (np.deg2rad(60.0), np.deg2rad(180.0)),
    size: int = 64,
    exposure: float | None = None,
) -> list[Path]:
    """Spheres under a light near and far from the view (Fig. 2 raw, Fig. 8 reconstruction).

    Parameters
    ----------
    brdf : callable
        ``brdf(light, view) -> (n, 3)``, NaN where undefined (drawn in magenta).
    out_dir, name
        As in :func:`plot_distribution_heatmaps`.
    near_light, far_light : (float, float)
        Light directions (see :func:`render_sphere`).
    size : int
        Pixels per sphere side.
    exposure : float, optional
        Radiance shown as white; by default the 99th percentile of the defined pixels, so
        pass the same value to compare raw and reconstructed renders.
    """
    renders = [render_sphere(brdf, light, size) for light in (near_light, far_light)]
    if exposure is None:
        defined = np.concatenate([img[inside].ravel() for img, inside in renders])
        defined = defined[np.isfinite(defined)]
        exposure = float(np.percentile(defined, 99)) if defined.size else 1.0
    fig = Figure(figsize=(6, 3.2), constrained_layout=True)
    axes = fig.subplots(1, 2)
    for ax, (img, inside), title in zip(
        axes, renders, ("light near view", "light far from view"), strict=True
    ):
        ax.imshow(tone_map(img, inside, exposure))
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    return [_save(fig, Path(out_dir) / f"{name}.png")]


def tone_map(image: np.ndarray, inside: np.ndarray, exposure: float) -> np.ndarray:
    """Linear radiance (H, W, 3) to display RGB: exposure, clip, gamma 2.2, flagged holes."""
    if not exposure > 0:
        raise ConfigError(f"exposure={exposure} must be > 0")
    display = np.clip(np.nan_to_num(image / exposure, nan=0.0), 0.0, 1.0) ** (1.0 / 2.2)
    holes = inside & np.any(~np.isfinite(image), axis=-1)
    display[holes] = MISSING_RGB
    display[~inside] = BACKGROUND_RGB
    return display


def _save(fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=100)
    return path
