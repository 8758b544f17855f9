"""Method C's texture generation in the app (``method=fourier_pattern``, PAPERS.md C 1-4).

    stack_data ─► stack_normals ─► fourier_fit ─┬─► pattern_quilt ─► pattern_render
            └──────► stack_segmentation ────────┘

The first stages are those of ``method=fourier`` (:mod:`pipeline.fourier.runner`,
same keys: a pattern job reuses the fit of a ``fourier`` run with the same M and λ).

* ``pattern_quilt``: per reflectance region, Image Quilting of the coefficient map
  (all 3 (2M + 2) channels), candidate blocks only inside that region of the chosen
  segmentation; the same grid filled by random blocks with straight seams is the
  baseline. Seam costs of both and the quilting time are its summary.
* ``pattern_render``: every region's synthesized map rendered for one light and view on
  the target's normals (the synthetic pot, or a normal-map file), blended with weight
  maps that sum to 1 (eq. 20: stripes, blobs or a painted file); written as PNG (sRGB)
  and EXR (linear, half float), with the weight map and a quilting comparison figure.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from pipeline.core.cache import Entry, save_arrays
from pipeline.core.errors import ConfigError
from pipeline.core.report import save_figure
from pipeline.core.stage import Context, plain_settings
from pipeline.data.images import write_exr, write_image_8bit
from pipeline.data.light_stack import load_normal_map
from pipeline.fourier import runner as fr
from pipeline.fourier.figures import display
from pipeline.fourier.optical_pattern import (
    blob_weights,
    load_weight_map,
    render_optical_pattern,
    stripe_weights,
)
from pipeline.fourier.quilting import candidate_positions, quilt, random_tiling, seam_cost
from pipeline.fourier.series import render_fourier
from pipeline.fourier.stack import data_stage, file_settings
from pipeline.fourier.synthetic import SyntheticStackConfig, make_synthetic_scene


def _file_settings(kind: str, value: str) -> dict:
    return file_settings(value, f"method.pattern.{kind}={value!r} is not a known choice nor a file")


def target_settings(cfg) -> dict:
    """The target object of the pattern: the synthetic pot or a normal-map file."""
    pattern = cfg.method.pattern
    if str(pattern.target) == "pot":
        size = [int(n) for n in pattern.size]
        return {"kind": "pot", "size": size, "seed": int(pattern.pot_seed)}
    return {"kind": "file", **_file_settings("target", str(pattern.target))}


def target_normals(target: dict) -> tuple[np.ndarray, np.ndarray]:
    """(normals (H, W, 3), mask (H, W) of pixels on the object) of the target."""
    if target["kind"] == "pot":
        scene = make_synthetic_scene(
            SyntheticStackConfig(size=tuple(target["size"]), seed=target["seed"])
        )
        return scene.normals, scene.mask
    normals = load_normal_map(target["path"])
    return normals, np.ones(normals.shape[:2], dtype=bool)


def quilt_stage(ctx: Context, fitted: Entry, segmented: Entry, out_shape) -> Entry:
    """Quilt each region's coefficients to ``out_shape``; random tiling as the baseline."""
    quilting = plain_settings(ctx.cfg.method.quilting)
    if quilting["labels"] not in ("paper", "kmeans"):
        raise ConfigError(f"method.quilting.labels={quilting['labels']!r} is not paper or kmeans")
    if not segmented.file(f"labels_{quilting['labels']}.npy").is_file():
        raise ConfigError(
            "method.quilting.labels=paper needs representative points: give "
            "method.segmentation.points=[[row, col], ...] or use labels=kmeans"
        )
    settings = {**quilting, "out_shape": [int(n) for n in out_shape]}
    block, overlap = int(quilting["block_size"]), int(quilting["overlap"])

    def compute(folder: Path) -> dict:
        coeffs = fitted.array("coeffs", mmap=False)
        height, width, _, n_coeffs = coeffs.shape
        source = coeffs.reshape(height, width, 3 * n_coeffs)
        labels = segmented.array(f"labels_{quilting['labels']}", mmap=False)
        regions = quilting["regions"]
        if regions is None:
            regions = [int(r) for r in np.unique(labels) if r >= 0]
        summary = {"regions": regions, "seconds_quilting": 0.0}
        for region in regions:
            mask = labels == region
            summary[f"candidates_r{region}"] = len(candidate_positions(mask, block))
            if summary[f"candidates_r{region}"] == 0:
                raise ConfigError(
                    f"region {region} ({int(mask.sum())} pixels) holds no "
                    f"{block}x{block} block: lower method.quilting.block_size"
                )
            grid = (source, out_shape, block, overlap)
            start = time.perf_counter()
            rng = np.random.default_rng([quilting["seed"], region])
            quilted = quilt(*grid, quilting["tolerance"], rng, mask=mask)
            summary["seconds_quilting"] += time.perf_counter() - start
            rng = np.random.default_rng([quilting["seed"], region, 1])
            tiled = random_tiling(*grid, rng, mask=mask)
            summary[f"seam_cost_quilting_r{region}"] = seam_cost(quilted, block, overlap)
            summary[f"seam_cost_random_r{region}"] = seam_cost(tiled, block, overlap)
            arrays = {f"quilted_r{region}": quilted.reshape(*out_shape, 3, n_coeffs)}
            arrays[f"random_r{region}"] = tiled.reshape(*out_shape, 3, n_coeffs).astype(np.float32)
            save_arrays(folder, **arrays)
        for kind in ("quilting", "random"):
            summary[f"seam_cost_{kind}"] = float(
                np.mean([summary[f"seam_cost_{kind}_r{r}"] for r in regions])
            )
        return summary

    inputs = {"fourier_fit": fitted, "stack_segmentation": segmented}
    return ctx.run("pattern_quilt", settings, inputs, compute, version="1")


def weight_maps(pattern: dict, n_regions: int, shape) -> np.ndarray:
    """Eq. 20's weights (n_regions, H, W) from ``method.pattern.weights``."""
    kind = pattern["weights"]
    if kind == "stripes":
        return stripe_weights(shape, n_regions, **pattern["stripes"])
    if kind == "blobs":
        blobs = dict(pattern["blobs"])
        rng = np.random.default_rng(blobs.pop("seed"))
        return blob_weights(shape, n_regions, rng=rng, **blobs)
    weights = load_weight_map(kind, n_regions)
    if weights.shape[1:] != tuple(shape):
        raise ConfigError(f"weight map {kind} is {weights.shape[1:]} but the target is {shape}")
    return weights


def pattern_stage(ctx: Context, fitted: Entry, quilted: Entry, target: dict) -> Entry:
    """Render, blend (eq. 20) and write the optical pattern as PNG and EXR."""
    pattern = plain_settings(ctx.cfg.method.pattern)
    settings = {
        key: pattern[key] for key in ("light", "view", "weights", "exposure", "mask_outside")
    }
    if pattern["weights"] in ("stripes", "blobs"):  # only the generator in use
        settings[pattern["weights"]] = pattern[pattern["weights"]]
    else:
        settings["weights_file"] = _file_settings("weights", pattern["weights"])
    settings["target"] = target
    clamp = bool(fitted.manifest["settings"]["clamp_diffuse"])
    regions = quilted.manifest["summary"]["regions"]

    def compute(folder: Path) -> dict:
        normals, on_object = target_normals(target)
        maps = [quilted.array(f"quilted_r{r}", mmap=False) for r in regions]
        weights = weight_maps(pattern, len(maps), normals.shape[:2])
        light = np.asarray(pattern["light"], dtype=np.float64)
        view = np.asarray(pattern["view"], dtype=np.float64)
        image = render_optical_pattern(maps, weights, light, normals, view, clamp)
        # Light cannot be negative (the unclamped cos θd term goes below 0 facing away).
        image = np.maximum(image, 0.0)
        if pattern["mask_outside"]:
            image[~on_object] = 0.0
        out = folder / "pattern"
        out.mkdir()
        write_exr(out / "pattern.exr", image)
        write_image_8bit(out / "pattern.png", display(image, pattern["exposure"]))
        colours = np.array([[0.9, 0.6, 0.3], [0.6, 0.1, 0.1], [0.2, 0.4, 0.8], [0.3, 0.7, 0.3]])
        palette = colours[np.arange(len(maps)) % len(colours)]
        write_image_8bit(out / "weights.png", np.einsum("nhw,nc->hwc", weights, palette))
        _quilting_figure(
            out / "quilting.png", quilted, regions, light, view, clamp, pattern["exposure"]
        )
        save_arrays(folder, pattern=image, weights=weights.astype(np.float32))
        return {"mean": float(image[on_object].mean()), "max": float(image.max())}

    inputs = {"pattern_quilt": quilted, "fourier_fit": fitted}
    return ctx.run("pattern_render", settings, inputs, compute, version="1")


def _quilting_figure(path, quilted: Entry, regions, light, view, clamp, exposure) -> None:
    """Per region: random tiling and quilted map, rendered flat under the pattern light."""
    from matplotlib.figure import Figure

    summary = quilted.manifest["summary"]
    fig = Figure(figsize=(6.4, 3.3 * len(regions)))
    axes = fig.subplots(len(regions), 2, squeeze=False)
    flat = np.array([0.0, 0.0, 1.0])
    for row, region in enumerate(regions):
        for col, kind in enumerate(("random", "quilted")):
            coeffs = quilted.array(f"{kind}_r{region}", mmap=False)
            image = np.maximum(render_fourier(coeffs, light, flat, view, clamp), 0.0)
            name = "quilting" if kind == "quilted" else "random"
            axes[row, col].imshow(display(image, exposure), interpolation="nearest")
            axes[row, col].set_title(
                f"region {region}: {kind}, seam cost {summary[f'seam_cost_{name}_r{region}']:.3g}",
                fontsize=8,
            )
            axes[row, col].axis("off")
    fig.tight_layout()
    save_figure(fig, path, dpi=90)


def run(ctx: Context) -> dict[str, float]:
    """The whole chain for ``method=fourier_pattern``; returns the metrics for MLflow."""
    data = data_stage(ctx)
    normals = fr.normals_stage(ctx, data)
    fitted = fr.fit_stage(ctx, data, normals)
    segmented = fr.segmentation_stage(ctx, data, fitted)
    target = target_settings(ctx.cfg)
    out_shape = target["size"] if target["kind"] == "pot" else target_normals(target)[0].shape[:2]
    quilted = quilt_stage(ctx, fitted, segmented, out_shape)
    rendered = pattern_stage(ctx, fitted, quilted, target)
    summary = quilted.manifest["summary"]
    metrics = {k: float(v) for k, v in summary.items() if k != "regions"}
    metrics.update({k: float(v) for k, v in segmented.json("metrics").items()})
    metrics["pattern_mean"] = float(rendered.manifest["summary"]["mean"])
    ctx.log.tags({"mlflow.runName": fr.describe(ctx.cfg, data)})
    ctx.log.folder(rendered.path / "pattern", "pattern")
    ctx.log.file(segmented.file("segmentation.png"), "figures")
    return metrics
