"""The UBO2014 DFMF file format: its layout, the constants reader and writer share, and
the parsed header (:class:`DFMFFile`).

DFMF ("decorrelated full-matrix factorisation") keeps, per colour channel, a truncated
factorisation of the BTF matrix whose rows are the (view, light) pairs and whose columns
are the texels: the value of direction row ``r`` at texel column ``t`` is ``U[r] · SV[t]``
(``SV`` = S·Vᵀ transposed, the singular values already folded in).

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

:func:`pipeline.data.ubo2014_header.read_dfmf` parses it into a :class:`DFMFFile`,
:mod:`pipeline.data.ubo2014_decode` decodes values from the factors, and
:mod:`pipeline.data.ubo2014_write` writes it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

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
