"""Measured BRDFs: an in-memory container, direction geometry, and the two real file layouts.

Conventions
-----------
A direction is ``(theta, phi)`` in radians in the local surface frame: ``theta`` is the
polar angle from the normal ``n = (0, 0, 1)``, ``phi`` the azimuth from the tangent
``t = (1, 0, 0)`` towards the bitangent ``b = (0, 1, 0)``. Reflectance is linear RGB BRDF
values (1/sr).

UTIA anisotropic BRDF ("Dense BRDF Measurements")
    Raw little-endian float64, no header, indexed ``[channel 3][theta_i 6][phi_i 48]
    [theta_v 6][phi_v 48]``, theta = 0, 15, ..., 75 deg, phi = 0, 7.5, ..., 352.5 deg,
    1,990,656 bytes. **Scaling chosen here: raw values.** Loaders in the wild disagree (some
    multiply by 1/140 and apply an sRGB curve); we apply neither, so the values stay linear
    and a user who wants a different absolute scale multiplies afterwards. Negative values
    are read as missing measurements (the writer writes -1); a NaN or an infinity is
    refused, naming the file: the layout holds none, so one means a damaged file or one
    in another layout (big-endian, float32).

MERL isotropic BRDF
    int32 header ``(90, 90, 180)``, then three 90*90*180 float64 blocks (R, G, B), index
    ``phi_d + 180 * (theta_d + 90 * theta_h)``, theta_h index ``floor(90 sqrt(theta_h /
    (pi/2)))``, theta_d index ``floor(theta_d / (pi/2) * 90)``, phi_d index
    ``floor(phi_d / pi * 180)``; channel scales 1/1500, 1.15/1500, 1.66/1500; negative means
    missing. The reader places each value at the lower edge of its index cell (the angles
    the index formula maps exactly back to) and, the table having no phi_h axis, at an
    azimuth phi_h of its own (:func:`read_merl_brdf`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import RegularGridInterpolator

from pipeline.core.errors import ConfigError, DataError
from pipeline.core.files import write_atomic
from pipeline.data.directions import unit_vectors

UTIA_THETA_DEG = np.arange(6) * 15.0
UTIA_PHI_DEG = np.arange(48) * 7.5
UTIA_SHAPE = (3, 6, 48, 6, 48)
UTIA_N_BYTES = int(np.prod(UTIA_SHAPE)) * 8  # 1,990,656

MERL_DIMS = (90, 90, 180)
MERL_SCALES = np.array([1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0])
MERL_N_BYTES = 3 * 4 + 3 * int(np.prod(MERL_DIMS)) * 8


@dataclass
class MeasuredBRDF:
    """Reflectance samples at pairs of directions.

    Attributes
    ----------
    reflectance : ndarray of shape (n, 3)
        Linear RGB BRDF values; the value at a missing sample is meaningless (0 here).
    light : ndarray of shape (n, 2)
        Light (incident) directions ``(theta, phi)`` in radians.
    view : ndarray of shape (n, 2)
        View (outgoing) directions ``(theta, phi)`` in radians.
    measured : ndarray of shape (n,), bool
        True where the sample was measured.
    half_diff : ndarray of shape (n, 3) or None
        ``(theta_h, theta_d, phi_d)`` of each sample for half/difference-indexed data (MERL).
    source : str
        Where the data came from (a path or a generator name), for messages.
    """

    reflectance: np.ndarray
    light: np.ndarray
    view: np.ndarray
    measured: np.ndarray
    half_diff: np.ndarray | None = None
    source: str = "<memory>"

    def __post_init__(self) -> None:
        self.reflectance = np.asarray(self.reflectance, dtype=np.float64)
        self.light = np.asarray(self.light, dtype=np.float64)
        self.view = np.asarray(self.view, dtype=np.float64)
        self.measured = np.asarray(self.measured, dtype=bool)
        if self.half_diff is not None:
            self.half_diff = np.asarray(self.half_diff, dtype=np.float64)
        n = self.reflectance.shape[0] if self.reflectance.ndim == 2 else -1
        if self.reflectance.ndim != 2 or self.reflectance.shape[1] != 3:
            raise DataError(
                f"{self.source}: reflectance has shape {self.reflectance.shape}, expected (n, 3)"
            )
        expected = {"light": (n, 2), "view": (n, 2), "measured": (n,), "half_diff": (n, 3)}
        for name, shape in expected.items():
            value = getattr(self, name)
            if value is not None and value.shape != shape:
                raise DataError(f"{self.source}: {name} has shape {value.shape}, expected {shape}")

    @property
    def n_samples(self) -> int:
        """Number of direction pairs, measured or not."""
        return int(self.reflectance.shape[0])


# ----------------------------------------------------------------------------- geometry


def to_unit_vectors(directions: np.ndarray) -> np.ndarray:
    """Convert ``(theta, phi)`` directions of shape (..., 2) to unit vectors (..., 3)."""
    directions = np.asarray(directions, dtype=np.float64)
    return unit_vectors(directions[..., 0], directions[..., 1])


def to_angles(vectors: np.ndarray) -> np.ndarray:
    """Convert unit vectors of shape (..., 3) to ``(theta, phi)`` with phi in [0, 2 pi)."""
    vectors = np.asarray(vectors, dtype=np.float64)
    theta = np.arccos(np.clip(vectors[..., 2], -1.0, 1.0))
    phi = np.mod(np.arctan2(vectors[..., 1], vectors[..., 0]), 2.0 * np.pi)
    return np.stack([theta, phi], axis=-1)


def above_horizon(light: np.ndarray, view: np.ndarray) -> np.ndarray:
    """Whether both directions of each pair lie above the horizon: (n, 2) each to (n,) bool."""
    return (light[:, 0] < 0.5 * np.pi) & (view[:, 0] < 0.5 * np.pi)


def half_vector_angles(light: np.ndarray, view: np.ndarray) -> tuple[np.ndarray, ...]:
    """Half vector of light/view pairs.

    Parameters
    ----------
    light, view : ndarray of shape (n, 2)
        Directions ``(theta, phi)`` in radians.

    Returns
    -------
    theta_h, phi_h : ndarray of shape (n,)
        Polar and azimuthal angle of the half vector (phi_h in [0, 2 pi)).
    cos_kh : ndarray of shape (n,)
        ``k . h`` (the same for k = light and k = view), the Fresnel argument.
    """
    k1, k2 = to_unit_vectors(light), to_unit_vectors(view)
    h = k1 + k2
    norm = np.linalg.norm(h, axis=-1, keepdims=True)
    # Exactly opposite directions have no half vector; the normal is as good as any.
    h = np.where(norm > 1e-12, h / np.maximum(norm, 1e-12), np.array([0.0, 0.0, 1.0]))
    angles = to_angles(h)
    cos_kh = np.clip(np.sum(k1 * h, axis=-1), 0.0, 1.0)
    return angles[..., 0], angles[..., 1], cos_kh


def missing_mask_by_polar_angle(brdf: MeasuredBRDF, max_theta_deg: float) -> MeasuredBRDF:
    """A copy of ``brdf`` in which every sample whose light or view polar angle exceeds
    ``max_theta_deg`` (degrees, in [0, 90]) is missing too, as for a device that cannot
    reach grazing directions."""
    if not np.isfinite(max_theta_deg) or not 0.0 <= max_theta_deg <= 90.0:
        raise ConfigError(f"max_theta_deg={max_theta_deg} must lie in [0, 90]")
    # A small slack keeps a grid angle that equals the threshold (e.g. 60 deg) measured.
    limit = np.deg2rad(max_theta_deg) + 1e-9
    keep = (brdf.light[:, 0] <= limit) & (brdf.view[:, 0] <= limit)
    return MeasuredBRDF(
        reflectance=brdf.reflectance.copy(),
        light=brdf.light.copy(),
        view=brdf.view.copy(),
        measured=brdf.measured & keep,
        half_diff=None if brdf.half_diff is None else brdf.half_diff.copy(),
        source=brdf.source,
    )


# ----------------------------------------------------------------------------- UTIA


def utia_directions() -> tuple[np.ndarray, np.ndarray]:
    """Light and view directions of the UTIA layout, in file order.

    Returns
    -------
    light, view : ndarray of shape (82944, 2)
        ``(theta, phi)`` in radians, ordered ``[theta_i][phi_i][theta_v][phi_v]``.
    """
    theta = np.deg2rad(UTIA_THETA_DEG)
    phi = np.deg2rad(UTIA_PHI_DEG)
    ti, pi_, tv, pv = np.meshgrid(theta, phi, theta, phi, indexing="ij")
    light = np.stack([ti.ravel(), pi_.ravel()], axis=-1)
    view = np.stack([tv.ravel(), pv.ravel()], axis=-1)
    return light, view


def read_utia_brdf(path: str | os.PathLike) -> MeasuredBRDF:
    """Read a UTIA anisotropic BRDF ``.bin`` (raw values, see the module docstring).

    Returns
    -------
    MeasuredBRDF
        82944 samples in file order; negative values are marked missing.

    Raises
    ------
    DataError
        Naming the file, when it is missing, has the wrong size or holds a NaN or an
        infinity (with how many and the byte offset of the first).
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"UTIA BRDF file {path} does not exist")
    size = path.stat().st_size
    if size != UTIA_N_BYTES:
        raise DataError(
            f"UTIA BRDF file {path} has {size} bytes, expected {UTIA_N_BYTES} "
            f"(float64 [3][6][48][6][48])"
        )
    raw = np.fromfile(path, dtype="<f8")
    bad = np.flatnonzero(~np.isfinite(raw))
    if bad.size:  # not a missing sample (those are negative): a damaged file
        raise DataError(
            f"UTIA BRDF file {path} holds {bad.size} non-finite values (the first, "
            f"{raw[bad[0]]}, at byte {8 * bad[0]}); a missing measurement is negative in "
            f"this layout, so the file is damaged or in another layout"
        )
    reflectance = raw.reshape(3, -1).T.copy()
    measured = np.all(reflectance >= 0.0, axis=1)
    reflectance[~measured] = 0.0
    light, view = utia_directions()
    return MeasuredBRDF(reflectance, light, view, measured, source=str(path))


def _checked(reflectance, measured, n: int, layout: str):
    """``reflectance`` as float64 (n, 3) and ``measured`` as bool (n,) or None, checked."""
    reflectance = np.asarray(reflectance, dtype=np.float64)
    if reflectance.shape != (n, 3):
        raise DataError(f"{layout} reflectance has shape {reflectance.shape}, expected ({n}, 3)")
    if measured is not None:
        measured = np.asarray(measured, dtype=bool)
        if measured.shape != (n,):
            raise DataError(f"{layout} measured mask has shape {measured.shape}, expected ({n},)")
    return reflectance, measured


def _write(path, payload: bytes) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_atomic(path, payload)


def write_utia_brdf(
    path: str | os.PathLike, reflectance: np.ndarray, measured: np.ndarray | None = None
) -> Path:
    """Write reflectance in UTIA file order as a UTIA binary (atomically); return ``path``.

    Parameters
    ----------
    reflectance : ndarray of shape (82944, 3)
        Linear RGB values ordered as :func:`utia_directions`.
    measured : ndarray of shape (82944,), bool, optional
        Missing samples are written as -1.

    Raises
    ------
    DataError
        For a wrong shape, or a NaN or an infinity among the samples written (which
        :func:`read_utia_brdf` would refuse); nothing is written then.
    """
    reflectance, measured = _checked(reflectance, measured, int(np.prod(UTIA_SHAPE[1:])), "UTIA")
    values = reflectance.copy()
    if measured is not None:
        values[~measured] = -1.0
    bad = np.flatnonzero(~np.all(np.isfinite(values), axis=1))
    if bad.size:
        raise DataError(
            f"UTIA reflectance for {path} holds non-finite values at {bad.size} measured "
            f"samples (the first: row {bad[0]}); mark missing samples with `measured`"
        )
    return _write(path, np.ascontiguousarray(values.T).astype("<f8").tobytes())


def utia_interpolator(brdf: MeasuredBRDF):
    """Multilinear interpolation of UTIA-layout data, undefined (NaN) where data is missing.

    Mirrors eq. 22 of the paper: inside the measured range a linearly interpolated value,
    outside it (theta above 75 deg, or a missing neighbour) no value. ``brdf`` holds the
    82944 samples in UTIA file order (:func:`read_utia_brdf`); the result is a callable
    ``lookup(light (n, 2), view (n, 2)) -> ndarray (n, 3)``.
    """
    n = int(np.prod(UTIA_SHAPE[1:]))
    if brdf.n_samples != n:
        raise DataError(f"{brdf.source}: {brdf.n_samples} samples, UTIA layout needs {n}")
    table = np.where(brdf.measured[:, None], brdf.reflectance, np.nan)
    table = table.reshape(6, 48, 6, 48, 3)
    # Periodic azimuth: repeat phi = 0 at phi = 360 so that interpolation wraps around.
    table = np.concatenate([table, table[:, :1]], axis=1)
    table = np.concatenate([table, table[:, :, :, :1]], axis=3)
    theta = np.deg2rad(UTIA_THETA_DEG)
    phi = np.deg2rad(np.append(UTIA_PHI_DEG, 360.0))
    interp = RegularGridInterpolator(
        (theta, phi, theta, phi), table, method="linear", bounds_error=False, fill_value=np.nan
    )

    def lookup(light: np.ndarray, view: np.ndarray) -> np.ndarray:
        light = np.asarray(light, dtype=np.float64).reshape(-1, 2)
        view = np.asarray(view, dtype=np.float64).reshape(-1, 2)
        points = np.concatenate([light, view], axis=1)
        points[:, 1::2] = np.mod(points[:, 1::2], 2 * np.pi)
        return interp(points)

    return lookup


# ----------------------------------------------------------------------------- MERL


def merl_half_diff_angles() -> np.ndarray:
    """``(theta_h, theta_d, phi_d)`` of every MERL table entry, in file order.

    Returns
    -------
    ndarray of shape (1458000, 3)
        Radians; the lower edge of each index cell (theta_h index i maps to
        ``(i / 90)**2 * pi / 2``).
    """
    i_h, i_d, i_p = np.meshgrid(
        np.arange(MERL_DIMS[0]), np.arange(MERL_DIMS[1]), np.arange(MERL_DIMS[2]), indexing="ij"
    )
    theta_h = (i_h.ravel() / 90.0) ** 2 * (np.pi / 2.0)
    theta_d = i_d.ravel() * (np.pi / 2.0) / 90.0
    phi_d = i_p.ravel() * np.pi / 180.0
    return np.stack([theta_h, theta_d, phi_d], axis=-1)


def merl_azimuths(n: int) -> np.ndarray:
    """Half-vector azimuths phi_h, shape (n,), radians, for ``n`` isotropic samples.

    The golden-ratio (Weyl) sequence ``phi_h[k] = 2 pi frac(k / golden)``: deterministic,
    equidistributed over [0, 2 pi) on every run of consecutive indices, and not aligned with
    the MERL table's (theta_d, phi_d) axes (an index stride like ``k mod n_phi`` would tie
    phi_h to phi_d, since the table index is ``phi_d + 180 (theta_d + 90 theta_h)``).
    """
    golden = 0.5 * (np.sqrt(5.0) - 1.0)
    return 2.0 * np.pi * np.mod(np.arange(n, dtype=np.float64) * golden, 1.0)


def half_diff_to_directions(
    half_diff: np.ndarray, phi_h: np.ndarray | float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Rusinkiewicz half/difference angles to light and view directions.

    Parameters
    ----------
    half_diff : ndarray of shape (n, 3)
        ``(theta_h, theta_d, phi_d)`` in radians.
    phi_h : float or ndarray of shape (n,), optional
        Azimuth of the half vector (default 0): both directions are rotated by it about
        the normal, which leaves theta_h, theta_d and phi_d unchanged.

    Returns
    -------
    light, view : ndarray of shape (n, 2)
        ``(theta, phi)``; theta may exceed pi/2 (below the horizon) for some entries.
    """
    theta_h, theta_d, phi_d = half_diff[:, 0], half_diff[:, 1], half_diff[:, 2]
    diff = unit_vectors(theta_d, phi_d)
    # Rotate the difference vector about the bitangent by theta_h (phi_h = 0 needs no
    # rotation about the normal); that maps the half-vector frame to the surface frame.
    c, s = np.cos(theta_h), np.sin(theta_h)
    light = np.stack(
        [c * diff[:, 0] + s * diff[:, 2], diff[:, 1], -s * diff[:, 0] + c * diff[:, 2]], axis=-1
    )
    half = np.stack([s, np.zeros_like(s), c], axis=-1)
    view = 2.0 * np.sum(light * half, axis=-1, keepdims=True) * half - light
    light, view = to_angles(light), to_angles(view)
    # Rotating about the normal adds phi_h to both azimuths (theta is unchanged).
    light[:, 1] = np.mod(light[:, 1] + phi_h, 2.0 * np.pi)
    view[:, 1] = np.mod(view[:, 1] + phi_h, 2.0 * np.pi)
    return light, view


def read_merl_brdf(path: str | os.PathLike, spread_azimuths: bool = True) -> MeasuredBRDF:
    """Read a MERL isotropic BRDF ``.binary``.

    Parameters
    ----------
    spread_azimuths : bool, optional
        Place table entry k at the half-vector azimuth ``merl_azimuths(n)[k]`` (default)
        instead of phi_h = 0. Isotropy makes each value hold at every phi_h; with
        phi_h = 0 for all entries the half vectors fill a single azimuth, and a fit of
        (theta_h, phi_h) (method B) sees one phi column of its observed distribution and
        loses the lobe. Replicating every entry at each of a fit's phi cells would be
        exact but multiply 1.46 M samples by ~100; one evenly spread azimuth per entry
        gives each (theta_h, phi_h) cell an unbiased subsample of the entries of its
        theta_h band (thousands of them at the default grids) at no cost.

    Returns
    -------
    MeasuredBRDF
        1458000 samples in table order with ``half_diff`` set; reflectance scaled by
        (1/1500, 1.15/1500, 1.66/1500); negative entries are missing.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"MERL BRDF file {path} does not exist")
    size = path.stat().st_size
    if size < 12:
        raise DataError(f"MERL BRDF file {path} has {size} bytes, too short for its header")
    with path.open("rb") as handle:
        dims = tuple(int(x) for x in np.fromfile(handle, dtype="<i4", count=3))
        if dims != MERL_DIMS:
            raise DataError(f"MERL BRDF file {path} has header dims {dims}, expected {MERL_DIMS}")
        if size != MERL_N_BYTES:
            raise DataError(
                f"MERL BRDF file {path} has {size} bytes, expected {MERL_N_BYTES} "
                f"(int32 header + 3 x 90x90x180 float64)"
            )
        raw = np.fromfile(handle, dtype="<f8").reshape(3, -1).T
    measured = np.all(np.isfinite(raw) & (raw >= 0.0), axis=1)
    reflectance = np.where(measured[:, None], raw * MERL_SCALES, 0.0)
    half_diff = merl_half_diff_angles()
    phi_h = merl_azimuths(half_diff.shape[0]) if spread_azimuths else 0.0
    light, view = half_diff_to_directions(half_diff, phi_h)
    return MeasuredBRDF(reflectance, light, view, measured, half_diff=half_diff, source=str(path))


def write_merl_brdf(
    path: str | os.PathLike, reflectance: np.ndarray, measured: np.ndarray | None = None
) -> Path:
    """Write reflectance in MERL table order as a MERL binary (atomically); return ``path``.

    Parameters
    ----------
    reflectance : ndarray of shape (1458000, 3)
        Linear RGB values in the order of :func:`merl_half_diff_angles` (physical units:
        the channel scales are divided out before writing).
    measured : ndarray of shape (1458000,), bool, optional
        Missing entries are written as -1.
    """
    reflectance, measured = _checked(reflectance, measured, int(np.prod(MERL_DIMS)), "MERL")
    raw = reflectance / MERL_SCALES
    if measured is not None:
        raw[~measured] = -1.0
    header = np.array(MERL_DIMS, dtype="<i4").tobytes()
    return _write(path, header + np.ascontiguousarray(raw.T).astype("<f8").tobytes())
