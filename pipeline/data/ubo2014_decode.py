"""Decoding UBO2014 DFMF values: only the direction rows and the texels of a crop wanted
are multiplied out, the factors read through memory maps, a block of directions at a time
(a 100 × 100 crop of a 400 × 400 texture reads 1/16 of the texel factors).

Conventions of this decoder, each as btflib decodes:

- Row ``view · n_lights + light``: view-major, as :mod:`pipeline.data.btf` orders images.
- Column ``y · width + x`` with ``y`` counted from the bottom: btflib flips the rows
  ("Flip origin") so that image row 0 is the top, and so does this decoder (pysmtb does
  not flip).
- Colour model 0: the channels are linear RGB. Colour model 11: channel 0 is the log of
  the luminance with the dynamic-range reduction undone as ``Y = exp(c0) − ε``, channels 1
  and 2 chroma ratios, ``U = c1·Y + ε``, ``V = c2·Y + ε`` (ε =
  :data:`~pipeline.data.ubo2014_format.DRR_EPS`, hard-coded in btflib and pysmtb, not
  stored), then BT.601 YUV → RGB (:data:`~pipeline.data.ubo2014_format.YUV_TO_RGB`),
  clipped to [0, 1] as btflib does. The colour mean and transform and the RGB scale are
  read but not applied: btflib ignores them too.
- The incident cosine. Method A expects it *in* the data, as UBO2003 photographs have it.
  A file whose cosine flag is 0 (or a version-1 file, which has no flag: pysmtb reads that
  as "not in the data") stores values with the cosine divided out; the decoder multiplies
  each row by cos θ_light (clamped at 0) so that every dataset reaches the chain the same
  way. ``include_cosine=False`` returns the stored values unchanged. btflib leaves this
  case a stub.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core.errors import ConfigError, DataError
from pipeline.core.files import output_array
from pipeline.data.crop_abrdfs import CropABRDFs
from pipeline.data.ubo2014_format import DRR_EPS, YUV_TO_RGB, DFMFFile


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


def check_crop(crop, dfmf: DFMFFile) -> tuple[int, int, int, int]:
    """``crop`` = [row, col, height, width] texels (None: all) checked against the texture;
    a ConfigError names a crop that does not fit, and the texture size."""
    if crop is None:
        return 0, 0, dfmf.height, dfmf.width
    try:
        row, col, height, width = (int(value) for value in crop)
    except (TypeError, ValueError):
        raise ConfigError(f"crop {crop!r} is not [row, col, height, width]") from None
    inside = row + height <= dfmf.height and col + width <= dfmf.width
    if min(height, width) < 1 or min(row, col) < 0 or not inside:
        raise ConfigError(
            f"crop {[row, col, height, width]} does not fit the texture of "
            f"{dfmf.height} × {dfmf.width} texels (height × width): {dfmf.path}"
        )
    return row, col, height, width


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


def decode_block(direction_factors, texel_factors, color_model: int) -> np.ndarray:
    """Values of some directions at some texels from their factors.

    Parameters
    ----------
    direction_factors : sequence of 3 ndarrays of shape (n, K_c)
        The U rows of each channel.
    texel_factors : sequence of 3 ndarrays of shape (m, K_c)
        The SV rows of each channel.
    color_model : {0, 11}

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
    return np.clip(rgb, 0.0, 1.0, out=rgb)


@dataclass(frozen=True)
class _Factors:
    """What decoding some direction rows at a crop needs: the rows' U, the crop's SV (each
    per channel, in the compute type), the cosine each row is multiplied by (or None), and
    the file's colour model and path."""

    rows: np.ndarray
    directions: list[np.ndarray]
    texels: list[np.ndarray]
    cosine: np.ndarray | None
    height: int
    width: int
    color_model: int
    path: Path

    def decode(self, rows, texels) -> np.ndarray:
        """Values (n_rows, n_texels, 3) of some of :attr:`rows` at some of the crop's texels
        (each an index array or a slice), times the cosine; a :class:`DataError` names the
        file where they are not finite."""
        u = [factor[rows] for factor in self.directions]
        sv = [factor[texels] for factor in self.texels]
        values = decode_block(u, sv, self.color_model)
        finite = np.isfinite(values)
        if not finite.all():
            bad = self.rows[rows][~finite.all(axis=(1, 2))]
            raise DataError(
                f"the factors give NaN or Inf at {len(bad)} direction rows (first {bad[0]}): "
                f"{self.path}"
            )
        if self.cosine is not None:
            values *= self.cosine[rows, None, None]
        return values


def _factors(dfmf: DFMFFile, rows, crop, include_cosine: bool = True) -> _Factors:
    if len(dfmf.channels) != 3:
        raise DataError(
            f"UBO2014 file has {len(dfmf.channels)} channels {list(dfmf.channel_names)}; "
            f"the decoder needs 3: {dfmf.path}"
        )
    rows = np.arange(dfmf.n_directions) if rows is None else np.asarray(rows, dtype=np.int64)
    if rows.ndim != 1 or (len(rows) and (rows.min() < 0 or rows.max() >= dfmf.n_directions)):
        raise ConfigError(f"direction rows must be a list of 0..{dfmf.n_directions - 1}")
    _, _, height, width = check_crop(crop, dfmf)
    dtype = _compute_dtype(dfmf)
    cosine = None
    if include_cosine and not dfmf.cosine_in_data:
        theta_light = dfmf.light_angles.reshape(-1, 2)[rows, 0]
        cosine = np.maximum(np.cos(theta_light), 0.0).astype(np.float32)
    return _Factors(
        rows=rows,
        directions=[
            np.asarray(channel_factors(dfmf, channel)[1][rows], dtype=dtype) for channel in range(3)
        ],
        texels=[crop_texel_factors(dfmf, channel, crop) for channel in range(3)],
        cosine=cosine,
        height=height,
        width=width,
        color_model=dfmf.color_model,
        path=dfmf.path,
    )


# About how many bytes of values decode_dfmf computes at once: its memory stays at the
# direction factors of its rows, the crop's texel factors and one such block.
BLOCK_BYTES = 32 << 20


def decode_dfmf(
    dfmf: DFMFFile,
    rows=None,
    crop=None,
    *,
    out: np.ndarray | None = None,
    include_cosine: bool = True,
) -> np.ndarray:
    """Decode the chosen direction rows at a crop of texels, and nothing else, as images.

    Parameters
    ----------
    rows : array-like of int, or None
        Direction rows (:func:`pipeline.data.ubo2014.select_rows`); None: all ``n_directions``.
    crop : [row, col, height, width] or None
        Texels, image row 0 at the top; None: the whole texture.
    out : ndarray of shape (n_rows, height, width, 3), float32, optional
        Writable array (e.g. a ``.npy`` memory map) to decode into.
    include_cosine : bool
        Multiply by cos θ_light when the file says the cosine is not in its data (see the
        module docstring); False returns the stored values.

    Returns
    -------
    ndarray of shape (n_rows, height, width, 3), float32
        Linear RGB, ``out`` when given.

    Raises
    ------
    DataError
        When the file does not have three channels, or its factors give NaN or Inf
        (naming the file).
    ConfigError
        For rows out of range, a crop that does not fit, or an ``out`` of the wrong
        shape or dtype.
    """
    f = _factors(dfmf, rows, crop, include_cosine)
    height, width = f.height, f.width
    out = output_array(out, (len(f.rows), height, width, 3))
    # Three float32 values per texel and direction, and about as much in temporaries.
    step = max(1, BLOCK_BYTES // (2 * 3 * 4 * height * width))
    for start in range(0, len(f.rows), step):
        stop = min(start + step, len(f.rows))
        block = f.decode(slice(start, stop), slice(None))
        out[start:stop] = block.reshape(stop - start, height, width, 3)
    return out


class FactorABRDFs(CropABRDFs):
    """A crop's ABRDFs (texels × direction rows × 3) served from a DFMF file's factors, as
    the (M, N, 3) float32 array-like method A's stages read
    (:class:`~pipeline.data.crop_abrdfs.CropABRDFs`): indexing decodes just the texels (and
    directions) asked for, a small matrix product, so the decoded crop is never written or
    held (a whole UBO2014 material would be 43.8 GB; its factors are a few MB).

    Parameters
    ----------
    rows : array-like of int
        Direction rows (:func:`pipeline.data.ubo2014.select_rows`).
    crop : [row, col, height, width]
        Texels, image row 0 at the top; texel ``r · width + c``.
    """

    def __init__(self, dfmf: DFMFFile, rows, crop):
        self._factors = _factors(dfmf, rows, crop)
        m = self._factors.height * self._factors.width
        self.shape = (m, len(self._factors.rows), 3)

    def _read(self, texel_rows: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(len(texel_rows), len(rows), 3): those texels at those direction rows."""
        block = self._factors.decode(rows, texel_rows)  # (directions, texels, 3)
        return np.ascontiguousarray(block.transpose(1, 0, 2))
