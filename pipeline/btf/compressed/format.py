"""The compressed BTF file's names and allowed values, its bytes from tensors and metadata,
and its header read back and counted (the format: :mod:`pipeline.btf.compressed`).
"""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path

import numpy as np

from pipeline.core.errors import DataError

FORMAT = "pipeline.btf.compressed"
FORMAT_VERSION = "1"
FILE_NAME = "btf.safetensors"
DIRECTIONS = "theta_light,phi_light,theta_view,phi_view"
DIRECTION_FEATURES = (
    "tan(theta_light/2)*cos(phi_light),tan(theta_light/2)*sin(phi_light),"
    "tan(theta_view/2)*cos(phi_view),tan(theta_view/2)*sin(phi_view)"
)
# What write_compressed writes (PCA: "pca"): a latent per texel (Neural BTF, and the latent
# texture folded into one latent per texel), or a latent per cluster and the list.
PER_TEXEL = ("neural_btf", "latent_texture")
METHODS = (*PER_TEXEL, "clustered")
PCA = "pca"
# How a PCA file is evaluated between its measured direction pairs (the docstring of
# pipeline.btf.compressed).
PCA_INTERPOLATION = "barycentric_light_x_view_stereographic_clamped_to_hull"
# Tensors that are not the model's size (Table 1) but say where its values lie.
SUPPORT_TENSORS = ("measured_directions",)
TEXEL_SCALES = ("none", "lstsq", "luminance")
WEIGHT_DTYPES = ("float32", "float16")
LIST_DTYPES = ("int32", "uint16")
EXTRA_DTYPES = ("float32", "float16")
# Columns of the pyfunc model's input (one row per query) and output.
QUERY_COLUMNS = ("texel", *DIRECTIONS.split(","))
RGB_COLUMNS = ("R", "G", "B")


def safetensors_bytes(tensors: dict[str, np.ndarray], metadata: dict[str, str]) -> bytes:
    """The safetensors file of ``tensors`` and ``metadata``, the metadata in sorted order.

    safetensors' own ``save`` writes the metadata in the order of a Rust hash map, which
    changes from process to process, so equal models would give files with different
    hashes; here the header is written again with its metadata sorted (the tensors keep
    safetensors' order and offsets, the header its padding to 8 bytes).
    """
    from safetensors.numpy import save

    data = save(tensors, metadata=metadata)
    (n,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8 : 8 + n])
    if "__metadata__" in header:
        header = {"__metadata__": dict(sorted(header.pop("__metadata__").items())), **header}
    text = json.dumps(header, separators=(",", ":"), ensure_ascii=False).encode()
    text += b" " * (-len(text) % 8)
    return struct.pack("<Q", len(text)) + text + data[8 + n :]


# ------------------------------------------------------------------------ reading the header


def read_header(path: str | os.PathLike) -> tuple[int, dict]:
    """The JSON header of a safetensors file and its length n in bytes (without the 8
    bytes that hold n), after checking that the file holds every byte the header names.

    Raises :class:`pipeline.core.errors.DataError` naming ``path`` when the file is
    missing, is not a safetensors file, or is truncated.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            prefix = f.read(8)
            if len(prefix) < 8:
                raise DataError(f"{path}: not a safetensors file ({size} bytes, no header)")
            (n,) = struct.unpack("<Q", prefix)
            if n > size - 8:
                raise DataError(
                    f"{path}: truncated or not a safetensors file (header of "
                    f"{n} bytes in a file of {size})"
                )
            header = json.loads(f.read(n))
    except FileNotFoundError:
        raise DataError(f"{path}: no such compressed BTF file") from None
    except OSError as error:
        raise DataError(f"{path}: cannot read the file ({error})") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DataError(f"{path}: not a safetensors file (unreadable header: {error})") from None
    if not isinstance(header, dict):
        raise DataError(f"{path}: not a safetensors file (the header is not a JSON object)")
    try:
        end = max(
            (int(t["data_offsets"][1]) for name, t in header.items() if name != "__metadata__"),
            default=0,
        )
    except (TypeError, KeyError, IndexError, ValueError):
        raise DataError(f"{path}: not a safetensors file (malformed tensor entries)") from None
    if size != 8 + n + end:
        raise DataError(
            f"{path}: truncated or damaged: the header describes "
            f"{8 + n + end} bytes, the file has {size}"
        )
    return n, header


def header_bytes(path: str | os.PathLike) -> int:
    """Bytes of the file that are not tensors: 8 (the header's length) + the JSON header."""
    n, _ = read_header(path)
    return 8 + n


def payload_bytes(path: str | os.PathLike) -> int:
    """Bytes of the model's tensors: Table 1's ``bytes_total`` of the run the file holds
    (every tensor but :data:`SUPPORT_TENSORS`)."""
    n, header = read_header(path)
    return Path(path).stat().st_size - 8 - n - _support_bytes(header)


def support_bytes(path: str | os.PathLike) -> int:
    """Bytes of :data:`SUPPORT_TENSORS` (a PCA file's measured direction pairs; 0 for the
    other models): in the file, not in Table 1."""
    return _support_bytes(read_header(path)[1])


def _support_bytes(header: dict) -> int:
    return sum(
        int(header[name]["data_offsets"][1]) - int(header[name]["data_offsets"][0])
        for name in SUPPORT_TENSORS
        if name in header
    )


# Table 1's parts (the evaluate and linear stages' ``bytes_<part>`` metrics) and the names
# of their tensors: a name, or a prefix ending in ".".
TABLE1_PARTS = {
    "decoder": ("decoder.", "mean", "basis"),
    "latents": ("latents", "coefficients"),
    "list": ("latent_of_texel",),
    "extra": ("texel_scale",),
}
SAFETENSORS_DTYPES = {
    "F16": "float16",
    "BF16": "bfloat16",
    "F32": "float32",
    "F64": "float64",
    "I32": "int32",
    "I64": "int64",
    "U16": "uint16",
    "U8": "uint8",
    "I16": "int16",
    "I8": "int8",
    "U32": "uint32",
}


def stored_parts(path: str | os.PathLike) -> dict[str, dict]:
    """Each of Table 1's parts as the file stores it, read from its header:
    ``{"decoder": {"dtype": "float32", "bytes": 97532}, ...}`` (parts it lacks left out; a
    part whose tensors differ in type lists them, e.g. ``"float16+float32"``)."""
    dtypes: dict[str, set[str]] = {}
    sizes: dict[str, int] = {}
    for name, info in read_header(path)[1].items():
        part = _table1_part(name)  # None for "__metadata__" too
        if part is not None:
            dtypes.setdefault(part, set()).add(SAFETENSORS_DTYPES.get(info["dtype"], info["dtype"]))
            start, stop = info["data_offsets"]
            sizes[part] = sizes.get(part, 0) + stop - start
    return {part: {"dtype": "+".join(sorted(dtypes[part])), "bytes": sizes[part]} for part in sizes}


def _table1_part(name: str) -> str | None:
    """The part of Table 1 that the tensor ``name`` belongs to (:data:`TABLE1_PARTS`)."""
    for part, names in TABLE1_PARTS.items():
        if any(name == n or (n.endswith(".") and name.startswith(n)) for n in names):
            return part
    return None
