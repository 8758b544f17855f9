"""Fourier-series BRDF fit (eq. 16, 19), RTI baselines, and optical-pattern blending."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from pipeline.core.errors import ConfigError, DataError
from pipeline.fourier.baselines import (
    fit_hsh,
    fit_ptm,
    hsh_basis,
    lambertian_normals,
    ptm_basis,
    render_hsh,
    render_ptm,
)
from pipeline.fourier.optical_pattern import (
    blend_renders,
    blob_weights,
    load_weight_map,
    render_optical_pattern,
    stripe_weights,
)
from pipeline.fourier.series import (
    design_condition,
    fit_fourier,
    fourier_features,
    fourier_penalty,
    render_fourier,
    resolve_solver,
    rms_error,
)
from pipeline.fourier.synthetic import (
    SyntheticStackConfig,
    grid_light_dirs,
    heldout_light_dirs,
    make_synthetic_scene,
)


def _lights(rng, n):
    """Random lights in the upper hemisphere, away from grazing."""
    dirs = rng.normal(size=(n, 3))
    dirs[:, 2] = np.abs(dirs[:, 2]) + 0.3
    return dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


def _normals(rng, shape):
    normals = rng.normal(scale=0.4, size=(*shape, 3))
    normals[..., 2] = 1.0
    return normals / np.linalg.norm(normals, axis=-1, keepdims=True)


@pytest.fixture
def tiny():
    rng = np.random.default_rng(0)
    return rng, _lights(rng, 24), _normals(rng, (3, 4))


# --------------------------------------------------------------------------- Fourier fit


@pytest.mark.parametrize("solver", ["normal", "svd"])
def test_fit_matches_per_pixel_lstsq(tiny, solver):
    rng, lights, normals = tiny
    M, lam = 3, 0.7
    images = rng.uniform(size=(len(lights), 3, 4, 3))
    coeffs = fit_fourier(images, lights, normals, M=M, lam=lam, solver=solver)
    features = fourier_features(lights, normals, M)  # (n, H, W, K)
    root_penalty = np.diag(np.sqrt(lam * fourier_penalty(M)))
    for row in range(3):
        for col in range(4):
            # Eq. 19 as an ordinary least-squares problem on an augmented system.
            design = np.vstack([features[:, row, col], root_penalty])
            target = np.vstack([images[:, row, col], np.zeros((2 * M + 2, 3))])
            expected, *_ = np.linalg.lstsq(design, target, rcond=None)
            np.testing.assert_allclose(coeffs[row, col], expected.T, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("solver", ["normal", "svd"])
def test_exact_recovery_without_regularization(tiny, solver):
    rng, lights, normals = tiny
    truth = rng.normal(size=(3, 4, 3, 8))  # M = 3
    images = np.einsum("nhwk,hwck->nhwc", fourier_features(lights, normals, 3), truth)
    recovered = fit_fourier(images, lights, normals, M=3, lam=0.0, solver=solver)
    np.testing.assert_allclose(recovered, truth, atol=1e-4)


def test_m_zero_is_the_diffuse_term_plus_a_constant(tiny):
    """M = 0 (allowed: pipeline.fourier.settings) is a_d cos θd + a_0 / √2, by hand: no
    term in θs, so λ has nothing to penalise, and two lights suffice (N >= 2M + 2)."""
    rng, lights, normals = tiny
    a_d, a_0 = rng.uniform(size=(3, 4, 3)), rng.uniform(size=(3, 4, 3))
    cos_d = np.einsum("hwi,ni->nhw", normals, lights / np.linalg.norm(lights, axis=1)[:, None])
    images = a_d * cos_d[..., None] + a_0 / np.sqrt(2.0)
    for lam in (0.0, 50.0):
        coeffs = fit_fourier(images, lights, normals, M=0, lam=lam)
        np.testing.assert_allclose(coeffs, np.stack([a_d, a_0], axis=-1), atol=1e-8)
    assert fit_fourier(images[:2], lights[:2], normals, M=0).shape == (3, 4, 3, 2)


def test_svd_solver_matches_lstsq_when_ill_conditioned(tiny):
    rng, lights, normals = tiny
    images = rng.uniform(size=(len(lights), 3, 4, 3))
    coeffs = fit_fourier(images, lights, normals, M=8, lam=0.0, solver="svd")
    features = fourier_features(lights, normals, 8)
    for row, col in ((0, 0), (2, 3)):
        expected, *_ = np.linalg.lstsq(features[:, row, col], images[:, row, col], rcond=None)
        np.testing.assert_allclose(coeffs[row, col], expected.T, rtol=1e-3, atol=1e-3)


def test_plain_least_squares_on_the_paper_grid_equals_lstsq():
    # Issue 18: λ = 0 on the paper's 6 x 55 light grid at M = 10, cond(A) ~ 1e12. The
    # default solver must be plain least squares there, not a truncated pseudo-inverse.
    lights = grid_light_dirs(SyntheticStackConfig().validated())
    assert lights.shape == (330, 3)
    normals = np.array([[[0.3, 0.1, 0.95], [-0.2, 0.25, 0.95]]])
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    cond, truncated = design_condition(lights, normals, 10)
    assert 1e11 < cond[0, 0] < 1e13 and not truncated[0, 0]
    # A glossy lobe plus noise: what a pixel of the synthetic pot sees.
    mirror = 2 * (lights @ normals[0, 0])[:, None] * normals[0, 0] - lights
    lobe = np.clip(mirror[:, 2], 0, 1) ** 30
    rng = np.random.default_rng(0)
    images = (0.2 * lights[:, 2] + lobe)[:, None, None, None] * np.ones((1, 1, 2, 3))
    images += rng.normal(0, 0.005, images.shape)
    features = fourier_features(lights, normals, 10)
    fitted = fit_fourier(images, lights, normals, M=10, lam=0.0)
    old = fit_fourier(images, lights, normals, M=10, lam=0.0, solver="normal")
    for col in range(2):
        expected, *_ = np.linalg.lstsq(features[:, 0, col], images[:, 0, col], rcond=None)
        scale = np.abs(expected).max()
        np.testing.assert_allclose(fitted[0, col], expected.T, rtol=0, atol=1e-6 * scale)
        # The normal equations' eigenvalue cutoff gave another (truncated) solution.
        assert np.abs(old[0, col] - expected.T).max() > 1e-2 * scale
    # λ > 0 keeps the normal equations, which the penalty conditions: same as the SVD.
    regularized = fit_fourier(images, lights, normals, M=10, lam=3.14)
    by_svd = fit_fourier(images, lights, normals, M=10, lam=3.14, solver="svd")
    np.testing.assert_allclose(regularized, by_svd, rtol=1e-6, atol=1e-9)


def test_solver_choice():
    assert resolve_solver("auto", 0.0) == "svd"
    assert resolve_solver("auto", 0.5) == "normal"
    assert resolve_solver("normal", 0.0) == "normal"
    assert resolve_solver("svd", 3.14) == "svd"
    with pytest.raises(ConfigError, match=r"solver must be one of \['auto', 'normal', 'svd'\]"):
        resolve_solver("qr", 0.0)


def test_design_condition_flags_normal_equal_to_view(tiny):
    _, lights, _ = tiny
    normals = np.array([[[0.0, 0.0, 1.0], [0.3, 0.0, 0.95]]])
    cond, truncated = design_condition(lights, normals, 2)
    # n = v: θs = θd for every light, so the a_d and a_1 columns coincide.
    assert truncated.tolist() == [[True, False]]
    assert cond[0, 1] < 1e6
    features = fourier_features(lights, normals, 2)[:, 0, 1]
    assert cond[0, 1] == pytest.approx(np.linalg.cond(features), rel=1e-6)


def test_regularization_damps_high_harmonics(tiny):
    rng, lights, normals = tiny
    M = 6
    images = rng.uniform(size=(len(lights), 3, 4, 3))
    high = [
        np.linalg.norm(fit_fourier(images, lights, normals, M=M, lam=lam)[..., 8:])
        for lam in (0.0, 0.5, 3.14, 10.0, 50.0)
    ]
    assert all(a > b for a, b in zip(high, high[1:], strict=False)), high


def test_features_follow_the_geometry():
    # Normal = view: θs is the light's polar angle, so cos θs = cos θd.
    lights = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.8, 0.6]])
    features = fourier_features(lights, np.array([[[0.0, 0.0, 1.0]]]), M=2)[:, 0, 0]
    np.testing.assert_allclose(features[:, 0], [1.0, 0.8, 0.6])
    np.testing.assert_allclose(features[:, 1], 1 / np.sqrt(2))
    np.testing.assert_allclose(features[:, 2], features[:, 0])  # cos θs
    np.testing.assert_allclose(features[:, 4], np.cos(2 * np.arccos(features[:, 0])))


def test_render_shapes_and_flat_normal(tiny):
    rng, lights, _ = tiny
    coeffs = rng.normal(size=(3, 4, 3, 6)).astype(np.float32)
    assert render_fourier(coeffs, lights[0], (0, 0, 1)).shape == (3, 4, 3)
    assert render_fourier(coeffs, lights[:5], (0, 0, 1)).shape == (5, 3, 4, 3)


def test_too_few_images_is_a_config_error(tiny):
    rng, lights, normals = tiny
    images = rng.uniform(size=(21, 3, 4, 3))
    with pytest.raises(ConfigError, match=r"M=10 needs N >= 2M \+ 2 = 22 images, got N=21"):
        fit_fourier(images, lights[:21], normals, M=10, lam=1.0)


def test_bad_inputs_are_named(tiny):
    rng, lights, normals = tiny
    images = rng.uniform(size=(24, 3, 4, 3))
    with pytest.raises(ConfigError, match="lam"):
        fit_fourier(images, lights, normals, M=2, lam=-1.0)
    with pytest.raises(ConfigError, match="23 images but 24 light"):
        fit_fourier(images[:23], lights, normals, M=2)
    with pytest.raises(ConfigError, match=r"light_dirs\[1\]"):
        fit_fourier(images[:2], [[0, 0, 1], [0, 0, 0]], normals, M=0)


def test_rms_error_with_mask():
    pred, target = np.zeros((2, 2, 2, 3)), np.zeros((2, 2, 2, 3))
    target[:, 0, 0] = 2.0
    assert rms_error(pred, target) == pytest.approx(1.0)
    assert rms_error(pred, target, mask=np.array([[True, False], [False, False]])) == 2.0


# --------------------------------------------------------------------------- baselines


def test_ptm_and_hsh_recover_their_own_models(tiny):
    rng, lights, _ = tiny
    for fit, render, basis in ((fit_ptm, render_ptm, ptm_basis), (fit_hsh, render_hsh, hsh_basis)):
        truth = rng.normal(size=(3, 4, 3, basis(lights).shape[1]))
        images = render(truth, lights)
        np.testing.assert_allclose(fit(images, lights), truth, atol=1e-4)


def test_hsh_basis_is_orthonormal_on_the_hemisphere():
    # Midpoint quadrature in (cos θ, φ): dω = d(cos θ) dφ.
    n = 400
    cos_theta = (np.arange(n) + 0.5) / n
    phi = (np.arange(2 * n) + 0.5) * np.pi / n
    c, p = np.meshgrid(cos_theta, phi, indexing="ij")
    s = np.sqrt(1 - c**2)
    basis = hsh_basis(np.stack([s * np.cos(p), s * np.sin(p), c], axis=-1).reshape(-1, 3))
    gram = basis.T @ basis * (1.0 / n) * (np.pi / n)
    np.testing.assert_allclose(gram, np.eye(9), atol=2e-3)


def test_lambertian_normals_recover_lambertian_surface(tiny):
    rng, lights, normals = tiny
    albedo = rng.uniform(0.2, 0.8, size=(3, 4, 1))
    images = albedo * np.maximum(np.einsum("hwc,nc->nhw", normals, lights), 0)[..., None]
    estimate, rho = lambertian_normals(
        np.repeat(images, 3, axis=-1), lights, drop_dark=0.0, drop_bright=0.0
    )
    lit_everywhere = np.all(np.einsum("hwc,nc->nhw", normals, lights) > 0, axis=0)
    np.testing.assert_allclose(estimate[lit_everywhere], normals[lit_everywhere], atol=1e-5)


def test_fourier_beats_baselines_on_synthetic_pot():
    config = SyntheticStackConfig(
        size=(40, 40), n_elevations=3, n_azimuths=15, azimuth_step_deg=10.0, n_heldout=5
    ).validated()
    scene = make_synthetic_scene(config)
    train_dirs = grid_light_dirs(config)
    test_dirs = heldout_light_dirs(config, np.random.default_rng(0))
    images, truth = scene.render(train_dirs), scene.render(test_dirs)
    coeffs = fit_fourier(images, train_dirs, scene.normals, M=10, lam=3.14, clamp_diffuse=True)
    fourier = rms_error(
        render_fourier(coeffs, test_dirs, scene.normals, clamp_diffuse=True), truth, scene.mask
    )
    ptm = rms_error(render_ptm(fit_ptm(images, train_dirs), test_dirs), truth, scene.mask)
    hsh = rms_error(render_hsh(fit_hsh(images, train_dirs), test_dirs), truth, scene.mask)
    assert fourier < min(ptm, hsh), (fourier, ptm, hsh)


# --------------------------------------------------------------------------- optical pattern


def test_weight_maps_sum_to_one(tmp_path):
    maps = [
        stripe_weights((20, 30), 3, period=9, angle_deg=30, softness=1.5),
        blob_weights((20, 30), 2, np.random.default_rng(0), n_blobs=4),
    ]
    grey = np.tile(np.linspace(0, 255, 30, dtype=np.uint8), (20, 1))
    Image.fromarray(grey).save(tmp_path / "grey.png")
    maps.append(load_weight_map(tmp_path / "grey.png", n_regions=2))
    Image.fromarray(np.dstack([grey, 255 - grey, np.full_like(grey, 10)])).save(
        tmp_path / "rgb.png"
    )
    maps.append(load_weight_map(tmp_path / "rgb.png"))
    for weights in maps:
        np.testing.assert_allclose(weights.sum(axis=0), 1.0, atol=1e-12)
        assert weights.min() >= 0
    assert set(np.unique(stripe_weights((4, 6), 2, period=2))) == {0.0, 1.0}


def test_weight_map_errors(tmp_path):
    np.save(tmp_path / "zero.npy", np.zeros((2, 3, 3)))
    with pytest.raises(DataError, match=r"zero.npy: every weight is zero at row 0, column 0"):
        load_weight_map(tmp_path / "zero.npy")
    with pytest.raises(ConfigError, match=r"sum to 1 .* row 1, column 2 .* sum to 0.5"):
        weights = np.full((2, 3, 4), 0.5)
        weights[0, 1, 2] = 0.0
        blend_renders(np.ones((2, 3, 4, 3)), weights)


def test_optical_pattern_blends_region_renders():
    rng = np.random.default_rng(1)
    normals = _normals(rng, (6, 8))
    red, grey = np.zeros((6, 8, 3, 4)), np.zeros((6, 8, 3, 4))
    red[..., 0, 0], grey[..., :, 0] = 1.0, 0.5  # diffuse-only materials
    weights = stripe_weights((6, 8), 2, period=4)
    light = np.array([0.3, 0.2, 0.93])
    pattern = render_optical_pattern([red, grey], weights, light, normals)
    shading = np.einsum("hwc,c->hw", normals, light / np.linalg.norm(light))
    expected = weights[0, ..., None] * [1, 0, 0] + weights[1, ..., None] * [0.5, 0.5, 0.5]
    np.testing.assert_allclose(pattern, expected * shading[..., None], atol=1e-6)
