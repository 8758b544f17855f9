"""Image Quilting on multi-channel maps: the cut, the FFT search, the region mask."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from pipeline.core.errors import ConfigError
from pipeline.fourier.quilting import (
    OverlapSearch,
    candidate_positions,
    min_error_boundary_cut,
    quilt,
    random_tiling,
    seam_cost,
)


def _texture(rng, size=64, channels=5):
    """Smooth noise plus oriented waves in channel 0: a texture with visible structure."""
    source = gaussian_filter(rng.normal(size=(size, size, channels)), (2, 2, 0), mode="wrap")
    yy, xx = np.mgrid[:size, :size]
    source[..., 0] += 2.0 * np.sin(xx / 3.0 + np.sin(yy / 7.0))
    return source


def _brute_force_cut(cost):
    height, width = cost.shape
    best, best_path = np.inf, None
    for start in range(width):
        for moves in itertools.product((-1, 0, 1), repeat=height - 1):
            path = np.cumsum([start, *moves])
            if path.min() < 0 or path.max() >= width:
                continue
            total = cost[np.arange(height), path].sum()
            if total < best:
                best, best_path = total, path
    return best, best_path


@pytest.mark.parametrize("seed", range(5))
def test_cut_is_the_minimum_error_path(seed):
    cost = np.random.default_rng(seed).uniform(size=(5, 4))
    path = min_error_boundary_cut(cost)
    best, _ = _brute_force_cut(cost)
    assert np.all(np.abs(np.diff(path)) <= 1) and path.min() >= 0 and path.max() < 4
    assert cost[np.arange(5), path].sum() == pytest.approx(best)


def test_cut_on_hand_made_cost():
    cost = np.array([[9, 0, 9, 9], [9, 9, 0, 9], [9, 9, 9, 0], [9, 9, 0, 9]], dtype=float)
    assert min_error_boundary_cut(cost).tolist() == [1, 2, 3, 2]
    assert min_error_boundary_cut(np.ones((3, 1))).tolist() == [0, 0, 0]
    with pytest.raises(ConfigError, match="non-empty 2-D"):
        min_error_boundary_cut(np.ones(3))


def test_fft_overlap_error_matches_brute_force():
    rng = np.random.default_rng(0)
    source = rng.normal(size=(20, 17, 3))
    block, overlap = 6, 2
    search = OverlapSearch(source, block, overlap)
    template = rng.normal(size=(block, block, 3))
    for left, top in ((True, False), (False, True), (True, True)):
        mask = search.masks[left, top][..., None]
        fast = search.errors(template, left, top)
        for y, x in ((0, 0), (14, 11), (7, 3)):
            slow = (mask * (source[y : y + block, x : x + block] - template) ** 2).sum()
            assert fast[y, x] == pytest.approx(slow, rel=1e-9, abs=1e-9)


def test_candidates_lie_inside_the_region():
    mask = np.zeros((12, 12), dtype=bool)
    mask[2:8, 3:10] = True
    positions = candidate_positions(mask, 4)
    assert {tuple(p) for p in positions} == {(y, x) for y in range(2, 5) for x in range(3, 7)}
    rng = np.random.default_rng(0)
    source = rng.normal(size=(12, 12, 2))
    _, used = quilt(source, (20, 20), 4, 1, 0.2, rng, mask=mask, return_positions=True)
    assert all(mask[y : y + 4, x : x + 4].all() for y, x in used)


def test_quilt_is_reproducible_and_sized():
    source = _texture(np.random.default_rng(0), 32, 3)
    first = quilt(source, (50, 45), 12, 3, 0.1, np.random.default_rng(7))
    again = quilt(source, (50, 45), 12, 3, 0.1, np.random.default_rng(7))
    assert first.shape == (50, 45, 3)
    np.testing.assert_array_equal(first, again)


def test_quilting_copies_a_periodic_texture_seamlessly():
    # A texture periodic with the grid step: the best candidate always matches exactly.
    yy, xx = np.mgrid[:40, :40]
    source = np.stack([np.sin(2 * np.pi * xx / 8), np.cos(2 * np.pi * yy / 8)], axis=-1)
    out = quilt(source, (60, 60), 12, 4, 0.0, np.random.default_rng(0))
    # No seam anywhere: the output is itself periodic with period 8.
    np.testing.assert_allclose(out[:, 8:], out[:, :-8], atol=1e-6)
    np.testing.assert_allclose(out[8:], out[:-8], atol=1e-6)


def test_quilting_beats_random_tiling_on_seam_cost():
    source = _texture(np.random.default_rng(1))
    quilted = quilt(source, (96, 96), 16, 4, 0.1, np.random.default_rng(2))
    tiled = random_tiling(source, (96, 96), 16, 4, np.random.default_rng(2))
    quilt_cost = seam_cost(quilted, 16, 4, reference=source)
    random_cost = seam_cost(tiled, 16, 4, reference=source)
    assert quilt_cost < 0.5 * random_cost, (quilt_cost, random_cost)


def test_settings_are_checked():
    rng = np.random.default_rng(0)
    source = rng.normal(size=(16, 16, 2))
    with pytest.raises(ConfigError, match="block_size=20 exceeds the source size 16x16"):
        quilt(source, (32, 32), 20, 4, 0.1, rng)
    with pytest.raises(ConfigError, match=r"overlap must be .* got 8"):
        quilt(source, (32, 32), 8, 8, 0.1, rng)
    with pytest.raises(ConfigError, match=r"no 8x8 block lies fully inside .* \(9 pixels\)"):
        mask = np.zeros((16, 16), dtype=bool)
        mask[:3, :3] = True
        quilt(source, (32, 32), 8, 2, 0.1, rng, mask=mask)
    with pytest.raises(ConfigError, match="rng must be a numpy.random.Generator"):
        quilt(source, (32, 32), 8, 2, 0.1, 42)


@pytest.mark.slow
def test_paper_sized_quilt_runs():
    """256 x 256 from 128 x 128 x 22. Its speed is measured by the fourier_pattern job
    (metric seconds_quilting), not asserted here: timings on shared machines are noise."""
    source = _texture(np.random.default_rng(0), 128, 22)
    out = quilt(source, (256, 256), 32, 8, 0.1, np.random.default_rng(0))
    assert out.shape == (256, 256, 22)


def test_optical_pattern_end_to_end():
    """Fit, quilt each region's coefficients, render on a new shape, blend (paper §4.2)."""
    from pipeline.fourier.optical_pattern import render_optical_pattern, stripe_weights
    from pipeline.fourier.series import fit_fourier
    from pipeline.fourier.synthetic import (
        SyntheticStackConfig,
        grid_light_dirs,
        make_synthetic_scene,
    )

    config = SyntheticStackConfig(
        size=(48, 48), n_elevations=2, n_azimuths=9, azimuth_step_deg=15.0
    ).validated()
    scene = make_synthetic_scene(config)
    lights = grid_light_dirs(config)
    coeffs = fit_fourier(scene.render(lights), lights, scene.normals, M=3, lam=3.14)
    rng = np.random.default_rng(0)
    maps = []
    for label in (1, 2):  # ground, streak
        flat = coeffs.reshape(48, 48, -1)
        quilted = quilt(flat, (40, 40), 6, 2, 0.1, rng, mask=scene.regions == label)
        maps.append(quilted.reshape(40, 40, 3, -1))
    yy, xx = (np.mgrid[:40, :40] - 19.5) / 25.0  # a shallow dome as the screen object
    target = np.dstack([xx, -yy, np.ones_like(xx)])
    weights = stripe_weights((40, 40), 2, period=10, angle_deg=45, softness=1.0)
    pattern = render_optical_pattern(maps, weights, [0.3, 0.4, 0.87], target)
    assert pattern.shape == (40, 40, 3) and np.all(np.isfinite(pattern))
    # The streak stripes are redder than the ground stripes, as in the source.
    redness = pattern[..., 0] / (pattern.sum(axis=-1) + 1e-6)
    assert redness[weights[1] > 0.99].mean() > redness[weights[0] > 0.99].mean() + 0.1
