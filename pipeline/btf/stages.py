"""Runners of the BTF chain's data stages: load, crop, preprocess, pca, kmeans, representatives.

Each runner reads only its own settings from the config, calls a pure function, and lets
:class:`pipeline.core.stage.Context` decide whether anything needs computing; each declares
its code version where it runs (bump it when a change alters the stage's output).
"""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from pipeline.btf.preprocess import Normalization, encoder_inputs, fit_normalization
from pipeline.core.cache import Entry, canonical_json, save_arrays, save_json
from pipeline.core.errors import ConfigError, DataError
from pipeline.core.files import reserved_memmap
from pipeline.core.stage import Context, folder_fingerprint, plain_settings

log = logging.getLogger(__name__)


def synthetic_folder(cfg: DictConfig) -> Path:
    """Where the built-in BTF of these settings is (or will be) written: named by a hash of
    the generator's settings and views."""
    from pipeline.btf.synthetic_dataset import generator_settings

    ds = cfg.dataset
    gen = plain_settings(ds.synthetic)
    # A UBO2014 file holds every view of its set: its reader picks dataset.views.
    views = None if ds.format == "ubo2014" else plain_settings(ds.views)
    named = {"gen": generator_settings(gen), "views": views}
    tag = hashlib.sha256(canonical_json(named).encode()).hexdigest()
    return Path(cfg.paths.data) / f"synthetic_btf-{ds.format}-{gen['ext']}-{tag[:10]}"


def dataset_root(cfg: DictConfig) -> Path:
    """The dataset: a folder or its ``.zip`` archive (UBO2003, UTIA), or a ``.btf`` file
    (UBO2014); the built-in synthetic BTF is generated into a folder on first use."""
    ds = cfg.dataset
    if built_in(cfg):
        from pipeline.btf.synthetic_dataset import write_synthetic_btf

        root = synthetic_folder(cfg)
        if not root.is_dir():
            log.info("generating the built-in synthetic BTF into %s", root)
        gen = plain_settings(ds.synthetic)
        return write_synthetic_btf(
            root,
            size=gen["size"],
            seed=gen["seed"],
            format=ds.format,
            ext=gen["ext"],
            views=None if ds.format == "ubo2014" else plain_settings(ds.views),
            quality=gen["quality"],
            material=gen["material"],
            directions=gen["directions"],
            n_lights=gen["n_lights"],
            n_views=gen["n_views"],
        )
    if ds.root is None:
        raise ConfigError(f"dataset={ds.name} needs dataset.root=/path/to/the/dataset")
    root = Path(ds.root).expanduser()
    if ds.format == "ubo2014":
        if not root.is_file():
            raise DataError(f"dataset root is not a UBO2014 .btf file: {root}")
        return root
    from pipeline.data.btf import is_archive

    if not (root.is_dir() or is_archive(root)):
        raise DataError(f"dataset root does not exist or is not a folder or .zip archive: {root}")
    return root


def file_fingerprint(path: Path) -> dict:
    """Name, size and modification time of one dataset file (a UBO2014 ``.btf``)."""
    stat = path.stat()
    return {"name": path.name, "bytes": stat.st_size, "mtime_ns": stat.st_mtime_ns}


def load(ctx: Context) -> Entry:
    """Decode the dataset once into a memory-mappable ``images.npy`` (n, H, W, 3).

    The key holds the dataset's fingerprint, not its location: a folder, the ``.zip``
    archive it was unpacked from and a copy that kept its file times share one entry
    (the location is in the entry's summary)."""
    from pipeline.data.btf import (
        DEFAULT_LINEARIZE,
        archive_fingerprint,
        check_linearize,
        count_btf_images,
        is_archive,
        load_btf,
    )

    ds = ctx.cfg.dataset
    if ds.format == "ubo2014":
        return _load_ubo2014(ctx)
    linearize = check_linearize(ds.get("linearize"), ds.format)
    root = dataset_root(ctx.cfg).resolve()
    views = plain_settings(ds.views)
    settings = {
        "format": ds.format,
        "views": views,
        "fingerprint": archive_fingerprint(root) if is_archive(root) else folder_fingerprint(root),
        "linearize": linearize,
    }
    own_encoding = DEFAULT_LINEARIZE[ds.format]
    if linearize not in (own_encoding, "none") and built_in(ctx.cfg):
        log.warning(
            "dataset.linearize=%s, but the built-in BTF is written in the %s layout's "
            "own encoding (%s): its values will not match the analytic ground truth",
            linearize,
            ds.format,
            own_encoding,
        )

    def compute(folder: Path) -> dict:
        n, height, width = count_btf_images(root, format=ds.format, views=views)
        check_crop_fits(ctx.cfg, height, width, root)  # before the images are decoded
        images = reserved_memmap(folder / "images.npy", (n, height, width, 3), np.float32)
        btf = load_btf(root, format=ds.format, views=views, out=images, linearize=linearize)
        images.flush()
        del images
        save_arrays(folder, directions=np.asarray(btf.directions, dtype=np.float64))
        return {"n_images": n, "height": height, "width": width, "root": str(root)}

    return ctx.run("load", settings, {}, compute, version="3")


def _load_ubo2014(ctx: Context) -> Entry:
    """The load stage for a UBO2014 ``.btf`` file: its header, directions and fingerprint,
    nothing decoded (the crop stage decodes ``btf.crop`` from the factors)."""
    from pipeline.data.ubo2014 import select_rows
    from pipeline.data.ubo2014_header import describe, read_dfmf

    ds = ctx.cfg.dataset
    path = dataset_root(ctx.cfg).resolve()
    views, lights = plain_settings(ds.views), plain_settings(ds.get("lights"))
    fingerprint = file_fingerprint(path)
    settings = {"format": "ubo2014", "fingerprint": fingerprint, "views": views, "lights": lights}

    def compute(folder: Path) -> dict:
        # Inside compute: a bad file raises here, and nothing is published.
        dfmf = read_dfmf(path)
        rows = select_rows(dfmf, views, lights)
        save_arrays(folder, directions=dfmf.directions()[rows], rows=rows)
        shape = {"n_images": len(rows), "height": dfmf.height, "width": dfmf.width}
        return {**shape, "root": str(path), **describe(dfmf)}

    return ctx.run("load", settings, {}, compute, version="4")


def check_crop_fits(cfg: DictConfig, height: int, width: int, root) -> None:
    """Refuse a ``btf.crop`` that does not fit a texture of ``height`` x ``width`` texels
    (known from the dataset's header, before anything is decoded), naming the setting,
    the texture and an offset that would fit."""
    size = int(cfg.btf.crop.size)
    y0, x0 = (int(v) for v in cfg.btf.crop.offset)
    if size > height or size > width:
        raise ConfigError(
            f"btf.crop.size={size} is larger than the texture of {height}x{width} texels: {root}"
        )
    if y0 + size > height or x0 + size > width:
        fits = [min(y0, height - size), min(x0, width - size)]
        raise ConfigError(
            f"btf.crop.size={size} at btf.crop.offset=[{y0}, {x0}] does not fit the texture "
            f"of {height}x{width} texels: give btf.crop.offset={fits} ({root})"
        )


def crop(ctx: Context, loaded: Entry) -> Entry:
    """Choose a ``btf.crop.size`` square at ``btf.crop.offset``, read as ABRDFs (M, N, 3)
    with :func:`abrdf`.

    Nothing is copied: the entry records which texels (and, for a UBO2014 file, which
    direction rows) the crop is. :func:`abrdf` reads them from the load stage's decoded
    images, or decodes them from a UBO2014 file's factors."""
    settings = plain_settings(ctx.cfg.btf.crop)
    size = int(settings["size"])
    y0, x0 = (int(v) for v in settings["offset"])
    summary = loaded.manifest["summary"]
    n, height, width = summary["n_images"], summary["height"], summary["width"]
    check_crop_fits(ctx.cfg, height, width, summary.get("root"))
    from_file = ctx.cfg.dataset.format == "ubo2014"

    def compute(folder: Path) -> dict:
        save_arrays(folder, directions=loaded.array("directions", mmap=False))
        crop = {"M": size * size, "N": n, "texels": [y0, x0, size, size]}
        if not from_file:
            return {**crop, "source": "images"}
        save_arrays(folder, rows=loaded.array("rows", mmap=False))
        fingerprint = loaded.manifest["settings"]["fingerprint"]
        return {**crop, "source": "factors", "root": summary["root"], "fingerprint": fingerprint}

    return ctx.run("crop", settings, {"load": loaded}, compute, version="2")


def abrdf(cropped: Entry):
    """The crop's ABRDFs, shape (M, N, 3), float32: from image formats, read from the load
    stage's ``images.npy`` (:func:`pipeline.data.image_abrdfs.crop_abrdfs`: in memory, or
    gathered where read for a crop too large to hold); for a UBO2014 file a
    :class:`~pipeline.data.ubo2014_decode.FactorABRDFs` that decodes what is indexed.
    Raises :class:`~pipeline.core.errors.DataError`, naming what is missing, when the load
    stage's images are gone from the cache or the UBO2014 file is gone or changed (its size
    or modification time).
    """
    summary = cropped.manifest["summary"]
    if summary["source"] == "images":
        from pipeline.data.image_abrdfs import crop_abrdfs

        load_key = cropped.manifest["inputs"]["load"]
        images = cropped.path.parents[1] / "load" / load_key / "images.npy"
        if not images.is_file():
            raise DataError(
                f"the images the cached crop {cropped.key} reads are gone from the cache "
                f"({images}): run the job again to decode them"
            )
        return crop_abrdfs(images, summary["texels"])
    from pipeline.data.ubo2014_decode import FactorABRDFs
    from pipeline.data.ubo2014_header import read_dfmf

    path = Path(summary["root"])
    if not path.is_file() or file_fingerprint(path) != summary["fingerprint"]:
        raise DataError(
            f"the UBO2014 file the cached crop {cropped.key} was made from is gone or has "
            f"changed since: {path}"
        )
    return FactorABRDFs(read_dfmf(path), cropped.array("rows", mmap=False), summary["texels"])


def preprocess(ctx: Context, cropped: Entry) -> Entry:
    """Fit the eq. 1-6 normalization (per-dimension mean/std of log values, alpha)."""

    def compute(folder: Path) -> dict:
        try:
            norm = fit_normalization(abrdf(cropped))
        except DataError as error:
            raise DataError(f"{error}: {ctx.cfg.dataset.root or 'the built-in BTF'}") from None
        save_arrays(folder, mean=norm.mean, std=norm.std)
        save_json(folder, "alpha", norm.alpha)
        return {"alpha": norm.alpha}

    return ctx.run("preprocess", {}, {"crop": cropped}, compute, version="1")


def normalization(entry: Entry) -> Normalization:
    return Normalization(
        entry.array("mean", mmap=False), entry.array("std", mmap=False), entry.json("alpha")
    )


def pca(ctx: Context, cropped: Entry, prep: Entry) -> Entry:
    """PCA of the preprocessed ABRDFs; independent of k and of the run's seed."""
    settings = plain_settings(ctx.cfg.btf.pca)

    def compute(folder: Path) -> dict:
        from pipeline.btf.clustering import pca_reduce, streamed_pca
        from pipeline.btf.streamed_svd import IN_MEMORY_BYTES

        source, norm = abrdf(cropped), normalization(prep)
        m, n, _ = source.shape
        k, seed = settings["n_components"], settings["random_state"]
        if m * n * 3 * 4 <= IN_MEMORY_BYTES:
            scores, ratio = pca_reduce(encoder_inputs(source, norm), k, seed)
        else:  # a block of texels at a time: the features are never held whole

            def rows(start: int, stop: int) -> np.ndarray:
                return norm.encoder_input(source[start:stop]).reshape(stop - start, -1)

            scores, ratio = streamed_pca(rows, m, 3 * n, k, seed)
        save_arrays(folder, scores=scores, explained_variance_ratio=ratio)
        return {"explained_variance": float(ratio.sum())}

    return ctx.run("pca", settings, {"crop": cropped, "preprocess": prep}, compute, version="1")


def kmeans(ctx: Context, reduced: Entry) -> Entry:
    """k-means++ on the PCA scores for the run's single ``model.k``."""
    # scikit-learn is imported only when a stage needs it: a cached rerun skips it.
    from pipeline.btf.clustering import check_k, kmeans_pp

    k = ctx.cfg.model.k
    check_k(k, reduced.array("scores").shape[0])
    settings = {"k": k, "seed": ctx.cfg.seed, **plain_settings(ctx.cfg.btf.kmeans)}

    def compute(folder: Path) -> dict:
        labels, centers, inertia = kmeans_pp(
            np.asarray(reduced.array("scores")),
            k,
            seed=ctx.cfg.seed,
            n_init=settings["n_init"],
            max_iter=settings["max_iter"],
        )
        save_arrays(folder, labels=labels, centers=centers)
        return {"inertia": inertia}

    return ctx.run("kmeans", settings, {"pca": reduced}, compute, version="1")


def representatives(ctx: Context, cropped: Entry, clusters: Entry) -> Entry:
    """The element-wise median ABRDF of each cluster, shape (k, N, 3)."""
    k = int(clusters.manifest["settings"]["k"])

    def compute(folder: Path) -> dict:
        from pipeline.btf.clustering import cluster_medians

        medians = cluster_medians(abrdf(cropped), clusters.array("labels"), k)
        save_arrays(folder, representatives=medians)
        return {"k": k}

    return ctx.run(
        "representatives", {}, {"crop": cropped, "kmeans": clusters}, compute, version="1"
    )


def built_in(cfg: DictConfig) -> bool:
    """Whether the run's data is the built-in synthetic BTF (which has an analytic truth)."""
    return cfg.dataset.name == "synthetic" and cfg.dataset.root is None


def data_truth_rmse(
    abrdf: np.ndarray, directions: np.ndarray, truth_of, alpha: float, chunk: int = 256
) -> float:
    """Eq. 10's RMSE of the data against the analytic truth: what a perfect model scores.

    Parameters
    ----------
    abrdf : ndarray of shape (M, N, 3), the data's values (a memory map is read in chunks).
    directions : ndarray of shape (N, 4), the data's directions (radians).
    truth_of : callable, directions (n, 4) -> ndarray (M, n, 3), the truth at the crop.
    alpha : the normalisation of eq. 10 (values / alpha lie in [0, 1]).
    """
    squares = 0.0
    for start in range(0, len(directions), chunk):
        stop = min(start + chunk, len(directions))
        data = np.asarray(abrdf[:, start:stop], dtype=np.float64)
        squares += float(np.square(data - truth_of(directions[start:stop])).sum())
    return float(np.sqrt(squares / abrdf.size)) / alpha


def truth_at_crop(cfg: DictConfig):
    """The synthetic generator's analytic truth over the run's crop: a function of
    directions (n, 4) to values (M, n, 3)."""
    from pipeline.btf.synthetic import SyntheticBTF

    gen = cfg.dataset.synthetic
    size = int(cfg.btf.crop.size)
    y0, x0 = (int(v) for v in cfg.btf.crop.offset)
    generator = SyntheticBTF(size=gen.size, seed=gen.seed, material=gen.material)

    def truth_of(directions: np.ndarray) -> np.ndarray:
        values = generator.evaluate(directions)[:, y0 : y0 + size, x0 : x0 + size]
        return values.reshape(len(directions), -1, 3).transpose(1, 0, 2)

    return truth_of


def truth_floor(ctx: Context, cropped: Entry, prep: Entry) -> Entry | None:
    """For the built-in BTF: the data's RMSE against the generator's analytic truth (the
    JPEG and 8-bit rounding of the written images), over the crop and all its directions;
    None for other data."""
    cfg = ctx.cfg
    if not built_in(cfg):
        return None
    from pipeline.btf.synthetic_dataset import generator_settings

    truth_of = truth_at_crop(cfg)

    def compute(folder: Path) -> dict:
        directions = cropped.array("directions", mmap=False)
        rmse = data_truth_rmse(abrdf(cropped), directions, truth_of, prep.json("alpha"))
        return {"rmse_data_vs_truth": rmse}

    gen = plain_settings(cfg.dataset.synthetic)
    settings = {"synthetic": generator_settings(gen), "crop": plain_settings(cfg.btf.crop)}
    return ctx.run(
        "truth_floor", settings, {"crop": cropped, "preprocess": prep}, compute, version="1"
    )
