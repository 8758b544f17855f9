"""The compressed BTF of method A as one file: ``btf.safetensors``.

What each model of method A stores after compression, in a `safetensors
<https://huggingface.co/docs/safetensors>`_ file, with everything needed to evaluate it in
the file's metadata: Neural BTF and its clustered variant (PAPERS.md A: decoder weights,
the latents, the list; the per-texel scale of the graininess fix when used) and the PCA
baseline (mean, basis, coefficients; :mod:`pipeline.btf.linear`).
:func:`write_compressed` (Neural BTF, clustered) and :func:`write_compressed_pca` write
one, :func:`load_compressed` reads either back as an object that answers RGB queries
(:class:`CompressedBTF`: numpy, safetensors and torch only; :class:`CompressedPCA`: numpy,
safetensors and scipy; a renderer needs neither MLflow nor Hydra); :mod:`pipeline.btf.export`
writes the file of a run into the stage cache and logs it to MLflow, with an MLflow pyfunc
model around it.

Layout (format version 1)
-------------------------
A safetensors file: an 8-byte little-endian header length n, n bytes of JSON header
(tensor names, dtypes, shapes, offsets, and the string-to-string ``__metadata__``, padded
with spaces to a multiple of 8), then the tensors back to back. The tensors are exactly
the bytes of Table 1 (``pipeline.btf.evaluate.storage_sizes``; the PCA's ``bytes_total``
of the linear stage), but for :data:`SUPPORT_TENSORS`, which only say where a model's
values lie (the PCA's measured direction pairs) and are not part of the model's size:
:func:`payload_bytes` is ``bytes_total``, :func:`support_bytes` those, :func:`header_bytes`
the rest of the file. The same model gives the same bytes: the file names no run.

Tensors of ``neural_btf`` and ``clustered`` (shape, dtype: what):

- ``decoder.{i}.weight`` (out, in) and ``decoder.{i}.bias`` (out,), weight_dtype: the
  fully connected layers i = 0 .. layers of the decoder (in of layer 0 = latent + 4, out
  of the last = 3).
- ``latents`` (R, latent), weight_dtype: R = M texels (neural_btf) or k clusters.
- ``latent_of_texel`` (M,), list_dtype: clustered only, the list (the latent of each
  texel); absent for neural_btf, where texel t has latent t.
- ``texel_scale`` (M,), extra_dtype: only with the graininess fix, a factor per texel.

weight_dtype is float32 or float16, list_dtype int32 or uint16, extra_dtype float32 or
float16 (``btf.sizes.*``).

Tensors of ``pca`` (M texels, N measured direction pairs, c components):

- ``mean`` (3N,), ``basis`` (c, 3N), weight_dtype: Table 1's "decoder" part.
- ``coefficients`` (M, c), weight_dtype: Table 1's "latents" part (``model.dtype``,
  float32 or float16, is weight_dtype).
- ``measured_directions`` (N, 4), float64: (theta_light, phi_light, theta_view, phi_view)
  radians of each measured pair, the crop's own values; not part of Table 1. Element
  3 j + ch of ``mean`` and of a basis row is channel ch (R, G, B) at pair j.

Texel t is row ``t // cols``, column ``t % cols`` of the crop (row-major), i.e. texel
(row + crop_offset[0], col + crop_offset[1]) of the dataset's texture.

Metadata (all values are strings; "JSON" ones are parsed with ``json.loads``). Every file:

- ``format``: ``pipeline.btf.compressed``; ``format_version``: ``1``.
- ``method``: ``neural_btf``, ``clustered``, ``latent_texture`` (the layout of ``neural_btf``:
  its pyramid folded into one latent per texel) or ``pca``.
- ``alpha`` (a float): multiply the model's normalised output by it to get linear RGB
  in the units of the source data (eq. 5-6: targets were divided by it).
- ``crop_size`` (JSON [rows, cols]), ``crop_offset`` (JSON [row, col]): the crop of the
  texture the texels cover; ``texel_order``: ``row_major``.
- ``directions``: ``theta_light,phi_light,theta_view,phi_view`` (radians).
- ``weight_dtype``: the stored type of the model's values (above).
- ``dataset``: the source dataset's name (``dataset.name``).

``neural_btf`` and ``clustered`` also:

- ``direction_encoding``: ``stereographic`` (eq. 7-9); ``direction_features``: the 4
  decoder inputs it makes of a direction pair, ``tan(theta_light/2)*cos(phi_light),
  tan(theta_light/2)*sin(phi_light), tan(theta_view/2)*cos(phi_view),
  tan(theta_view/2)*sin(phi_view)`` (what ``pipeline.btf.stereographic.direction_features``
  computes).
- ``decoder_latent``, ``decoder_hidden``, ``decoder_layers`` (ints): the decoder is
  (latent + 4) -> hidden -> ... -> hidden -> 3 with ``decoder_layers`` hidden layers;
  ``decoder_activation``: ``relu`` (after every layer but the last);
  ``decoder_input``: ``latent,direction_features`` (the order they are concatenated in).
- ``list_dtype``, ``extra_dtype``: the ``btf.sizes`` of the run (with weight_dtype).
- ``k`` (JSON int, ``null`` for neural_btf); ``texel_scale``: ``none``, ``lstsq`` or
  ``luminance`` (the graininess fix used).

``pca`` also: ``n_components`` (c) and ``n_directions`` (N), ints; ``value_layout``:
``direction,channel`` (element 3 j + ch, above); ``interpolation``: :data:`PCA_INTERPOLATION`
(below).

RGB of texel t for a direction pair (what :meth:`CompressedBTF.query` computes)::

    z = latents[latent_of_texel[t]]            (latents[t] when there is no list)
    h = concat(z, direction_features(directions))
    h = relu(W_i @ h + b_i) for i < layers;  out = W_layers @ h + b_layers
    rgb = out * texel_scale[t] * alpha         (texel_scale[t] = 1 when absent)

The output is not clamped, as in the evaluation (eq. 10): a renderer may clamp at 0.

RGB of a PCA texel t (what :meth:`CompressedPCA.query_pairs` computes): at measured pair
j, ``alpha * (mean + coefficients[t] @ basis)[3 j : 3 j + 3]``; at any other pair, those
values piecewise-linearly interpolated as the renderer interpolates the measured BTF
(:class:`pipeline.btf.render.surfaces.LinearMaterial`, which the reader uses): barycentric
weights in the Delaunay triangulation of the light set times those of the view set
(stereographic coordinates, radius tan(theta / 2); the sets are the distinct lights and
views of ``measured_directions``, which must be a full product L x V), 9 stored values per
query; weights within 1e-7 of a corner snap onto it, and a light (view) beyond the polygon
its set spans is first moved onto it (theta lowered, phi kept). Not clamped either.

Querying from plain Python, with numpy and safetensors only: ``btf_rgb`` answers a
Neural BTF or clustered file at any direction pair, ``pca_rgb`` a PCA file at its measured
pairs (between them, interpolate as above, or call :func:`load_compressed`);
``tests/test_compressed.py`` runs this block against ``query_pairs``::

    import numpy as np
    from safetensors import safe_open

    def btf_rgb(path, texels, directions):
        # texels (n,) ints; directions (n, 4) radians -> (n, 3) linear RGB
        with safe_open(path, framework="numpy") as f:
            meta = f.metadata()
            t = {name: f.get_tensor(name) for name in f.keys()}
        texels = np.asarray(texels)
        d = np.asarray(directions, dtype=np.float64)
        ids = t["latent_of_texel"][texels] if "latent_of_texel" in t else texels
        r_l, r_v = np.tan(d[:, 0] / 2), np.tan(d[:, 2] / 2)
        features = np.stack([r_l * np.cos(d[:, 1]), r_l * np.sin(d[:, 1]),
                             r_v * np.cos(d[:, 3]), r_v * np.sin(d[:, 3])], axis=1)
        h = np.concatenate([t["latents"][ids], features], axis=1).astype(np.float32)
        layers = int(meta["decoder_layers"])
        for i in range(layers + 1):
            h = h @ t[f"decoder.{i}.weight"].astype(np.float32).T + t[f"decoder.{i}.bias"]
            h = np.maximum(h, 0) if i < layers else h
        if "texel_scale" in t:
            h = h * t["texel_scale"][texels, None]
        return h * np.float32(float(meta["alpha"]))

    def pca_rgb(path, texels, pairs):
        # texels (n,) ints; pairs (n,) rows of measured_directions -> (n, 3) linear RGB
        with safe_open(path, framework="numpy") as f:
            meta = f.metadata()
            t = {name: f.get_tensor(name).astype(np.float64)
                 for name in ("mean", "basis", "coefficients")}
        columns = 3 * np.asarray(pairs)[:, None] + np.arange(3)  # (n, 3): R, G, B
        values = t["mean"][columns] + np.einsum(
            "nc,cnk->nk", t["coefficients"][np.asarray(texels)], t["basis"][:, columns])
        return values * float(meta["alpha"])
"""

from __future__ import annotations

import json
import math
import os
import struct
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.btf.stereographic import direction_features
from pipeline.core.errors import DataError
from pipeline.core.files import write_atomic

if TYPE_CHECKING:
    from pipeline.btf.model import Decoder

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
# How a PCA file is evaluated between its measured direction pairs (module docstring).
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
# Rows of the first hidden layer computed at once (rows x hidden float32 values); a PCA's
# interpolated queries at once.
_ROWS_PER_BATCH = 1 << 16


# ----------------------------------------------------------------------------- writing


def write_compressed(
    path: str | os.PathLike,
    decoder: Decoder,
    latents: np.ndarray,
    alpha: float,
    *,
    crop_size: tuple[int, int],
    crop_offset: tuple[int, int] = (0, 0),
    method: str,
    k: int | None = None,
    dataset: str,
    latent_of_texel: np.ndarray | None = None,
    texel_scale: np.ndarray | None = None,
    texel_scale_mode: str = "none",
    weight_dtype: str = "float32",
    list_dtype: str = "int32",
    extra_dtype: str = "float32",
) -> Path:
    """Write a compressed BTF to ``path`` (the layout is in the module docstring).

    The file is written next to ``path`` under a temporary name and renamed onto it, so
    that an interrupted write never leaves a partial file at ``path``; the same model
    gives the same bytes (:func:`safetensors_bytes`).

    Parameters
    ----------
    decoder : the trained :class:`pipeline.btf.model.Decoder`.
    latents : ndarray of shape (R, latent); R = M = rows x cols (neural_btf) or k (clustered).
    alpha : the normalisation of the targets (:class:`pipeline.btf.preprocess.Normalization`).
    crop_size, crop_offset : (rows, cols) and (row, col) of the crop the M texels cover.
    method : ``neural_btf`` or ``latent_texture`` (no list: texel t has latent t) or ``clustered`` (needs
        ``latent_of_texel``, ndarray of shape (M,), and ``k`` = R).
    texel_scale : ndarray of shape (M,), the graininess fix's factors, with the
        ``texel_scale_mode`` that made them (``lstsq`` or ``luminance``); None for none.
    weight_dtype, list_dtype, extra_dtype : stored dtypes (``btf.sizes``).

    Raises
    ------
    DataError
        Naming ``path`` and the space left, when the disk is full.
    """
    tensors, meta = _contents(
        decoder,
        latents,
        alpha,
        crop_size,
        crop_offset,
        method,
        k,
        dataset,
        latent_of_texel,
        texel_scale,
        texel_scale_mode,
        weight_dtype,
        list_dtype,
        extra_dtype,
    )
    path = Path(path)
    write_atomic(path, safetensors_bytes(tensors, meta))
    return path


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


def _contents(
    decoder,
    latents,
    alpha,
    crop_size,
    crop_offset,
    method,
    k,
    dataset,
    latent_of_texel,
    texel_scale,
    texel_scale_mode,
    weight_dtype,
    list_dtype,
    extra_dtype,
) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """The tensors and metadata of a file, after checking that they fit together."""
    for name, value, allowed in (
        ("method", method, METHODS),
        ("texel_scale_mode", texel_scale_mode, TEXEL_SCALES),
        ("weight_dtype", weight_dtype, WEIGHT_DTYPES),
        ("list_dtype", list_dtype, LIST_DTYPES),
        ("extra_dtype", extra_dtype, EXTRA_DTYPES),
    ):
        if value not in allowed:
            raise ValueError(f"{name}={value!r} must be one of {list(allowed)}")
    rows, cols = (int(v) for v in crop_size)
    m = rows * cols
    latents = np.asarray(latents)
    if latents.ndim != 2 or latents.shape[1] != decoder.latent:
        raise ValueError(f"latents must have shape (R, {decoder.latent}), got {latents.shape}")
    n_latents = latents.shape[0]
    if method in PER_TEXEL:
        if latent_of_texel is not None:
            raise ValueError(
                f"model={method} stores no list (texel t has latent t): pass latent_of_texel=None"
            )
        if n_latents != m:
            raise ValueError(
                f"model={method} needs one latent per texel: {n_latents} "
                f"latents for a crop of {rows}x{cols}={m} texels"
            )
        k = None
    else:
        if latent_of_texel is None:
            raise ValueError("model=clustered needs latent_of_texel, the list")
        latent_of_texel = np.asarray(latent_of_texel)
        if latent_of_texel.shape != (m,):
            raise ValueError(
                f"latent_of_texel must have shape ({m},) for a crop of "
                f"{rows}x{cols} texels, got {latent_of_texel.shape}"
            )
        if m and (latent_of_texel.min() < 0 or latent_of_texel.max() >= n_latents):
            raise ValueError(f"latent_of_texel holds ids outside [0, {n_latents})")
        if k is not None and int(k) != n_latents:
            raise ValueError(f"k={k} but there are {n_latents} latents")
        if list_dtype == "uint16" and n_latents > 65536:
            raise ValueError(f"list_dtype=uint16 cannot index k={n_latents} > 65536 clusters")
        k = n_latents
    if (texel_scale is None) != (texel_scale_mode == "none"):
        raise ValueError(
            f"texel_scale_mode={texel_scale_mode!r} but texel_scale is "
            f"{'absent' if texel_scale is None else 'given'}"
        )

    tensors: dict[str, np.ndarray] = {}
    linears = [layer for layer in decoder.net if hasattr(layer, "weight")]
    for i, layer in enumerate(linears):
        tensors[f"decoder.{i}.weight"] = _as(layer.weight.detach().cpu().numpy(), weight_dtype)
        tensors[f"decoder.{i}.bias"] = _as(layer.bias.detach().cpu().numpy(), weight_dtype)
    tensors["latents"] = _as(latents, weight_dtype)
    if latent_of_texel is not None:
        tensors["latent_of_texel"] = _as(latent_of_texel, list_dtype)
    if texel_scale is not None:
        texel_scale = np.asarray(texel_scale)
        if texel_scale.shape != (m,):
            raise ValueError(f"texel_scale must have shape ({m},), got {texel_scale.shape}")
        tensors["texel_scale"] = _as(texel_scale, extra_dtype)

    meta = {
        **_common_metadata(method, alpha, (rows, cols), crop_offset, weight_dtype, dataset),
        "direction_encoding": "stereographic",
        "direction_features": DIRECTION_FEATURES,
        "decoder_latent": str(decoder.latent),
        "decoder_hidden": str(linears[0].out_features),
        "decoder_layers": str(len(linears) - 1),
        "decoder_activation": "relu",
        "decoder_input": "latent,direction_features",
        "list_dtype": list_dtype,
        "extra_dtype": extra_dtype,
        "k": json.dumps(k),
        "texel_scale": texel_scale_mode,
    }
    return tensors, meta


def _common_metadata(method, alpha, crop_size, crop_offset, weight_dtype, dataset) -> dict:
    """The metadata every file has (module docstring), checked."""
    if not (isinstance(alpha, int | float) and math.isfinite(alpha) and alpha > 0):
        raise ValueError(f"alpha={alpha!r} must be a positive finite number")
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "method": method,
        "alpha": repr(float(alpha)),
        "crop_size": json.dumps([int(v) for v in crop_size]),
        "crop_offset": json.dumps([int(v) for v in crop_offset]),
        "texel_order": "row_major",
        "directions": DIRECTIONS,
        "weight_dtype": weight_dtype,
        "dataset": str(dataset),
    }


def write_compressed_pca(
    path: str | os.PathLike,
    mean: np.ndarray,
    basis: np.ndarray,
    coefficients: np.ndarray,
    alpha: float,
    *,
    measured_directions: np.ndarray,
    crop_size: tuple[int, int],
    crop_offset: tuple[int, int] = (0, 0),
    dataset: str,
    weight_dtype: str = "float32",
) -> Path:
    """Write the PCA baseline (:mod:`pipeline.btf.linear`) to ``path`` (method ``pca``;
    the layout is in the module docstring), atomically, as :func:`write_compressed`.

    Parameters
    ----------
    mean : ndarray of shape (3N,); basis : ndarray of shape (c, 3N); coefficients :
        ndarray of shape (M, c): the linear stage's model in normalised units (element
        3 j + ch is channel ch at direction pair j), stored as ``weight_dtype``.
    alpha : the normalisation of the targets (:class:`pipeline.btf.preprocess.Normalization`).
    measured_directions : ndarray of shape (N, 4), radians: the crop's direction pairs, a
        full product of a light and a view set that each surround the normal (stored as
        float64; the renderer interpolates between them).
    crop_size, crop_offset : (rows, cols) and (row, col) of the crop, M = rows x cols.
    dataset : the source dataset's name.
    weight_dtype : ``float32`` or ``float16`` (``model.dtype``).

    Raises
    ------
    ValueError
        Naming what does not fit, before anything is written; a
        :class:`~pipeline.core.errors.DataError` (a ValueError) for direction pairs that
        cannot be interpolated between, or naming ``path`` when the disk is full.
    """
    if weight_dtype not in WEIGHT_DTYPES:
        raise ValueError(f"weight_dtype={weight_dtype!r} must be one of {list(WEIGHT_DTYPES)}")
    mean, basis, coefficients = (np.asarray(a) for a in (mean, basis, coefficients))
    measured = np.asarray(measured_directions, dtype=np.float64)
    if measured.ndim != 2 or measured.shape[1] != 4:
        raise ValueError(f"measured_directions must have shape (N, 4), got {measured.shape}")
    n = len(measured)
    if mean.shape != (3 * n,) or basis.ndim != 2 or basis.shape[1] != 3 * n:
        raise ValueError(
            f"mean {mean.shape} and basis {basis.shape} must be (3N,) and "
            f"(c, 3N) with N = {n} measured direction pairs"
        )
    meta = _common_metadata(PCA, alpha, crop_size, crop_offset, weight_dtype, dataset)
    tensors = {
        "mean": _as(mean, weight_dtype),
        "basis": _as(basis, weight_dtype),
        "coefficients": _as(coefficients, weight_dtype),
        "measured_directions": np.ascontiguousarray(measured),
    }
    # Built as the reader builds it: a file that is written can be queried.
    _linear_material(tensors, float(alpha), json.loads(meta["crop_size"]))
    meta.update(
        n_components=str(basis.shape[0]),
        n_directions=str(n),
        value_layout="direction,channel",
        interpolation=PCA_INTERPOLATION,
    )
    path = Path(path)
    write_atomic(path, safetensors_bytes(tensors, meta))
    return path


def _linear_material(tensors: dict[str, np.ndarray], alpha: float, crop_size):
    """The renderer's PCA material (:class:`pipeline.btf.render.surfaces.LinearMaterial`)
    of a PCA file's tensors: the one evaluation of the format's interpolation."""
    from pipeline.btf.render.surfaces import LinearMaterial

    return LinearMaterial(
        tensors["mean"],
        tensors["basis"],
        tensors["coefficients"],
        tuple(crop_size),
        alpha,
        tensors["measured_directions"],
    )


def _as(array: np.ndarray, dtype: str) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(array).astype(dtype, copy=False))


# ----------------------------------------------------------------------------- reading


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
    _, header = read_header(path)
    parts: dict[str, dict] = {}
    for name, info in header.items():
        if name == "__metadata__":
            continue
        part = _table1_part(name)
        if part is None:
            continue
        found = parts.setdefault(part, {"dtypes": set(), "bytes": 0})
        found["dtypes"].add(SAFETENSORS_DTYPES.get(info["dtype"], info["dtype"]))
        start, stop = info["data_offsets"]
        found["bytes"] += stop - start
    return {
        part: {"dtype": "+".join(sorted(found["dtypes"])), "bytes": found["bytes"]}
        for part, found in parts.items()
    }


def _table1_part(name: str) -> str | None:
    """The part of Table 1 that the tensor ``name`` belongs to (:data:`TABLE1_PARTS`)."""
    for part, names in TABLE1_PARTS.items():
        if any(name == n or (n.endswith(".") and name.startswith(n)) for n in names):
            return part
    return None


class _CompressedFile:
    """What every model read back from a file answers (:class:`CompressedBTF`,
    :class:`CompressedPCA`): its crop, its texels, and every texel at every direction.
    Subclasses have ``path``, ``crop_size``, ``metadata`` and ``query``."""

    path: Path
    crop_size: tuple[int, int]
    metadata: dict[str, str]

    @property
    def n_texels(self) -> int:
        return self.crop_size[0] * self.crop_size[1]

    @property
    def method(self) -> str:
        return self.metadata["method"]

    def texel_index(self, row, col) -> np.ndarray:
        """Texel indices of (row, col) positions within the crop (arrays of one shape)."""
        row, col = np.asarray(row), np.asarray(col)
        rows, cols = self.crop_size
        if np.any((row < 0) | (row >= rows) | (col < 0) | (col >= cols)):
            raise ValueError(f"(row, col) outside the crop of {rows}x{cols} texels")
        return row * cols + col

    def reconstruct(self, directions) -> np.ndarray:
        """Every texel at every direction pair: (D, 4) radians -> (M, D, 3) float32."""
        return self.query(np.arange(self.n_texels), directions)

    def _texels(self, texels) -> np.ndarray:
        texels = np.asarray(texels)
        if texels.ndim != 1 or not (texels.size == 0 or np.issubdtype(texels.dtype, np.integer)):
            raise ValueError(
                f"texels must be a 1-D array of ints, got shape {texels.shape} of {texels.dtype}"
            )
        if texels.size and (texels.min() < 0 or texels.max() >= self.n_texels):
            bad = texels[(texels < 0) | (texels >= self.n_texels)][0]
            raise ValueError(f"texel {bad} is outside [0, {self.n_texels}) ({self.path})")
        return texels.astype(np.int64)

    @staticmethod
    def _directions(directions) -> np.ndarray:
        directions = np.asarray(directions, dtype=np.float64)
        if directions.ndim != 2 or directions.shape[1] != 4:
            raise ValueError(
                "directions must have shape (n, 4) = (theta_light, phi_light, "
                f"theta_view, phi_view), got {directions.shape}"
            )
        return directions


@dataclass
class CompressedBTF(_CompressedFile):
    """A compressed BTF read back from its file (:func:`load_compressed`).

    Attributes
    ----------
    path : the file it was read from.
    decoder : :class:`pipeline.btf.model.Decoder` in float32 (weights as stored, widened).
    latents : ndarray of shape (R, latent), in the stored dtype.
    latent_of_texel : ndarray of shape (M,), in the stored dtype; None = the identity.
    texel_scale : ndarray of shape (M,), in the stored dtype; None when not used.
    alpha : normalised output x alpha = linear RGB in the data's units.
    crop_size, crop_offset : (rows, cols) and (row, col) of the crop; M = rows x cols.
    metadata : every metadata string of the file, as stored.
    """

    path: Path
    decoder: Decoder
    latents: np.ndarray
    latent_of_texel: np.ndarray | None
    texel_scale: np.ndarray | None
    alpha: float
    crop_size: tuple[int, int]
    crop_offset: tuple[int, int]
    metadata: dict[str, str] = field(default_factory=dict)

    @property
    def k(self) -> int | None:
        return json.loads(self.metadata["k"])

    def query(self, texels, directions) -> np.ndarray:
        """Linear RGB of every given texel at every given direction pair.

        Parameters
        ----------
        texels : array_like of ints of shape (T,), indices in [0, M) (:meth:`texel_index`).
        directions : array_like of shape (D, 4), (theta_light, phi_light, theta_view,
            phi_view) in radians.

        Returns
        -------
        ndarray of shape (T, D, 3), float32.
        """
        texels = self._texels(texels)
        features = direction_features(self._directions(directions))
        ids = texels if self.latent_of_texel is None else self.latent_of_texel[texels]
        # Each latent is decoded once, however many texels share it (clustered).
        unique, inverse = np.unique(ids, return_inverse=True)
        decoded = self._decode_grid(unique, features)
        out = decoded if np.array_equal(inverse, np.arange(len(ids))) else decoded[inverse]
        if self.texel_scale is not None:
            out *= self.texel_scale[texels].astype(np.float32)[:, None, None]
        out *= np.float32(self.alpha)
        return out

    def query_pairs(self, texels, directions) -> np.ndarray:
        """Linear RGB of texel ``texels[i]`` at direction pair ``directions[i]``.

        texels : array_like of ints of shape (n,); directions : array_like of shape (n, 4)
        in radians -> ndarray of shape (n, 3), float32.
        """
        import torch

        texels = self._texels(texels)
        directions = self._directions(directions)
        if len(directions) != len(texels):
            raise ValueError(f"{len(texels)} texels but {len(directions)} direction pairs")
        ids = texels if self.latent_of_texel is None else self.latent_of_texel[texels]
        latents = np.asarray(self.latents, dtype=np.float32)
        features = direction_features(directions)
        out = np.empty((len(texels), 3), dtype=np.float32)
        with torch.no_grad():
            for start in range(0, len(texels), _ROWS_PER_BATCH):
                stop = start + _ROWS_PER_BATCH
                z = torch.from_numpy(latents[ids[start:stop]])
                out[start:stop] = self.decoder(z, torch.from_numpy(features[start:stop])).numpy()
        if self.texel_scale is not None:
            out *= self.texel_scale[texels].astype(np.float32)[:, None]
        out *= np.float32(self.alpha)
        return out

    def _decode_grid(self, ids: np.ndarray, features: np.ndarray) -> np.ndarray:
        """Decode latents ``ids`` at every direction: (U,) x (D, 4) -> (U, D, 3) float32."""
        import torch

        latents = np.asarray(self.latents[ids], dtype=np.float32)
        out = np.empty((len(ids), len(features), 3), dtype=np.float32)
        chunk = max(1, _ROWS_PER_BATCH // max(len(features), 1))
        features = torch.from_numpy(features)
        with torch.no_grad():
            for start in range(0, len(ids), chunk):
                z = torch.from_numpy(latents[start : start + chunk])
                out[start : start + len(z)] = self.decoder.decode_grid(z, features).numpy()
        return out


@dataclass
class CompressedPCA(_CompressedFile):
    """The PCA baseline read back from its file (:func:`load_compressed`, method ``pca``):
    the same queries as :class:`CompressedBTF`, evaluated as the renderer evaluates the
    linear stage's arrays (module docstring).

    Attributes
    ----------
    path : the file it was read from.
    mean : ndarray of shape (3N,); basis : ndarray of shape (c, 3N); coefficients :
        ndarray of shape (M, c): normalised units, in the stored dtype.
    measured_directions : ndarray of shape (N, 4), float64 radians.
    alpha : normalised value x alpha = linear RGB in the data's units.
    crop_size, crop_offset : (rows, cols) and (row, col) of the crop; M = rows x cols.
    metadata : every metadata string of the file, as stored.
    """

    path: Path
    mean: np.ndarray
    basis: np.ndarray
    coefficients: np.ndarray
    measured_directions: np.ndarray
    alpha: float
    crop_size: tuple[int, int]
    crop_offset: tuple[int, int]
    metadata: dict[str, str] = field(default_factory=dict)

    @property
    def k(self) -> None:
        """No clusters (None, as for a Neural BTF)."""
        return None

    @property
    def n_components(self) -> int:
        return self.basis.shape[0]

    @cached_property
    def material(self):
        """The renderer's PCA material over these arrays
        (:class:`pipeline.btf.render.surfaces.LinearMaterial`), built on first use."""
        return _linear_material(
            self._tensors(self.mean, self.basis, self.coefficients), self.alpha, self.crop_size
        )

    def query_pairs(self, texels, directions) -> np.ndarray:
        """Linear RGB of texel ``texels[i]`` at direction pair ``directions[i]``: exactly
        :attr:`material`'s ``evaluate``.

        texels : array_like of ints of shape (n,); directions : array_like of shape (n, 4)
        in radians -> ndarray of shape (n, 3), float32.
        """
        texels = self._texels(texels)
        directions = self._directions(directions)
        if len(directions) != len(texels):
            raise ValueError(f"{len(texels)} texels but {len(directions)} direction pairs")
        return self.material.evaluate(texels, directions)

    def query(self, texels, directions) -> np.ndarray:
        """Linear RGB of every given texel at every given direction pair.

        The model is linear in its coefficients, so the mean and the c basis vectors are
        interpolated once per direction pair and combined with each texel's coefficients:
        (c + 1) D interpolations, not T D. Equal to :meth:`query_pairs` up to float32
        rounding (the sums run in another order).

        Parameters
        ----------
        texels : array_like of ints of shape (T,), indices in [0, M).
        directions : array_like of shape (D, 4), radians.

        Returns
        -------
        ndarray of shape (T, D, 3), float32.
        """
        texels = self._texels(texels)
        directions = self._directions(directions)
        coefficients = np.asarray(self.coefficients[texels], dtype=np.float32)
        parts = self.n_components + 1  # pseudo-texel 0: the mean; i + 1: basis vector i
        out = np.empty((len(texels), len(directions), 3), dtype=np.float32)
        chunk = max(1, _ROWS_PER_BATCH // parts)
        for start in range(0, len(directions), chunk):
            block = directions[start : start + chunk]
            values = self._basis_material.evaluate(
                np.repeat(np.arange(parts), len(block)), np.tile(block, (parts, 1))
            ).reshape(parts, len(block), 3)
            out[:, start : start + len(block)] = values[0] + np.einsum(
                "tc,cdk->tdk", coefficients, values[1:]
            )
        return out

    @cached_property
    def _basis_material(self):
        """A material whose pseudo-texel 0 is the mean and i + 1 basis vector i, scaled."""
        stacked = np.concatenate([self.mean[None], self.basis]).astype(np.float32)
        tensors = self._tensors(
            np.zeros_like(stacked[0]), stacked, np.eye(len(stacked), dtype=np.float32)
        )
        return _linear_material(tensors, self.alpha, (1, len(stacked)))

    def _tensors(self, mean, basis, coefficients) -> dict[str, np.ndarray]:
        return {
            "mean": mean,
            "basis": basis,
            "coefficients": coefficients,
            "measured_directions": self.measured_directions,
        }


def load_compressed(path: str | os.PathLike) -> CompressedBTF | CompressedPCA:
    """Read a file written by :func:`write_compressed` (a :class:`CompressedBTF`) or
    :func:`write_compressed_pca` (a :class:`CompressedPCA`).

    Raises :class:`pipeline.core.errors.DataError` naming ``path`` when the file is
    missing, truncated or damaged, of another format or format version, or lacks a
    tensor or metadata key of the format.
    """
    from safetensors import SafetensorError, safe_open

    path = Path(path)
    read_header(path)
    try:
        with safe_open(path, framework="numpy") as f:
            meta = dict(f.metadata() or {})
            tensors = {name: f.get_tensor(name) for name in f.keys()}
    except (SafetensorError, OSError, ValueError) as error:
        raise DataError(f"{path}: not a readable safetensors file ({error})") from None
    if meta.get("format") != FORMAT:
        raise DataError(
            f"{path}: not a compressed BTF (metadata format="
            f"{meta.get('format')!r}, expected {FORMAT!r})"
        )
    if meta.get("format_version") != FORMAT_VERSION:
        raise DataError(
            f"{path}: compressed BTF format version "
            f"{meta.get('format_version')!r}; this code reads version "
            f"{FORMAT_VERSION!r}"
        )
    if meta.get("method") == PCA:
        return _load_pca(path, tensors, meta)
    import torch

    from pipeline.btf.model import Decoder

    try:
        latent, hidden, layers = (
            int(meta[f"decoder_{key}"]) for key in ("latent", "hidden", "layers")
        )
        alpha = float(meta["alpha"])
        crop_size = tuple(int(v) for v in json.loads(meta["crop_size"]))
        crop_offset = tuple(int(v) for v in json.loads(meta["crop_offset"]))
        decoder = Decoder(latent=latent, hidden=hidden, layers=layers)
        state = {
            f"net.{2 * i}.{part}": torch.from_numpy(
                tensors[f"decoder.{i}.{part}"].astype(np.float32)
            )
            for i in range(layers + 1)
            for part in ("weight", "bias")
        }
        decoder.load_state_dict(state)
        latents = tensors["latents"]
    except KeyError as error:
        raise DataError(f"{path}: a compressed BTF without {error.args[0]!r}") from None
    except (ValueError, TypeError, RuntimeError) as error:
        raise DataError(f"{path}: inconsistent compressed BTF ({error})") from None
    btf = CompressedBTF(
        path=path,
        decoder=decoder.eval(),
        latents=latents,
        latent_of_texel=tensors.get("latent_of_texel"),
        texel_scale=tensors.get("texel_scale"),
        alpha=alpha,
        crop_size=crop_size,
        crop_offset=crop_offset,
        metadata=meta,
    )
    m = btf.n_texels
    expected = m if btf.latent_of_texel is None else None
    if (
        (expected is not None and latents.shape[0] != expected)
        or (btf.latent_of_texel is not None and btf.latent_of_texel.shape != (m,))
        or (btf.texel_scale is not None and btf.texel_scale.shape != (m,))
    ):
        raise DataError(f"{path}: the tensors do not fit a crop of {crop_size} texels")
    return btf


def _load_pca(path: Path, tensors: dict[str, np.ndarray], meta: dict[str, str]) -> CompressedPCA:
    """A PCA file's contents, checked (:func:`load_compressed`)."""
    if meta.get("interpolation") != PCA_INTERPOLATION:
        raise DataError(
            f"{path}: a PCA with interpolation={meta.get('interpolation')!r}; "
            f"this code interpolates by {PCA_INTERPOLATION!r}"
        )
    try:
        pca = CompressedPCA(
            path=path,
            mean=tensors["mean"],
            basis=tensors["basis"],
            coefficients=tensors["coefficients"],
            measured_directions=tensors["measured_directions"],
            alpha=float(meta["alpha"]),
            crop_size=tuple(int(v) for v in json.loads(meta["crop_size"])),
            crop_offset=tuple(int(v) for v in json.loads(meta["crop_offset"])),
            metadata=meta,
        )
        pca.material  # noqa: B018 (built now: arrays that do not fit are refused here)
    except KeyError as error:
        raise DataError(f"{path}: a compressed PCA without {error.args[0]!r}") from None
    except (ValueError, TypeError) as error:  # DataError included
        raise DataError(f"{path}: inconsistent compressed PCA ({error})") from None
    return pca
