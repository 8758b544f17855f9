"""Reading a compressed BTF file back (the format: :mod:`pipeline.btf.compressed`):
:func:`load_compressed` gives a :class:`CompressedBTF` (Neural BTF, latent texture,
clustered) or a :class:`CompressedPCA` (the PCA baseline).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.btf.compressed.format import (
    FORMAT,
    FORMAT_VERSION,
    PCA,
    PCA_INTERPOLATION,
    read_header,
)
from pipeline.btf.stereographic import direction_features
from pipeline.core.errors import DataError

if TYPE_CHECKING:
    from pipeline.btf.model import Decoder

# Rows of the first hidden layer computed at once (rows x hidden float32 values); a PCA's
# interpolated queries at once.
_ROWS_PER_BATCH = 1 << 16


@dataclass(kw_only=True)
class _CompressedFile:
    """What every model read back from a file has (:class:`CompressedBTF`,
    :class:`CompressedPCA`) and answers: its crop, its texels, and every texel at every
    direction (subclasses define ``query``).

    Attributes
    ----------
    path : the file it was read from.
    alpha : the model's normalised output x alpha = linear RGB in the data's units.
    crop_size, crop_offset : (rows, cols) and (row, col) of the crop; M = rows x cols.
    metadata : every metadata string of the file, as stored.
    """

    path: Path
    alpha: float
    crop_size: tuple[int, int]
    crop_offset: tuple[int, int]
    metadata: dict[str, str] = field(default_factory=dict)

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
        """``texels`` checked: a 1-D array of ints in [0, M), as int64."""
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

    def _pairs(self, texels, directions) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_texels` and :meth:`_directions`, of one length n (``query_pairs``)."""
        texels, directions = self._texels(texels), self._directions(directions)
        if len(directions) != len(texels):
            raise ValueError(f"{len(texels)} texels but {len(directions)} direction pairs")
        return texels, directions


@dataclass(kw_only=True)
class CompressedBTF(_CompressedFile):
    """A compressed BTF read back from its file (:func:`load_compressed`).

    Attributes
    ----------
    decoder : :class:`pipeline.btf.model.Decoder` in float32 (weights as stored, widened).
    latents : ndarray of shape (R, latent), in the stored dtype.
    latent_of_texel : ndarray of shape (M,), in the stored dtype; None = the identity.
    texel_scale : ndarray of shape (M,), in the stored dtype; None when not used.
    path, alpha, crop_size, crop_offset, metadata : as every file's (``_CompressedFile``).
    """

    decoder: Decoder
    latents: np.ndarray
    latent_of_texel: np.ndarray | None
    texel_scale: np.ndarray | None

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

        texels, directions = self._pairs(texels, directions)
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


@dataclass(kw_only=True)
class CompressedPCA(_CompressedFile):
    """The PCA baseline read back from its file (:func:`load_compressed`, method ``pca``):
    the same queries as :class:`CompressedBTF`, evaluated as the renderer evaluates the
    linear stage's arrays (:mod:`pipeline.btf.compressed`).

    Attributes
    ----------
    mean : ndarray of shape (3N,); basis : ndarray of shape (c, 3N); coefficients :
        ndarray of shape (M, c): normalised units, in the stored dtype.
    measured_directions : ndarray of shape (N, 4), float64 radians.
    path, alpha, crop_size, crop_offset, metadata : as every file's (``_CompressedFile``).
    """

    mean: np.ndarray
    basis: np.ndarray
    coefficients: np.ndarray
    measured_directions: np.ndarray

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
        return pca_material(
            self.mean,
            self.basis,
            self.coefficients,
            self.measured_directions,
            self.alpha,
            self.crop_size,
        )

    def query_pairs(self, texels, directions) -> np.ndarray:
        """Linear RGB of texel ``texels[i]`` at direction pair ``directions[i]``: exactly
        :attr:`material`'s ``evaluate``.

        texels : array_like of ints of shape (n,); directions : array_like of shape (n, 4)
        in radians -> ndarray of shape (n, 3), float32.
        """
        texels, directions = self._pairs(texels, directions)
        return self.material.evaluate(texels, directions)

    def query(self, texels, directions) -> np.ndarray:
        """Linear RGB of every given texel at every given direction pair, as
        :meth:`CompressedBTF.query`: (T,) ints, (D, 4) radians -> (T, D, 3) float32.

        The model is linear in its coefficients, so the mean and the c basis vectors are
        interpolated once per direction pair and combined with each texel's coefficients:
        (c + 1) D interpolations, not T D. Equal to :meth:`query_pairs` up to float32
        rounding (the sums run in another order).
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
        identity = np.eye(len(stacked), dtype=np.float32)
        zero = np.zeros_like(stacked[0])
        return pca_material(
            zero, stacked, identity, self.measured_directions, self.alpha, (1, len(stacked))
        )


def load_compressed(path: str | os.PathLike) -> CompressedBTF | CompressedPCA:
    """Read a file written by :func:`pipeline.btf.compressed.write_compressed` (a
    :class:`CompressedBTF`) or :func:`pipeline.btf.compressed.write_compressed_pca` (a
    :class:`CompressedPCA`).

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
        common = _common(meta)
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
        **common,
        metadata=meta,
    )
    m = btf.n_texels
    if (
        (btf.latent_of_texel is None and latents.shape[0] != m)
        or (btf.latent_of_texel is not None and btf.latent_of_texel.shape != (m,))
        or (btf.texel_scale is not None and btf.texel_scale.shape != (m,))
    ):
        raise DataError(f"{path}: the tensors do not fit a crop of {btf.crop_size} texels")
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
            **_common(meta),
            metadata=meta,
        )
        pca.material  # noqa: B018 (built now: arrays that do not fit are refused here)
    except KeyError as error:
        raise DataError(f"{path}: a compressed PCA without {error.args[0]!r}") from None
    except (ValueError, TypeError) as error:  # DataError included
        raise DataError(f"{path}: inconsistent compressed PCA ({error})") from None
    return pca


def _common(meta: dict[str, str]) -> dict:
    """``alpha``, ``crop_size`` and ``crop_offset`` of a file's metadata."""
    alpha = float(meta["alpha"])
    size, offset = (
        tuple(int(v) for v in json.loads(meta[k])) for k in ("crop_size", "crop_offset")
    )
    return {"alpha": alpha, "crop_size": size, "crop_offset": offset}


def pca_material(mean, basis, coefficients, measured_directions, alpha: float, crop_size):
    """The renderer's PCA material (:class:`pipeline.btf.render.surfaces.LinearMaterial`)
    of a PCA file's tensors: the one evaluation of the format's interpolation (the reader's
    and, before it writes a file, :func:`pipeline.btf.compressed.write_compressed_pca`'s)."""
    from pipeline.btf.render.surfaces import LinearMaterial

    return LinearMaterial(mean, basis, coefficients, tuple(crop_size), alpha, measured_directions)
