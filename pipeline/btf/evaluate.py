"""Reconstruction error (eq. 10) and exact storage sizes (Table 1).

RMSE is taken over all texels x directions x channels in the normalized space of the
paper (values divided by alpha, so the data lie in [0, 1]). The clustered method decodes
its k latents at the N directions once and indexes the result with the list, so it never
decodes M x N queries. A model is scored as stored: :func:`as_stored` rounds its decoder
weights and latents to ``btf.sizes.weight_dtype``, ``reconstruction_error`` its per-texel
scale to ``extra_dtype``, so that a float16 model's RMSE is the float16 model's.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.btf.model import LATENT_DIM, Decoder, parameter_count
from pipeline.core.progress import progress

DTYPE_BYTES = {"float32": 4, "float16": 2, "int32": 4, "uint16": 2}
FLOAT_TYPES = ("float32", "float16")  # storage types of weights, latents and the scale


@dataclass
class Reconstruction:
    """Errors of one reconstruction.

    rmse : over everything (with the per-texel scale when one is used).
    rmse_per_direction : ndarray of shape (N,).
    rmse_unscaled / rmse_scaled : clustered only, without / with a per-texel scale.
    texel_scale : ndarray of shape (M,) or None.
    """

    rmse: float
    rmse_per_direction: np.ndarray
    rmse_unscaled: float | None = None
    rmse_scaled: float | None = None
    texel_scale: np.ndarray | None = None


@torch.no_grad()
def decode_all(
    decoder: Decoder, latents: np.ndarray, dir_features: np.ndarray, chunk: int = 32
) -> np.ndarray:
    """Decode every latent at every direction: (R, latent) x (N, 4) -> (R, N, 3) float32."""
    out = np.empty((latents.shape[0], dir_features.shape[0], 3), dtype=np.float32)
    features = torch.from_numpy(np.asarray(dir_features, dtype=np.float32))
    decoder.eval()
    for start in range(0, latents.shape[0], chunk):
        z = torch.from_numpy(np.asarray(latents[start : start + chunk], dtype=np.float32))
        out[start : start + len(z)] = decoder.decode_grid(z, features).numpy()
    return out


def round_to(values: np.ndarray, dtype: str) -> np.ndarray:
    """``values`` (any shape) as float32 holding exactly what storing them in ``dtype``
    (float32 or float16, rounded to nearest even) keeps."""
    if dtype not in FLOAT_TYPES:
        raise ValueError(f"storage type {dtype!r} must be one of {list(FLOAT_TYPES)}")
    values = np.asarray(values, dtype=np.float32)
    return values if dtype == "float32" else values.astype(dtype).astype(np.float32)


@torch.no_grad()
def as_stored(
    decoder: Decoder, latents: np.ndarray, weight_dtype: str
) -> tuple[Decoder, np.ndarray]:
    """The model as its compressed file holds it (:mod:`pipeline.btf.compressed` writes the
    same rounded values): a copy of ``decoder`` whose parameters are rounded to
    ``weight_dtype``, and ``latents`` (R, latent) rounded to it, as float32; float32: the
    same decoder."""
    latents = round_to(latents, weight_dtype)
    if weight_dtype == "float32":
        return decoder, latents
    rounded = copy.deepcopy(decoder)
    for parameter in rounded.parameters():
        parameter.copy_(parameter.to(getattr(torch, weight_dtype)).to(parameter.dtype))
    return rounded, latents


def texel_scales(target: np.ndarray, pred: np.ndarray, mode: str) -> np.ndarray:
    """One scalar per texel that multiplies its cluster's reconstruction.

    ``lstsq``: the least-squares optimal factor <t, r> / <r, r>; ``luminance``: the ratio
    of the texel's mean value to its reconstruction's (the paper's suggestion).
    target, pred : ndarray of shape (m, N, 3) -> (m,) float32
    """
    t = target.reshape(len(target), -1).astype(np.float64)
    r = pred.reshape(len(pred), -1).astype(np.float64)
    if mode == "lstsq":
        scale = (t * r).sum(1) / np.maximum((r * r).sum(1), 1e-12)
    elif mode == "luminance":
        scale = t.mean(1) / np.maximum(r.mean(1), 1e-12)
    else:
        raise ValueError(f"model.texel_scale={mode!r} must be none, lstsq or luminance")
    return scale.astype(np.float32)


def reconstruction_error(
    decoder: Decoder,
    latents: np.ndarray,
    latent_of_texel: np.ndarray,
    abrdf: np.ndarray,
    alpha: float,
    dir_features: np.ndarray,
    texel_scale: str = "none",
    chunk: int = 64,
    scale_dtype: str = "float32",
) -> Reconstruction:
    """RMSE of the reconstruction against the measured ABRDFs.

    Parameters
    ----------
    latents : ndarray of shape (R, latent); R = M (Neural BTF) or k (clustered).
    latent_of_texel : ndarray of shape (M,): identity, or the cluster list.
    abrdf : ndarray of shape (M, N, 3), raw values (a memory map is read chunk by chunk).
    texel_scale : ``none``, ``lstsq`` or ``luminance`` (clustered only).
    scale_dtype : the per-texel scale is rounded to it (``btf.sizes.extra_dtype``) before
        it is applied: the "with scale" error is that of the scale as stored.
    """
    m, n, _ = abrdf.shape
    clustered = latents.shape[0] != m or not np.array_equal(latent_of_texel, np.arange(m))
    decoded = decode_all(decoder, latents, dir_features) if clustered else None
    sq_dir = np.zeros(n, dtype=np.float64)
    sq_dir_scaled = np.zeros(n, dtype=np.float64)
    scales = np.empty(m, dtype=np.float32) if clustered else None
    for start in progress(range(0, m, chunk), "evaluate", total=m, unit="texel", scale=chunk):
        stop = min(start + chunk, m)
        target = np.asarray(abrdf[start:stop], dtype=np.float32) / np.float32(alpha)
        if clustered:
            pred = decoded[latent_of_texel[start:stop]]
            mode = texel_scale if texel_scale != "none" else "lstsq"
            scales[start:stop] = round_to(texel_scales(target, pred, mode), scale_dtype)
            diff_scaled = pred * scales[start:stop, None, None] - target
            sq_dir_scaled += np.square(diff_scaled, dtype=np.float64).sum(axis=(0, 2))
        else:
            pred = decode_all(decoder, latents[start:stop], dir_features)
        sq_dir += np.square(pred - target, dtype=np.float64).sum(axis=(0, 2))
    rmse_per_direction = np.sqrt(sq_dir / (m * 3))
    rmse_unscaled = float(np.sqrt(sq_dir.sum() / (m * n * 3)))
    if not clustered:
        return Reconstruction(rmse_unscaled, rmse_per_direction)
    rmse_scaled = float(np.sqrt(sq_dir_scaled.sum() / (m * n * 3)))
    if texel_scale == "none":
        return Reconstruction(rmse_unscaled, rmse_per_direction, rmse_unscaled, rmse_scaled)
    # Every figure of a run describes what that run stores: here, the scaled model.
    per_direction = np.sqrt(sq_dir_scaled / (m * 3))
    return Reconstruction(rmse_scaled, per_direction, rmse_unscaled, rmse_scaled, scales)


def mean_abrdf_rmse(abrdf: np.ndarray, alpha: float, chunk: int = 256) -> float:
    """RMSE of the trivial model that predicts the mean ABRDF for every texel."""
    m = abrdf.shape[0]
    total = np.zeros(abrdf.shape[1:], dtype=np.float64)
    for start in progress(range(0, m, chunk), "mean ABRDF", total=m, unit="texel", scale=chunk):
        total += np.asarray(abrdf[start : start + chunk], dtype=np.float64).sum(0)
    mean = total / m
    sq = 0.0
    for start in progress(range(0, m, chunk), "its RMSE", total=m, unit="texel", scale=chunk):
        sq += float(np.square(np.asarray(abrdf[start : start + chunk]) - mean).sum())
    return float(np.sqrt(sq / abrdf.size)) / alpha


def storage_sizes(
    decoder: Decoder,
    n_latents: int,
    n_texels: int,
    n_directions: int,
    clustered: bool,
    weight_dtype: str = "float32",
    list_dtype: str = "int32",
    extra_dtype: str | None = None,
    latent_dim: int = LATENT_DIM,
) -> dict[str, int | float]:
    """Exact stored bytes (the keys are the MLflow metric names users rely on);
    ``latent_dim`` values per latent (``btf.network.latent``).

    ``compression_ratio`` = bytes_original / bytes_total with the original stored as
    float32 RGB (M x N x 3 x 4 bytes), as in the paper's "751 MB".
    """
    if list_dtype == "uint16" and n_latents > 65536:
        raise ValueError(f"method.list_dtype=uint16 cannot index k={n_latents} > 65536 clusters")
    w = DTYPE_BYTES[weight_dtype]
    sizes = {
        "bytes_decoder": parameter_count(decoder) * w,
        "bytes_latents": n_latents * latent_dim * w,
        "bytes_list": n_texels * DTYPE_BYTES[list_dtype] if clustered else 0,
        "bytes_extra": n_texels * DTYPE_BYTES[extra_dtype] if extra_dtype else 0,
        "bytes_original": n_texels * n_directions * 3 * 4,
    }
    parts = ("bytes_decoder", "bytes_latents", "bytes_list", "bytes_extra")
    sizes["bytes_total"] = sum(sizes[part] for part in parts)
    sizes["compression_ratio"] = sizes["bytes_original"] / sizes["bytes_total"]
    return sizes
