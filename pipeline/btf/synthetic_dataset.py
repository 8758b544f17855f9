"""Built-in fabric datasets on disk: their direction sets, and the writer in real layouts.

A written dataset (:func:`write_synthetic_btf`) holds :class:`pipeline.btf.synthetic.SyntheticBTF`
images with light and view sampled on a direction set (:func:`synthetic_directions`).
:func:`generator_settings` gives the ``dataset.synthetic`` settings as the dataset's folder
name, its marker and the cache keys record them.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import uuid
from os import PathLike
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pipeline.btf.synthetic import SyntheticBTF
from pipeline.core.errors import ConfigError, DataError
from pipeline.data.btf import encode_btf_image
from pipeline.data.directions import (
    N_DIRECTIONS,
    canonical_views,
    direction_index,
    fibonacci_hemisphere,
    grid_81,
    grid_81_degrees,
    product_directions,
    ubo2003_file_name,
    utia_file_name,
    view_folder_name,
)

# Recorded in each dataset's marker: a folder whose marker holds another version is not
# taken for this generator's output.
_GENERATOR_VERSION = 1
_MARKER_NAME = "synthetic_btf.json"
UBO2014_FILE_NAME = "synthetic.btf"  # inside the dataset folder, beside the marker

# The direction sets of a written dataset (dataset.synthetic.directions), and how far from
# the normal a Fibonacci set reaches (about UBO2014's reach; below 90 degrees, where the
# shading of every texel fades out).
DIRECTION_SETS = ("ubo2003", "fibonacci")
FIBONACCI_MAX_THETA_DEGREES = 80.0
# The direction-set settings at their defaults. They came after datasets and cache entries
# existed: at these values they are left out of the dataset's folder name, its marker and
# the cache keys (generator_settings), so that those stay in use.
DEFAULT_DIRECTIONS = {"directions": "ubo2003", "n_lights": None, "n_views": None}


def generator_settings(gen: dict) -> dict:
    """``dataset.synthetic`` settings as folder names, markers and cache keys hold them:
    without the direction-set settings when those are all at their defaults
    (:data:`DEFAULT_DIRECTIONS`)."""
    if all(gen.get(key) == value for key, value in DEFAULT_DIRECTIONS.items()):
        return {key: value for key, value in gen.items() if key not in DEFAULT_DIRECTIONS}
    return dict(gen)


def synthetic_directions(
    directions: str = "ubo2003", n_lights: int | None = None, n_views: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The light and the view set, (L, 2) and (V, 2) (θ, φ) radians, of a written built-in
    BTF: for ``directions="ubo2003"`` the 81-grid for both (``n_lights`` and ``n_views``
    None), for ``"fibonacci"`` :func:`pipeline.data.directions.fibonacci_hemisphere` spirals
    of ``n_lights`` and ``n_views`` directions up to :data:`FIBONACCI_MAX_THETA_DEGREES`.
    ConfigError for an unknown set, or counts that do not go with it."""
    if directions not in DIRECTION_SETS:
        raise ConfigError(
            f"dataset.synthetic.directions={directions!r} is not one of {list(DIRECTION_SETS)}"
        )
    counts = {"n_lights": n_lights, "n_views": n_views}
    if directions == "ubo2003":
        given = [name for name, count in counts.items() if count is not None]
        if given:
            raise ConfigError(
                f"dataset.synthetic.{given[0]}={counts[given[0]]!r} goes with "
                f"directions=fibonacci only; directions=ubo2003 is the 81-grid (set it null)"
            )
        return grid_81(), grid_81()
    for name, count in counts.items():
        if count is None:
            raise ConfigError(
                f"dataset.synthetic.directions=fibonacci needs "
                f"dataset.synthetic.{name} (an integer >= 3)"
            )
    return (
        fibonacci_hemisphere(n_lights, FIBONACCI_MAX_THETA_DEGREES),
        fibonacci_hemisphere(n_views, FIBONACCI_MAX_THETA_DEGREES),
    )


# --- writer in the real layouts ----------------------------------------------------------

_WRITABLE = {"ubo2003": ("jpg", "png", "exr"), "utia": ("png", "exr"), "ubo2014": ("btf",)}


def _read_marker(root: Path) -> dict | None:
    try:
        marker = json.loads((root / _MARKER_NAME).read_text())
    except (OSError, ValueError):
        return None
    # Markers written before there were presets describe the same plain weave.
    if isinstance(marker, dict):
        marker.setdefault("material", "plain_weave")
    return marker


def write_synthetic_btf(
    root: str | PathLike,
    size: int = 64,
    seed: int = 0,
    format: str = "ubo2003",
    ext: str = "jpg",
    views=None,
    quality: int = 95,
    material: str = "plain_weave",
    directions: str = "ubo2003",
    n_lights: int | None = None,
    n_views: int | None = None,
) -> Path:
    """Write :class:`SyntheticBTF` images as a dataset in the UBO2003, UTIA or UBO2014 layout.

    The dataset is written into a hidden temporary sibling folder, one view at a time
    (memory stays at one view's 81 images), then renamed to ``root``; a killed run thus
    never leaves a half dataset under ``root``. A ``synthetic_btf.json`` marker in
    ``root`` records the parameters; when ``root`` already holds a dataset written with
    the same parameters, nothing is rewritten.

    The UBO2014 layout holds any direction set (:func:`synthetic_directions`): one file,
    ``root / UBO2014_FILE_NAME``, with every light under every view, stored losslessly
    (:func:`_write_ubo2014`).

    Parameters
    ----------
    root : path-like, the dataset folder to create.
    size, seed, material
        Passed to :class:`SyntheticBTF` (and recorded in the marker).
    format : {"ubo2003", "utia", "ubo2014"}
    ext : str
        ``ubo2003``: ``"jpg"`` (gamma 2.2, JPEG ``quality``), ``"png"`` (gamma 2.2, 8-bit)
        or ``"exr"`` (half linear RGB). ``utia``: ``"png"`` (8-bit sRGB) or ``"exr"``
        (half XYZ). ``ubo2014``: ``"btf"``.
    views : sequence of (θ_view, φ_view) in degrees, or None
        Write only these view folders; None writes all 81. The UBO2014 layout writes every
        view of its set (None only): its reader picks views.
    quality : int, JPEG quality, 1..100.
    directions, n_lights, n_views
        The direction set (:func:`synthetic_directions`); other than the default
        ``ubo2003`` only in the ``ubo2014`` layout.

    Returns
    -------
    Path
        ``root``; for the UBO2014 layout the file ``root / UBO2014_FILE_NAME``.

    Raises
    ------
    ConfigError
        For an unknown format/extension pair or material, an off-grid view, a direction
        set the layout cannot hold, views given to the UBO2014 layout, or a bad quality.
    DataError
        If ``root`` exists, is not an empty folder, and is not this generator's output
        with these parameters.
    """
    if format not in _WRITABLE:
        raise ConfigError(f"format {format!r} is not one of {sorted(_WRITABLE)}")
    if ext not in _WRITABLE[format]:
        raise ConfigError(f"ext {ext!r} is not one of {_WRITABLE[format]} for format {format!r}")
    if not 1 <= int(quality) <= 100:
        raise ConfigError(f"JPEG quality={quality!r} must be in 1..100")
    fabric = SyntheticBTF(size=size, seed=seed, material=material)
    light_set, view_set = synthetic_directions(directions, n_lights, n_views)
    if format != "ubo2014" and directions != "ubo2003":
        raise ConfigError(
            f"dataset.synthetic.directions={directions!r} cannot be written in the {format} "
            f"layout, whose file names hold the 81-grid only: write it as UBO2014 "
            f"(dataset.format=ubo2014 dataset.synthetic.ext=btf)"
        )
    if format == "ubo2014" and views is not None:
        raise ConfigError(
            f"views={views!r}: the UBO2014 layout writes every view of the set; choose views "
            f"when reading it (dataset.views)"
        )
    view_list = canonical_views(views) if format != "ubo2014" else None
    root = Path(root)
    marker = {
        "generator": "pipeline.btf.synthetic.SyntheticBTF",
        "version": _GENERATOR_VERSION,
        "size": fabric.size,
        "seed": int(seed),
        "material": fabric.material,
        "n_threads": fabric.n_threads,
        "format": format,
        "ext": ext,
        "views": None if view_list is None else [list(view) for view in view_list],
        "quality": int(quality),
        # Only when not the default: markers written before the setting existed match.
        **generator_settings({"directions": directions, "n_lights": n_lights, "n_views": n_views}),
    }
    written = root / UBO2014_FILE_NAME if format == "ubo2014" else root
    if root.exists() and not (root.is_dir() and not any(root.iterdir())):
        if _read_marker(root) == marker:
            return written
        raise DataError(
            f"{root} exists but is not a synthetic BTF written with {marker}; "
            f"remove it or choose another root"
        )
    root.parent.mkdir(parents=True, exist_ok=True)
    partial = root.parent / f".{root.name}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    partial.mkdir()
    try:
        if format == "ubo2014":
            _write_ubo2014(partial / UBO2014_FILE_NAME, fabric, light_set, view_set)
        else:
            _write_view_folders(partial, fabric, view_list, format, ext, quality, root.name)
        os.sync()  # every image on disk before the marker and the rename publish them
        # The marker goes in last: its presence means every image before it was written.
        (partial / _MARKER_NAME).write_text(json.dumps(marker, indent=1))
        try:
            partial.rename(root)
        except OSError:
            # Another process finished the same dataset first; keep theirs if it matches.
            if _read_marker(root) != marker:
                raise
            shutil.rmtree(partial, ignore_errors=True)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return written


def _write_view_folders(
    partial: Path, fabric: SyntheticBTF, view_list, format: str, ext: str, quality: int, name: str
) -> None:
    """The 81 lights of each view of ``view_list`` (degrees) as images in the UBO2003 or
    UTIA layout, one view folder at a time, under ``partial``."""
    lights = grid_81_degrees()
    light_radians = np.deg2rad(lights.astype(np.float64))
    show_bar = sys.stderr.isatty()
    for view in tqdm(view_list, desc=f"write {name}", leave=False, disable=not show_bar):
        view_index = direction_index(*view)
        folder = partial / view_folder_name(*view)
        folder.mkdir()
        view_radians = np.broadcast_to(
            np.deg2rad(np.array(view, dtype=np.float64)), (N_DIRECTIONS, 2)
        )
        images = fabric.evaluate(np.concatenate([light_radians, view_radians], axis=1))
        for light_index, (theta_light, phi_light) in enumerate(lights):
            if format == "ubo2003":
                # The index in the full view-major order: a subset of views is named as
                # the full dataset's folders are.
                number = view_index * N_DIRECTIONS + light_index
                file_name = ubo2003_file_name(number, theta_light, phi_light, *view, ext)
            else:
                file_name = utia_file_name(theta_light, phi_light, *view, ext)
            # Not synced one by one: one os.sync covers the whole folder.
            encode_btf_image(folder / file_name, images[light_index], format, quality, sync=False)


def _write_ubo2014(path: Path, fabric: SyntheticBTF, lights: np.ndarray, views: np.ndarray):
    """The fabric at every light (L, 2) under every view (V, 2), as a lossless DFMF file:
    colour model 0 (linear RGB), the incident cosine in the data, and float32 factors of
    full rank (one of U and SV is the identity) that :mod:`pipeline.data.ubo2014` decodes
    exactly."""
    from pipeline.data.ubo2014_write import write_dfmf

    # The file stores float32 angles: render at exactly those, so data and truth agree.
    lights, views = lights.astype(np.float32), views.astype(np.float32)
    images = fabric.evaluate(product_directions(lights, views))  # (N, size, size, 3)
    n, texels = len(images), fabric.size**2
    # The file's texel order: column y · width + x with y from the bottom (image row r is
    # the file's row size - 1 - r), as pipeline.data.ubo2014_write.encode_values lays out.
    matrices = images[:, ::-1].reshape(n, texels, 3)
    factors = []
    for channel in range(3):
        matrix = np.ascontiguousarray(matrices[..., channel])  # (N, texels)
        # Full rank K = min(N, texels) with one factor the identity: U · SVᵀ is the data,
        # each value a sum of one product by 1 and exact zeros.
        if n <= texels:
            u, sv = np.eye(n, dtype=np.float32), np.ascontiguousarray(matrix.T)
        else:
            u, sv = matrix, np.eye(texels, dtype=np.float32)
        factors.append((np.ones(len(u.T), dtype=np.float32), u, sv))
    stored = {"color_model": 0, "dtype": "float32", "cosine_in_data": True}
    write_dfmf(path, views, lights, fabric.size, fabric.size, factors=factors, **stored, sync=False)
