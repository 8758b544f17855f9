"""Read and write RTI light stacks: a folder of images plus one ``.lp`` light file.

An RTI light stack (method C, PAPERS.md part C) is a fixed camera looking at a fixed
object while one light moves. The standard ``.lp`` file holds, on its first non-blank
line, the number of images, then one line per image::

    72
    image01.jpg 0.2051 -0.2370 0.9495
    ...

``filename lx ly lz`` is a vector towards the light in the camera frame (x right, y up,
z towards the camera). Non-unit vectors are normalized; zero vectors are rejected.

A fixed view of a UBO2003 or UTIA BTF (one ``tvTTT_pvPPP/`` folder: 81 lights) is also a
light stack: :func:`load_btf_view` reads it with the BTF reader. Its frame is the
material's (z = the sample's normal, the BTF's θ/φ), and the view is that folder's
direction rather than (0, 0, 1).

Images may be JPEG, PNG (sRGB-encoded: linearized with the IEC 61966-2-1 EOTF; 16-bit
grey PNGs keep their precision, 16-bit RGB ones are reduced to 8 bits by Pillow) or EXR
(taken as linear).

Example
-------
>>> stack = load_light_stack("/data/rti/coin")            # doctest: +SKIP
>>> stack.images.shape, stack.light_dirs.shape            # doctest: +SKIP
((72, 395, 402, 3), (72, 3))
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from pipeline.core.errors import ConfigError, DataError
from pipeline.data.directions import unit_vectors
from pipeline.data.images import read_exr, srgb_eotf

__all__ = [
    "LightStack",
    "load_btf_view",
    "load_light_stack",
    "load_normal_map",
    "read_lp",
    "write_lp",
    "read_linear_rgb",
    "srgb_to_linear",
]

# A light vector shorter than this cannot be a direction: it is a typo or a placeholder.
_MIN_LIGHT_NORM = 1e-6
# Same for normals: a decoded normal this short means the map holds no normal there.
_MIN_NORMAL_NORM = 1e-3
_IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".exr"}


@dataclass
class LightStack:
    """A fixed-camera image stack under known light directions.

    Attributes
    ----------
    images : ndarray of shape (n, H, W, 3), float32
        Linear RGB, one image per light, in ``.lp`` order.
    light_dirs : ndarray of shape (n, 3), float32
        Unit vectors towards the light, camera frame (x right, y up, z to the camera).
    paths : list of Path
        The image files, in the same order.
    normals : ndarray of shape (H, W, 3), float32, or None
        Unit surface normals in the camera frame, when a normal map was given.
    lp_path : Path or None
        The ``.lp`` file the stack was read from.
    view_dir : ndarray of shape (3,), float64
        Unit vector towards the camera in the frame of ``light_dirs``: (0, 0, 1) for an
        RTI stack (camera frame), the view folder's direction for a BTF view.
    """

    images: np.ndarray
    light_dirs: np.ndarray
    paths: list[Path]
    normals: np.ndarray | None = None
    lp_path: Path | None = None
    view_dir: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of every image."""
        return int(self.images.shape[1]), int(self.images.shape[2])

    def subset(self, index) -> LightStack:
        """The stack restricted to the lights selected by ``index`` (mask or indices)."""
        index = np.asarray(index)
        if index.dtype == bool:
            index = np.flatnonzero(index)
        paths = [self.paths[i] for i in index]
        return replace(
            self, images=self.images[index], light_dirs=self.light_dirs[index], paths=paths
        )


# --------------------------------------------------------------------------- images


# sRGB decoding and EXR reading are shared with the BTF readers (pipeline.data.images).
srgb_to_linear = srgb_eotf


def _read_exr(path: Path) -> np.ndarray:
    channels = read_exr(path)
    if all(c in channels for c in "RGB"):
        planes = [channels[c] for c in "RGB"]
    elif "Y" in channels:
        planes = [channels["Y"]] * 3
    else:
        raise DataError(f"EXR image {path} has channels {sorted(channels)}, expected R, G, B or Y")
    return np.stack(planes, axis=-1).astype(np.float32)


def _read_pillow(path: Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            image.load()
            if image.mode in ("I;16", "I;16B", "I;16L", "I"):
                # 16-bit PNG: Pillow keeps the integer samples; scale by the 16-bit range.
                values = np.asarray(image, dtype=np.float32) / 65535.0
                values = np.repeat(values[..., None], 3, axis=-1)
            else:
                values = np.asarray(image.convert("RGB"), dtype=np.float32) / 255.0
    except (OSError, UnidentifiedImageError, SyntaxError) as exc:
        raise DataError(f"cannot read image {path}: {exc}") from exc
    return srgb_to_linear(values)


def read_linear_rgb(path: str | os.PathLike) -> np.ndarray:
    """Read a JPEG or PNG (sRGB-encoded, linearized here) or an EXR (taken as linear) as
    linear RGB of shape (H, W, 3), float32."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"image file {path} does not exist")
    if path.suffix.lower() == ".exr":
        return _read_exr(path)
    return _read_pillow(path)


# --------------------------------------------------------------------------- .lp files


def read_lp(lp_path: str | os.PathLike) -> tuple[list[Path], np.ndarray]:
    """Parse an RTI ``.lp`` file.

    Returns
    -------
    paths : list of Path
        Image files, resolved relative to the ``.lp`` file's folder. A listed path that
        does not exist but whose base name does (the file was written on another machine
        with absolute paths) resolves to that base name.
    light_dirs : ndarray of shape (n, 3), float32
        Unit light vectors.
    """
    paths, light_dirs, _ = _parse_lp(Path(lp_path))
    return paths, light_dirs


def _parse_lp(lp_path: Path) -> tuple[list[Path], np.ndarray, list[int]]:
    """:func:`read_lp`, also returning the line number of each entry (for messages)."""
    try:
        text = lp_path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise DataError(f"cannot read light file {lp_path}: {exc}") from exc
    lines = [(number, line.strip()) for number, line in enumerate(text.splitlines(), start=1)]
    lines = [(number, line) for number, line in lines if line]
    if not lines:
        raise DataError(f"light file {lp_path} is empty")
    count_line, count_text = lines[0]
    try:
        count = int(count_text.split()[0])
    except ValueError:
        raise DataError(
            f"{lp_path}, line {count_line}: expected the number of images, got {count_text!r}"
        ) from None
    entries = lines[1:]
    if count != len(entries):
        raise DataError(
            f"{lp_path}, line {count_line}: the count says {count} images but "
            f"{len(entries)} light lines follow"
        )
    paths, dirs, numbers = [], [], []
    for number, line in entries:
        tokens = line.split()
        try:
            if len(tokens) < 4:
                raise ValueError
            vector = np.array([float(t) for t in tokens[-3:]], dtype=np.float64)
        except ValueError:
            raise DataError(
                f"{lp_path}, line {number}: expected 'filename lx ly lz', got {line!r}"
            ) from None
        norm = float(np.linalg.norm(vector))
        if not np.isfinite(norm) or norm < _MIN_LIGHT_NORM:
            raise DataError(
                f"{lp_path}, line {number}: light vector {vector.tolist()} is zero or not "
                "finite, so it gives no direction"
            )
        # File names may contain spaces: everything before the three numbers is the name.
        name = " ".join(tokens[:-3])
        paths.append(_resolve_image(lp_path, number, name))
        dirs.append(vector / norm)
        numbers.append(number)
    return paths, np.asarray(dirs, dtype=np.float32).reshape(-1, 3), numbers


def _resolve_image(lp_path: Path, number: int, name: str) -> Path:
    listed = Path(name)
    candidate = listed if listed.is_absolute() else lp_path.parent / listed
    if candidate.is_file():
        return candidate
    # .lp files written on Windows often hold absolute paths of the capture machine.
    basename = lp_path.parent / name.replace("\\", "/").split("/")[-1]
    if basename.is_file():
        return basename
    raise DataError(f"{lp_path}, line {number}: listed image {candidate} does not exist")


def write_lp(path: str | os.PathLike, filenames: list[str], dirs: np.ndarray) -> Path:
    """Write an RTI ``.lp`` file at ``path`` and return it.

    Parameters
    ----------
    filenames : list of str
        Image file names, relative to the ``.lp`` file's folder; no line breaks.
    dirs : array_like of shape (n, 3)
        Vectors towards the light, written as given (readers normalize) with 9 decimals.
    """
    path = Path(path)
    dirs = np.asarray(dirs, dtype=np.float64)
    if dirs.ndim != 2 or dirs.shape[1] != 3:
        raise DataError(f"light directions for {path} must have shape (n, 3), got {dirs.shape}")
    if len(filenames) != len(dirs):
        raise DataError(f"{path}: {len(filenames)} file names but {len(dirs)} light directions")
    lines = [str(len(filenames))]
    for name, (x, y, z) in zip(filenames, dirs, strict=True):
        if not name or any(c in name for c in "\r\n"):
            raise DataError(f"{path}: file name {name!r} cannot be written to a .lp line")
        lines.append(f"{name} {x:.9f} {y:.9f} {z:.9f}")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


# --------------------------------------------------------------------------- normals


def load_normal_map(path: str | os.PathLike, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read a normal map as unit normals of shape (H, W, 3), float32.

    Parameters
    ----------
    path : path-like
        ``.png`` (n = 2 v / 255 - 1, no sRGB curve), ``.npy`` of shape (H, W, 3), or
        ``.exr`` with R, G, B = x, y, z.
    shape : (H, W), optional
        The expected image size; a mismatch is a DataError.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"normal map {path} does not exist")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        try:
            raw = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise DataError(f"cannot read normal map {path}: {exc}") from exc
    elif suffix == ".exr":
        raw = _read_exr(path)
    elif suffix == ".png":
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(path) as image:
                image.load()
                if image.mode.startswith("I"):
                    raise DataError(f"normal map {path} is single-channel; need RGB")
                # 16-bit RGB PNGs are opened by Pillow as 8-bit: fine for normals.
                raw = np.asarray(image.convert("RGB"), dtype=np.float32)
        except (OSError, UnidentifiedImageError, SyntaxError) as exc:
            raise DataError(f"cannot read normal map {path}: {exc}") from exc
        raw = 2.0 * raw / 255.0 - 1.0
    else:
        raise DataError(f"normal map {path}: unsupported suffix {suffix!r} (.png, .npy, .exr)")
    return _check_normals(np.asarray(raw), str(path), shape)


def _check_normals(raw: np.ndarray, name: str, shape: tuple[int, int] | None) -> np.ndarray:
    if raw.ndim != 3 or raw.shape[2] != 3:
        raise DataError(f"normal map {name} must have shape (H, W, 3), got {raw.shape}")
    if shape is not None and tuple(raw.shape[:2]) != tuple(shape):
        raise DataError(
            f"normal map {name} has size {raw.shape[:2]} but the images are {tuple(shape)}"
        )
    raw = raw.astype(np.float64)
    norm = np.linalg.norm(raw, axis=-1)
    bad = ~(np.isfinite(norm) & (norm > _MIN_NORMAL_NORM))
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise DataError(
            f"normal map {name} has {int(bad.sum())} zero or non-finite normals "
            f"(first at row {row}, column {col})"
        )
    return (raw / norm[..., None]).astype(np.float32)


# --------------------------------------------------------------------------- stack


def load_light_stack(
    root: str | os.PathLike, normals: str | os.PathLike | np.ndarray | None = None
) -> LightStack:
    """Read a light stack: the images listed in the folder's single ``.lp`` file.

    Parameters
    ----------
    root : path-like
        Folder with the images and exactly one ``.lp`` file.
    normals : path-like or ndarray of shape (H, W, 3), optional
        A normal map (see :func:`load_normal_map`) or an array of normals.

    Raises
    ------
    DataError
        Missing folder, zero or several ``.lp`` files, a malformed line (named with its
        line number), a missing or unreadable image, a zero light vector, images of
        different sizes, or a normal map of the wrong shape.
    """
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"light-stack folder {root} does not exist")
    lp_files = sorted(p for p in root.iterdir() if p.suffix.lower() == ".lp" and p.is_file())
    if not lp_files:
        raise DataError(f"light-stack folder {root} holds no .lp light file")
    if len(lp_files) > 1:
        names = ", ".join(p.name for p in lp_files)
        raise DataError(f"light-stack folder {root} holds several .lp files ({names}); keep one")
    lp_path = lp_files[0]
    paths, light_dirs, line_numbers = _parse_lp(lp_path)
    if not paths:
        raise DataError(f"light file {lp_path} lists no images")

    images = None
    for index, path in enumerate(paths):
        if path.suffix.lower() not in _IMAGE_SUFFIXES:
            raise DataError(
                f"{lp_path}, line {line_numbers[index]}: image {path} has unsupported suffix {path.suffix!r} "
                "(JPEG, PNG or EXR)"
            )
        try:
            image = read_linear_rgb(path)
        except DataError as exc:
            raise DataError(f"{lp_path}, line {line_numbers[index]}: {exc}") from exc
        if images is None:
            # Allocate once: a stack is large, and a list of arrays plus np.stack doubles it.
            images = np.empty((len(paths), *image.shape), dtype=np.float32)
        elif image.shape != images.shape[1:]:
            raise DataError(
                f"image {path} is {image.shape[1]}x{image.shape[0]} (WxH) but {paths[0]} is "
                f"{images.shape[2]}x{images.shape[1]}: a light stack needs one image size"
            )
        images[index] = image

    normal_map = None
    if isinstance(normals, np.ndarray):
        normal_map = _check_normals(normals, "array", images.shape[1:3])
    elif normals is not None:
        normal_map = load_normal_map(normals, images.shape[1:3])
    return LightStack(
        images=images, light_dirs=light_dirs, paths=paths, normals=normal_map, lp_path=lp_path
    )


# --------------------------------------------------------------------------- BTF view


def load_btf_view(root: str | os.PathLike, format: str = "ubo2003", view=(0, 0)) -> LightStack:
    """One view folder of a UBO2003 or UTIA BTF as a light stack (81 lights).

    Parameters
    ----------
    root : path-like
        The BTF's folder, holding the view folders ``tvTTT_pvPPP/``.
    format : {"ubo2003", "utia"}
        The layout and colour encoding (:mod:`pipeline.data.btf`).
    view : (θ_view, φ_view) in whole degrees
        One of the 81 grid directions, whose folder must be on disk.

    Returns
    -------
    LightStack
        Images in the canonical light order; ``light_dirs`` and ``view_dir`` are unit
        vectors in the material's frame (x = φ 0°, z = the sample's normal), computed
        from the angles in the file names. ``lp_path`` is None.

    Raises
    ------
    ConfigError
        ``view`` is not one grid direction, or ``format`` is unknown.
    DataError
        As :func:`pipeline.data.btf.load_btf` (missing folder, missing lights, ...).
    """
    from pipeline.data.btf import load_btf

    angles = np.asarray(view, dtype=np.float64)
    if angles.shape != (2,):
        raise ConfigError(
            f"a BTF view is one [theta_v, phi_v] pair in degrees, got {np.asarray(view).tolist()}"
        )
    btf = load_btf(root, format, views=[tuple(angles)], progress=False)
    light_dirs = unit_vectors(btf.directions[:, 0], btf.directions[:, 1])
    view_dir = unit_vectors(btf.directions[0, 2], btf.directions[0, 3])
    return LightStack(
        images=btf.images,
        light_dirs=light_dirs.astype(np.float32),
        paths=btf.paths,
        view_dir=view_dir.astype(np.float64),
    )
