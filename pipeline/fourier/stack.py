"""Method C's light stack: the ``stack_data`` stage, the split of its lights and the crop
and downsampling every array goes through (the chain: :mod:`pipeline.fourier.runner`).

The stack is a light-stack folder's ``.lp`` stack, read with the real reader.
``dataset=synthetic_stack`` (``root: null``) first writes the built-in pot under
``${paths.data}``; its held-out lights are the stack's own ``heldout/`` set and, since
``scene.json`` is there, the reference images are the generator's noise-free renders (the
8-bit PNGs differ from them by quantization only). ``dataset=light_stack`` holds out every
``holdout_every``-th light of the folder; its reference images are the measured ones. A
dataset with ``format: ubo2003|utia`` (``dataset=btf_view``, or ``dataset=ubo2003|utia``
with one ``dataset.views`` entry) reads that one view folder of a BTF (81 lights) in the
material's frame, with the folder's view direction in eq. 4 (the view is (0, 0, 1)
otherwise). The held-out lights are split in turn into validation and test lights
(:func:`validation_mask`). The key holds the folder's fingerprint, so editing the folder
in place re-reads it.
"""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from pipeline.core.cache import Entry, canonical_json, save_arrays
from pipeline.core.errors import ConfigError, DataError
from pipeline.core.stage import Context, folder_fingerprint, plain_settings
from pipeline.data.directions import canonical_views, view_folder_name
from pipeline.data.light_stack import load_btf_view, load_light_stack, load_normal_map
from pipeline.fourier.series import VIEW
from pipeline.fourier.synthetic import load_synthetic_scene, write_synthetic_stack

log = logging.getLogger(__name__)

BTF_FORMATS = ("ubo2003", "utia")
# dataset=ubo2003|utia hold no method-C keys: these stand in for them (btf_view.yaml).
BTF_HOLDOUT_EVERY = 6
VALIDATION_EVERY = 2


def shrink(array: np.ndarray, crop, factor: int, labels: bool = False) -> np.ndarray:
    """Crop ``[row, col, height, width]`` then box-average ``factor`` x ``factor`` pixels.

    ``array`` is (..., H, W, C) (images, normals: normals are renormalized by the caller)
    or, with ``labels=True``, an (H, W) label map that takes each block's majority label.
    """
    if labels:
        values = np.unique(array)
        one_hot = (array[..., None] == values).astype(np.float32)
        return values[shrink(one_hot, crop, factor).argmax(axis=-1)]
    if crop is not None:
        row, col, height, width = (int(v) for v in crop)
        full_h, full_w = array.shape[-3:-1]
        if (
            min(row, col) < 0
            or min(height, width) < 1
            or row + height > full_h
            or col + width > full_w
        ):
            raise ConfigError(
                f"dataset.crop=[{row}, {col}, {height}, {width}] (row, col, height, width) "
                f"does not fit images of {full_h}x{full_w}"
            )
        array = array[..., row : row + height, col : col + width, :]
    if factor > 1:
        height, width = (n // factor * factor for n in array.shape[-3:-1])
        if height == 0 or width == 0:
            raise ConfigError(
                f"dataset.downsample={factor} leaves no pixel of {array.shape[-3:-1]}"
            )
        blocks = array[..., :height, :width, :].reshape(
            *array.shape[:-3], height // factor, factor, width // factor, factor, array.shape[-1]
        )
        array = blocks.mean(axis=(-4, -2), dtype=np.float64).astype(np.float32)
    return np.ascontiguousarray(array)


def unit_normals(normals: np.ndarray) -> np.ndarray:
    return (normals / np.linalg.norm(normals, axis=-1, keepdims=True)).astype(np.float32)


def file_settings(value: str, error: str) -> dict:
    """A settings file as ``{"path", "fingerprint"}`` (a key changes when the file does);
    ConfigError ``error`` when ``value`` is not a file."""
    path = Path(value).expanduser().resolve()
    if not path.is_file():
        raise ConfigError(error)
    stat = path.stat()
    return {"path": str(path), "fingerprint": {"bytes": stat.st_size, "mtime_ns": stat.st_mtime_ns}}


def btf_view(ds) -> tuple[int, int] | None:
    """The one view (θ_v, φ_v) in degrees of a BTF dataset (``format: ubo2003|utia``).

    None for a light-stack folder (no ``format``). Method C reads one view folder of a
    BTF as a light stack, so ``dataset.views`` must name exactly one grid direction.
    """
    if ds.get("format") is None:
        return None
    if ds.format not in BTF_FORMATS:
        raise ConfigError(f"dataset.format={ds.format!r} is not one of {list(BTF_FORMATS)}")
    views = ds.get("views")
    if views is None or len(views) != 1:
        shown = None if views is None else plain_settings(views)
        raise ConfigError(
            f"method C reads one view folder of a BTF as a light stack: set "
            f"dataset.views=[[theta_v,phi_v]] (degrees), got dataset.views={shown}"
        )
    return canonical_views(plain_settings(views))[0]


def stack_root(cfg) -> Path:
    """The stack folder; the built-in synthetic pot is written under paths.data first."""
    ds = cfg.dataset
    if OmegaConf.is_missing(ds, "root"):
        raise ConfigError(f"dataset={ds.name} needs dataset.root=/path/to/the/data")
    if ds.get("root") is None and ds.name == "synthetic_stack":
        gen = plain_settings(ds.synthetic)
        tag = hashlib.sha256(canonical_json(gen).encode()).hexdigest()[:10]
        root = (Path(cfg.paths.data) / f"synthetic_stack-{tag}").resolve()
        if not (root / "scene.json").is_file():
            log.info("generating the built-in synthetic light stack into %s", root)
            try:
                write_synthetic_stack(root, **gen)
            except (ConfigError, OSError):
                if not (root / "scene.json").is_file():  # not a sweep job that lost the race
                    raise
        return root
    if ds.get("root") is None:
        what = "a BTF's folder of view folders" if btf_view(ds) else "images plus one .lp file"
        raise ConfigError(f"dataset={ds.name} needs dataset.root=/path/to/a/folder ({what})")
    root = Path(str(ds.root)).expanduser().resolve()
    if not root.is_dir():
        raise DataError(f"light-stack folder {root} does not exist or is not a folder")
    return root


def _split(cfg, root: Path):
    """(train images, train dirs, held-out images, held-out dirs, view) of the stack."""
    ds = cfg.dataset
    view = btf_view(ds)
    if view is None:
        stack = load_light_stack(root)
        every = ds.get("holdout_every")
    else:
        stack = load_btf_view(root, ds.format, view)
        every = ds.get("holdout_every", BTF_HOLDOUT_EVERY)
    if every is None:
        if not (root / "heldout").is_dir():
            raise DataError(
                f"{root} has no heldout/ folder of held-out lights; set "
                "dataset.holdout_every=K to hold out every K-th light instead"
            )
        test = load_light_stack(root / "heldout")
        return stack.images, stack.light_dirs, test.images, test.light_dirs, stack.view_dir
    n = len(stack.light_dirs)
    if isinstance(every, bool) or int(every) != every or not 2 <= every <= n:
        raise ConfigError(f"dataset.holdout_every={every!r} must be an integer in [2, {n}]")
    held = np.arange(n) % int(every) == int(every) - 1
    images, dirs = stack.images, stack.light_dirs
    return images[~held], dirs[~held], images[held], dirs[held], stack.view_dir


def validation_mask(n_heldout: int, every) -> np.ndarray:
    """Which held-out lights are validation lights: every ``every``-th from the first.

    The rest are test lights. (M, λ) are chosen on the validation lights and the error
    is reported on the test lights, so the reported error is not the one minimized.
    """
    if isinstance(every, bool) or int(every) != every or every < 2:
        raise ConfigError(f"dataset.validation_every={every!r} must be an integer >= 2")
    if n_heldout < 2:
        raise DataError(
            f"{n_heldout} held-out light(s): need at least 2 (one validation, one test)"
        )
    return np.arange(n_heldout) % int(every) == 0


def data_stage(ctx: Context) -> Entry:
    """Read (or generate) the stack, split the lights, shrink, store arrays."""
    ds = ctx.cfg.dataset
    root = stack_root(ctx.cfg)
    crop = plain_settings(ds.get("crop"))
    factor = int(ds.get("downsample") or 1)
    if factor < 1:
        raise ConfigError(f"dataset.downsample={factor} must be an integer >= 1")
    view = btf_view(ds)
    every = ds.get("validation_every", VALIDATION_EVERY)
    settings = {
        "root": str(root),
        "fingerprint": folder_fingerprint(root if view is None else root / view_folder_name(*view)),
        "holdout_every": ds.get("holdout_every", None if view is None else BTF_HOLDOUT_EVERY),
        "validation_every": every,
        "crop": crop,
        "downsample": factor,
    }
    if view is not None:
        settings.update(format=str(ds.format), view=list(view))

    def compute(folder: Path) -> dict:
        train, train_dirs, test, test_dirs, view_dir = _split(ctx.cfg, root)
        is_validation = validation_mask(len(test_dirs), every)
        reference = "images"
        if (root / "scene.json").is_file():  # the generator's truth, free of noise
            test, reference = load_synthetic_scene(root).render(test_dirs), "analytic"
        arrays = {
            "train_images": shrink(train, crop, factor),
            "train_dirs": train_dirs,
            "heldout_images": shrink(test, crop, factor),
            "heldout_dirs": test_dirs,
            "heldout_is_validation": is_validation,
        }
        if (root / "normals.npy").is_file():
            normals = load_normal_map(root / "normals.npy", train.shape[1:3])
            arrays["given_normals"] = unit_normals(shrink(normals, crop, factor))
        if (root / "regions.npy").is_file():
            arrays["regions"] = shrink(np.load(root / "regions.npy"), crop, factor, labels=True)
        save_arrays(folder, **arrays)
        n, height, width, _ = arrays["train_images"].shape
        return {
            "n_train": n,
            "n_heldout": len(test_dirs),
            "n_validation": int(is_validation.sum()),
            "n_test": int((~is_validation).sum()),
            "view_dir": [float(v) for v in view_dir],
            "height": height,
            "width": width,
            "reference": reference,
            "regions": "regions" in arrays,
            "given_normals": "given_normals" in arrays,
        }

    return ctx.run("stack_data", settings, {}, compute, version="2")


def view_of(data: Entry) -> np.ndarray:
    """The view direction of a ``stack_data`` entry, (3,)."""
    return np.asarray(data.manifest["summary"].get("view_dir", VIEW), dtype=np.float64)
