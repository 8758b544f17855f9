"""Readers and writers of the UTIA anisotropic and MERL isotropic BRDF layouts."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.brdf_map.synthetic import SyntheticAnisotropicBRDF, write_synthetic_utia_brdf
from pipeline.core.errors import ConfigError, DataError
from pipeline.data.brdf import (
    MERL_SCALES,
    UTIA_N_BYTES,
    MeasuredBRDF,
    half_vector_angles,
    merl_azimuths,
    merl_half_diff_angles,
    missing_mask_by_polar_angle,
    read_merl_brdf,
    read_utia_brdf,
    utia_directions,
    utia_interpolator,
    write_merl_brdf,
    write_utia_brdf,
)

N_UTIA = 6 * 48 * 6 * 48
N_MERL = 90 * 90 * 180


# ----------------------------------------------------------------------------- UTIA


def test_utia_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    reflectance = rng.random((N_UTIA, 3))
    measured = rng.random(N_UTIA) > 0.1
    path = write_utia_brdf(tmp_path / "m.bin", reflectance, measured)
    assert path.stat().st_size == UTIA_N_BYTES == 1_990_656
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left behind
    brdf = read_utia_brdf(path)
    np.testing.assert_array_equal(brdf.measured, measured)
    np.testing.assert_array_equal(brdf.reflectance[measured], reflectance[measured])
    light, view = utia_directions()
    np.testing.assert_array_equal(brdf.light, light)
    np.testing.assert_array_equal(brdf.view, view)


def test_utia_layout_by_hand(tmp_path):
    # Raw float64 [channel][theta_i][phi_i][theta_v][phi_v]: put a marker at one index.
    table = np.zeros((3, 6, 48, 6, 48))
    table[2, 4, 10, 1, 47] = 7.0
    path = tmp_path / "hand.bin"
    table.astype("<f8").tofile(path)
    brdf = read_utia_brdf(path)
    row = ((4 * 48 + 10) * 6 + 1) * 48 + 47
    assert brdf.reflectance[row, 2] == 7.0
    assert brdf.reflectance.sum() == 7.0
    np.testing.assert_allclose(np.rad2deg(brdf.light[row]), [60.0, 75.0])
    np.testing.assert_allclose(np.rad2deg(brdf.view[row]), [15.0, 352.5])


def test_utia_wrong_size_names_file_and_size(tmp_path):
    path = tmp_path / "short.bin"
    path.write_bytes(b"\0" * 800)
    with pytest.raises(DataError, match=r"short\.bin.*800 bytes"):
        read_utia_brdf(path)


def test_utia_missing_file(tmp_path):
    with pytest.raises(DataError, match="nope.bin"):
        read_utia_brdf(tmp_path / "nope.bin")


def test_utia_writer_rejects_wrong_shape(tmp_path):
    with pytest.raises(DataError, match=r"\(10, 3\)"):
        write_utia_brdf(tmp_path / "x.bin", np.zeros((10, 3)))


def test_utia_writer_refuses_what_the_reader_would(tmp_path):
    """NaN or inf where a sample is written: refused, nothing written; masked out: -1."""
    reflectance = np.full((N_UTIA, 3), 0.5)
    reflectance[[7, 9], 1] = [np.nan, np.inf]
    with pytest.raises(DataError, match=r"x\.bin holds non-finite values at 2 .*row 7"):
        write_utia_brdf(tmp_path / "x.bin", reflectance)
    assert list(tmp_path.iterdir()) == []
    measured = np.ones(N_UTIA, dtype=bool)
    measured[[7, 9]] = False
    brdf = read_utia_brdf(write_utia_brdf(tmp_path / "x.bin", reflectance, measured))
    np.testing.assert_array_equal(brdf.measured, measured)


def test_utia_file_holding_inf_or_nan_names_the_file(tmp_path):
    """A missing measurement is negative in the layout; a non-finite value is damage."""
    for value, offset in ((np.inf, 0), (-np.inf, N_UTIA * 3 - 1), (np.nan, 12345)):
        raw = np.full(N_UTIA * 3, 0.25)
        raw[offset] = value
        path = tmp_path / "damaged.bin"
        raw.astype("<f8").tofile(path)
        with pytest.raises(
            DataError, match=rf"damaged\.bin holds 1 non-finite .*byte {8 * offset}"
        ):
            read_utia_brdf(path)


def test_utia_interpolator_nodes_holes_and_range():
    light, view = utia_directions()
    values = np.stack([light[:, 0], light[:, 1], view[:, 1]], axis=-1)  # a known function
    measured = np.ones(N_UTIA, bool)
    measured[0] = False  # theta_i = theta_v = 0, phi_i = phi_v = 0
    lookup = utia_interpolator(MeasuredBRDF(values, light, view, measured))
    rows = np.array([5, 1000, 70000])
    np.testing.assert_allclose(lookup(light[rows], view[rows]), values[rows])
    assert np.all(np.isnan(lookup(light[:1], view[:1])))
    # Above 75 deg nothing was measured: no value.
    assert np.all(np.isnan(lookup(np.array([[np.deg2rad(80), 0.0]]), view[5:6])))
    # Between phi = 352.5 and 360 (= 0) deg the azimuth wraps around.
    mid = lookup(np.array([[np.deg2rad(30), np.deg2rad(356.25)]]), np.array([[0.5, 1.0]]))
    assert np.isfinite(mid).all()


def test_utia_interpolator_rejects_other_layouts():
    brdf = MeasuredBRDF(np.zeros((4, 3)), np.zeros((4, 2)), np.zeros((4, 2)), np.ones(4, bool))
    with pytest.raises(DataError, match="4 samples"):
        utia_interpolator(brdf)


# ----------------------------------------------------------------------------- MERL


def test_merl_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    reflectance = rng.random((N_MERL, 3))
    measured = rng.random(N_MERL) > 0.2
    path = write_merl_brdf(tmp_path / "m.binary", reflectance, measured)
    brdf = read_merl_brdf(path)
    np.testing.assert_array_equal(brdf.measured, measured)
    np.testing.assert_allclose(brdf.reflectance[measured], reflectance[measured], rtol=1e-12)
    assert brdf.half_diff.shape == (N_MERL, 3)


def test_merl_layout_by_hand(tmp_path):
    # Header (90, 90, 180), then R, G, B blocks indexed phi_d + 180 (theta_d + 90 theta_h).
    i_h, i_d, i_p = 30, 20, 45
    index = i_p + 180 * (i_d + 90 * i_h)
    blocks = np.zeros((3, N_MERL))
    blocks[1, index] = 1500.0
    path = tmp_path / "hand.binary"
    path.write_bytes(np.array([90, 90, 180], "<i4").tobytes() + blocks.astype("<f8").tobytes())
    brdf = read_merl_brdf(path)
    assert brdf.reflectance[index, 1] == pytest.approx(1500.0 * MERL_SCALES[1])  # 1.15
    theta_h, theta_d, phi_d = brdf.half_diff[index]
    assert 90 * np.sqrt(theta_h / (np.pi / 2)) == pytest.approx(i_h)
    assert theta_d / (np.pi / 2) * 90 == pytest.approx(i_d)
    assert phi_d / np.pi * 180 == pytest.approx(i_p)


def test_merl_directions_reproduce_half_angle():
    half_diff = merl_half_diff_angles()[::997]  # a spread-out subset keeps this fast
    from pipeline.data.brdf import half_diff_to_directions, to_unit_vectors

    light, view = half_diff_to_directions(half_diff)
    k1, k2 = to_unit_vectors(light), to_unit_vectors(view)
    h = (k1 + k2) / np.linalg.norm(k1 + k2, axis=-1, keepdims=True)
    np.testing.assert_allclose(np.arccos(np.clip(h[:, 2], -1, 1)), half_diff[:, 0], atol=1e-6)
    np.testing.assert_allclose(
        np.arccos(np.sum(k1 * h, -1).clip(-1, 1)), half_diff[:, 1], atol=1e-6
    )
    # phi_h = 0: the half vector lies in the x-z plane.
    np.testing.assert_allclose(h[:, 1], 0.0, atol=1e-9)


def test_merl_wrong_header(tmp_path):
    path = tmp_path / "bad.binary"
    path.write_bytes(np.array([90, 90, 90], "<i4").tobytes() + b"\0" * 64)
    with pytest.raises(DataError, match=r"bad\.binary.*\(90, 90, 90\)"):
        read_merl_brdf(path)


def test_merl_wrong_size(tmp_path):
    path = tmp_path / "cut.binary"
    path.write_bytes(np.array([90, 90, 180], "<i4").tobytes() + b"\0" * 64)
    with pytest.raises(DataError, match=r"cut\.binary.*76 bytes"):
        read_merl_brdf(path)


# ----------------------------------------------------------------------------- masks, data


def test_missing_mask_by_polar_angle():
    light, view = utia_directions()
    brdf = MeasuredBRDF(np.zeros((N_UTIA, 3)), light, view, np.ones(N_UTIA, bool))
    masked = missing_mask_by_polar_angle(brdf, 60.0)
    assert masked.measured.mean() == pytest.approx((5 / 6) ** 2)  # theta = 75 deg removed
    grazing = (light[:, 0] > np.deg2rad(61)) | (view[:, 0] > np.deg2rad(61))
    np.testing.assert_array_equal(masked.measured, ~grazing)
    assert brdf.measured.all()  # the input is not modified


def test_missing_mask_rejects_bad_threshold():
    brdf = MeasuredBRDF(np.zeros((1, 3)), np.zeros((1, 2)), np.zeros((1, 2)), np.ones(1, bool))
    with pytest.raises(ConfigError, match="120"):
        missing_mask_by_polar_angle(brdf, 120.0)


def test_measured_brdf_checks_shapes():
    with pytest.raises(DataError, match="view has shape"):
        MeasuredBRDF(np.zeros((3, 3)), np.zeros((3, 2)), np.zeros((2, 2)), np.ones(3, bool))


def test_half_vector_of_mirror_pair_is_the_normal():
    light = np.array([[np.deg2rad(40), 0.3]])
    view = np.array([[np.deg2rad(40), 0.3 + np.pi]])
    theta_h, _, cos_kh = half_vector_angles(light, view)
    assert theta_h[0] == pytest.approx(0.0, abs=1e-7)
    assert cos_kh[0] == pytest.approx(np.cos(np.deg2rad(40)))


def test_synthetic_utia_file_holds_the_ground_truth(tmp_path):
    truth = SyntheticAnisotropicBRDF(alpha_x=0.25, alpha_y=0.5)
    path = tmp_path / "syn.bin"
    write_synthetic_utia_brdf(path, truth, missing_above_deg=60.0)
    brdf = read_utia_brdf(path)
    assert brdf.measured.mean() == pytest.approx((5 / 6) ** 2)
    expected = truth.evaluate(brdf.light, brdf.view)
    np.testing.assert_allclose(brdf.reflectance[brdf.measured], expected[brdf.measured])
    assert list(tmp_path.iterdir()) == [path]


def test_merl_azimuths_are_spread_evenly():
    phi_h = merl_azimuths(90 * 180)  # one theta_h row of the table
    assert phi_h.min() >= 0.0 and phi_h.max() < 2 * np.pi
    counts = np.bincount((phi_h / (2 * np.pi) * 96).astype(int), minlength=96)
    assert counts.min() >= 165 and counts.max() <= 173  # 16200 / 96 = 168.75 per cell


def test_merl_reader_places_entries_at_their_azimuths(tmp_path):
    reflectance = np.ones((N_MERL, 3))
    brdf = read_merl_brdf(write_merl_brdf(tmp_path / "m.binary", reflectance))
    light, view = brdf.light[::991], brdf.view[::991]
    theta_h, phi_h, cos_kh = half_vector_angles(light, view)
    half_diff = brdf.half_diff[::991]
    np.testing.assert_allclose(theta_h, half_diff[:, 0], atol=1e-6)
    np.testing.assert_allclose(np.arccos(cos_kh), half_diff[:, 1], atol=1e-6)
    expected = merl_azimuths(N_MERL)[::991]
    off_pole = theta_h > 1e-3  # the half vector's azimuth is undefined at the normal
    np.testing.assert_allclose(np.angle(np.exp(1j * (phi_h - expected)))[off_pole], 0.0, atol=1e-6)
    # spread_azimuths=False keeps the table's own frame: every half vector at phi_h = 0.
    plain = read_merl_brdf(tmp_path / "m.binary", spread_azimuths=False)
    _, phi_plain, _ = half_vector_angles(plain.light[::991], plain.view[::991])
    np.testing.assert_allclose(np.sin(phi_plain[off_pole]), 0.0, atol=1e-9)
