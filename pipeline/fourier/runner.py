"""Method C's chain in the app (``method=fourier``): light stack, normals, fit, baselines.

    stack_data ─┬─► stack_normals ─► fourier_fit ─┐
                ├─► relight_baselines ────────────┼─► fourier_evaluate (metrics, figures)
                └─► stack_segmentation ───────────┘  (segmentation: its own metrics, figure)

* ``stack_data``: reads the folder's ``.lp`` stack with the real reader and splits the
  lights into training and held-out ones. ``dataset=synthetic_stack`` (``root: null``)
  first writes the built-in pot under ``${paths.data}``; its held-out lights are the
  stack's own ``heldout/`` set and, since ``scene.json`` is there, the reference images
  are the generator's noise-free renders (the 8-bit PNGs differ from them by
  quantization only). ``dataset=light_stack`` holds out every ``holdout_every``-th light
  of the folder; its reference images are the measured ones. ``crop``/``downsample``
  shrink every array alike. The key holds the folder's fingerprint, so editing the
  folder in place re-reads it.
* ``stack_normals``: ``given`` (the stack's ``normals.npy``), ``flat`` (0, 0, 1),
  ``photometric`` (Lambertian photometric stereo on the training images) or a file.
* ``fourier_fit``: eq. 19 with ``method.M``, ``method.lam``, ``method.clamp_diffuse``.
* ``relight_baselines``: PTM and HSH on the same training lights; their key does not
  hold M or λ, so a Fig. 6 sweep fits them once.
* ``stack_segmentation``: the paper's nearest-representative labelling and k-means,
  scored against the ground-truth regions when the stack has them.
* ``fourier_evaluate``: held-out and training RMS, figures.
"""

from __future__ import annotations

import hashlib
import logging
import time
from pathlib import Path

import mlflow
import numpy as np

from pipeline.core.cache import Entry, canonical_json, save_arrays, save_json
from pipeline.core.errors import ConfigError, DataError
from pipeline.core.stage import Context, folder_fingerprint, plain_settings
from pipeline.data.light_stack import load_light_stack, load_normal_map
from pipeline.fourier.baselines import (
    fit_hsh,
    fit_ptm,
    lambertian_normals,
    render_hsh,
    render_ptm,
)
from pipeline.fourier.segmentation import (
    mean_image,
    segment_by_representatives,
    segment_kmeans,
    segmentation_accuracy,
)
from pipeline.fourier.series import fit_fourier, render_fourier, rms_error
from pipeline.fourier.synthetic import load_synthetic_scene, write_synthetic_stack

log = logging.getLogger(__name__)

FIT_KEYS = ("M", "lam", "clamp_diffuse", "solver")


# --------------------------------------------------------------------------- helpers


def display(linear: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear RGB -> sRGB-encoded values in [0, 1] for PNG figures."""
    from pipeline.data.images import srgb_oetf

    return srgb_oetf(np.clip(np.asarray(linear) * exposure, 0.0, 1.0))


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
        array = array[..., :height, :width, :]
        shape = (
            *array.shape[:-3],
            height // factor,
            factor,
            width // factor,
            factor,
            array.shape[-1],
        )
        array = array.reshape(shape).mean(axis=(-4, -2), dtype=np.float64).astype(np.float32)
    return np.ascontiguousarray(array)


def _unit(normals: np.ndarray) -> np.ndarray:
    return (normals / np.linalg.norm(normals, axis=-1, keepdims=True)).astype(np.float32)


# --------------------------------------------------------------------------- data


def stack_root(cfg) -> Path:
    """The stack folder; the built-in synthetic pot is written under paths.data first."""
    ds = cfg.dataset
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
        raise ConfigError(
            f"dataset={ds.name} needs dataset.root=/path/to/a/folder (images plus one .lp file)"
        )
    root = Path(str(ds.root)).expanduser().resolve()
    if not root.is_dir():
        raise DataError(f"light-stack folder {root} does not exist or is not a folder")
    return root


def _split(cfg, root: Path):
    """(train images, train dirs, held-out images, held-out dirs) of the stack in ``root``."""
    stack = load_light_stack(root)
    every = cfg.dataset.get("holdout_every")
    if every is None:
        if not (root / "heldout").is_dir():
            raise DataError(
                f"{root} has no heldout/ folder of held-out lights; set "
                "dataset.holdout_every=K to hold out every K-th light instead"
            )
        test = load_light_stack(root / "heldout")
        return stack.images, stack.light_dirs, test.images, test.light_dirs
    n = len(stack.light_dirs)
    if isinstance(every, bool) or int(every) != every or not 2 <= every <= n:
        raise ConfigError(f"dataset.holdout_every={every!r} must be an integer in [2, {n}]")
    held = np.arange(n) % int(every) == int(every) - 1
    return (
        stack.images[~held],
        stack.light_dirs[~held],
        stack.images[held],
        stack.light_dirs[held],
    )


def data_stage(ctx: Context) -> Entry:
    """Read (or generate) the stack, split the lights, shrink, store arrays."""
    ds = ctx.cfg.dataset
    root = stack_root(ctx.cfg)
    crop = plain_settings(ds.get("crop"))
    factor = int(ds.get("downsample") or 1)
    if factor < 1:
        raise ConfigError(f"dataset.downsample={factor} must be an integer >= 1")
    settings = {
        "root": str(root),
        "fingerprint": folder_fingerprint(root),
        "holdout_every": ds.get("holdout_every"),
        "crop": crop,
        "downsample": factor,
    }

    def compute(folder: Path) -> dict:
        train, train_dirs, test, test_dirs = _split(ctx.cfg, root)
        reference = "images"
        if (root / "scene.json").is_file():  # the generator's truth, free of noise
            test, reference = load_synthetic_scene(root).render(test_dirs), "analytic"
        arrays = {
            "train_images": shrink(train, crop, factor),
            "train_dirs": train_dirs,
            "heldout_images": shrink(test, crop, factor),
            "heldout_dirs": test_dirs,
        }
        if (root / "normals.npy").is_file():
            normals = load_normal_map(root / "normals.npy", train.shape[1:3])
            arrays["given_normals"] = _unit(shrink(normals, crop, factor))
        if (root / "regions.npy").is_file():
            arrays["regions"] = shrink(np.load(root / "regions.npy"), crop, factor, labels=True)
        save_arrays(folder, **arrays)
        n, height, width, _ = arrays["train_images"].shape
        return {
            "n_train": n,
            "n_heldout": len(test_dirs),
            "height": height,
            "width": width,
            "reference": reference,
            "regions": "regions" in arrays,
            "given_normals": "given_normals" in arrays,
        }

    return ctx.run("stack_data", settings, {}, compute, version="1")


# --------------------------------------------------------------------------- normals


def normals_stage(ctx: Context, data: Entry) -> Entry:
    """Per-pixel normals: given, flat, photometric stereo, or a normal-map file."""
    ds = ctx.cfg.dataset
    mode = str(ds.get("normals") or "flat")
    settings: dict = {"mode": mode}
    if mode == "photometric":
        settings.update(plain_settings(ds.photometric))
    elif mode == "given" and not data.manifest["summary"]["given_normals"]:
        raise ConfigError(
            f"dataset.normals=given but {data.manifest['settings']['root']} has no "
            "normals.npy: use flat, photometric or a normal-map file"
        )
    elif mode not in ("given", "flat"):
        path = Path(mode).expanduser().resolve()
        if not path.is_file():
            raise ConfigError(
                f"dataset.normals={mode!r} is neither given, flat, photometric nor a file"
            )
        stat = path.stat()
        settings = {
            "mode": "file",
            "path": str(path),
            "fingerprint": {"bytes": stat.st_size, "mtime_ns": stat.st_mtime_ns},
        }

    def compute(folder: Path) -> dict:
        shape = data.array("train_images").shape[1:3]
        if settings["mode"] == "given":
            normals = data.array("given_normals", mmap=False)
        elif settings["mode"] == "flat":
            normals = np.broadcast_to(np.float32([0, 0, 1]), (*shape, 3)).copy()
        elif settings["mode"] == "photometric":
            normals, _ = lambertian_normals(
                data.array("train_images"),
                data.array("train_dirs"),
                settings["drop_dark"],
                settings["drop_bright"],
            )
        else:
            read = data.manifest["settings"]
            normals = _unit(
                shrink(load_normal_map(settings["path"]), read["crop"], read["downsample"])
            )
            if normals.shape[:2] != tuple(shape):
                raise DataError(
                    f"normal map {settings['path']} is {normals.shape[:2]} after "
                    f"crop/downsample but the images are {tuple(shape)}"
                )
        save_arrays(folder, normals=normals.astype(np.float32))
        return {"mean_nz": float(normals[..., 2].mean())}

    return ctx.run("stack_normals", settings, {"stack_data": data}, compute, version="1")


# --------------------------------------------------------------------------- fits


def fit_settings(cfg) -> dict:
    """The eq. 19 settings of ``method.*`` (shared by method=fourier and fourier_pattern)."""
    method = cfg.method
    return {key: method[key] for key in FIT_KEYS}


def fit_stage(ctx: Context, data: Entry, normals: Entry) -> Entry:
    """Eq. 19 at every pixel: coefficients (H, W, 3, 2M + 2), float64."""
    settings = fit_settings(ctx.cfg)

    def compute(folder: Path) -> dict:
        start = time.perf_counter()
        coeffs = fit_fourier(
            data.array("train_images"),
            data.array("train_dirs"),
            normals.array("normals"),
            M=int(settings["M"]),
            lam=float(settings["lam"]),
            clamp_diffuse=bool(settings["clamp_diffuse"]),
            solver=settings["solver"],
        )
        seconds = time.perf_counter() - start
        save_arrays(folder, coeffs=coeffs)
        return {"seconds": seconds, "n_coeffs": int(coeffs.shape[-1])}

    return ctx.run("fourier_fit", settings, {"stack_data": data, "stack_normals": normals}, compute, version="1")


def baselines_stage(ctx: Context, data: Entry) -> Entry:
    """PTM and HSH on the training lights, with their held-out and training RMS."""

    def compute(folder: Path) -> dict:
        train, train_dirs = data.array("train_images"), data.array("train_dirs")
        test, test_dirs = data.array("heldout_images"), data.array("heldout_dirs")
        metrics = {}
        for name, fit, render in (("ptm", fit_ptm, render_ptm), ("hsh", fit_hsh, render_hsh)):
            start = time.perf_counter()
            coeffs = fit(train, train_dirs)
            metrics[f"time_fit_{name}"] = time.perf_counter() - start
            save_arrays(folder, **{name: coeffs})
            metrics[f"rmse_heldout_{name}"] = rms_error(render(coeffs, test_dirs), test)
            metrics[f"rmse_train_{name}"] = rms_error(render(coeffs, train_dirs), train)
        save_json(folder, "metrics", metrics)
        return metrics

    return ctx.run("relight_baselines", {"models": ["ptm", "hsh"]}, {"stack_data": data}, compute, version="1")


# --------------------------------------------------------------------------- segmentation


def representative_points(regions: np.ndarray) -> list[list[int]]:
    """One pixel per ground-truth label (in label order): the one farthest from its edge.

    Stands in for the user's click of the paper's method on data with known regions.
    """
    from scipy.ndimage import distance_transform_edt

    points = []
    for label in np.unique(regions):
        depth = distance_transform_edt(np.pad(regions == label, 1))[1:-1, 1:-1]
        points.append([int(i) for i in np.unravel_index(depth.argmax(), depth.shape)])
    return points


def segmentation_stage(ctx: Context, data: Entry, fitted: Entry) -> Entry:
    """Labels by the paper's method (when points exist) and by k-means; accuracy vs truth."""
    seg = plain_settings(ctx.cfg.method.segmentation)
    if seg["features"] not in ("mean_colour", "coefficients"):
        raise ConfigError(
            f"method.segmentation.features={seg['features']!r} is not mean_colour or coefficients"
        )
    points = seg["points"]
    if points is None and data.manifest["summary"]["regions"]:
        points = representative_points(data.array("regions", mmap=False))
    settings = {**seg, "points": points}
    inputs = {"stack_data": data}
    if seg["features"] == "coefficients":
        inputs["fourier_fit"] = fitted

    def compute(folder: Path) -> dict:
        mean = mean_image(data.array("train_images"))
        labels = {}
        if points is not None:
            labels["paper"] = segment_by_representatives(mean, points, seg["colour_space"])
        if seg["features"] == "coefficients":
            features, space = fitted.array("coeffs", mmap=False), None
        else:
            features, space = mean, seg["colour_space"]
        labels["kmeans"] = segment_kmeans(
            features, seg["n_regions"], seed=seg["seed"], colour_space=space, n_init=seg["n_init"]
        )
        save_arrays(folder, mean_image=mean, **{f"labels_{k}": v for k, v in labels.items()})
        metrics = {}
        truth = data.array("regions", mmap=False) if (data.path / "regions.npy").is_file() else None
        if truth is not None:
            for name, found in labels.items():
                metrics[f"segmentation_accuracy_{name}"] = segmentation_accuracy(found, truth)
        _segmentation_figure(folder / "segmentation.png", mean, truth, labels)
        save_json(folder, "metrics", metrics)
        return metrics

    return ctx.run("stack_segmentation", settings, inputs, compute, version="1")


def _segmentation_figure(path: Path, mean, truth, labels: dict) -> None:
    from matplotlib.figure import Figure

    panels = [("mean image", display(mean / max(float(mean.max()), 1e-12)))]
    if truth is not None:
        panels.append(("ground truth", truth))
    panels += [(f"{name}", found) for name, found in labels.items()]
    fig = Figure(figsize=(3 * len(panels), 3.2))
    axes = fig.subplots(1, len(panels), squeeze=False)
    for ax, (title, image) in zip(axes[0], panels, strict=True):
        ax.imshow(image, cmap="tab10", vmin=0, vmax=9, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)


# --------------------------------------------------------------------------- evaluation


def evaluate_stage(
    ctx: Context, data: Entry, normals: Entry, fitted: Entry, baselines: Entry
) -> Entry:
    """Held-out and training RMS of the Fourier fit; the held-out and normals figures."""
    figures = plain_settings(ctx.cfg.method.figures)
    clamp = bool(fitted.manifest["settings"]["clamp_diffuse"])

    def compute(folder: Path) -> dict:
        coeffs, normal_map = fitted.array("coeffs", mmap=False), normals.array("normals")
        test, test_dirs = data.array("heldout_images"), data.array("heldout_dirs")
        predicted = render_fourier(coeffs, test_dirs, normal_map, clamp_diffuse=clamp)
        train = data.array("train_images")
        metrics = {
            "rmse_heldout_fourier": rms_error(predicted, test),
            "rmse_train_fourier": rms_error(
                render_fourier(coeffs, data.array("train_dirs"), normal_map, clamp_diffuse=clamp),
                train,
            ),
        }
        shown = np.linspace(0, len(test_dirs) - 1, min(figures["n_lights"], len(test_dirs)))
        shown = np.unique(shown.round().astype(int))
        rows = {
            "reference": test[shown],
            "Fourier": predicted[shown],
            "PTM": render_ptm(baselines.array("ptm"), test_dirs[shown]),
            "HSH": render_hsh(baselines.array("hsh"), test_dirs[shown]),
        }
        (folder / "figures").mkdir()
        _heldout_figure(
            folder / "figures" / "heldout.png", rows, test_dirs[shown], float(figures["exposure"])
        )
        _normals_figure(folder / "figures" / "normals.png", np.asarray(normal_map))
        save_json(folder, "metrics", metrics)
        return metrics

    inputs = {
        "stack_data": data,
        "stack_normals": normals,
        "fourier_fit": fitted,
        "relight_baselines": baselines,
    }
    return ctx.run("fourier_evaluate", figures, inputs, compute, version="1")


def _heldout_figure(path: Path, rows: dict, dirs: np.ndarray, exposure: float) -> None:
    from matplotlib.figure import Figure

    reference = rows["reference"]
    names = list(rows)
    fig = Figure(figsize=(2.4 * len(names), 2.5 * len(dirs)))
    axes = fig.subplots(len(dirs), len(names), squeeze=False)
    for i, light in enumerate(dirs):
        for j, name in enumerate(names):
            ax = axes[i, j]
            ax.imshow(display(rows[name][i], exposure), interpolation="nearest")
            if name == "reference":
                label = "reference, l = ({:.2f}, {:.2f}, {:.2f})".format(*light)
            else:
                label = f"{name}  RMS {rms_error(rows[name][i], reference[i]):.4f}"
            ax.set_title(label, fontsize=8)
            ax.axis("off")
    fig.suptitle("held-out lights: reference and relit models", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def _normals_figure(path: Path, normals: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(np.round((normals * 0.5 + 0.5) * 255).astype(np.uint8)).save(path)


# --------------------------------------------------------------------------- the job


def describe(cfg, data: Entry) -> str:
    """A short run name: method, M, λ, data and normals."""
    root = Path(data.manifest["settings"]["root"]).name
    return (
        f"{cfg.method.name} M={cfg.method.M} lam={cfg.method.lam} "
        f"{cfg.dataset.name}:{root} normals={Path(str(cfg.dataset.normals)).name}"
    )


def run(ctx: Context) -> dict[str, float]:
    """The whole chain for ``method=fourier``; returns the metrics for MLflow."""
    data = data_stage(ctx)
    normals = normals_stage(ctx, data)
    fitted = fit_stage(ctx, data, normals)
    baselines = baselines_stage(ctx, data)
    segmented = segmentation_stage(ctx, data, fitted)
    evaluated = evaluate_stage(ctx, data, normals, fitted, baselines)
    metrics = {
        **evaluated.json("metrics"),
        **baselines.json("metrics"),
        **segmented.json("metrics"),
    }
    summary = data.manifest["summary"]
    metrics.update(
        time_fit_fourier=fitted.manifest["summary"]["seconds"],
        n_train_lights=summary["n_train"],
        n_heldout_lights=summary["n_heldout"],
    )
    if mlflow.active_run() is not None:
        mlflow.set_tag("mlflow.runName", describe(ctx.cfg, data))
        mlflow.set_tag("heldout_reference", summary["reference"])
        mlflow.log_artifacts(str(evaluated.path / "figures"), "figures")
        mlflow.log_artifact(str(segmented.file("segmentation.png")), "figures")
    return {k: float(v) for k, v in metrics.items()}
