"""The Ashikhmin-Shirley lobe shared by method A's synthetic fabrics and method B's baseline
(pipeline/data/brdf_models.py), against its angle form and a numeric integral."""

import numpy as np
import pytest

from pipeline.data.brdf_models import ashikhmin_shirley_lobe, ashikhmin_shirley_normalization


def test_lobe_equals_the_angle_form_of_the_paper():
    """Catches the exponents swapped between the tangent and the bitangent, or a lobe that
    is not (n.h)^(n_u cos^2 phi + n_v sin^2 phi) with phi the half vector's azimuth from
    the tangent (Ashikhmin and Shirley 2000, eq. 4)."""
    rng = np.random.default_rng(0)
    theta, phi = rng.uniform(0.01, 1.5, 200), rng.uniform(0.0, 2 * np.pi, 200)
    n_u, n_v = 120.0, 7.0
    lobe = ashikhmin_shirley_lobe(
        np.cos(theta), np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), n_u, n_v
    )
    expected = np.cos(theta) ** (n_u * np.cos(phi) ** 2 + n_v * np.sin(phi) ** 2)
    np.testing.assert_allclose(lobe, expected, rtol=1e-10, atol=1e-300)


def test_lobe_at_the_normal_below_the_surface_and_in_float32():
    """Catches 0/0 at h = n (the lobe is 1 there), a lobe for half vectors below the
    surface, and float32 inputs widened to float64 (the fabric renderer is float32)."""
    n_dot_h = np.array([1.0, 0.0, -0.5, 0.8], np.float32)
    t_dot_h = np.array([0.0, 1.0, 0.6, 0.6], np.float32)
    b_dot_h = np.array([0.0, 0.0, 0.6, 0.0], np.float32)
    exponents = np.full(4, 50.0, np.float32)
    lobe = ashikhmin_shirley_lobe(n_dot_h, t_dot_h, b_dot_h, exponents, exponents)
    assert lobe.dtype == np.float32
    np.testing.assert_allclose(lobe, [1.0, 0.0, 0.0, 0.8**50], rtol=1e-5)


@pytest.mark.parametrize("exponent", [1.0, 20.0, 500.0])
def test_isotropic_lobe_is_a_normalized_half_vector_density(exponent):
    """Catches a wrong normalization: with n_u = n_v = n, 4 x normalization x lobe is a
    density of half vectors over the hemisphere, (n + 1) / (2 pi) cos^n, integrating to 1
    (the 4 is the half-vector Jacobian the 8 pi carries)."""
    edges = np.linspace(0.0, 0.5 * np.pi, 20_001)
    theta = 0.5 * (edges[1:] + edges[:-1])
    lobe = ashikhmin_shirley_lobe(
        np.cos(theta), np.sin(theta), np.zeros_like(theta), exponent, exponent
    )
    integral = 2 * np.pi * np.sum(lobe * np.sin(theta)) * (edges[1] - edges[0])
    total = 4 * ashikhmin_shirley_normalization(exponent, exponent) * integral
    assert total == pytest.approx(1.0, rel=1e-4)
