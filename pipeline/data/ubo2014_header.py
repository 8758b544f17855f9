"""Parser of a UBO2014 DFMF file's header: :func:`read_dfmf` checks every field against
the layout (:mod:`pipeline.data.ubo2014_format`) and locates each channel's factors
without reading them; :func:`describe` gives the header's facts as plain values.

Every damaged or unknown file is a :class:`~pipeline.core.errors.DataError` naming the
file, and a count read from the file is checked against the bytes left before anything
is allocated for it.
"""

from __future__ import annotations

import struct
from os import PathLike
from pathlib import Path

import numpy as np

from pipeline.core.errors import DataError
from pipeline.data.ubo2014_format import (
    CHANNEL_HEADER,
    COLOR_MODELS,
    FIXED_HEADER,
    KNOWN_VERSIONS,
    ROTATIONS_MARK,
    SCALAR_DTYPES,
    SIGNATURE,
    ChannelFactors,
    DFMFFile,
)


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
    """Parse the header of a UBO2014 ``.btf`` (DFMF) file and locate its factors (which are
    not read).

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
        handle = open(path, "rb")
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
        scalar_size, k, n_rows, n_columns = cur.unpack(CHANNEL_HEADER, f"channel {name!r}'s header")
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
        path=path,
        version=version,
        measurement_setup=_c_string(setup),
        image_sensor=_c_string(sensor),
        light_source=_c_string(source),
        ppmm=float(ppmm),
        rgb_scale=tuple(float(value) for value in rgb),
        cosine_in_data=cosine_in_data,
        xml=xml,
        channel_names=channel_names,
        view_angles=view_angles,
        light_angles=light_angles,
        width=width,
        height=height,
        has_rotations=has_rotations,
        rotations=rotations,
        components=components,
        color_model=color_model,
        color_mean=color_mean,
        color_transform=color_transform,
        channels=tuple(channels),
        size=cur.size,
    )


def describe(dfmf: DFMFFile) -> dict:
    """The header's facts as plain values (for logs, a cache summary and ``info``)."""
    return {
        "version": dfmf.version,
        "n_views": dfmf.n_views,
        "n_lights": dfmf.n_lights,
        "width": dfmf.width,
        "height": dfmf.height,
        "color_model": dfmf.color_model,
        "cosine_in_data": dfmf.cosine_in_data,
        "channels": list(dfmf.channel_names),
        "components": [channel.components for channel in dfmf.channels],
        "scalar_bytes": [channel.dtype.itemsize for channel in dfmf.channels],
        "measurement_setup": dfmf.measurement_setup,
        "image_sensor": dfmf.image_sensor,
        "light_source": dfmf.light_source,
    }
