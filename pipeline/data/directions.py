"""The 81 standard directions of UBO2003 and UTIA BTFs, the file names that encode them,
and the light and view sets of any other BTF's direction pairs.

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

Other BTFs (UBO2014's 151 x 151 directions, the built-in BTF on a Fibonacci set) sample
light and view on sets of their own. :func:`direction_sets` finds the light and the view
set of any list of (light, view) pairs, so that the chain never needs the 81-grid;
:func:`fibonacci_hemisphere` makes such a set.

File and folder names: :func:`view_folder_name`, :func:`ubo2003_file_name`,
:func:`utia_file_name`.

Examples
--------
>>> grid_81().shape
(81, 2)
>>> ubo2003_file_name(8, 0, 0, 30, 30, "jpg")
'00008 tl000 pl000 tv030 pv030.jpg'
>>> parse_ubo2003_file_name("00008 tl000 pl000 tv030 pv030.jpg")
ImageName(number=8, theta_light=0, phi_light=0, theta_view=30, phi_view=30, ext='jpg')
>>> sets = direction_sets(btf_directions([(0, 0), (30, 90)]))
>>> len(sets.lights), len(sets.views), sets.is_product()
(81, 2, True)
"""

from __future__ import annotations

import re
from os import PathLike
from pathlib import Path
from typing import NamedTuple

import numpy as np

from pipeline.core.errors import ConfigError, DataError

# (θ in degrees, number of azimuths on that ring); the azimuth step is 360 / count.
RINGS_DEGREES = ((0, 1), (15, 6), (30, 12), (45, 18), (60, 20), (75, 24))
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
    """The 81 standard directions in canonical order, shape (81, 2) int64: (θ, φ) in degrees."""
    rows = [
        (theta, step_index * (360 // count))
        for theta, count in RINGS_DEGREES
        for step_index in range(count)
    ]
    return np.array(rows, dtype=np.int64)


def grid_81() -> np.ndarray:
    """The 81 standard directions in canonical order, shape (81, 2) float64: (θ, φ) in radians."""
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
    """Canonical index (0..80) of a grid direction given in whole degrees; a KeyError for
    any other, which callers turn into an error naming the file or setting at fault."""
    return _INDEX_OF_DEGREES[(int(theta_degrees), int(phi_degrees))]


def is_grid_direction(theta_degrees: float, phi_degrees: float) -> bool:
    """Whether (θ, φ) in degrees is exactly one of the 81 grid directions."""
    if theta_degrees != int(theta_degrees) or phi_degrees != int(phi_degrees):
        return False
    return (int(theta_degrees), int(phi_degrees)) in _INDEX_OF_DEGREES


def canonical_views(views=None) -> list[tuple[int, int]]:
    """Check a list of view directions and return it as (int, int) pairs in canonical order.

    Parameters
    ----------
    views : sequence of (θ_view, φ_view) in degrees, or None
        None means all 81 views. Duplicates are dropped.

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
    """Light and view directions of a BTF's images (:func:`product_directions` of the grid
    and ``views``, which are as in :func:`canonical_views`), shape (n_views * 81, 4)."""
    view_degrees = np.array(canonical_views(views), dtype=np.float64).reshape(-1, 2)
    return product_directions(grid_81(), np.deg2rad(view_degrees))


# --- any direction set ----------------------------------------------------------------

# Two angles within this many radians are one direction in :func:`direction_sets`: far
# below any sampling step, far above the float32 rounding of angles read from a file.
SAME_DIRECTION_RADIANS = 1e-7


class DirectionSets(NamedTuple):
    """The light and view sets of a BTF's direction pairs (:func:`direction_sets`).

    Attributes
    ----------
    lights : ndarray of shape (L, 2), float64
        (θ, φ) radians of each distinct light direction, ordered by θ, then φ in [0, 2π)
        (for UBO2003 and UTIA data: the canonical order of the 81-grid).
    views : ndarray of shape (V, 2), float64
        The same for the view directions.
    light_of, view_of : ndarray of shape (N,), int64
        Index into ``lights`` (``views``) of each pair's light (view).
    """

    lights: np.ndarray
    views: np.ndarray
    light_of: np.ndarray
    view_of: np.ndarray

    def is_product(self) -> bool:
        """Whether every light appears under every view exactly once (N = L · V)."""
        pairs = self.light_of * len(self.views) + self.view_of
        return len(pairs) == len(self.lights) * len(self.views) == len(np.unique(pairs))


def _distinct_directions(angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct directions of ``angles`` (n, 2) radians, sorted by (θ, φ mod 2π), and
    the index of each row among them. φ is ignored at the normal (θ = 0), where every φ is
    one direction."""
    step = SAME_DIRECTION_RADIANS
    theta = np.round(angles[:, 0] / step).astype(np.int64)
    phi = np.round(np.mod(angles[:, 1], 2 * np.pi) / step).astype(np.int64)
    phi[(phi == round(2 * np.pi / step)) | (theta == 0)] = 0
    keys = np.column_stack([theta, phi])
    _, first, index = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    # The data's own values (the first occurrence), not the rounded keys.
    return angles[first], index.reshape(-1)


def direction_sets(directions: np.ndarray) -> DirectionSets:
    """Split (light, view) pairs into the set of light and the set of view directions.

    Parameters
    ----------
    directions : array_like of shape (N, 4)
        (θ_light, φ_light, θ_view, φ_view) in radians, any order; directions within
        :data:`SAME_DIRECTION_RADIANS` of each other (in θ and in φ) are one.

    Returns
    -------
    DirectionSets
        Whether the pairs are a full product L × V is :meth:`DirectionSets.is_product`.

    Raises
    ------
    DataError
        If ``directions`` is not of shape (N, 4), N >= 1, or holds NaN or Inf.
    """
    directions = np.asarray(directions, dtype=np.float64)
    if directions.ndim != 2 or directions.shape[1] != 4 or len(directions) == 0:
        raise DataError(f"directions must have shape (N, 4), N >= 1, not {directions.shape}")
    if not np.isfinite(directions).all():
        raise DataError("directions hold NaN or Inf values")
    lights, light_of = _distinct_directions(directions[:, :2])
    views, view_of = _distinct_directions(directions[:, 2:])
    return DirectionSets(lights, views, light_of, view_of)


def fibonacci_hemisphere(count: int, max_theta_degrees: float = 80.0) -> np.ndarray:
    """``count`` directions spread evenly (in solid angle) over a cap of the hemisphere.

    A Fibonacci spiral: point ``i`` at cos θ = 1 - (i + ½) / count · (1 - cos θ_max) and
    φ = i times the golden angle, so each point stands for an equal share of the cap's
    solid angle and no two share a ring, as the UBO2003 grid's do.

    Parameters
    ----------
    count : int, >= 3
    max_theta_degrees : float in (0, 90]
        The cap's polar radius; the outermost point lies a little inside it.

    Returns
    -------
    ndarray of shape (count, 2), float64
        (θ, φ) radians, θ increasing; φ in [0, 2π).

    Raises
    ------
    ConfigError
        For fewer than 3 directions (no triangle to interpolate in) or a cap outside
        (0, 90] degrees.

    Examples
    --------
    >>> np.degrees(fibonacci_hemisphere(4, 60.0)[:, 0]).round(1)
    array([20.4, 35.7, 46.6, 55.8])
    """
    if isinstance(count, bool) or not isinstance(count, int | np.integer) or count < 3:
        raise ConfigError(f"a Fibonacci direction set needs an integer count >= 3, not {count!r}")
    if not 0.0 < float(max_theta_degrees) <= 90.0:
        raise ConfigError(f"max_theta_degrees={max_theta_degrees!r} must lie in (0, 90]")
    cos_max = np.cos(np.radians(float(max_theta_degrees)))
    index = np.arange(count, dtype=np.float64)
    theta = np.arccos(1.0 - (index + 0.5) / count * (1.0 - cos_max))
    golden_angle = np.pi * (3.0 - np.sqrt(5.0))
    return np.column_stack([theta, np.mod(index * golden_angle, 2 * np.pi)])


def product_directions(lights: np.ndarray, views: np.ndarray) -> np.ndarray:
    """Every light under every view, view-major as the readers order a BTF's images.

    ``lights`` (L, 2) and ``views`` (V, 2) are (θ, φ) radians; the result has shape
    (V · L, 4), float64, rows (θ_light, φ_light, θ_view, φ_view), row ``v * L + l`` being
    (light ``l``, view ``v``).
    """
    lights = np.asarray(lights, dtype=np.float64).reshape(-1, 2)
    views = np.asarray(views, dtype=np.float64).reshape(-1, 2)
    return np.concatenate(
        [np.tile(lights, (len(views), 1)), np.repeat(views, len(lights), axis=0)], axis=1
    )


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
    """(θ_view, φ_view) in whole degrees from a folder name like ``tv030_pv030``; a
    DataError names a folder whose name does not follow the pattern."""
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
    """UBO2003 image name ``00008 tl000 pl000 tv030 pv030.jpg``: the running ``number``
    (0..99999; a full dataset uses 0..6560), angles in whole degrees, ``ext`` without the dot."""
    if not 0 <= number <= 99999:
        raise ConfigError(f"running number {number} does not fit five digits")
    tl, pl, tv, pv = _name_angles(theta_light, phi_light, theta_view, phi_view)
    return f"{number:05d} tl{tl:03d} pl{pl:03d} tv{tv:03d} pv{pv:03d}.{ext}"


def parse_ubo2003_file_name(path: str | PathLike) -> ImageName:
    """Running number and angles from a UBO2003 image name (the folder part is ignored); a
    DataError names a file whose name does not follow the pattern."""
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
    """Angles from a UTIA image name (the folder part is ignored); ``number`` is None. A
    DataError names a file whose name does not follow the pattern."""
    match = _UTIA_FILE_PATTERN.match(Path(path).name)
    if match is None:
        raise DataError(f"UTIA image name not of the form 'tlTTT_plPPP_tvTTT_pvPPP.ext': {path}")
    tl, pl, tv, pv = (int(group) for group in match.groups()[:4])
    return ImageName(None, tl, pl, tv, pv, match[5])
