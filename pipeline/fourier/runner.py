"""Method C's chain in the app (``method=fourier``): light stack, normals, fit, baselines.

    stack_data ─┬─► stack_normals ─┬─► fourier_fit ─┐
                │                  └─► fourier_condition (cond(A) per M: metrics only)
                ├─► relight_baselines ──────────────┼─► fourier_evaluate (metrics, figures)
                └─► stack_segmentation ─────────────┘  (segmentation: its own metrics, figure)

``stack_data`` (:mod:`pipeline.fourier.stack`) reads the stack and splits its lights into
training, validation and test lights; each stage here is described where it is defined.
A stage's key holds only what it reads: ``fourier_condition`` has no λ and
``relight_baselines`` neither M nor λ, so a Fig. 6 sweep computes them once per M and once.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from pipeline.core.cache import Entry, save_arrays, save_json
from pipeline.core.errors import ConfigError, DataError
from pipeline.core.settings import check_settings
from pipeline.core.stage import Context, plain_settings
from pipeline.data.light_stack import load_normal_map
from pipeline.fourier.baselines import fit_hsh, fit_ptm, lambertian_normals, render_hsh, render_ptm
from pipeline.fourier.figures import heldout_figure, normals_figure, segmentation_figure
from pipeline.fourier.segmentation import (
    COLOUR_SPACES,
    mean_image,
    score_segmentation,
    segment_by_representatives,
    segment_kmeans,
)
from pipeline.fourier.series import (
    design_condition,
    fit_fourier,
    render_fourier,
    resolve_solver,
    rms_error,
)
from pipeline.fourier.settings import CONSTRAINTS, fourier_settings
from pipeline.fourier.stack import data_stage, file_settings, shrink, unit_normals, view_of


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
        error = f"dataset.normals={mode!r} is neither given, flat, photometric nor a file"
        settings = {"mode": "file", **file_settings(mode, error)}

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
            normals = unit_normals(
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


def fit_settings(cfg) -> dict:
    """The eq. 19 settings of ``method.*`` (shared by method=fourier and fourier_pattern),
    checked (:class:`~pipeline.fourier.settings.FourierSettings`), with the solver that
    runs (``auto`` resolved: the same fit gets the same key)."""
    settings = asdict(fourier_settings(cfg))
    settings["solver"] = resolve_solver(settings["solver"], float(settings["lam"]))
    return settings


def fit_stage(ctx: Context, data: Entry, normals: Entry) -> Entry:
    """Eq. 19 at every pixel: coefficients (H, W, 3, 2M + 2), float64."""
    settings = fit_settings(ctx.cfg)
    n_train = data.manifest["summary"]["n_train"]
    if n_train < 2 * settings["M"] + 2:  # known once the stack is read: named as set
        raise ConfigError(
            f"method.M={settings['M']} needs N >= 2M + 2 = {2 * settings['M'] + 2} images, "
            f"got N={n_train} training lights in {data.manifest['settings']['root']}"
        )

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

    inputs = {"stack_data": data, "stack_normals": normals}
    return ctx.run("fourier_fit", settings, inputs, compute, version="2")


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
        M, clamp = int(settings["M"]), bool(settings["clamp_diffuse"])
        cond, truncated = design_condition(data.array("train_dirs"), normal_map, M, view, clamp)
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

    settings = {"models": ["ptm", "hsh"]}
    return ctx.run("relight_baselines", settings, {"stack_data": data}, compute, version="2")


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
    # The job checks these at the door; a library call (a test's, a script's) is checked here.
    check_settings(ctx.cfg, CONSTRAINTS)
    seg = plain_settings(ctx.cfg.method.segmentation)
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
        kmeans = {"k": seg["n_regions"], "seed": seg["seed"], "n_init": seg["n_init"]}
        labels = {}  # (name, colour space or None) -> (H, W) labels
        for space in spaces:
            if points is not None:
                labels["paper", space] = segment_by_representatives(mean, points, space)
            if seg["features"] == "mean_colour":
                labels["kmeans", space] = segment_kmeans(mean, colour_space=space, **kmeans)
        if seg["features"] == "coefficients":
            coeffs = fitted.array("coeffs", mmap=False)
            labels["kmeans", None] = segment_kmeans(coeffs, **kmeans)
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
        segmentation_figure(folder / "segmentation.png", mean, truth, used)
        save_json(folder, "metrics", metrics)
        return metrics

    return ctx.run("stack_segmentation", settings, inputs, compute, version="2")


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
        heldout_figure(
            folder / "figures" / "heldout.png", rows, test_dirs[shown], float(figures["exposure"])
        )
        normals_figure(folder / "figures" / "normals.png", np.asarray(normal_map))
        save_json(folder, "metrics", metrics)
        return metrics

    inputs = {
        "stack_data": data,
        "stack_normals": normals,
        "fourier_fit": fitted,
        "relight_baselines": baselines,
    }
    return ctx.run("fourier_evaluate", figures, inputs, compute, version="2")


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
    ctx.log.tags(
        {
            "mlflow.runName": describe(ctx.cfg, data),
            "fourier_solver": fitted.manifest["settings"]["solver"],
            "heldout_reference": summary["reference"],
        }
    )
    ctx.log.folder(evaluated.path / "figures", "figures")
    ctx.log.file(segmented.file("segmentation.png"), "figures")
    return {k: float(v) for k, v in metrics.items()}
