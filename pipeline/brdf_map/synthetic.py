"""A known anisotropic microfacet BRDF, written in the UTIA layout, with full ground truth.

The specular part is the Ashikhmin-Premoze-Shirley form (eq. 1 of the method's paper)

    rho_s(k1, k2) = k_s p(h) <h.n> F(k.h) / (4 g(k1) g(k2)),

a Lambertian term rho_d / pi is added per channel. Two microfacet distributions p:

``kind="beckmann"`` (default): anisotropic Beckmann

    p(h) = exp(-tan^2 theta_h (cos^2 phi'/a_x^2 + sin^2 phi'/a_y^2)) / (pi a_x a_y cos^4 theta_h),

    phi' = phi_h - tangent_angle, normalised so that <h.n> = int (h.n) p dw = 1. For it
    g(k) = int (h.k)_+ p dw has the closed form cos(theta_k) (1 + Lambda(k)) with Smith's
    Beckmann Lambda(k) = (erf(a) - 1)/2 + exp(-a^2) / (2 a sqrt(pi)), a = 1/(alpha(phi_k)
    tan theta_k), alpha(phi)^2 = a_x^2 cos^2 phi' + a_y^2 sin^2 phi' (the visible-normal
    normalisation, Heitz 2014). No numerical integration is needed and the method's
    numerical g can be tested against it. This p is *not* separable in (theta_h, phi_h): at
    the pole it cannot depend on phi, which the method's u(theta) v(phi) model cannot
    reproduce -- a realistic model mismatch.

``kind="separable"``: the paper's own separable class,

    p(h) = exp(-tan^2 theta_h / a^2) / (pi a^2 cos^4 theta_h) (1 + kappa cos 2 phi'),

    a = sqrt(a_x a_y), kappa = (a_x^2 - a_y^2) / (a_x^2 + a_y^2) (more microfacets tilted
    towards the rougher axis, like the Beckmann case); <h.n> = 1 still holds (the cos 2 phi
    term integrates to 0). g(k) is integrated numerically on a fine (0.5 deg) grid, through
    the form the cos 2 phi factor gives it: with k at azimuth phi_k, substituting
    phi_h = phi_k + psi and dropping the sin 2 psi part (odd about k's plane, so it
    integrates to 0),

    g(theta_k, phi_k) = A(theta_k) + kappa B(theta_k) cos 2(phi_k - tangent_angle),

    A, B = int (h.k0)_+ R(theta_h) {1, cos 2 psi} dw_h, k0 = (theta_k, 0), R the radial
    factor: two integrals per distinct theta_k (tabulated on a 0.25 deg grid and
    interpolated when there are many), instead of one per distinct direction.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy.special import erf

from pipeline.core.errors import ConfigError
from pipeline.data.brdf import (
    above_horizon,
    half_vector_angles,
    to_unit_vectors,
    utia_directions,
    write_utia_brdf,
)


@dataclass(frozen=True)
class SyntheticAnisotropicBRDF:
    """Anisotropic Beckmann microfacet BRDF plus a Lambertian term.

    Attributes
    ----------
    kind : {"beckmann", "separable"}
        Microfacet distribution (module docstring).
    alpha_x, alpha_y : float
        Beckmann roughness along the tangent and the bitangent (radians of slope, > 0).
    tangent_angle : float
        Azimuth (radians) of the roughness axis ``alpha_x``.
    fresnel_rs : float
        Schlick reflectance at normal incidence.
    specular_scale : tuple of 3 floats
        Per-channel factor k_s on the specular term (1 = physically normalised).
    diffuse_albedo : tuple of 3 floats
        Lambertian albedo rho_d per channel (the term is rho_d / pi).
    """

    kind: str = "beckmann"
    alpha_x: float = 0.2
    alpha_y: float = 0.45
    tangent_angle: float = 0.0
    fresnel_rs: float = 0.05
    specular_scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    diffuse_albedo: tuple[float, float, float] = (0.5, 0.3, 0.15)

    def __post_init__(self) -> None:
        if self.kind not in ("beckmann", "separable"):
            raise ConfigError(f"kind={self.kind!r} must be 'beckmann' or 'separable'")
        if not (self.alpha_x > 0 and self.alpha_y > 0):
            raise ConfigError(
                f"alpha_x={self.alpha_x}, alpha_y={self.alpha_y}: roughness must be > 0"
            )
        if not 0.0 <= self.fresnel_rs <= 1.0:
            raise ConfigError(f"fresnel_rs={self.fresnel_rs} must lie in [0, 1]")
        if len(self.specular_scale) != 3 or len(self.diffuse_albedo) != 3:
            raise ConfigError(
                f"specular_scale={self.specular_scale} and diffuse_albedo="
                f"{self.diffuse_albedo} need 3 channels each"
            )

    def distribution(self, theta_h: np.ndarray, phi_h: np.ndarray) -> np.ndarray:
        """Microfacet density p(h) per unit solid angle at the polar and azimuthal angles
        ``theta_h``, ``phi_h`` (radians, same shape) of the microfacet normal; 0 below the
        horizon."""
        theta_h = np.asarray(theta_h, dtype=np.float64)
        cos_t = np.cos(theta_h)
        above = cos_t > 1e-12
        safe_cos = np.where(above, cos_t, 1.0)
        tan2 = np.where(above, np.tan(np.where(above, theta_h, 0.0)) ** 2, 0.0)
        phi = np.asarray(phi_h, dtype=np.float64) - self.tangent_angle
        norm = np.pi * self.alpha_x * self.alpha_y * safe_cos**4
        if self.kind == "beckmann":
            aniso = np.cos(phi) ** 2 / self.alpha_x**2 + np.sin(phi) ** 2 / self.alpha_y**2
            value = np.exp(-tan2 * aniso) / norm
        else:
            kappa = (self.alpha_x**2 - self.alpha_y**2) / (self.alpha_x**2 + self.alpha_y**2)
            radial = np.exp(-tan2 / (self.alpha_x * self.alpha_y)) / norm
            value = radial * (1.0 + kappa * np.cos(2.0 * phi))
        return np.where(above, value, 0.0)

    def g(self, directions: np.ndarray) -> np.ndarray:
        """g(k) = int (h.k)_+ p(h) dw_h, shape (n,), at ``directions`` (n, 2) ``(theta, phi)``
        with theta in [0, pi/2): the closed form cos(theta_k)(1 + Lambda(k)) for Beckmann,
        from two tabulated harmonics for ``kind="separable"`` (module docstring)."""
        directions = np.asarray(directions, dtype=np.float64).reshape(-1, 2)
        if self.kind == "separable":
            return self._numeric_g(directions)
        theta, phi = directions[:, 0], directions[:, 1] - self.tangent_angle
        alpha = np.sqrt(self.alpha_x**2 * np.cos(phi) ** 2 + self.alpha_y**2 * np.sin(phi) ** 2)
        tan_t = np.tan(theta)
        # a -> infinity at normal incidence, where Lambda -> 0; avoid dividing by zero.
        a = np.where(tan_t > 1e-12, 1.0 / (alpha * np.maximum(tan_t, 1e-12)), np.inf)
        finite_a = np.where(np.isfinite(a), a, 1.0)
        lam = np.where(
            np.isfinite(a),
            (erf(finite_a) - 1.0) / 2.0
            + np.exp(-(finite_a**2)) / (2.0 * finite_a * np.sqrt(np.pi)),
            0.0,
        )
        return np.cos(theta) * (1.0 + lam)

    def _numeric_g(self, directions: np.ndarray) -> np.ndarray:
        """g for ``kind="separable"`` from its two polar harmonics (module docstring)."""
        theta, phi = directions[:, 0], directions[:, 1] - self.tangent_angle
        kappa = (self.alpha_x**2 - self.alpha_y**2) / (self.alpha_x**2 + self.alpha_y**2)
        unique, inverse = np.unique(np.round(theta, 10), return_inverse=True)
        if unique.size <= _G_TABLE_NODES.size:
            a, b = _separable_g_harmonics(unique, self.alpha_x * self.alpha_y)
            a, b = a[inverse.ravel()], b[inverse.ravel()]
        else:  # dense queries (renders): A and B are smooth in theta_k
            table_a, table_b = _separable_g_table(self.alpha_x * self.alpha_y)
            a = np.interp(theta, _G_TABLE_NODES, table_a)
            b = np.interp(theta, _G_TABLE_NODES, table_b)
        return a + kappa * b * np.cos(2.0 * phi)

    def specular(self, light: np.ndarray, view: np.ndarray) -> np.ndarray:
        """Specular BRDF of shape (n, 3) at light/view pairs of shape (n, 2); 0 below horizon."""
        light = np.asarray(light, dtype=np.float64).reshape(-1, 2)
        view = np.asarray(view, dtype=np.float64).reshape(-1, 2)
        above = above_horizon(light, view)
        theta_h, phi_h, cos_kh = half_vector_angles(light, view)
        fresnel = self.fresnel_rs + (1.0 - self.fresnel_rs) * (1.0 - cos_kh) ** 5
        g1 = self.g(np.where(above[:, None], light, 0.0))
        g2 = self.g(np.where(above[:, None], view, 0.0))
        # <h.n> = 1 for this normalisation of p.
        value = self.distribution(theta_h, phi_h) * fresnel / (4.0 * g1 * g2)
        value = np.where(above, value, 0.0)
        return value[:, None] * np.asarray(self.specular_scale)[None, :]

    def diffuse(self, light: np.ndarray, view: np.ndarray) -> np.ndarray:
        """Lambertian BRDF rho_d / pi of shape (n, 3); 0 below the horizon."""
        light = np.asarray(light, dtype=np.float64).reshape(-1, 2)
        view = np.asarray(view, dtype=np.float64).reshape(-1, 2)
        above = above_horizon(light, view)
        return above[:, None] * (np.asarray(self.diffuse_albedo)[None, :] / np.pi)

    def evaluate(self, light: np.ndarray, view: np.ndarray) -> np.ndarray:
        """Full BRDF (diffuse + specular) of shape (n, 3) at pairs of shape (n, 2)."""
        return self.diffuse(light, view) + self.specular(light, view)


_G_TABLE_NODES = np.deg2rad(np.linspace(0.0, 90.0, 361))  # 0.25 deg


def _separable_g_harmonics(theta: np.ndarray, alpha2: float) -> tuple[np.ndarray, np.ndarray]:
    """A(theta_k) and B(theta_k), shape (n,) each, of the separable distribution (module
    docstring) at polar angles ``theta`` (n,) of k (its azimuth taken as 0); ``alpha2`` is
    a^2 = a_x a_y of the radial factor."""
    h, solid_angle, theta_h, phi_h = _fine_hemisphere()
    cos_t = np.cos(theta_h)
    radial = np.exp(-(np.tan(theta_h) ** 2) / alpha2) / (np.pi * alpha2 * cos_t**4)
    weights = np.stack([radial, radial * np.cos(2.0 * phi_h)], axis=-1) * solid_angle[:, None]
    k = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=-1)
    out = np.empty((theta.size, 2))
    for start in range(0, theta.size, 32):  # bounds the temporary to ~33 MB
        out[start : start + 32] = np.maximum(k[start : start + 32] @ h.T, 0.0) @ weights
    return out[:, 0], out[:, 1]


@lru_cache(maxsize=4)
def _separable_g_table(alpha2: float) -> tuple[np.ndarray, np.ndarray]:
    """A and B on ``_G_TABLE_NODES`` (cached: renders query them repeatedly)."""
    return _separable_g_harmonics(_G_TABLE_NODES, alpha2)


@lru_cache(maxsize=1)
def _fine_hemisphere(n_theta: int = 180, n_phi: int = 720):
    """Midpoint grid (0.5 deg) of the upper hemisphere: vectors, solid angles, angles."""
    theta = (np.arange(n_theta) + 0.5) * (0.5 * np.pi / n_theta)
    phi = (np.arange(n_phi) + 0.5) * (2.0 * np.pi / n_phi)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    area = np.sin(t) * (0.5 * np.pi / n_theta) * (2.0 * np.pi / n_phi)
    vectors = to_unit_vectors(np.stack([t.ravel(), p.ravel()], axis=-1))
    return vectors, area.ravel(), t.ravel(), p.ravel()


def write_synthetic_utia_brdf(
    path: str | os.PathLike, brdf: SyntheticAnisotropicBRDF, missing_above_deg: float | None = None
) -> SyntheticAnisotropicBRDF:
    """Evaluate ``brdf`` on the UTIA grid, write it at ``path`` as a UTIA binary
    (atomically) and return it.

    With ``missing_above_deg``, samples whose light or view polar angle exceeds it are
    written as missing (-1), mimicking a device that cannot measure grazing directions.
    """
    light, view = utia_directions()
    measured = None
    if missing_above_deg is not None:
        if not 0.0 <= missing_above_deg <= 90.0:
            raise ConfigError(f"missing_above_deg={missing_above_deg} must lie in [0, 90]")
        limit = np.deg2rad(missing_above_deg) + 1e-9
        measured = (light[:, 0] <= limit) & (view[:, 0] <= limit)
    write_utia_brdf(Path(path), brdf.evaluate(light, view), measured)
    return brdf
