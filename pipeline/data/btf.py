"""Readers for measured BTFs in the UBO2003 and UTIA folder layouts.

Both layouts hold one folder per view direction, ``tvTTT_pvPPP/``, each with one image per
light direction; the angles are parsed from the names, never taken from the order of the
files (see :mod:`pipeline.data.directions`). Images come back in canonical order: views
in grid order, and within each view the 81 lights in grid order.

Formats and their colour encodings:

``ubo2003``
    ``00008 tl000 pl000 tv030 pv030.jpg``: 8-bit JPEG, gamma 2.2 (linearized here).
    A lossless variant with the same names is also read: ``.png`` (8-bit, gamma 2.2) or
    ``.exr`` (half-float linear RGB, channels R, G, B).
``utia``
    ``tl000_pl000_tv000_pv000.png``: 8-bit sRGB (linearized with the sRGB EOTF), or
    ``.exr``: half-float CIE XYZ (D65) in channels X, Y, Z, converted to linear sRGB.
    Some UTIA EXR files label their XYZ data R, G, B; when X, Y, Z are absent, R, G, B
    are read *as X, Y, Z*.

A dataset may also be read straight from its ``.zip`` archive (no unpacking): give the
archive as the root. The view folders may sit at the archive's top level or inside one
folder (``WOOL/tv000_pv000/...``); the images decode bit for bit as from the unpacked folder.

How 8-bit images are linearized is a setting (``linearize``): each layout's own
convention by default (:data:`DEFAULT_LINEARIZE`), or ``"gamma2.2"``, ``"srgb"`` or
``"none"`` (keep the encoded values; the paper does not say whether its UBO2003 errors
are on the encoded or the linear scale). EXR files hold linear values and are never
re-encoded.

Examples
--------
>>> n, height, width = count_btf_images(root, "ubo2003")         # doctest: +SKIP
>>> images = np.lib.format.open_memmap(path, "w+", np.float32, (n, height, width, 3))  # doctest: +SKIP
>>> btf = load_btf(root, "ubo2003", out=images)                    # doctest: +SKIP
"""

from __future__ import annotations

import hashlib
import re
import struct
import sys
import time
import zipfile
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import NamedTuple

import numpy as np
from tqdm import tqdm

from pipeline.core.errors import ConfigError, DataError
from pipeline.core.files import output_array
from pipeline.data.directions import (
    N_DIRECTIONS,
    canonical_views,
    direction_index,
    grid_81_degrees,
    is_grid_direction,
    parse_ubo2003_file_name,
    parse_utia_file_name,
    parse_view_folder_name,
    ubo2003_file_name,
    utia_file_name,
    view_folder_name,
)
from pipeline.data.images import (
    gamma_decode,
    gamma_encode,
    image_size,
    linear_srgb_to_xyz,
    read_exr,
    read_exr_channels,
    read_image_8bit,
    srgb_eotf,
    srgb_oetf,
    write_exr,
    write_image_8bit,
    xyz_to_linear_srgb,
)

# Image extensions (lower case, no dot) each format may use.
FORMAT_EXTENSIONS = {"ubo2003": ("jpg", "jpeg", "png", "exr"), "utia": ("png", "exr")}
UBO2003_GAMMA = 2.2
ARCHIVE_SUFFIX = ".zip"
_VIEW_FOLDER = re.compile(r"^tv\d{3}_pv\d{3}$")
# Folders never read as view folders: hidden ones, and the resource forks macOS adds to
# the archives it makes.
_MACOS_FORKS = "__MACOSX"
# How 8-bit images are decoded to linear values: a layout's own convention and the choices.
DEFAULT_LINEARIZE = {"ubo2003": "gamma2.2", "utia": "srgb"}
LINEARIZE_CHOICES = ("gamma2.2", "srgb", "none")


def check_linearize(linearize: str | None, format: str) -> str:
    """The decoding to apply: ``linearize``, or ``format``'s convention when None."""
    _check_format(format)
    if linearize is None:
        return DEFAULT_LINEARIZE[format]
    if linearize not in LINEARIZE_CHOICES:
        raise ConfigError(
            f"dataset.linearize={linearize!r} is not one of {list(LINEARIZE_CHOICES)} "
            f"(or null for the layout's own: {DEFAULT_LINEARIZE})"
        )
    return linearize


@dataclass
class BTF:
    """A BTF in memory (or memory-mapped).

    Attributes
    ----------
    images : ndarray of shape (n_images, height, width, 3), float32
        Linear RGB, in canonical order (view-major).
    directions : ndarray of shape (n_images, 4), float64
        (θ_light, φ_light, θ_view, φ_view) in radians, row ``i`` belonging to ``images[i]``.
    paths : list of Path (or zipfile.Path, for an archive's members)
        Source file of each image.
    view_folders : list of Path (or zipfile.Path)
        The view folders read, in canonical order.
    root : Path
        The dataset folder (or its ``.zip`` archive).
    """

    images: np.ndarray
    directions: np.ndarray
    paths: list[Path]
    view_folders: list[Path]
    root: Path


class BTFFile(NamedTuple):
    """One image file of a BTF dataset, with its angles in whole degrees."""

    path: Path
    theta_light: int
    phi_light: int
    theta_view: int
    phi_view: int


def _check_format(format: str) -> None:
    if format not in FORMAT_EXTENSIONS:
        raise ConfigError(f"BTF format {format!r} is not one of {sorted(FORMAT_EXTENSIONS)}")


_NAME_PARSERS = {"ubo2003": parse_ubo2003_file_name, "utia": parse_utia_file_name}


# --- zip archives ------------------------------------------------------------------------


def is_archive(root: str | PathLike) -> bool:
    """Whether ``root`` is a ``.zip`` file (a dataset read without unpacking)."""
    root = Path(root)
    return root.suffix.lower() == ARCHIVE_SUFFIX and root.is_file()


def _open_archive(archive: Path) -> zipfile.ZipFile:
    try:
        return zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, OSError) as error:
        raise DataError(f"cannot read zip archive {archive}: {error}") from None


def _archive_prefix(names: list[str], archive: Path) -> str:
    """The folder inside the archive holding the view folders: "" (the top) or "WOOL/"."""
    prefixes = set()
    for name in names:
        parts = name.split("/")
        if parts[0] == _MACOS_FORKS:
            continue
        for depth, part in enumerate(parts[:-1]):
            if _VIEW_FOLDER.match(part):
                prefixes.add("".join(f"{folder}/" for folder in parts[:depth]))
                break
    if not prefixes:
        raise DataError(f"no view folders (tvTTT_pvPPP) in zip archive {archive}")
    if len(prefixes) > 1:
        raise DataError(
            f"zip archive holds view folders in {len(prefixes)} places "
            f"{sorted(prefix or '(top)' for prefix in prefixes)}; "
            f"one dataset per archive: {archive}"
        )
    return prefixes.pop()


def _open_root(root: str | PathLike):
    """``root`` itself, or the view folders' folder in a ``.zip`` archive (a
    :class:`zipfile.Path`, which lists and reads members like a Path)."""
    root = Path(root)
    if root.is_dir():
        return root
    if not is_archive(root):
        raise DataError(f"BTF root folder (or .zip archive) does not exist: {root}")
    archive = _open_archive(root)
    return zipfile.Path(archive, at=_archive_prefix(archive.namelist(), root))


def _unzipped_mtime_ns(info: zipfile.ZipInfo) -> int:
    """The modification time ``unzip`` gives a member's file, in whole seconds as ns: an
    extended-timestamp field's Unix time, else an NTFS field's, else the DOS time (which
    has no time zone: read as local time, as ``unzip`` does)."""
    extra, position, ntfs = info.extra, 0, None
    while position + 4 <= len(extra):
        tag, size = struct.unpack_from("<HH", extra, position)
        data = extra[position + 4 : position + 4 + size]
        if tag == 0x5455 and len(data) >= 5 and data[0] & 1:  # "UT": flags, mtime
            return struct.unpack_from("<i", data, 1)[0] * 10**9
        if tag == 0x000A and len(data) >= 32 and struct.unpack_from("<H", data, 4)[0] == 1:
            filetime = struct.unpack_from("<Q", data, 8)[0]  # 100 ns since 1601
            ntfs = (filetime - 116_444_736_000_000_000) // 10**7 * 10**9
        position += 4 + size
    if ntfs is not None:
        return ntfs
    return int(time.mktime((*info.date_time, 0, 0, -1))) * 10**9


def archive_fingerprint(archive: str | PathLike) -> dict:
    """The fingerprint of a zipped dataset, from the archive's directory alone.

    The same as :func:`pipeline.core.stage.folder_fingerprint` of the folder holding the
    view folders once ``unzip`` has unpacked it (which restores the recorded times), so
    the archive and its unpacked folder share one cache entry of the load stage.

    Raises
    ------
    DataError
        Naming the archive, if it is unreadable or holds no view folders.
    """
    archive = Path(archive)
    with _open_archive(archive) as opened:
        members = opened.infolist()
    prefix = _archive_prefix([member.filename for member in members], archive)
    files = [m for m in members if m.filename.startswith(prefix) and not m.is_dir()]
    names = sorted(member.filename[len(prefix) :] for member in files)
    return {
        "files": len(files),
        "bytes": sum(member.file_size for member in files),
        "mtime_ns": max((_unzipped_mtime_ns(member) for member in files), default=0),
        "names": hashlib.sha256("\n".join(names).encode()).hexdigest()[:16],
    }


def _expected_name_hint(folder, format: str, light, view, ext: str, number_bases: set[int]):
    """Best guess of the path of a missing image, for the error message.

    UBO2003 running numbers are not implied by the angles; when every present file of the
    folder has number = base + light index for one base, the missing number is that too.
    """
    if format == "utia":
        return folder / utia_file_name(*light, *view, ext)
    if len(number_bases) == 1:
        number = next(iter(number_bases)) + direction_index(*light)
        if 0 <= number <= 99999:
            return folder / ubo2003_file_name(number, *light, *view, ext)
    return folder / ubo2003_file_name(0, *light, *view, ext).replace("00000", "?????", 1)


def _visible_entries(folder) -> list:
    """The entries of ``folder`` (a Path or zipfile.Path) not hidden, sorted by name."""
    return [path for path in sorted(folder.iterdir(), key=str) if not path.name.startswith(".")]


def _list_view_folder(folder, view: tuple[int, int], format: str) -> list[BTFFile]:
    """Parse and check the image names of one view folder; return them in light order."""
    allowed = FORMAT_EXTENSIONS[format]
    image_paths = [
        path
        for path in _visible_entries(folder)
        if path.is_file() and path.suffix.lower().lstrip(".") in allowed
    ]
    if not image_paths:
        raise DataError(f"view folder holds no {'/'.join(allowed)} images: {folder}")
    by_light: dict[tuple[int, int], Path] = {}
    number_bases: set[int] = set()
    for path in image_paths:
        # str(): the parsers take the name of a path, which a zipfile.Path is not.
        name = _NAME_PARSERS[format](str(path))
        if (name.theta_view, name.phi_view) != view:
            raise DataError(
                f"image's view angles (tv={name.theta_view}, pv={name.phi_view}) disagree "
                f"with its folder {folder.name}: {path}"
            )
        light = (name.theta_light, name.phi_light)
        if not is_grid_direction(*light):
            raise DataError(
                f"light (tl={light[0]}, pl={light[1]}) is not one of the 81 grid directions: {path}"
            )
        if light in by_light:
            raise DataError(f"two images for the same light: {by_light[light]} and {path}")
        by_light[light] = path
        if name.number is not None:
            number_bases.add(name.number - direction_index(*light))
    grid = [(int(theta), int(phi)) for theta, phi in grid_81_degrees()]
    missing = [light for light in grid if light not in by_light]
    if missing:
        ext = image_paths[0].suffix.lstrip(".")
        hints = [
            str(_expected_name_hint(folder, format, light, view, ext, number_bases))
            for light in missing[:3]
        ]
        more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
        raise DataError(
            f"view folder {folder} has {len(by_light)} of the {N_DIRECTIONS} lights; "
            f"missing image(s): {', '.join(hints)}{more}"
        )
    return [BTFFile(by_light[light], *light, *view) for light in grid]


def list_btf_files(root: str | PathLike, format: str = "ubo2003", views=None) -> list[BTFFile]:
    """Find, parse and check the image files of a BTF dataset, without decoding any.

    Parameters
    ----------
    root : path-like
        Dataset folder holding the view folders ``tvTTT_pvPPP``, or a ``.zip`` archive of
        it (read without unpacking). Files at the top level, hidden folders (starting
        with ``.``) and ``__MACOSX`` are ignored.
    format : {"ubo2003", "utia"}
    views : sequence of (θ_view, φ_view) in degrees, or None
        Only these views (each must be on disk); None means every view folder present.

    Returns
    -------
    list of BTFFile
        In canonical order, ``n_views * 81`` entries; for an archive, each ``path`` is a
        :class:`zipfile.Path` (its ``str`` is ``archive.zip/folder/name``).

    Raises
    ------
    DataError
        Naming the path at fault: missing root, an unreadable archive, no view folders,
        an unparseable or off-grid name, view angles disagreeing with the folder, a
        requested view without a folder, a missing or doubled light, or image files of
        mixed extensions.
    ConfigError
        For an unknown ``format`` or a ``views`` entry off the grid.
    """
    _check_format(format)
    root = _open_root(root)
    requested = None if views is None else canonical_views(views)
    folders = [
        path for path in _visible_entries(root) if path.is_dir() and path.name != _MACOS_FORKS
    ]
    if not folders:
        raise DataError(f"no view folders (tvTTT_pvPPP) in BTF root {root}")
    folder_of_view: dict[tuple[int, int], Path] = {}
    for folder in folders:
        view = parse_view_folder_name(str(folder))
        if not is_grid_direction(*view):
            raise DataError(f"view folder's angles are not one of the 81 grid directions: {folder}")
        folder_of_view[view] = folder
    if requested is not None:
        absent = [view for view in requested if view not in folder_of_view]
        if absent:
            names = ", ".join(str(root / view_folder_name(*view)) for view in absent)
            raise DataError(f"requested view folder(s) not found: {names}")
        chosen_views = requested
    else:
        chosen_views = sorted(folder_of_view, key=lambda view: direction_index(*view))

    files: list[BTFFile] = []
    for view in chosen_views:
        files.extend(_list_view_folder(folder_of_view[view], view, format))
    # Mixed extensions would mean two different encodings in one dataset.
    first_ext = files[0].path.suffix.lower()
    for entry in files:
        if entry.path.suffix.lower() != first_ext:
            raise DataError(
                f"image extension differs from the dataset's first image "
                f"({files[0].path}): {entry.path}"
            )
    return files


def decode_btf_image(
    path: str | PathLike, format: str = "ubo2003", linearize: str | None = None
) -> np.ndarray:
    """Read one BTF image file as linear RGB.

    Parameters
    ----------
    path : path-like or zipfile.Path
        A ``.jpg``/``.jpeg``/``.png`` (8-bit) or ``.exr`` (half float) file, or such a
        member of a zip archive.
    format : {"ubo2003", "utia"}
        Chooses the encoding (see the module docstring).
    linearize : {"gamma2.2", "srgb", "none"} or None
        Decoding of 8-bit files; None is the format's own (:data:`DEFAULT_LINEARIZE`).

    Returns
    -------
    ndarray of shape (H, W, 3), float32
        Linear RGB. UTIA XYZ converted to sRGB may hold small negative values for
        out-of-gamut colours; they are kept, not clipped.

    Raises
    ------
    DataError
        Naming the file, if it is missing, corrupt, lacks the channels, or holds NaN/Inf.
    """
    linearize = check_linearize(linearize, format)  # checks the format too
    path = path if isinstance(path, zipfile.Path) else Path(path)
    if path.suffix.lower() == ".exr":
        if format == "ubo2003":
            return read_exr_channels(path, ("R", "G", "B"))
        channels = read_exr(path)
        for names in ("XYZ", "RGB"):  # some UTIA files label their XYZ data R, G, B
            if all(name in channels for name in names):
                return xyz_to_linear_srgb(np.stack([channels[name] for name in names], axis=-1))
        raise DataError(
            f"UTIA EXR has neither X, Y, Z nor R, G, B channels (has {sorted(channels)}): {path}"
        )
    encoded = read_image_8bit(path)
    if linearize == "gamma2.2":
        return gamma_decode(encoded, UBO2003_GAMMA)
    if linearize == "srgb":
        return srgb_eotf(encoded)
    return encoded.astype(np.float32)


def encode_btf_image(
    path: str | PathLike,
    linear_rgb: np.ndarray,
    format: str = "ubo2003",
    quality: int = 95,
    *,
    sync: bool = True,
) -> None:
    """Write one linear RGB image as ``format`` stores it (:func:`decode_btf_image`'s inverse).

    Parameters
    ----------
    path : path-like
        Its extension picks the file type: ``.jpg``/``.jpeg`` (JPEG ``quality``, UBO2003
        only), ``.png`` (8-bit) or ``.exr`` (half float: R, G, B for UBO2003, X, Y, Z for
        UTIA).
    linear_rgb : ndarray of shape (H, W, 3)
        Linear RGB; 8-bit encodings clip it to [0, 1].
    format : {"ubo2003", "utia"}
    quality : int
        JPEG quality 1..100.
    sync : bool
        fsync before the rename; False for a staging folder published as a whole.
    """
    _check_format(format)
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix not in FORMAT_EXTENSIONS[format]:
        raise ConfigError(f"extension {suffix!r} is not used by format {format!r}: {path}")
    if suffix == "exr":
        if format == "utia":
            write_exr(path, linear_srgb_to_xyz(linear_rgb), names=("X", "Y", "Z"), sync=sync)
        else:
            write_exr(path, linear_rgb, names=("R", "G", "B"), sync=sync)
    elif format == "utia":
        write_image_8bit(path, srgb_oetf(linear_rgb), sync=sync)
    else:
        write_image_8bit(path, gamma_encode(linear_rgb, UBO2003_GAMMA), quality=quality, sync=sync)


def count_btf_images(
    root: str | PathLike, format: str = "ubo2003", views=None
) -> tuple[int, int, int]:
    """(n_images, height, width) of a dataset, checking names and reading one header, to
    allocate :func:`load_btf`'s ``out``; raises as :func:`list_btf_files`."""
    files = list_btf_files(root, format, views)
    height, width = image_size(files[0].path)
    return len(files), height, width


def load_btf(
    root: str | PathLike,
    format: str = "ubo2003",
    views=None,
    out: np.ndarray | None = None,
    progress: bool = True,
    linearize: str | None = None,
) -> BTF:
    """Load a UBO2003 or UTIA BTF as linear RGB in canonical order.

    Parameters
    ----------
    root, format, views
        As in :func:`list_btf_files`.
    out : ndarray of shape (n_images, H, W, 3), float32, optional
        Writable array (e.g. ``np.lib.format.open_memmap``) to decode into, so a large
        dataset is never held twice; get its shape from :func:`count_btf_images`.
    progress : bool
        Show a tqdm progress bar (only when stderr is a terminal).
    linearize : {"gamma2.2", "srgb", "none"} or None
        Decoding of 8-bit images (see :func:`decode_btf_image`).

    Returns
    -------
    BTF
        ``images`` is ``out`` when given.

    Raises
    ------
    DataError, ConfigError
        As :func:`list_btf_files`; also a DataError for a missing, corrupt or
        differently sized image or NaN/Inf in an EXR, a ConfigError for a wrong ``out``.
    """
    linearize = check_linearize(linearize, format)
    files = list_btf_files(root, format, views)
    height, width = image_size(files[0].path)
    shape = (len(files), height, width, 3)
    out = output_array(out, shape)
    show_bar = progress and sys.stderr.isatty()
    for index, entry in enumerate(
        tqdm(files, desc=f"decode {Path(root).name}", unit="img", leave=False, disable=not show_bar)
    ):
        image = decode_btf_image(entry.path, format, linearize)
        if image.shape[:2] != (height, width):
            raise DataError(
                f"image is {image.shape[1]}x{image.shape[0]} (width x height) but "
                f"{files[0].path} is {width}x{height}: {entry.path}"
            )
        out[index] = image
    return BTF(
        images=out,
        directions=np.deg2rad(np.array([entry[1:] for entry in files], np.float64).reshape(-1, 4)),
        paths=[entry.path for entry in files],
        view_folders=[entry.path.parent for entry in files[::N_DIRECTIONS]],
        root=Path(root),
    )
