"""The built-in BRDF of method B: g of the separable class against direct integration."""

from __future__ import annotations

import numpy as np

from pipeline.brdf_map.synthetic import SyntheticAnisotropicBRDF
from pipeline.data.brdf import to_unit_vectors


def _direct_g(brdf: SyntheticAnisotropicBRDF, directions: np.ndarray) -> np.ndarray:
    """g(k) = sum of (h.k)_+ p(h) dw over the 0.5 deg midpoint grid of the hemisphere
    (the generator's own quadrature grid), each direction directly."""
    theta = (np.arange(180) + 0.5) * (0.5 * np.pi / 180)
    phi = (np.arange(720) + 0.5) * (2.0 * np.pi / 720)
    theta_h, phi_h = (a.ravel() for a in np.meshgrid(theta, phi, indexing="ij"))
    solid_angle = np.sin(theta_h) * (0.5 * np.pi / 180) * (2.0 * np.pi / 720)
    h = to_unit_vectors(np.stack([theta_h, phi_h], axis=-1))
    mass = brdf.distribution(theta_h, phi_h) * solid_angle
    return np.maximum(to_unit_vectors(directions) @ h.T, 0.0) @ mass


def test_separable_g_from_its_harmonics_matches_direct_integration():
    brdf = SyntheticAnisotropicBRDF(kind="separable", alpha_x=0.45, alpha_y=0.2, tangent_angle=0.7)
    rng = np.random.default_rng(0)
    few = np.stack([rng.uniform(0, 1.5, 12), rng.uniform(0, 2 * np.pi, 12)], -1)
    # Exact harmonics on few distinct theta; the A, B table (0.25 deg) on many.
    many = np.concatenate([few, np.stack([rng.uniform(0, 1.5, 400), np.zeros(400)], -1)])
    # The direct sum is exact on the 0.5 deg grid, the harmonics in continuous phi:
    # they differ by the grid's discretisation, ~1e-7 of g ~ 1.
    np.testing.assert_allclose(brdf.g(few), _direct_g(brdf, few), atol=1e-6)
    np.testing.assert_allclose(brdf.g(many)[:12], _direct_g(brdf, few), atol=2e-5)


def test_separable_g_is_exact_on_the_utia_directions():
    # UTIA azimuths are multiples of 7.5 deg, symmetries of the fine grid: no
    # discretisation difference, only rounding.
    brdf = SyntheticAnisotropicBRDF(kind="separable")
    theta, phi = np.meshgrid(np.deg2rad([0, 15, 45, 75]), np.deg2rad([0, 7.5, 90, 352.5]))
    directions = np.stack([theta.ravel(), phi.ravel()], -1)
    np.testing.assert_allclose(brdf.g(directions), _direct_g(brdf, directions), rtol=1e-9)
