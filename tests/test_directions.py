"""The 81-direction grid and the UBO2003 / UTIA file names that encode it."""

import numpy as np
import pytest

from pipeline.core.errors import ConfigError, DataError
from pipeline.data.directions import (
    btf_directions,
    canonical_views,
    direction_index,
    grid_81,
    grid_81_degrees,
    parse_ubo2003_file_name,
    parse_utia_file_name,
    parse_view_folder_name,
    ubo2003_file_name,
    utia_file_name,
    view_folder_name,
)


def test_grid_has_81_unique_directions_with_the_ring_counts():
    degrees = grid_81_degrees()
    assert degrees.shape == (81, 2)
    assert len({tuple(row) for row in degrees}) == 81
    thetas, counts = np.unique(degrees[:, 0], return_counts=True)
    assert dict(zip(thetas.tolist(), counts.tolist(), strict=True)) == {
        0: 1,
        15: 6,
        30: 12,
        45: 18,
        60: 20,
        75: 24,
    }


def test_grid_is_in_canonical_order_with_even_azimuth_steps():
    degrees = grid_81_degrees()
    assert (np.diff(degrees[:, 0]) >= 0).all()
    for theta, step in [(15, 60), (30, 30), (45, 20), (60, 18), (75, 15)]:
        phis = degrees[degrees[:, 0] == theta, 1]
        np.testing.assert_array_equal(phis, np.arange(0, 360, step))
    assert tuple(degrees[0]) == (0, 0)


def test_grid_81_is_the_degree_grid_in_radians():
    np.testing.assert_allclose(np.rad2deg(grid_81()), grid_81_degrees(), atol=1e-12)


def test_direction_index_inverts_the_grid():
    for index, (theta, phi) in enumerate(grid_81_degrees()):
        assert direction_index(theta, phi) == index
    with pytest.raises(KeyError):
        direction_index(15, 30)


def test_btf_directions_are_view_major_in_canonical_order():
    directions = btf_directions()
    assert directions.shape == (6561, 4)
    grid = grid_81()
    np.testing.assert_array_equal(directions[:81, :2], grid)
    np.testing.assert_array_equal(directions[:81, 2:], np.zeros((81, 2)))
    np.testing.assert_array_equal(directions[81 * 5 : 81 * 6, 2:], np.tile(grid[5], (81, 1)))
    np.testing.assert_array_equal(directions[81 * 5 : 81 * 6, :2], grid)


def test_btf_directions_puts_requested_views_in_canonical_order():
    directions = btf_directions([(75, 15), (0, 0), (75, 15)])
    assert directions.shape == (162, 4)
    np.testing.assert_allclose(np.rad2deg(directions[0, 2:]), [0, 0], atol=1e-12)
    np.testing.assert_allclose(np.rad2deg(directions[81, 2:]), [75, 15], atol=1e-12)


@pytest.mark.parametrize("bad_view", [(15, 30), (30, 30.5), (90, 0)])
def test_off_grid_view_is_a_config_error_naming_it(bad_view):
    with pytest.raises(ConfigError, match=f"theta={bad_view[0]:g}, phi={bad_view[1]:g}"):
        canonical_views([bad_view])


def test_all_6561_ubo2003_names_round_trip():
    directions_degrees = np.rint(np.rad2deg(btf_directions())).astype(int)
    for number, (tl, pl, tv, pv) in enumerate(directions_degrees):
        name = ubo2003_file_name(number, tl, pl, tv, pv, "jpg")
        assert len(name) == len("00008 tl000 pl000 tv030 pv030.jpg")
        parsed = parse_ubo2003_file_name(name)
        assert (parsed.number, parsed.theta_light, parsed.phi_light) == (number, tl, pl)
        assert (parsed.theta_view, parsed.phi_view, parsed.ext) == (tv, pv, "jpg")


def test_ubo2003_name_matches_the_published_example():
    assert ubo2003_file_name(8, 0, 0, 30, 30, "jpg") == "00008 tl000 pl000 tv030 pv030.jpg"
    assert view_folder_name(30, 30) == "tv030_pv030"


def test_all_6561_utia_names_round_trip():
    directions_degrees = np.rint(np.rad2deg(btf_directions())).astype(int)
    for tl, pl, tv, pv in directions_degrees:
        name = utia_file_name(tl, pl, tv, pv, "exr")
        parsed = parse_utia_file_name(f"{view_folder_name(tv, pv)}/{name}")
        assert parsed == (None, tl, pl, tv, pv, "exr")
    assert utia_file_name(0, 0, 0, 0, "png") == "tl000_pl000_tv000_pv000.png"


def test_all_81_view_folder_names_round_trip():
    for theta, phi in grid_81_degrees():
        assert parse_view_folder_name(view_folder_name(theta, phi)) == (theta, phi)


@pytest.mark.parametrize(
    "bad_name",
    [
        "8 tl000 pl000 tv030 pv030.jpg",  # running number not five digits
        "00008_tl000_pl000_tv030_pv030.jpg",  # underscores instead of spaces
        "00008 tl000 pl000 tv030 pv030",  # no extension
        "00008 tl00 pl000 tv030 pv030.jpg",  # two-digit angle
        "thumbs.jpg",
    ],
)
def test_unparseable_ubo2003_name_is_a_data_error_naming_it(bad_name):
    with pytest.raises(DataError, match=bad_name.replace(".", r"\.")):
        parse_ubo2003_file_name(f"/data/tv030_pv030/{bad_name}")


@pytest.mark.parametrize("bad_name", ["tl000-pl000-tv000-pv000.png", "tl000_pl000_tv000.png"])
def test_unparseable_utia_name_is_a_data_error_naming_it(bad_name):
    with pytest.raises(DataError, match=bad_name.replace(".", r"\.")):
        parse_utia_file_name(bad_name)


@pytest.mark.parametrize("bad_folder", ["tv30_pv30", "view_030_030", "tv030-pv030"])
def test_unparseable_view_folder_is_a_data_error_naming_it(bad_folder):
    with pytest.raises(DataError, match=bad_folder):
        parse_view_folder_name(f"/data/{bad_folder}")


def test_fractional_angles_cannot_be_written_into_names():
    with pytest.raises(ConfigError, match="352.5"):
        utia_file_name(0, 352.5, 0, 0)
