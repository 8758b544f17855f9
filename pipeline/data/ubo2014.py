"""Reader of Bonn UBO2014 BTFs: one ``.btf`` file per material, stored as DFMF; the
dataset adapter that the pipeline's load stage calls.

Nothing is decoded until asked: :func:`~pipeline.data.ubo2014_header.read_dfmf` parses
the header and locates the factors, :func:`select_rows` turns the dataset's views and
lights into direction rows, and :func:`~pipeline.data.ubo2014_decode.decode_dfmf`
multiplies only those rows at the texels of a crop. :func:`load_ubo2014` does all three
and returns a :class:`~pipeline.data.btf.BTF`. The layout is described in
:mod:`pipeline.data.ubo2014_format`.

Examples
--------
>>> dfmf = read_dfmf("carpet01.btf")                                   # doctest: +SKIP
>>> rows = select_rows(dfmf, views=[0, 10], lights=None)               # doctest: +SKIP
>>> images = decode_dfmf(dfmf, rows, crop=(0, 0, 100, 100))            # doctest: +SKIP

From the shell: ``python -m pipeline.data.ubo2014_info file=PATH`` (header, views and
lights); ``python -m benchmarks.ubo2014_load`` (peak memory of loading a crop).
"""

from __future__ import annotations

from os import PathLike
from pathlib import Path

import numpy as np

from pipeline.core.errors import ConfigError
from pipeline.data.directions import unit_vectors
from pipeline.data.ubo2014_decode import check_crop, decode_dfmf
from pipeline.data.ubo2014_format import DFMFFile
from pipeline.data.ubo2014_header import read_dfmf

# A [θ, φ] entry of dataset.views / dataset.lights must lie this close to a file direction.
MATCH_TOLERANCE_DEG = 0.5


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


def count_ubo2014_images(
    path: str | PathLike, views=None, lights=None, crop=None
) -> tuple[int, int, int]:
    """(n_images, height, width) that :func:`load_ubo2014` returns, from the header alone."""
    dfmf = read_dfmf(path)
    _, _, height, width = check_crop(crop, dfmf)
    return len(select_rows(dfmf, views, lights)), height, width


def load_ubo2014(
    path: str | PathLike, views=None, lights=None, crop=None, out: np.ndarray | None = None
):
    """Load a crop of a UBO2014 BTF as linear RGB images in view-major order; raises as
    :func:`read_dfmf`, :func:`select_rows` and :func:`decode_dfmf`.

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

    Returns
    -------
    pipeline.data.btf.BTF
        ``images`` (n, height, width, 3); ``directions`` (n, 4) = (θ_light, φ_light,
        θ_view, φ_view) radians from the file; ``paths`` the file for every image;
        ``view_folders`` empty; ``root`` the file.
    """
    from pipeline.data.btf import BTF

    dfmf = read_dfmf(path)
    rows = select_rows(dfmf, views, lights)
    images = decode_dfmf(dfmf, rows, crop, out=out)
    return BTF(
        images=images,
        directions=dfmf.directions()[rows],
        paths=[dfmf.path] * len(rows),
        view_folders=[],
        root=dfmf.path,
    )
