"""Method C's chain in the app (``method=fourier``): light stack, normals, fit, baselines.

    stack_data ─┬─► stack_normals ─┬─► fourier_fit ─┐
                │                  └─► fourier_condition (cond(A) per M: metrics only)
                ├─► relight_baselines ──────────────┼─► fourier_evaluate (metrics, figures)
                └─► stack_segmentation ─────────────┘  (segmentation: its own metrics, figure)

* ``stack_data``: reads the folder's ``.lp`` stack with the real reader and splits the
  lights into training and held-out ones. ``dataset=synthetic_stack`` (``root: null``)
  first writes the built-in pot under ``${paths.data}``; its held-out lights are the
  stack's own ``heldout/`` set and, since ``scene.json`` is there, the reference images
  are the generator's noise-free renders (the 8-bit PNGs differ from them by
  quantization only). ``dataset=light_stack`` holds out every ``holdout_every``-th light
  of the folder; its reference images are the measured ones. A dataset with
  ``format: ubo2003|utia`` (``dataset=btf_view``, or ``dataset=ubo2003|utia`` with one
  ``dataset.views`` entry) reads that one view folder of a BTF (81 lights) in the
  material's frame, with the folder's view direction in eq. 4 (the view is (0, 0, 1)
  otherwise). The held-out lights are split in turn into validation lights (every
  ``validation_every``-th, from the first) and test lights: M and λ are chosen on the
  former and reported on the latter (``pipeline/fourier/report.py``).
  ``crop``/``downsample`` shrink every array alike. The key holds the folder's
  fingerprint, so editing the folder in place re-reads it.
* ``stack_normals``: ``given`` (the stack's ``normals.npy``), ``flat`` (0, 0, 1),
  ``photometric`` (Lambertian photometric stereo on the training images) or a file.
* ``fourier_fit``: eq. 19 with ``method.M``, ``method.lam``, ``method.clamp_diffuse``
  and the solver that runs (``method.solver: auto`` = SVD least squares at λ = 0, normal
  equations at λ > 0); logged as the tag ``fourier_solver``.
* ``fourier_condition``: cond(A) of every pixel's unregularized design matrix; its key
  does not hold λ, so a Fig. 6 sweep computes it once per M.
* ``relight_baselines``: PTM and HSH on the same training lights; their key does not
  hold M or λ, so a Fig. 6 sweep fits them once.
* ``stack_segmentation``: the paper's nearest-representative labelling and k-means, in
  RGB and in chromaticity, scored against the ground-truth regions when the stack has
  them: over all pixels and over the object's pixels (region label != 0, the backdrop).
* ``fourier_evaluate``: held-out (all, validation, test) and training RMS, figures.
"""

from __future__ import annotations

import hashlib
import logging
import time
from pathlib import Path

import mlflow
import numpy as np
from omegaconf import OmegaConf

from pipeline.core.cache import Entry, canonical_json, save_arrays, save_json
from pipeline.core.errors import ConfigError, DataError
from pipeline.core.stage import Context, folder_fingerprint, plain_settings
from pipeline.data.directions import canonical_views, view_folder_name
from pipeline.data.light_stack import load_btf_view, load_light_stack, load_normal_map
from pipeline.fourier.baselines import (
    fit_hsh,
    fit_ptm,
    lambertian_normals,
    render_hsh,
    render_ptm,
)
from pipeline.fourier.segmentation import (
    COLOUR_SPACES,
    mean_image,
    score_segmentation,
    segment_by_representatives,
    segment_kmeans,
)
from pipeline.fourier.series import (
    VIEW,
    design_condition,
    fit_fourier,
    render_fourier,
    resolve_solver,
    rms_error,
)
from pipeline.fourier.synthetic import load_synthetic_scene, write_synthetic_stack

log = logging.getLogger(__name__)

FIT_KEYS = ("M", "lam", "clamp_diffuse", "solver")
BTF_FORMATS = ("ubo2003", "utia")
# dataset=ubo2003|utia hold no method-C keys: these stand in for them (btf_view.yaml).
BTF_HOLDOUT_EVERY = 6
VALIDATION_EVERY = 2


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
    return (
        stack.images[~held],
        stack.light_dirs[~held],
        stack.images[held],
        stack.light_dirs[held],
        stack.view_dir,
    )


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
            arrays["given_normals"] = _unit(shrink(normals, crop, factor))
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
    """The eq. 19 settings of ``method.*`` (shared by method=fourier and fourier_pattern),
    with the solver that runs (``auto`` resolved: the same fit gets the same key)."""
    method = cfg.method
    settings = {key: method[key] for key in FIT_KEYS}
    settings["solver"] = resolve_solver(str(settings["solver"]), float(settings["lam"]))
    return settings


def fit_stage(ctx: Context, data: Entry, normals: Entry) -> Entry:
    """Eq. 19 at every pixel: coefficients (H, W, 3, 2M + 2), float64."""
    settings = fit_settings(ctx.cfg)

    def compute(folder: Path) -> dict:
        start = time.perf_counter()
        coeffs = fit_fourier(
            data.array("train_images"),
            data.array("train_dirs"),
            normals.array("normals"),
            view=view_of(data),
            M=int(settings["M"]),
            lam=float(settings["lam"]),
            clamp_diffuse=bool(settings["clamp_diffuse"]),
            solver=settings["solver"],
        )
        seconds = time.perf_counter() - start
        save_arrays(folder, coeffs=coeffs)
        return {"seconds": seconds, "n_coeffs": int(coeffs.shape[-1])}

    return ctx.run(
        "fourier_fit",
        settings,
        {"stack_data": data, "stack_normals": normals},
        compute,
        version="2",
    )


def condition_stage(ctx: Context, data: Entry, normals: Entry) -> Entry:
    """cond(A) of each pixel's unregularized design matrix at ``method.M`` (not λ).

    Metrics: the median and largest cond(A) over the pixels whose normal is not the view
    (where it is, θs = θd for every light and A is singular by construction: the
    synthetic pot's flat backdrop), and the fraction of all pixels where
    ``np.linalg.lstsq``'s cutoff drops a singular value (numerically rank-deficient: the
    λ = 0 fit is minimum-norm there).
    """
    settings = {key: ctx.cfg.method[key] for key in ("M", "clamp_diffuse")}

    def compute(folder: Path) -> dict:
        view = view_of(data)
        normal_map = normals.array("normals", mmap=False)
        cond, truncated = design_condition(
            data.array("train_dirs"),
            normal_map,
            int(settings["M"]),
            view=view,
            clamp_diffuse=bool(settings["clamp_diffuse"]),
        )
        unit = normal_map / np.linalg.norm(normal_map, axis=-1, keepdims=True)
        generic = (unit @ view < 1.0 - 1e-6) & np.isfinite(cond)
        metrics = {"frac_pixels_rank_deficient": float(truncated.mean())}
        if generic.any():  # else no value: JSON and MLflow take no NaN
            metrics["cond_design_median"] = float(np.median(cond[generic]))
            metrics["cond_design_max"] = float(cond[generic].max())
        save_json(folder, "metrics", metrics)
        return metrics

    inputs = {"stack_data": data, "stack_normals": normals}
    return ctx.run("fourier_condition", settings, inputs, compute, version="2")


def heldout_errors(name: str, predicted, reference, is_validation) -> dict[str, float]:
    """RMS on all held-out lights, on the validation lights and on the test lights."""
    is_validation = np.asarray(is_validation, dtype=bool)
    predicted, reference = np.asarray(predicted), np.asarray(reference)
    return {
        f"rmse_heldout_{name}": rms_error(predicted, reference),
        f"rmse_validation_{name}": rms_error(predicted[is_validation], reference[is_validation]),
        f"rmse_test_{name}": rms_error(predicted[~is_validation], reference[~is_validation]),
    }


def baselines_stage(ctx: Context, data: Entry) -> Entry:
    """PTM and HSH on the training lights, with their held-out and training RMS."""

    def compute(folder: Path) -> dict:
        train, train_dirs = data.array("train_images"), data.array("train_dirs")
        test, test_dirs = data.array("heldout_images"), data.array("heldout_dirs")
        is_validation = data.array("heldout_is_validation")
        metrics = {}
        for name, fit, render in (("ptm", fit_ptm, render_ptm), ("hsh", fit_hsh, render_hsh)):
            start = time.perf_counter()
            coeffs = fit(train, train_dirs)
            metrics[f"time_fit_{name}"] = time.perf_counter() - start
            save_arrays(folder, **{name: coeffs})
            metrics.update(heldout_errors(name, render(coeffs, test_dirs), test, is_validation))
            metrics[f"rmse_train_{name}"] = rms_error(render(coeffs, train_dirs), train)
        save_json(folder, "metrics", metrics)
        return metrics

    return ctx.run(
        "relight_baselines", {"models": ["ptm", "hsh"]}, {"stack_data": data}, compute, version="2"
    )


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
    """Labels by the paper's method (when points exist) and by k-means; accuracy vs truth.

    ``labels_paper`` / ``labels_kmeans`` (what quilting reads) use
    ``method.segmentation.colour_space``; both colour spaces are scored. Metrics, for
    ``<name>`` in paper, kmeans: ``segmentation_accuracy_<name>`` (all pixels) and
    ``segmentation_accuracy_object_<name>`` (object pixels: ground-truth label != 0) in
    the chosen colour space, and the same with ``_rgb`` / ``_chromaticity`` appended.
    """
    seg = plain_settings(ctx.cfg.method.segmentation)
    if seg["features"] not in ("mean_colour", "coefficients"):
        raise ConfigError(
            f"method.segmentation.features={seg['features']!r} is not mean_colour or coefficients"
        )
    if seg["colour_space"] not in COLOUR_SPACES:
        raise ConfigError(
            f"method.segmentation.colour_space={seg['colour_space']!r} is not one of "
            f"{list(COLOUR_SPACES)}"
        )
    points = seg["points"]
    if points is None and data.manifest["summary"]["regions"]:
        points = representative_points(data.array("regions", mmap=False))
    settings = {**seg, "points": points}
    inputs = {"stack_data": data}
    if seg["features"] == "coefficients":
        inputs["fourier_fit"] = fitted
    chosen = seg["colour_space"]
    spaces = [chosen, *(s for s in COLOUR_SPACES if s != chosen)]

    def compute(folder: Path) -> dict:
        mean = mean_image(data.array("train_images"))
        labels = {}  # (name, colour space or None) -> (H, W) labels
        for space in spaces:
            if points is not None:
                labels["paper", space] = segment_by_representatives(mean, points, space)
            if seg["features"] == "mean_colour":
                labels["kmeans", space] = segment_kmeans(
                    mean,
                    seg["n_regions"],
                    seed=seg["seed"],
                    colour_space=space,
                    n_init=seg["n_init"],
                )
        if seg["features"] == "coefficients":
            labels["kmeans", None] = segment_kmeans(
                fitted.array("coeffs", mmap=False),
                seg["n_regions"],
                seed=seg["seed"],
                n_init=seg["n_init"],
            )
        used = {name: found for (name, space), found in labels.items() if space in (chosen, None)}
        save_arrays(folder, mean_image=mean, **{f"labels_{k}": v for k, v in used.items()})
        metrics = {}
        truth = data.array("regions", mmap=False) if (data.path / "regions.npy").is_file() else None
        if truth is not None:
            for (name, space), found in labels.items():
                scores = score_segmentation(found, truth)
                suffixes = [""] if space is None else [f"_{space}"]
                if space == chosen:
                    suffixes.append("")
                for suffix in suffixes:
                    metrics[f"segmentation_accuracy_{name}{suffix}"] = scores["all"]
                    if "object" in scores:
                        metrics[f"segmentation_accuracy_object_{name}{suffix}"] = scores["object"]
        _segmentation_figure(folder / "segmentation.png", mean, truth, used)
        save_json(folder, "metrics", metrics)
        return metrics

    return ctx.run("stack_segmentation", settings, inputs, compute, version="2")


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
        view = view_of(data)
        predicted = render_fourier(coeffs, test_dirs, normal_map, view, clamp_diffuse=clamp)
        train = data.array("train_images")
        train_predicted = render_fourier(
            coeffs, data.array("train_dirs"), normal_map, view, clamp_diffuse=clamp
        )
        metrics = {
            **heldout_errors("fourier", predicted, test, data.array("heldout_is_validation")),
            "rmse_train_fourier": rms_error(train_predicted, train),
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
    return ctx.run("fourier_evaluate", figures, inputs, compute, version="2")


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
    """A short run name: method, M, λ, data (and view) and normals."""
    read = data.manifest["settings"]
    root = Path(read["root"]).name
    view = f" view={read['view']}" if "view" in read else ""
    normals = Path(str(cfg.dataset.get("normals") or "flat")).name
    return (
        f"{cfg.method.name} M={cfg.method.M} lam={cfg.method.lam} "
        f"{cfg.dataset.name}:{root}{view} normals={normals}"
    )


def run(ctx: Context) -> dict[str, float]:
    """The whole chain for ``method=fourier``; returns the metrics for MLflow."""
    data = data_stage(ctx)
    normals = normals_stage(ctx, data)
    fitted = fit_stage(ctx, data, normals)
    condition = condition_stage(ctx, data, normals)
    baselines = baselines_stage(ctx, data)
    segmented = segmentation_stage(ctx, data, fitted)
    evaluated = evaluate_stage(ctx, data, normals, fitted, baselines)
    metrics = {
        **evaluated.json("metrics"),
        **baselines.json("metrics"),
        **segmented.json("metrics"),
        **condition.json("metrics"),
    }
    summary = data.manifest["summary"]
    metrics.update(
        time_fit_fourier=fitted.manifest["summary"]["seconds"],
        n_train_lights=summary["n_train"],
        n_heldout_lights=summary["n_heldout"],
        n_validation_lights=summary["n_validation"],
        n_test_lights=summary["n_test"],
    )
    if mlflow.active_run() is not None:
        mlflow.set_tag("mlflow.runName", describe(ctx.cfg, data))
        mlflow.set_tag("fourier_solver", fitted.manifest["settings"]["solver"])
        mlflow.set_tag("heldout_reference", summary["reference"])
        mlflow.log_artifacts(str(evaluated.path / "figures"), "figures")
        mlflow.log_artifact(str(segmented.file("segmentation.png")), "figures")
    return {k: float(v) for k, v in metrics.items()}
