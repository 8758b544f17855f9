"""The compressed BTF of method A as one file: ``btf.safetensors``.

What each model of method A stores after compression, in a `safetensors
<https://huggingface.co/docs/safetensors>`_ file whose metadata hold everything needed to
evaluate it: Neural BTF and its clustered variant (PAPERS.md A) and the PCA baseline
(:mod:`pipeline.btf.linear`). :func:`write_compressed` and :func:`write_compressed_pca`
write one; :func:`load_compressed` reads either back as an object that answers RGB queries
without MLflow or Hydra (:class:`CompressedBTF`: numpy, safetensors and torch;
:class:`CompressedPCA`: numpy, safetensors and scipy); :mod:`pipeline.btf.export` writes
the file of a run into the stage cache and logs it to MLflow as a pyfunc model.

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

from pipeline.btf.compressed.format import (
    DIRECTION_FEATURES,
    DIRECTIONS,
    EXTRA_DTYPES,
    FILE_NAME,
    FORMAT,
    FORMAT_VERSION,
    LIST_DTYPES,
    METHODS,
    PCA,
    PCA_INTERPOLATION,
    PER_TEXEL,
    QUERY_COLUMNS,
    RGB_COLUMNS,
    SAFETENSORS_DTYPES,
    SUPPORT_TENSORS,
    TABLE1_PARTS,
    TEXEL_SCALES,
    WEIGHT_DTYPES,
    header_bytes,
    payload_bytes,
    read_header,
    safetensors_bytes,
    stored_parts,
    support_bytes,
)
from pipeline.btf.compressed.read import CompressedBTF, CompressedPCA, load_compressed
from pipeline.btf.compressed.write import write_compressed, write_compressed_pca

__all__ = [
    "DIRECTIONS",
    "DIRECTION_FEATURES",
    "EXTRA_DTYPES",
    "FILE_NAME",
    "FORMAT",
    "FORMAT_VERSION",
    "LIST_DTYPES",
    "METHODS",
    "PCA",
    "PCA_INTERPOLATION",
    "PER_TEXEL",
    "QUERY_COLUMNS",
    "RGB_COLUMNS",
    "SAFETENSORS_DTYPES",
    "SUPPORT_TENSORS",
    "TABLE1_PARTS",
    "TEXEL_SCALES",
    "WEIGHT_DTYPES",
    "CompressedBTF",
    "CompressedPCA",
    "header_bytes",
    "load_compressed",
    "payload_bytes",
    "read_header",
    "safetensors_bytes",
    "stored_parts",
    "support_bytes",
    "write_compressed",
    "write_compressed_pca",
]
