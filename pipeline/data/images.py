"""Small image I/O: 8-bit JPEG/PNG via Pillow, half-float EXR via OpenEXR, colour transforms.

Every reader raises :class:`~pipeline.core.errors.DataError` naming the file when it is missing,
truncated, corrupt (as far as the decoder tells: JPEG has no checksum, and a flipped bit in
its compressed data mostly decodes to wrong pixels without a word) or holds non-finite
values, so a bad file in a 6561-image dataset is reported by path rather than as a library
traceback. Every writer writes atomically (:func:`pipeline.core.files.write_atomic`): a
file is whole or absent, and a full disk is a DataError naming it.

Colour conventions:

- 8-bit images are returned as float32 in [0, 1] (code / 255), still encoded; decode with
  :func:`srgb_eotf` (UTIA PNG) or :func:`gamma_decode` (UBO2003, gamma 2.2).
- EXR channels are returned as float32 exactly equal to the stored half values.
- XYZ is CIE 1931 XYZ relative to the D65 white; linear sRGB uses the ITU-R BT.709
  primaries and D65 white of IEC 61966-2-1.
"""

from __future__ import annotations

import io
import zipfile
import zlib
from collections.abc import Sequence
from os import PathLike
from pathlib import Path

import numpy as np
from PIL import Image

from pipeline.core.errors import DataError
from pipeline.core.files import write_atomic

# What Pillow raises for a file it cannot decode: OSError (truncated, corrupt, unknown
# format), SyntaxError and ValueError (bad headers), DecompressionBombError (a header
# that claims billions of pixels, e.g. a flipped bit in a JPEG's size).
_DECODE_ERRORS = (OSError, ValueError, SyntaxError, EOFError, Image.DecompressionBombError)


def _as_path(path):
    """A member of a zip archive (:class:`zipfile.Path`) as it is; anything else as a Path."""
    return path if isinstance(path, zipfile.Path) else Path(path)


def _source(path):
    """What the decoders open: a file name, or the bytes of a zip archive's member (a
    :class:`zipfile.Path`, which neither Pillow nor OpenEXR opens by name) as a stream."""
    if isinstance(path, zipfile.Path):
        try:
            return io.BytesIO(path.read_bytes())
        except (zipfile.BadZipFile, KeyError, EOFError, OSError, zlib.error) as error:
            # A damaged member (bad CRC, cut short) or one the listing named but is gone.
            raise DataError(f"cannot read {path} from its zip archive: {error}") from None
    return str(path) if isinstance(path, (str, PathLike)) else path


# --- transfer functions ---------------------------------------------------------------

# IEC 61966-2-1: linear segment below these breakpoints, 2.4 power law above.
_SRGB_ENCODED_BREAK = 0.04045
_SRGB_LINEAR_BREAK = 0.0031308


def srgb_eotf(encoded: np.ndarray) -> np.ndarray:
    """sRGB decoding (IEC 61966-2-1) of encoded values (clipped to [0, 1]), float32, same shape."""
    encoded = np.clip(np.asarray(encoded, dtype=np.float32), 0.0, 1.0)
    return np.where(
        encoded <= _SRGB_ENCODED_BREAK,
        encoded / np.float32(12.92),
        ((encoded + np.float32(0.055)) / np.float32(1.055)) ** np.float32(2.4),
    ).astype(np.float32)


def srgb_oetf(linear: np.ndarray) -> np.ndarray:
    """sRGB encoding (IEC 61966-2-1) of linear values (clipped to [0, 1]), float32, same shape."""
    linear = np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0)
    return np.where(
        linear <= _SRGB_LINEAR_BREAK,
        linear * np.float32(12.92),
        np.float32(1.055) * linear ** np.float32(1 / 2.4) - np.float32(0.055),
    ).astype(np.float32)


def gamma_decode(encoded: np.ndarray, gamma: float = 2.2) -> np.ndarray:
    """Pure power-law decoding ``encoded ** gamma`` (values clipped to [0, 1]), float32."""
    encoded = np.clip(np.asarray(encoded, dtype=np.float32), 0.0, 1.0)
    return (encoded ** np.float32(gamma)).astype(np.float32)


def gamma_encode(linear: np.ndarray, gamma: float = 2.2) -> np.ndarray:
    """Pure power-law encoding ``linear ** (1 / gamma)`` (values clipped to [0, 1]), float32."""
    linear = np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0)
    return (linear ** np.float32(1.0 / gamma)).astype(np.float32)


# --- XYZ <-> linear sRGB ----------------------------------------------------------------


def _rgb_to_xyz_matrix() -> np.ndarray:
    """Derive the RGB→XYZ matrix from the sRGB primaries and the D65 white point.

    Derived rather than typed in so that the two matrices are exact inverses; it agrees
    with the 4-digit matrix printed in IEC 61966-2-1 to the printed precision.
    """
    primaries_xy = np.array([[0.64, 0.33], [0.30, 0.60], [0.15, 0.06]])
    white_xy = np.array([0.3127, 0.3290])

    def xyz_of(xy):
        return np.array([xy[0] / xy[1], 1.0, (1.0 - xy[0] - xy[1]) / xy[1]])

    primaries_xyz = np.stack([xyz_of(xy) for xy in primaries_xy], axis=1)  # columns R, G, B
    scale = np.linalg.solve(primaries_xyz, xyz_of(white_xy))
    return primaries_xyz * scale


LINEAR_SRGB_TO_XYZ: np.ndarray = _rgb_to_xyz_matrix()
"""(3, 3) matrix: ``xyz = LINEAR_SRGB_TO_XYZ @ rgb`` (D65, Y of white = 1)."""
XYZ_TO_LINEAR_SRGB: np.ndarray = np.linalg.inv(LINEAR_SRGB_TO_XYZ)
"""(3, 3) matrix: ``rgb = XYZ_TO_LINEAR_SRGB @ xyz``."""


def xyz_to_linear_srgb(xyz: np.ndarray) -> np.ndarray:
    """CIE XYZ (D65) to linear sRGB; last axis is the colour axis, shape (..., 3), float32.

    Out-of-gamut colours give components outside [0, 1]; they are not clipped.
    """
    xyz = np.asarray(xyz, dtype=np.float32)
    return xyz @ XYZ_TO_LINEAR_SRGB.T.astype(np.float32)


def linear_srgb_to_xyz(rgb: np.ndarray) -> np.ndarray:
    """Linear sRGB to CIE XYZ (D65); last axis is the colour axis, shape (..., 3), float32."""
    rgb = np.asarray(rgb, dtype=np.float32)
    return rgb @ LINEAR_SRGB_TO_XYZ.T.astype(np.float32)


# --- 8-bit images ------------------------------------------------------------------------

_EIGHT_BIT_MODES = {"1", "L", "LA", "P", "RGB", "RGBA", "CMYK", "YCbCr"}


def read_image_8bit(path: str | PathLike) -> np.ndarray:
    """Read an 8-bit JPEG or PNG as code values / 255 (still encoded), shape (H, W, 3),
    float32 in [0, 1]. Grey images are repeated to three channels; alpha is dropped.

    Raises
    ------
    DataError
        Naming the file, if it is missing, truncated, corrupt or not 8 bits per channel.
    """
    try:
        with Image.open(_source(path)) as image:
            if image.mode not in _EIGHT_BIT_MODES:
                raise DataError(f"not an 8-bit image (Pillow mode {image.mode!r}): {path}")
            # Image.open only reads the header; load() forces the full decode so a
            # truncated file fails here rather than returning a half-grey image.
            image.load()
            codes = np.asarray(image.convert("RGB"), dtype=np.uint8)
    except DataError:
        raise
    except FileNotFoundError:
        raise DataError(f"image file missing: {path}") from None
    except _DECODE_ERRORS as error:
        raise DataError(f"cannot decode image {path}: {error}") from None
    return codes.astype(np.float32) / np.float32(255.0)


def quantize_8bit(encoded: np.ndarray) -> np.ndarray:
    """Round encoded values in [0, 1] to 8-bit codes (clipping first), uint8, same shape."""
    encoded = np.clip(np.asarray(encoded, dtype=np.float32), 0.0, 1.0)
    return np.rint(encoded * np.float32(255.0)).astype(np.uint8)


def write_image_8bit(
    path: str | PathLike, encoded: np.ndarray, quality: int = 95, *, sync: bool = True
) -> None:
    """Write encoded values in [0, 1] as an 8-bit image (atomically).

    Parameters
    ----------
    path : path-like
        ``.jpg``/``.jpeg`` (JPEG, 4:4:4 chroma, ``quality``) or ``.png`` (lossless).
    encoded : ndarray of shape (H, W, 3)
        Already-encoded values (apply :func:`srgb_oetf` or :func:`gamma_encode` first).
    quality : int
        JPEG quality 1..100; ignored for PNG.
    sync : bool
        fsync before the rename (:func:`~pipeline.core.files.write_atomic`); False for
        images written into a staging folder that is published as a whole.

    Raises
    ------
    DataError
        Naming the file, for an unknown extension or when the disk is full.
    """
    encoded = np.asarray(encoded)
    if encoded.ndim != 3 or encoded.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) image for {path}, got shape {encoded.shape}")
    suffix = Path(path).suffix.lower()
    if suffix in (".jpg", ".jpeg"):
        # 4:4:4 (no chroma subsampling) keeps thread-scale colour detail of small textures.
        options = {"format": "JPEG", "quality": int(quality), "subsampling": 0}
    elif suffix == ".png":
        options = {"format": "PNG"}
    else:
        raise DataError(f"cannot write an 8-bit image with extension {suffix!r}: {path}")
    image = Image.fromarray(quantize_8bit(encoded))
    write_atomic(path, lambda tmp: image.save(tmp, **options), sync=sync)


def image_size(path: str | PathLike) -> tuple[int, int]:
    """(height, width) of a JPEG, PNG or EXR file, read from its header only.

    Raises
    ------
    DataError
        Naming the file, if it is missing or its header is unreadable.
    """
    path = _as_path(path)
    if path.suffix.lower() == ".exr":
        try:
            import OpenEXR  # imported where used: the numerics import this module

            with OpenEXR.File(_source(path), header_only=True) as exr_file:
                low, high = exr_file.header()["dataWindow"]
        except Exception as error:  # OpenEXR raises RuntimeError or ValueError
            raise DataError(f"cannot read EXR header of {path}: {error}") from None
        return int(high[1] - low[1] + 1), int(high[0] - low[0] + 1)
    try:
        with Image.open(_source(path)) as image:
            width, height = image.size
    except FileNotFoundError:
        raise DataError(f"image file missing: {path}") from None
    except _DECODE_ERRORS as error:
        raise DataError(f"cannot read image header of {path}: {error}") from None
    return height, width


# --- EXR -----------------------------------------------------------------------------------


def read_exr(path: str | PathLike) -> dict[str, np.ndarray]:
    """Read every channel of a single-part scanline or tiled EXR, one array per channel.

    Returns
    -------
    dict of str to ndarray of shape (H, W), float32
        Channel name (e.g. ``"R"``, ``"X"``) to its pixels, top row first. Half values
        are widened exactly.

    Raises
    ------
    DataError
        Naming the file, if it is missing, truncated or corrupt, or if any channel
        holds NaN or Inf.
    """
    path = _as_path(path)
    if not path.is_file():
        raise DataError(f"EXR file missing: {path}")
    import OpenEXR

    try:
        # separate_channels=True keeps R, G, B as separate entries; without it the
        # binding merges them into one (H, W, 3) "RGB" channel.
        with OpenEXR.File(_source(path), separate_channels=True) as exr_file:
            channels = {
                name: np.asarray(channel.pixels, dtype=np.float32)
                for name, channel in exr_file.channels().items()
            }
    except Exception as error:  # OpenEXR raises RuntimeError or ValueError for bad data
        raise DataError(f"cannot decode EXR {path}: {error}") from None
    for name, pixels in channels.items():
        if pixels.ndim != 2:
            raise DataError(f"EXR channel {name!r} has shape {pixels.shape}, not (H, W): {path}")
        if not np.isfinite(pixels).all():
            raise DataError(f"EXR channel {name!r} holds NaN or Inf values: {path}")
    return channels


def read_exr_channels(path: str | PathLike, names: Sequence[str]) -> np.ndarray:
    """The channels ``names`` (e.g. ``("R", "G", "B")``) of an EXR, stacked on the last
    axis: shape (H, W, len(names)), float32. Raises as :func:`read_exr`, or a DataError
    naming the file and the missing channels."""
    channels = read_exr(path)
    missing = [name for name in names if name not in channels]
    if missing:
        raise DataError(f"EXR lacks channels {missing} (has {sorted(channels)}): {path}")
    return np.stack([channels[name] for name in names], axis=-1)


def write_exr(
    path: str | PathLike,
    image: np.ndarray,
    names: Sequence[str] = ("R", "G", "B"),
    *,
    sync: bool = True,
) -> None:
    """Write an image as a half-float, ZIP-compressed scanline EXR (atomically).

    Parameters
    ----------
    image : ndarray of shape (H, W, C)
        Values to store; they are rounded to half precision.
    names : sequence of C str
        Channel names, e.g. ``("R", "G", "B")`` or ``("X", "Y", "Z")``.
    sync : bool
        As in :func:`write_image_8bit`; a full disk is a DataError naming the file.
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != len(names):
        raise ValueError(f"image of shape {image.shape} does not match channel names {list(names)}")
    import OpenEXR

    # The binding picks the pixel type from the array dtype: float16 gives HALF channels.
    channels = {
        name: OpenEXR.Channel(np.ascontiguousarray(image[:, :, index], dtype=np.float16))
        for index, name in enumerate(names)
    }
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    def write(tmp: Path) -> None:
        with OpenEXR.File(header, channels) as exr_file:
            exr_file.write(str(tmp))

    write_atomic(path, write, sync=sync)
