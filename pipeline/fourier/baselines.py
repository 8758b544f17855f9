"""Standard RTI relighting baselines and Lambertian photometric stereo.

Both baselines fit, per pixel and channel, a linear combination of basis functions of
the light direction alone (they ignore the normal), so one design matrix serves every
pixel and one least-squares solve with many right-hand sides fits the whole image.

- PTM (Malzbender, Gelb & Wolters 2001, "Polynomial texture maps", eq. 2): the
  biquadratic L(lu, lv) = a0 lu² + a1 lv² + a2 lu lv + a3 lu + a4 lv + a5, where
  (lu, lv) are the x, y components of the unit light vector.
- HSH (Gautron, Křivánek, Pattanaik & Bouatouch 2004, "A novel hemispherical basis for
  accurate and efficient rendering", eq. 3-4), order 2, 9 terms. With θ, φ the polar and
  azimuth angles of the light about the camera axis, the hemisphere is mapped onto the
  sphere by cos θ' = 2 cos θ - 1, and H_l^m = √2 K_l^m P_l^|m|(cos θ') cos(mφ) (m > 0),
  √2 K_l^m P_l^|m|(cos θ') sin(|m|φ) (m < 0), K_l^0 P_l^0(cos θ') (m = 0), with
  K_l^m = sqrt((2l + 1) (l - |m|)! / (2π (l + |m|)!)). Written out with c = cos θ
  (the same functions RTI tools use, Mudge et al. 2008), up to the Condon-Shortley sign::

      H_0^0  = 1 / sqrt(2π)
      H_1^±1 = sqrt(6/π)  sqrt(c - c²)            {sin φ, cos φ}
      H_1^0  = sqrt(3/(2π)) (2c - 1)
      H_2^±2 = sqrt(30/π) (c - c²)                 {sin 2φ, cos 2φ}
      H_2^±1 = sqrt(30/π) (2c - 1) sqrt(c - c²)    {sin φ, cos φ}
      H_2^0  = sqrt(5/(2π)) (6c² - 6c + 1)

  They are orthonormal on the upper hemisphere (tested). Lights below the horizon are
  clamped to it (c = 0).
"""

from __future__ import annotations

import numpy as np

from pipeline.core.errors import ConfigError
from pipeline.fourier.series import check_coeffs, check_dirs, check_images


def ptm_basis(light_dirs) -> np.ndarray:
    """PTM basis [lu², lv², lu lv, lu, lv, 1] for lights (n, 3); returns (n, 6)."""
    dirs, _ = check_dirs(light_dirs)
    lu, lv = dirs[:, 0], dirs[:, 1]
    return np.stack([lu * lu, lv * lv, lu * lv, lu, lv, np.ones_like(lu)], axis=1)


def hsh_basis(light_dirs) -> np.ndarray:
    """Order-2 hemispherical harmonics (module docstring) for lights (n, 3); (n, 9).

    Column order: H_0^0, H_1^-1, H_1^0, H_1^1, H_2^-2, H_2^-1, H_2^0, H_2^1, H_2^2.
    """
    dirs, _ = check_dirs(light_dirs)
    c = np.clip(dirs[:, 2], 0.0, 1.0)
    phi = np.arctan2(dirs[:, 1], dirs[:, 0])
    s = np.sqrt(np.maximum(c - c * c, 0.0))  # sqrt(c - c²) = sin θ' / 2
    x = 2.0 * c - 1.0  # cos θ'
    pi = np.pi
    return np.stack(
        [
            np.full_like(c, 1.0 / np.sqrt(2.0 * pi)),
            np.sqrt(6.0 / pi) * s * np.sin(phi),
            np.sqrt(3.0 / (2.0 * pi)) * x,
            np.sqrt(6.0 / pi) * s * np.cos(phi),
            np.sqrt(30.0 / pi) * s * s * np.sin(2.0 * phi),
            np.sqrt(30.0 / pi) * x * s * np.sin(phi),
            np.sqrt(5.0 / (2.0 * pi)) * (6.0 * c * c - 6.0 * c + 1.0),
            np.sqrt(30.0 / pi) * x * s * np.cos(phi),
            np.sqrt(30.0 / pi) * s * s * np.cos(2.0 * phi),
        ],
        axis=1,
    )


def _fit_shared_basis(images: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """Least squares with one (n, K) design matrix for all pixels; returns (H, W, 3, K)."""
    n, height, width, _ = images.shape
    if n < basis.shape[1]:
        raise ConfigError(
            f"{basis.shape[1]} basis functions need >= {basis.shape[1]} images, got {n}"
        )
    targets = images.reshape(n, -1).astype(np.float64)
    solution, *_ = np.linalg.lstsq(basis, targets, rcond=None)  # (K, H*W*3)
    return solution.T.reshape(height, width, 3, basis.shape[1]).astype(np.float32)


def _render_shared_basis(coeffs: np.ndarray, basis: np.ndarray, single: bool) -> np.ndarray:
    out = np.einsum("nk,hwck->nhwc", basis, coeffs.astype(np.float64)).astype(np.float32)
    return out[0] if single else out


def fit_ptm(images, light_dirs) -> np.ndarray:
    """Fit a polynomial texture map to images (N, H, W, 3), N >= 6, under lights (N, 3).

    Returns (H, W, 3, 6) float32 coefficients in the order of :func:`ptm_basis`.
    """
    dirs, _ = check_dirs(light_dirs)
    return _fit_shared_basis(check_images(images, len(dirs)), ptm_basis(dirs))


def render_ptm(coeffs, light_dirs) -> np.ndarray:
    """Relight a PTM: (H, W, 3) for one light (3,), (n, H, W, 3) for lights (n, 3)."""
    coeffs = check_coeffs(coeffs, 6)
    dirs, single = check_dirs(light_dirs)
    return _render_shared_basis(coeffs, ptm_basis(dirs), single)


def fit_hsh(images, light_dirs) -> np.ndarray:
    """Fit order-2 hemispherical harmonics to images (N, H, W, 3), N >= 9, under lights (N, 3).

    Returns (H, W, 3, 9) float32 coefficients in the order of :func:`hsh_basis`.
    """
    dirs, _ = check_dirs(light_dirs)
    return _fit_shared_basis(check_images(images, len(dirs)), hsh_basis(dirs))


def render_hsh(coeffs, light_dirs) -> np.ndarray:
    """Relight an HSH fit: (H, W, 3) for one light (3,), (n, H, W, 3) for lights (n, 3)."""
    coeffs = check_coeffs(coeffs, 9)
    dirs, single = check_dirs(light_dirs)
    return _render_shared_basis(coeffs, hsh_basis(dirs), single)


def lambertian_normals(
    images, light_dirs, drop_dark: float = 0.2, drop_bright: float = 0.1
) -> tuple[np.ndarray, np.ndarray]:
    """Photometric-stereo normals under the Lambertian model (Woodham 1980).

    Solves I_n = ρ (n · l_n) per pixel on the luminance, after dropping, per pixel, the
    darkest and brightest fractions of its observations: the darkest are likely in
    (attached or cast) shadow, the brightest specular, and neither is Lambertian.

    Parameters
    ----------
    images : ndarray of shape (N, H, W, 3)
    light_dirs : array_like of shape (N, 3)
    drop_dark, drop_bright : float in [0, 1)
        Fractions of each pixel's observations left out; at least 3 must remain.

    Returns
    -------
    normals : ndarray of shape (H, W, 3), float32
        Unit normals; (0, 0, 1) where the pixel is black under every used light.
    albedo : ndarray of shape (H, W), float32
        ρ of the luminance.
    """
    dirs, _ = check_dirs(light_dirs)
    images = check_images(images, len(dirs))
    n, height, width, _ = images.shape
    if not (0 <= drop_dark < 1 and 0 <= drop_bright < 1):
        raise ConfigError(f"drop_dark={drop_dark} and drop_bright={drop_bright} must be in [0, 1)")
    low, high = int(np.floor(drop_dark * n)), n - int(np.floor(drop_bright * n))
    if high - low < 3:
        raise ConfigError(f"photometric stereo keeps {high - low} of {n} lights; it needs 3")
    luminance = images.reshape(n, -1, 3) @ np.array([0.2126, 0.7152, 0.0722])  # (N, P)
    rank = np.argsort(np.argsort(luminance, axis=0, kind="stable"), axis=0)
    weight = ((rank >= low) & (rank < high)).astype(np.float64)  # (N, P)
    # Batched weighted normal equations: G_p = Σ_n w_pn l_n l_nᵀ, b_p = Σ_n w_pn I_pn l_n.
    outer = dirs[:, :, None] * dirs[:, None, :]  # (N, 3, 3)
    gram = np.einsum("np,nij->pij", weight, outer)
    rhs = np.einsum("np,ni->pi", weight * luminance, dirs)
    scaled = np.linalg.solve(gram + 1e-12 * np.eye(3), rhs[..., None])[..., 0]  # (P, 3)
    albedo = np.linalg.norm(scaled, axis=1)
    normals = np.tile(np.array([0.0, 0.0, 1.0]), (len(albedo), 1))
    lit = albedo > 1e-12
    normals[lit] = scaled[lit] / albedo[lit, None]
    return (
        normals.reshape(height, width, 3).astype(np.float32),
        albedo.reshape(height, width).astype(np.float32),
    )
