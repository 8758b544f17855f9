"""The 81 standard directions of UBO2003 and UTIA BTFs, and the file names that encode them.

Both databases sample light and view on the same hemisphere grid of 81 directions: rings
of constant elevation θ, each sampled at equal azimuth steps φ::

    θ =  0°:  1 direction  (φ = 0)
    θ = 15°:  6 directions (every 60°)
    θ = 30°: 12 directions (every 30°)
    θ = 45°: 18 directions (every 20°)
    θ = 60°: 20 directions (every 18°)
    θ = 75°: 24 directions (every 15°)

The *canonical order* is ring by ring (increasing θ), then increasing φ within a ring. A
BTF's 81 × 81 = 6561 images are ordered view-major: all lights of the first view, then all
lights of the second view, and so on, with views and lights each in canonical order.

All angle steps are whole degrees, so the angles written into file names are exact.

File and folder names::

    UBO2003:  tv030_pv030/00008 tl000 pl000 tv030 pv030.jpg
    UTIA:     tv000_pv000/tl000_pl000_tv000_pv000.png   (or .exr)

Examples
--------
>>> grid_81().shape
(81, 2)
>>> ubo2003_file_name(8, 0, 0, 30, 30, "jpg")
'00008 tl000 pl000 tv030 pv030.jpg'
>>> parse_ubo2003_file_name("00008 tl000 pl000 tv030 pv030.jpg")
ImageName(number=8, theta_light=0, phi_light=0, theta_view=30, phi_view=30, ext='jpg')
"""

from __future__ import annotations

import re
from os import PathLike
from pathlib import Path
from typing import NamedTuple

import numpy as np

from pipeline.core.errors import ConfigError, DataError

# (θ in degrees, number of azimuths on that ring); the azimuth step is 360 / count.
RINGS_DEGREES: tuple[tuple[int, int], ...] = (
    (0, 1),
    (15, 6),
    (30, 12),
    (45, 18),
    (60, 20),
    (75, 24),
)
N_DIRECTIONS = 81


class ImageName(NamedTuple):
    """The angles (whole degrees) written into one BTF image file name.

    ``number`` is the UBO2003 running number, ``None`` for UTIA names; ``ext`` is the
    extension without the dot, as written (not lower-cased).
    """

    number: int | None
    theta_light: int
    phi_light: int
    theta_view: int
    phi_view: int
    ext: str


def grid_81_degrees() -> np.ndarray:
    """The 81 standard directions in whole degrees, in canonical order.

    Returns
    -------
    ndarray of shape (81, 2), int64
        Rows (θ, φ) in degrees.
    """
    rows = [
        (theta, step_index * (360 // count))
        for theta, count in RINGS_DEGREES
        for step_index in range(count)
    ]
    return np.array(rows, dtype=np.int64)


def grid_81() -> np.ndarray:
    """The 81 standard directions in radians, in canonical order.

    Returns
    -------
    ndarray of shape (81, 2), float64
        Rows (θ, φ) in radians; θ is the angle from the surface normal.
    """
    return np.deg2rad(grid_81_degrees().astype(np.float64))


# Lookup (θ, φ) in whole degrees -> canonical index.
_INDEX_OF_DEGREES: dict[tuple[int, int], int] = {
    (int(theta), int(phi)): index for index, (theta, phi) in enumerate(grid_81_degrees())
}


def unit_vectors(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Angles in radians, any shape, to unit vectors of shape theta.shape + (3,)."""
    sin_theta = np.sin(theta)
    return np.stack([sin_theta * np.cos(phi), sin_theta * np.sin(phi), np.cos(theta)], axis=-1)


def direction_index(theta_degrees: int, phi_degrees: int) -> int:
    """Canonical index (0..80) of a grid direction given in whole degrees.

    Raises
    ------
    KeyError
        If (θ, φ) is not one of the 81 grid directions. Callers turn this into a
        DataError or ConfigError naming the file or setting at fault.
    """
    return _INDEX_OF_DEGREES[(int(theta_degrees), int(phi_degrees))]


def is_grid_direction(theta_degrees: float, phi_degrees: float) -> bool:
    """Whether (θ, φ) in degrees is exactly one of the 81 grid directions."""
    if theta_degrees != int(theta_degrees) or phi_degrees != int(phi_degrees):
        return False
    return (int(theta_degrees), int(phi_degrees)) in _INDEX_OF_DEGREES


def canonical_views(views=None) -> list[tuple[int, int]]:
    """Check a list of view directions (degrees) and return it in canonical order.

    Parameters
    ----------
    views : sequence of (θ_view, φ_view) in degrees, or None
        None means all 81 views. Duplicates are dropped.

    Returns
    -------
    list of (int, int)
        The views in canonical (grid) order.

    Raises
    ------
    ConfigError
        If a view is not a grid direction or is not a pair of numbers.
    """
    if views is None:
        return [(int(theta), int(phi)) for theta, phi in grid_81_degrees()]
    checked: set[tuple[int, int]] = set()
    for view in views:
        try:
            theta, phi = (float(angle) for angle in view)
        except (TypeError, ValueError):
            raise ConfigError(
                f"view {view!r} is not a pair (theta_view, phi_view) in degrees"
            ) from None
        if not is_grid_direction(theta, phi):
            raise ConfigError(
                f"view (theta={theta:g}, phi={phi:g}) degrees is not one of the 81 grid directions"
            )
        checked.add((int(theta), int(phi)))
    return sorted(checked, key=lambda view: direction_index(*view))


def btf_directions(views=None) -> np.ndarray:
    """Light and view directions of a BTF's images, view-major, in radians.

    Parameters
    ----------
    views : sequence of (θ_view, φ_view) in degrees, or None
        Restrict to these views (put in canonical order); None means all 81.

    Returns
    -------
    ndarray of shape (n_views * 81, 4), float64
        Rows (θ_light, φ_light, θ_view, φ_view); row ``v * 81 + l`` is light ``l`` (in
        canonical order) under the ``v``-th view.
    """
    view_degrees = np.array(canonical_views(views), dtype=np.float64).reshape(-1, 2)
    grid = grid_81()
    n_views = len(view_degrees)
    lights = np.tile(grid, (n_views, 1))
    view_radians = np.repeat(np.deg2rad(view_degrees), N_DIRECTIONS, axis=0)
    return np.concatenate([lights, view_radians], axis=1)


# --- names ----------------------------------------------------------------------------

_VIEW_FOLDER_PATTERN = re.compile(r"^tv(\d{3})_pv(\d{3})$")
_UBO2003_FILE_PATTERN = re.compile(
    r"^(\d{5}) tl(\d{3}) pl(\d{3}) tv(\d{3}) pv(\d{3})\.([A-Za-z0-9]+)$"
)
_UTIA_FILE_PATTERN = re.compile(r"^tl(\d{3})_pl(\d{3})_tv(\d{3})_pv(\d{3})\.([A-Za-z0-9]+)$")


def _whole_degrees(value: float, what: str) -> int:
    if value != int(value) or not 0 <= value < 1000:
        raise ConfigError(f"{what}={value!r} cannot be written as three whole-degree digits")
    return int(value)


def _name_angles(theta_light, phi_light, theta_view, phi_view) -> list[int]:
    """The four angles of an image name as whole degrees (checked)."""
    names = ("theta_light", "phi_light", "theta_view", "phi_view")
    values = (theta_light, phi_light, theta_view, phi_view)
    return [_whole_degrees(value, what) for value, what in zip(values, names, strict=True)]


def view_folder_name(theta_view: float, phi_view: float) -> str:
    """Folder of one view, shared by UBO2003 and UTIA: ``tv030_pv030``."""
    theta = _whole_degrees(theta_view, "theta_view")
    phi = _whole_degrees(phi_view, "phi_view")
    return f"tv{theta:03d}_pv{phi:03d}"


def parse_view_folder_name(path: str | PathLike) -> tuple[int, int]:
    """(θ_view, φ_view) in whole degrees from a folder name like ``tv030_pv030``.

    Raises
    ------
    DataError
        Naming the folder, if its name does not follow the pattern.
    """
    match = _VIEW_FOLDER_PATTERN.match(Path(path).name)
    if match is None:
        raise DataError(f"view folder name not of the form 'tvTTT_pvPPP': {path}")
    return int(match[1]), int(match[2])


def ubo2003_file_name(
    number: int,
    theta_light: float,
    phi_light: float,
    theta_view: float,
    phi_view: float,
    ext: str = "jpg",
) -> str:
    """UBO2003 image name: ``00008 tl000 pl000 tv030 pv030.jpg``.

    Parameters
    ----------
    number : int
        Running number, 0..99999 (a full dataset uses 0..6560).
    theta_light, phi_light, theta_view, phi_view : float
        Angles in whole degrees.
    ext : str
        Extension without the dot.
    """
    if not 0 <= number <= 99999:
        raise ConfigError(f"running number {number} does not fit five digits")
    tl, pl, tv, pv = _name_angles(theta_light, phi_light, theta_view, phi_view)
    return f"{number:05d} tl{tl:03d} pl{pl:03d} tv{tv:03d} pv{pv:03d}.{ext}"


def parse_ubo2003_file_name(path: str | PathLike) -> ImageName:
    """Running number and angles from a UBO2003 image name (the folder part is ignored).

    Raises
    ------
    DataError
        Naming the file, if its name does not follow the pattern.
    """
    match = _UBO2003_FILE_PATTERN.match(Path(path).name)
    if match is None:
        raise DataError(
            f"UBO2003 image name not of the form 'NNNNN tlTTT plPPP tvTTT pvPPP.ext': {path}"
        )
    number, tl, pl, tv, pv = (int(group) for group in match.groups()[:5])
    return ImageName(number, tl, pl, tv, pv, match[6])


def utia_file_name(
    theta_light: float, phi_light: float, theta_view: float, phi_view: float, ext: str = "png"
) -> str:
    """UTIA image name: ``tl000_pl000_tv000_pv000.png``; angles in whole degrees."""
    tl, pl, tv, pv = _name_angles(theta_light, phi_light, theta_view, phi_view)
    return f"tl{tl:03d}_pl{pl:03d}_tv{tv:03d}_pv{pv:03d}.{ext}"


def parse_utia_file_name(path: str | PathLike) -> ImageName:
    """Angles from a UTIA image name (the folder part is ignored); ``number`` is None.

    Raises
    ------
    DataError
        Naming the file, if its name does not follow the pattern.
    """
    match = _UTIA_FILE_PATTERN.match(Path(path).name)
    if match is None:
        raise DataError(f"UTIA image name not of the form 'tlTTT_plPPP_tvTTT_pvPPP.ext': {path}")
    tl, pl, tv, pv = (int(group) for group in match.groups()[:4])
    return ImageName(None, tl, pl, tv, pv, match[5])
