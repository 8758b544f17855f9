"""Writing a compressed BTF file (the format: :mod:`pipeline.btf.compressed`), atomically and
with the same bytes for the same model.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.btf.compressed.format import (
    DIRECTION_FEATURES,
    DIRECTIONS,
    EXTRA_DTYPES,
    FORMAT,
    FORMAT_VERSION,
    LIST_DTYPES,
    METHODS,
    PCA,
    PCA_INTERPOLATION,
    PER_TEXEL,
    TEXEL_SCALES,
    WEIGHT_DTYPES,
    safetensors_bytes,
)
from pipeline.btf.compressed.read import pca_material
from pipeline.core.files import write_atomic

if TYPE_CHECKING:
    from pipeline.btf.model import Decoder


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
    """Write a compressed BTF to ``path`` (the layout is in the docstring of
    :mod:`pipeline.btf.compressed`).

    The file is written next to ``path`` under a temporary name and renamed onto it, so
    that an interrupted write never leaves a partial file at ``path``; the same model
    gives the same bytes (:func:`pipeline.btf.compressed.format.safetensors_bytes`).

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
    path = Path(path)
    write_atomic(path, safetensors_bytes(tensors, meta))
    return path


def _common_metadata(method, alpha, crop_size, crop_offset, weight_dtype, dataset) -> dict:
    """The metadata every file has (:mod:`pipeline.btf.compressed`), checked."""
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
    the layout is in the docstring of :mod:`pipeline.btf.compressed`), atomically, as
    :func:`write_compressed`.

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
    pca_material(**tensors, alpha=float(alpha), crop_size=json.loads(meta["crop_size"]))
    meta.update(
        n_components=str(basis.shape[0]),
        n_directions=str(n),
        value_layout="direction,channel",
        interpolation=PCA_INTERPOLATION,
    )
    path = Path(path)
    write_atomic(path, safetensors_bytes(tensors, meta))
    return path


def _as(array: np.ndarray, dtype: str) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(array).astype(dtype, copy=False))
