"""Reader of Bonn UBO2014 BTFs: one ``.btf`` file per material, stored as DFMF.

DFMF ("decorrelated full-matrix factorisation") keeps, per colour channel, a truncated
factorisation of the BTF matrix whose rows are the (view, light) pairs and whose columns
are the texels: the value of direction row ``r`` at texel column ``t`` is ``U[r] · SV[t]``
(``SV`` = S·Vᵀ transposed, the singular values already folded in). Nothing is decoded
until asked: :func:`read_dfmf` parses the header and locates the factors, and
:func:`decode_dfmf` multiplies only the direction rows and the texel columns wanted (a
100 × 100 crop of a 400 × 400 texture reads 1/16 of the texel factors, through a memory
map), a block of directions at a time.

Layout (little-endian), as btflib's decoder (``btf.hh``, republished in
2-propanol/BTF_extractor) and pysmtb's ``read_ubo_btf_dfmf`` read it::

    "!DFMF08FC", then "R" if a rotations block follows width and height
    header block: uint32 size (counting itself, up to the channel names), uint32 version,
        char[80] measurement setup, char[80] image sensor, char[80] light source,
        float32 ppmm, float32[3] RGB scale
        version > 1: uint32 cosine flag (1: the incident cosine is in the data)
        version > 2: uint32 length + that many bytes of XML
        version > 3: uint32 channel count, then per channel uint32 length + name
        (version <= 3: channels R, G, B)
    uint32 view count; per view float32 θ, φ (radians), uint32 light count, then that
        many float32 (θ, φ)
    uint32 width, height; ("R") uint32 rotation count + 3 × 3 float32 each
    uint32 components, int32 colour model, float32[3] colour mean, float32[3 × 3] colour
        transform
    per channel: uint8 scalar size (2: float16, 4: float32, 8: float64), uint32
        components K, rows (views × lights), columns (width × height), then S (K),
        U (rows × K), SV (columns × K); the file ends there.

Conventions of this reader, each as btflib decodes:

- Row ``view · n_lights + light``: view-major, as :mod:`pipeline.data.btf` orders images.
- Column ``y · width + x`` with ``y`` counted from the bottom: btflib flips the rows
  ("Flip origin") so that image row 0 is the top, and so does this reader (pysmtb does
  not flip).
- Colour model 0: the channels are linear RGB. Colour model 11: channel 0 is the log of
  the luminance with the dynamic-range reduction undone as ``Y = exp(c0) − ε``, channels 1
  and 2 chroma ratios, ``U = c1·Y + ε``, ``V = c2·Y + ε`` (ε = :data:`DRR_EPS`,
  hard-coded in btflib and pysmtb, not stored), then BT.601 YUV → RGB
  (:data:`YUV_TO_RGB`), clipped to [0, 1] as btflib does (``clip=False`` keeps the
  unclipped values). The colour mean and transform and the RGB scale are read but not
  applied: btflib ignores them too.
- The incident cosine. Method A expects it *in* the data, as UBO2003 photographs have it.
  A file whose cosine flag is 0 (or a version-1 file, which has no flag: pysmtb reads that
  as "not in the data") stores values with the cosine divided out; the reader multiplies
  each row by cos θ_light (clamped at 0) so that every dataset reaches the chain the same
  way. ``include_cosine=False`` returns the stored values unchanged. btflib leaves this
  case a stub.

Examples
--------
>>> dfmf = read_dfmf("carpet01.btf")                                   # doctest: +SKIP
>>> rows = select_rows(dfmf, views=[0, 10], lights=None)               # doctest: +SKIP
>>> images = decode_dfmf(dfmf, rows, crop=(0, 0, 100, 100))            # doctest: +SKIP

From the shell: ``python -m pipeline.data.ubo2014_bench info file=PATH`` (header, views and
lights), ``python -m pipeline.data.ubo2014_bench bench [file=PATH]`` (peak memory of loading
a crop).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from os import PathLike
from pathlib import Path

import numpy as np

from pipeline.core.errors import ConfigError, DataError
from pipeline.core.files import output_array
from pipeline.data.directions import unit_vectors

SIGNATURE = b"!DFMF08FC"
ROTATIONS_MARK = b"R"
KNOWN_VERSIONS = (1, 2, 3, 4)
COLOR_MODELS = {0: "RGB", 11: "log-luminance and chroma ratios (btflib's YUV)"}
SCALAR_DTYPES = {2: np.dtype("<f2"), 4: np.dtype("<f4"), 8: np.dtype("<f8")}
DRR_EPS = np.float32(1e-5)
# BT.601 YUV -> RGB, the rows of btflib's YUVToRGB.
YUV_TO_RGB = np.array(
    [[1.0, 0.0, 1.13983], [1.0, -0.39465, -0.5806], [1.0, 2.03211, 0.0]], dtype=np.float32
)
# uint32 size, uint32 version, 3 × char[80], float32 ppmm, float32[3] RGB scale.
FIXED_HEADER = struct.Struct("<II80s80s80sf3f")
CHANNEL_HEADER = struct.Struct("<BIII")
# A [θ, φ] entry of dataset.views / dataset.lights must lie this close to a file direction.
MATCH_TOLERANCE_DEG = 0.5


@dataclass(frozen=True)
class ChannelFactors:
    """Where one channel's factors lie in the file: S (K,), then U (rows, K), SV (columns, K)."""

    name: str
    dtype: np.dtype
    components: int
    rows: int
    columns: int
    offset: int

    @property
    def u_offset(self) -> int:
        return self.offset + self.components * self.dtype.itemsize

    @property
    def sv_offset(self) -> int:
        return self.u_offset + self.rows * self.components * self.dtype.itemsize

    @property
    def end(self) -> int:
        return self.sv_offset + self.columns * self.components * self.dtype.itemsize


@dataclass(frozen=True, eq=False)
class DFMFFile:
    """The parsed header of a DFMF file and where its factors are; no factor is read.

    Attributes
    ----------
    view_angles : ndarray of shape (n_views, 2), float32
        (θ, φ) of each view in radians, in file order.
    light_angles : ndarray of shape (n_views, n_lights, 2), float32
        (θ, φ) of each light under each view, in radians.
    rotations : ndarray of shape (n_rotations, 3, 3), float32
    color_mean : ndarray of shape (3,); color_transform : ndarray of shape (3, 3)
        Read, not applied (btflib ignores them).
    cosine_in_data : bool
        The file's cosine flag; False for version 1, which has none.
    channels : tuple of ChannelFactors
    size : int
        The file's size in bytes (the factors end exactly there).
    """

    path: Path
    version: int
    measurement_setup: str
    image_sensor: str
    light_source: str
    ppmm: float
    rgb_scale: tuple[float, float, float]
    cosine_in_data: bool
    xml: str
    channel_names: tuple[str, ...]
    view_angles: np.ndarray
    light_angles: np.ndarray
    width: int
    height: int
    has_rotations: bool
    rotations: np.ndarray
    components: int
    color_model: int
    color_mean: np.ndarray
    color_transform: np.ndarray
    channels: tuple[ChannelFactors, ...]
    size: int

    @property
    def n_views(self) -> int:
        return len(self.view_angles)

    @property
    def n_lights(self) -> int:
        return self.light_angles.shape[1]

    @property
    def n_directions(self) -> int:
        return self.n_views * self.n_lights

    def directions(self) -> np.ndarray:
        """(θ_light, φ_light, θ_view, φ_view) in radians of every row, shape (n_directions, 4),
        float64; row ``view · n_lights + light``."""
        lights = self.light_angles.reshape(-1, 2).astype(np.float64)
        views = np.repeat(self.view_angles.astype(np.float64), self.n_lights, axis=0)
        return np.concatenate([lights, views], axis=1)


# --------------------------------------------------------------------------- header


class _Cursor:
    """Little-endian fields read in order; a read past the end names the file and sizes."""

    def __init__(self, handle, path: Path, size: int):
        self.handle, self.path, self.size = handle, path, size

    def tell(self) -> int:
        return self.handle.tell()

    def take(self, count: int, what: str) -> bytes:
        start = self.tell()
        # Checked before reading: a damaged count must not become a huge allocation.
        if start + count > self.size:
            raise DataError(
                f"UBO2014 file is truncated: {what} needs bytes {start}..{start + count}, "
                f"but the file has {self.size} bytes: {self.path}"
            )
        return self.handle.read(count)

    def unpack(self, layout: struct.Struct, what: str) -> tuple:
        return layout.unpack(self.take(layout.size, what))

    def uint32(self, what: str) -> int:
        return struct.unpack("<I", self.take(4, what))[0]

    def floats(self, count: int, what: str) -> np.ndarray:
        return np.frombuffer(self.take(4 * count, what), dtype="<f4").astype(np.float32)

    def text(self, count: int, what: str) -> str:
        return self.take(count, what).decode("utf-8", errors="replace")


def _c_string(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("latin-1")


def read_dfmf(path: str | PathLike) -> DFMFFile:
    """Parse a DFMF file's header and locate its factors (which are not read).

    Parameters
    ----------
    path : path-like
        A UBO2014 ``.btf`` file.

    Returns
    -------
    DFMFFile

    Raises
    ------
    DataError
        Naming the file: missing, a wrong signature, an unknown version or colour model,
        a header block whose size disagrees with its fields, views with different light
        counts, an unknown scalar size, factor shapes disagreeing with the header
        (rows ≠ views × lights, columns ≠ width × height), a truncated file (with the
        size expected and the actual size), or bytes after the last channel.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        handle = open(path, "rb")  # noqa: SIM115 - closed by the with below
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
        raise DataError(f"UBO2014 file missing (or not a file): {path}") from None
    with handle:
        return _parse(_Cursor(handle, path, size))


def _parse(cur: _Cursor) -> DFMFFile:
    path = cur.path
    signature = cur.handle.read(len(SIGNATURE))
    if signature != SIGNATURE:
        raise DataError(
            f"not a UBO2014 DFMF file: it starts with {signature!r}, not "
            f"{SIGNATURE + ROTATIONS_MARK!r}: {path}"
        )
    has_rotations = cur.handle.read(1) == ROTATIONS_MARK
    if not has_rotations:
        cur.handle.seek(len(SIGNATURE))
    start = cur.tell()
    block_size, version, setup, sensor, source, ppmm, *rgb = cur.unpack(FIXED_HEADER, "the header")
    if version not in KNOWN_VERSIONS:
        raise DataError(
            f"UBO2014 header version {version} is not one this reader knows "
            f"({KNOWN_VERSIONS[0]} to {KNOWN_VERSIONS[-1]}): {path}"
        )
    cosine_in_data = bool(cur.uint32("the cosine flag")) if version > 1 else False
    xml = cur.text(cur.uint32("the XML length"), "the XML block") if version > 2 else ""
    channel_names: tuple[str, ...] = ("R", "G", "B")
    if version > 3:
        count = cur.uint32("the channel count")
        if 4 * count > cur.size - cur.tell():
            raise DataError(f"UBO2014 header's channel count {count} cannot fit the file: {path}")
        channel_names = tuple(
            cur.text(cur.uint32(f"channel {index}'s name length"), f"channel {index}'s name")
            for index in range(count)
        )
    if cur.tell() - start != block_size:
        raise DataError(
            f"UBO2014 header block says it is {block_size} bytes, but its fields (version "
            f"{version}) take {cur.tell() - start}: {path}"
        )

    n_views = cur.uint32("the view count")
    if 12 * n_views > cur.size - cur.tell():
        raise DataError(f"UBO2014 view count {n_views} cannot fit the file: {path}")
    view_angles = np.empty((n_views, 2), dtype=np.float32)
    light_lists = []
    for view in range(n_views):
        view_angles[view] = cur.floats(2, f"view {view}'s angles")
        n_lights = cur.uint32(f"view {view}'s light count")
        if light_lists and n_lights != len(light_lists[0]):
            raise DataError(
                f"UBO2014 view {view} has {n_lights} lights but view 0 has "
                f"{len(light_lists[0])}; rows view × lights need one count: {path}"
            )
        light_lists.append(cur.floats(2 * n_lights, f"view {view}'s lights").reshape(-1, 2))
    if n_views == 0 or len(light_lists[0]) == 0:
        raise DataError(f"UBO2014 file has {n_views} views and no lights: {path}")
    light_angles = np.stack(light_lists)
    width, height = cur.uint32("the width"), cur.uint32("the height")
    rotations = np.zeros((0, 3, 3), dtype=np.float32)
    if has_rotations:
        count = cur.uint32("the rotation count")
        rotations = cur.floats(9 * count, "the rotations").reshape(count, 3, 3)
    components = cur.uint32("the component count")
    (color_model,) = struct.unpack("<i", cur.take(4, "the colour model"))
    if color_model not in COLOR_MODELS:
        raise DataError(
            f"UBO2014 colour model {color_model} is not one this reader knows "
            f"{sorted(COLOR_MODELS)}: {path}"
        )
    color_mean = cur.floats(3, "the colour mean")
    color_transform = cur.floats(9, "the colour transform").reshape(3, 3)

    channels = []
    rows, columns = n_views * len(light_lists[0]), width * height
    for index, name in enumerate(channel_names):
        scalar_size, k, n_rows, n_columns = cur.unpack(
            CHANNEL_HEADER, f"channel {name!r}'s header"
        )
        if scalar_size not in SCALAR_DTYPES:
            raise DataError(
                f"UBO2014 channel {name!r} has scalars of {scalar_size} bytes, "
                f"not 2, 4 or 8: {path}"
            )
        if n_rows != rows or n_columns != columns:
            raise DataError(
                f"UBO2014 channel {name!r}'s factors are {n_rows} rows × {n_columns} columns, "
                f"but the header's {n_views} views × {len(light_lists[0])} lights and "
                f"{width} × {height} texels make {rows} × {columns}: {path}"
            )
        factors = ChannelFactors(name, SCALAR_DTYPES[scalar_size], k, n_rows, n_columns, cur.tell())
        if factors.end > cur.size:
            raise DataError(
                f"UBO2014 file is truncated: channel {index} ({name!r}, {k} components) ends "
                f"at byte {factors.end}, but the file has {cur.size} bytes: {path}"
            )
        cur.handle.seek(factors.end)
        channels.append(factors)
    if cur.tell() != cur.size:
        raise DataError(
            f"UBO2014 file has {cur.size - cur.tell()} bytes after its last channel "
            f"(expected {cur.tell()} bytes, actual {cur.size}): {path}"
        )
    return DFMFFile(
        path=path, version=version, measurement_setup=_c_string(setup),
        image_sensor=_c_string(sensor), light_source=_c_string(source), ppmm=float(ppmm),
        rgb_scale=tuple(float(value) for value in rgb), cosine_in_data=cosine_in_data,
        xml=xml, channel_names=channel_names, view_angles=view_angles,
        light_angles=light_angles, width=width, height=height, has_rotations=has_rotations,
        rotations=rotations, components=components, color_model=color_model,
        color_mean=color_mean, color_transform=color_transform, channels=tuple(channels),
        size=cur.size,
    )


def channel_factors(dfmf: DFMFFile, channel: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """S, U and SV of one channel as read-only memory maps, in the file's dtype.

    Returns
    -------
    S : ndarray of shape (K,)
    U : ndarray of shape (n_directions, K)
    SV : ndarray of shape (width × height, K)
        Column ``y · width + x``, ``y`` counted from the bottom (the file's order).
    """
    factors = dfmf.channels[channel]
    k = factors.components

    def mapped(offset: int, shape: tuple[int, ...]) -> np.ndarray:
        return np.memmap(dfmf.path, dtype=factors.dtype, mode="r", offset=offset, shape=shape)

    return (
        mapped(factors.offset, (k,)),
        mapped(factors.u_offset, (factors.rows, k)),
        mapped(factors.sv_offset, (factors.columns, k)),
    )


# --------------------------------------------------------------------------- selection


def _pick(entries, angles: np.ndarray, what: str, path: Path) -> np.ndarray:
    """File indices of ``entries`` (indices, or [θ, φ] degrees matched to ``angles``)."""
    if entries is None:
        return np.arange(len(angles))
    angles = np.asarray(angles, dtype=np.float64)
    vectors = unit_vectors(angles[:, 0], angles[:, 1])
    picked = []
    for entry in entries:
        if isinstance(entry, (int, np.integer)) and not isinstance(entry, bool):
            if not 0 <= entry < len(angles):
                raise ConfigError(
                    f"dataset.{what} entry {entry} is not an index of the file's "
                    f"{len(angles)} {what} (0..{len(angles) - 1}): {path}"
                )
            picked.append(int(entry))
            continue
        try:
            theta, phi = (float(value) for value in entry)
        except (TypeError, ValueError):
            raise ConfigError(
                f"dataset.{what} entry {entry!r} is neither an index nor [theta, phi] in degrees"
            ) from None
        target = unit_vectors(np.radians(theta), np.radians(phi))
        distance = np.degrees(np.arccos(np.clip(vectors @ target, -1.0, 1.0)))
        nearest = int(np.argmin(distance))
        if distance[nearest] > MATCH_TOLERANCE_DEG:
            near_theta, near_phi = np.degrees(angles[nearest])
            raise ConfigError(
                f"dataset.{what} entry [{theta:g}, {phi:g}] degrees is {distance[nearest]:.2f} "
                f"degrees from the nearest of the file's {what} (index {nearest}: "
                f"[{near_theta:.2f}, {near_phi:.2f}]); allowed {MATCH_TOLERANCE_DEG}: {path}"
            )
        picked.append(nearest)
    if not picked:
        raise ConfigError(f"dataset.{what} is an empty list; null means all of them")
    return np.unique(picked)


def select_rows(dfmf: DFMFFile, views=None, lights=None) -> np.ndarray:
    """Direction rows of the chosen views and lights, view-major, in file order.

    Parameters
    ----------
    dfmf : DFMFFile
    views, lights : sequence or None
        None: all. Otherwise entries each either an index into the file's views (lights),
        or ``[θ, φ]`` in degrees within :data:`MATCH_TOLERANCE_DEG` of one (lights are
        matched to view 0's list; light ``l`` is the ``l``-th of every view). Duplicates
        are dropped; the order is the file's.

    Returns
    -------
    ndarray of shape (n_views_chosen × n_lights_chosen,), int64
        Rows ``view · n_lights + light``.

    Raises
    ------
    ConfigError
        For an index out of range, an angle pair far from every direction, or an empty list.
    """
    view_ids = _pick(views, dfmf.view_angles, "views", dfmf.path)
    light_ids = _pick(lights, dfmf.light_angles[0], "lights", dfmf.path)
    return (view_ids[:, None] * dfmf.n_lights + light_ids[None, :]).ravel().astype(np.int64)


def check_crop(crop, dfmf: DFMFFile) -> tuple[int, int, int, int]:
    """``crop`` = [row, col, height, width] texels (None: all) checked against the texture.

    Raises
    ------
    ConfigError
        Naming the crop and the texture size, when it does not fit.
    """
    if crop is None:
        return 0, 0, dfmf.height, dfmf.width
    try:
        row, col, height, width = (int(value) for value in crop)
    except (TypeError, ValueError):
        raise ConfigError(f"dataset.crop={crop!r} is not [row, col, height, width]") from None
    if height < 1 or width < 1 or row < 0 or col < 0 or row + height > dfmf.height or (
        col + width > dfmf.width
    ):
        raise ConfigError(
            f"dataset.crop={[row, col, height, width]} does not fit the texture of "
            f"{dfmf.height} × {dfmf.width} texels (height × width): {dfmf.path}"
        )
    return row, col, height, width


# --------------------------------------------------------------------------- decoding


def _compute_dtype(dfmf: DFMFFile) -> np.dtype:
    # btflib sums float16 and float32 factors in float32, float64 factors in float64.
    return np.dtype(np.float64 if dfmf.channels[0].dtype.itemsize == 8 else np.float32)


def crop_texel_factors(dfmf: DFMFFile, channel: int, crop=None) -> np.ndarray:
    """SV rows of the crop's texels, image row 0 at the top, shape (height × width, K)."""
    row, col, height, width = check_crop(crop, dfmf)
    sv = channel_factors(dfmf, channel)[2].reshape(dfmf.height, dfmf.width, -1)
    # Image row r is the file's row height - 1 - r (btflib's origin flip): read the
    # file's rows of the crop, then reverse them. Only those rows' pages are touched.
    bottom = dfmf.height - row - height
    block = sv[bottom : bottom + height, col : col + width][::-1]
    return np.ascontiguousarray(block, dtype=_compute_dtype(dfmf)).reshape(height * width, -1)


def decode_block(
    direction_factors, texel_factors, color_model: int, clip: bool = True
) -> np.ndarray:
    """Values of some directions at some texels from their factors.

    Parameters
    ----------
    direction_factors : sequence of 3 ndarrays of shape (n, K_c)
        The U rows of each channel.
    texel_factors : sequence of 3 ndarrays of shape (m, K_c)
        The SV rows of each channel.
    color_model : {0, 11}
    clip : bool
        Colour model 11 only: clip RGB to [0, 1] as btflib does.

    Returns
    -------
    ndarray of shape (n, m, 3), float32
        Linear RGB (before any cosine).
    """
    channels = [
        (u @ sv.T).astype(np.float32, copy=False)
        for u, sv in zip(direction_factors, texel_factors, strict=True)
    ]
    if color_model == 0:
        return np.stack(channels, axis=-1)
    luminance = np.exp(channels[0]) - DRR_EPS
    yuv = np.stack(
        [luminance, channels[1] * luminance + DRR_EPS, channels[2] * luminance + DRR_EPS], axis=-1
    )
    rgb = yuv @ YUV_TO_RGB.T
    return np.clip(rgb, 0.0, 1.0, out=rgb) if clip else rgb


def decode_dfmf(
    dfmf: DFMFFile,
    rows=None,
    crop=None,
    *,
    out: np.ndarray | None = None,
    include_cosine: bool = True,
    clip: bool = True,
    block_bytes: int = 32 << 20,
) -> np.ndarray:
    """Decode the chosen direction rows at a crop of texels, and nothing else.

    Parameters
    ----------
    dfmf : DFMFFile
    rows : array-like of int, or None
        Direction rows (:func:`select_rows`); None: all ``n_directions``.
    crop : [row, col, height, width] or None
        Texels, image row 0 at the top; None: the whole texture.
    out : ndarray of shape (n_rows, height, width, 3), float32, optional
        Writable array (e.g. a ``.npy`` memory map) to decode into.
    include_cosine : bool
        Multiply by cos θ_light when the file says the cosine is not in its data (see the
        module docstring); False returns the stored values.
    clip : bool
        See :func:`decode_block`.
    block_bytes : int
        About how many bytes of values are computed at once: memory stays at the
        direction factors of ``rows``, the crop's texel factors and one such block.

    Returns
    -------
    ndarray of shape (n_rows, height, width, 3), float32
        Linear RGB, ``out`` when given.

    Raises
    ------
    DataError
        When the file does not have three channels.
    ConfigError
        For rows out of range, a crop that does not fit, or an ``out`` of the wrong
        shape or dtype.
    """
    if len(dfmf.channels) != 3:
        raise DataError(
            f"UBO2014 file has {len(dfmf.channels)} channels {list(dfmf.channel_names)}; "
            f"the decoder needs 3: {dfmf.path}"
        )
    rows = np.arange(dfmf.n_directions) if rows is None else np.asarray(rows, dtype=np.int64)
    if rows.ndim != 1 or (len(rows) and (rows.min() < 0 or rows.max() >= dfmf.n_directions)):
        raise ConfigError(f"direction rows must be a list of 0..{dfmf.n_directions - 1}")
    _, _, height, width = check_crop(crop, dfmf)
    shape = (len(rows), height, width, 3)
    out = output_array(out, shape)
    dtype = _compute_dtype(dfmf)
    texel_factors = [crop_texel_factors(dfmf, channel, crop) for channel in range(3)]
    direction_factors = [
        np.asarray(channel_factors(dfmf, channel)[1][rows], dtype=dtype) for channel in range(3)
    ]
    cosine = None
    if include_cosine and not dfmf.cosine_in_data:
        theta_light = dfmf.light_angles.reshape(-1, 2)[rows, 0]
        cosine = np.maximum(np.cos(theta_light), 0.0).astype(np.float32)
    # Three float32 values per texel and direction, and about as much in temporaries.
    step = max(1, block_bytes // (2 * 3 * 4 * height * width))
    for start in range(0, len(rows), step):
        stop = min(start + step, len(rows))
        block = decode_block([u[start:stop] for u in direction_factors], texel_factors,
                             dfmf.color_model, clip)
        if cosine is not None:
            block *= cosine[start:stop, None, None]
        out[start:stop] = block.reshape(stop - start, height, width, 3)
    return out


# --------------------------------------------------------------------------- the dataset


def count_ubo2014_images(
    path: str | PathLike, views=None, lights=None, crop=None
) -> tuple[int, int, int]:
    """(n_images, height, width) that :func:`load_ubo2014` returns, from the header alone."""
    dfmf = read_dfmf(path)
    _, _, height, width = check_crop(crop, dfmf)
    return len(select_rows(dfmf, views, lights)), height, width


def load_ubo2014(
    path: str | PathLike,
    views=None,
    lights=None,
    crop=None,
    out: np.ndarray | None = None,
    include_cosine: bool = True,
):
    """Load a crop of a UBO2014 BTF as linear RGB images in view-major order.

    Parameters
    ----------
    path : path-like
        The ``.btf`` file.
    views, lights : see :func:`select_rows`
    crop : [row, col, height, width] or None
        Texels to decode; None decodes the whole texture (n × 400 × 400 × 3 float32 for
        a UBO2014 file: give ``out`` as a memory map).
    out : ndarray of shape (n_images, height, width, 3), float32, optional
        Get the shape from :func:`count_ubo2014_images`.
    include_cosine : bool
        See :func:`decode_dfmf`.

    Returns
    -------
    pipeline.data.btf.BTF
        ``images`` (n, height, width, 3); ``directions`` (n, 4) = (θ_light, φ_light,
        θ_view, φ_view) radians from the file; ``paths`` the file for every image;
        ``view_folders`` empty; ``root`` the file.

    Raises
    ------
    DataError, ConfigError
        As :func:`read_dfmf`, :func:`select_rows` and :func:`decode_dfmf`.
    """
    from pipeline.data.btf import BTF

    dfmf = read_dfmf(path)
    rows = select_rows(dfmf, views, lights)
    images = decode_dfmf(dfmf, rows, crop, out=out, include_cosine=include_cosine)
    return BTF(images=images, directions=dfmf.directions()[rows],
               paths=[dfmf.path] * len(rows), view_folders=[], root=dfmf.path)


def describe(dfmf: DFMFFile) -> dict:
    """The header's facts as plain values (for logs, a cache summary and ``info``)."""
    return {
        "version": dfmf.version, "n_views": dfmf.n_views, "n_lights": dfmf.n_lights,
        "width": dfmf.width, "height": dfmf.height, "color_model": dfmf.color_model,
        "cosine_in_data": dfmf.cosine_in_data, "channels": list(dfmf.channel_names),
        "components": [channel.components for channel in dfmf.channels],
        "scalar_bytes": [channel.dtype.itemsize for channel in dfmf.channels],
        "measurement_setup": dfmf.measurement_setup, "image_sensor": dfmf.image_sensor,
        "light_source": dfmf.light_source,
    }
