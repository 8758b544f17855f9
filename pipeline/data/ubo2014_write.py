"""Writer of UBO2014 DFMF files, byte for byte in the layout :mod:`pipeline.data.ubo2014` reads.

For tests and synthetic data: a BTF given as values (factorised here by a truncated SVD
per channel, after the colour model's encoding) or as factors (written as given), with
either colour model and float16, float32 or float64 scalars.

Examples
--------
>>> write_dfmf(path, views, lights, 4, 4, values=images, color_model=11)   # doctest: +SKIP
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from os import PathLike
from pathlib import Path

import numpy as np

from pipeline.core.errors import ConfigError
from pipeline.core.files import write_atomic
from pipeline.data.ubo2014_format import (
    CHANNEL_HEADER,
    DRR_EPS,
    FIXED_HEADER,
    KNOWN_VERSIONS,
    ROTATIONS_MARK,
    SIGNATURE,
    YUV_TO_RGB,
)

_DTYPES = {"float16": np.dtype("<f2"), "float32": np.dtype("<f4"), "float64": np.dtype("<f8")}


def encode_values(values: np.ndarray, color_model: int) -> np.ndarray:
    """What the file's channels hold for some linear RGB values, in the file's texel order.

    Parameters
    ----------
    values : ndarray of shape (n_rows, height, width, 3)
        Linear RGB, image row 0 at the top.
    color_model : {0, 11}
        11 needs a positive luminance everywhere (its log is stored).

    Returns
    -------
    ndarray of shape (3, n_rows, height × width), float64
        Channel matrices; column ``y · width + x`` with ``y`` from the bottom.
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 4 or values.shape[-1] != 3:
        raise ConfigError(f"values must have shape (n_rows, height, width, 3), not {values.shape}")
    n_rows, height, width, _ = values.shape
    # Image row r is the file's row height - 1 - r (the reader flips back, as btflib does).
    rgb = values[:, ::-1].reshape(n_rows, height * width, 3)
    if color_model == 0:
        return np.moveaxis(rgb, -1, 0).copy()
    if color_model != 11:
        raise ConfigError(f"color_model={color_model} cannot encode values (0 or 11)")
    yuv = rgb @ np.linalg.inv(YUV_TO_RGB.astype(np.float64)).T
    luminance = yuv[..., 0]
    if not (luminance > 0).all():
        raise ConfigError("colour model 11 stores log-luminance: every value needs luminance > 0")
    eps = float(DRR_EPS)
    return np.stack(
        [np.log(luminance + eps), (yuv[..., 1] - eps) / luminance, (yuv[..., 2] - eps) / luminance]
    )


def factorize(matrix: np.ndarray, components: int | None = None):
    """Truncated SVD of one channel: ``matrix ≈ U @ SV.T``.

    Parameters
    ----------
    matrix : ndarray of shape (rows, columns)
    components : int or None
        K; None keeps min(rows, columns) (exact up to rounding).

    Returns
    -------
    S : ndarray of shape (K,)
    U : ndarray of shape (rows, K), orthonormal columns
    SV : ndarray of shape (columns, K), (S·Vᵀ)ᵀ
    """
    u, s, vt = np.linalg.svd(matrix, full_matrices=False)
    k = len(s) if components is None else int(components)
    if not 1 <= k <= len(s):
        raise ConfigError(f"components={k} must lie in 1..{len(s)}")
    return s[:k], u[:, :k], (s[:k, None] * vt[:k]).T


def write_dfmf(
    path: str | PathLike,
    view_angles: np.ndarray,
    light_angles: np.ndarray,
    width: int,
    height: int,
    *,
    values: np.ndarray | None = None,
    factors: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None,
    components: int | None = None,
    color_model: int = 0,
    dtype: str = "float16",
    cosine_in_data: bool = True,
    version: int = 4,
    channel_names: Sequence[str] = ("R", "G", "B"),
    xml: str = "",
    with_rotations: bool = True,
    rotations: np.ndarray | None = None,
    measurement_setup: str = "pipeline synthetic",
    image_sensor: str = "",
    light_source: str = "",
    ppmm: float = 0.0,
    rgb_scale: Sequence[float] = (1.0, 1.0, 1.0),
    color_mean: Sequence[float] = (0.0, 0.0, 0.0),
    color_transform: np.ndarray | None = None,
    sync: bool = True,
) -> Path:
    """Write a BTF as a UBO2014 DFMF file (atomically).

    Parameters
    ----------
    path : path-like
    view_angles : ndarray of shape (n_views, 2)
        (θ, φ) radians.
    light_angles : ndarray of shape (n_lights, 2) or (n_views, n_lights, 2)
        (θ, φ) radians: one list for every view, or one per view.
    width, height : int
        Texels.
    values : ndarray of shape (n_views × n_lights, height, width, 3), optional
        Linear RGB as the file stores it (rows view-major; with ``cosine_in_data=False``
        the reader multiplies by cos θ_light), encoded by ``color_model`` and factorised
        to ``components`` (None: full rank).
    factors : sequence of one (S, U, SV) per channel, optional
        S (K,), U (rows, K), SV (columns, K) in the file's texel order (row ``y`` from the
        bottom), written as given in ``dtype``; instead of ``values``.
    color_model : int
        Written as given; ``values`` need 0 (RGB) or 11 (log-luminance, chroma ratios).
    dtype : {"float16", "float32", "float64"}
    cosine_in_data : bool
        The cosine flag (not written for ``version`` 1).
    version : {1, 2, 3, 4}
        Header version: > 1 writes the cosine flag, > 2 the XML, > 3 the channel names
        (versions 1 to 3 mean channels R, G, B).
    with_rotations : bool
        Write the "R" signature and a rotations block (``rotations``, (n, 3, 3); None:
        none), as the UBO2014 files have.
    sync : bool
        fsync before the rename.

    Returns ``path``.
    """
    if (values is None) == (factors is None):
        raise ConfigError("write_dfmf needs exactly one of values and factors")
    if dtype not in _DTYPES:
        raise ConfigError(f"dtype={dtype!r} is not one of {sorted(_DTYPES)}")
    if version not in KNOWN_VERSIONS:
        raise ConfigError(f"version={version} is not one of {KNOWN_VERSIONS}")
    channel_names = tuple(channel_names)
    if version <= 3 and channel_names != ("R", "G", "B"):
        raise ConfigError(f"header version {version} has no channel names: R, G, B only")
    view_angles = np.asarray(view_angles, dtype=np.float32).reshape(-1, 2)
    light_angles = np.asarray(light_angles, dtype=np.float32)
    if light_angles.ndim == 2:
        light_angles = np.broadcast_to(light_angles, (len(view_angles), *light_angles.shape))
    n_views, n_lights = light_angles.shape[:2]
    if n_views != len(view_angles) or light_angles.shape[2] != 2:
        raise ConfigError(
            f"light_angles of shape {light_angles.shape} do not match {len(view_angles)} views"
        )
    rows, columns = n_views * n_lights, int(width) * int(height)
    if values is not None:
        values = np.asarray(values)
        if values.shape != (rows, height, width, 3):
            raise ConfigError(f"values have shape {values.shape}, need {(rows, height, width, 3)}")
        factors = [factorize(matrix, components) for matrix in encode_values(values, color_model)]
    factors = [tuple(np.asarray(part) for part in channel) for channel in factors]
    if len(factors) != len(channel_names):
        raise ConfigError(f"{len(factors)} channels of factors for names {list(channel_names)}")
    for name, (s, u, sv) in zip(channel_names, factors, strict=True):
        k = len(s)
        if u.shape != (rows, k) or sv.shape != (columns, k):
            raise ConfigError(
                f"channel {name!r}: U {u.shape} and SV {sv.shape} with {k} components; "
                f"need ({rows}, {k}) and ({columns}, {k})"
            )

    def counted(text: str) -> bytes:
        encoded = text.encode("utf-8")
        return struct.pack("<I", len(encoded)) + encoded

    body = b""
    if version > 1:
        body += struct.pack("<I", int(cosine_in_data))
    if version > 2:
        body += counted(xml)
    if version > 3:
        body += struct.pack("<I", len(channel_names)) + b"".join(map(counted, channel_names))
    texts = [text.encode("latin-1") for text in (measurement_setup, image_sensor, light_source)]
    header = FIXED_HEADER.pack(FIXED_HEADER.size + len(body), version, *texts, ppmm, *rgb_scale)
    directions = [struct.pack("<I", n_views)]
    for view, lights in zip(view_angles, light_angles, strict=True):
        light_list = struct.pack("<I", n_lights) + lights.astype("<f4").tobytes()
        directions += [view.astype("<f4").tobytes(), light_list]
    size = struct.pack("<II", width, height)
    if with_rotations:
        rotations = np.zeros((0, 3, 3)) if rotations is None else np.asarray(rotations)
        size += struct.pack("<I", len(rotations)) + rotations.astype("<f4").tobytes()
    transform = np.eye(3) if color_transform is None else np.asarray(color_transform)
    colour = (
        struct.pack("<Ii", max(len(s) for s, _, _ in factors), color_model)
        + np.asarray(color_mean, dtype="<f4").tobytes()
        + transform.astype("<f4").tobytes()
    )
    scalar = _DTYPES[dtype]

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as handle:
            handle.write(SIGNATURE + (ROTATIONS_MARK if with_rotations else b"") + header + body)
            handle.write(b"".join(directions) + size + colour)
            for s, u, sv in factors:
                handle.write(CHANNEL_HEADER.pack(scalar.itemsize, len(s), rows, columns))
                for part in (s, u, sv):
                    handle.write(np.ascontiguousarray(part, dtype=scalar).tobytes())

    return write_atomic(path, write, sync=sync)
