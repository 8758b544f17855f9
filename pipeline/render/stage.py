"""Method A's render stages: Fig. 8 and Tables 3-4 of the clustering paper.

    crop   -> render_reference   the measured BTF, interpolated between its 81 x 81 directions
    export -> render             the run's compressed BTF (Neural BTF or clustered), compared
                                 with the reference: same scene, same samples, same seed
    linear -> render             or the PCA baseline, interpolated like the measured BTF

Both render :func:`pipeline.render.scene.default_scene` with the crop tiled over the sheet,
once per entry of ``btf.render.spp`` (say 1, 16 and 128 samples per pixel), so that the
graininess of a reconstruction can be followed as the samples average over each pixel.

Two crops of the rendered frame, a dark and a bright region, are compared with the
reference at every spp (Tables 3 and 4 at the largest): the RMSE of linear radiance, and
the ratio of high-frequency energy (the image minus its Gaussian blur, sigma 1 pixel) of the
model's crop to the reference's, which is above 1 where the model adds grain. Unless
given (``btf.render.crops``), the crops are chosen on the reference at the largest spp: of
the windows wholly on lit cloth (every camera sample of every pixel on cloth that a light
sees: no background, floor, shadow or silhouette), the darkest and the brightest by mean
luminance.

Both stages' code version (``version=`` below) covers :mod:`pipeline.render.scene`,
``engine`` and ``materials`` too: bump it when a change there alters the images.

Units: the key light gives irradiance 1 at the sheet's centre, so radiance is in the BTF's
own units (the data's linear RGB), and the RMSE is comparable with eq. 10's un-normalised.
"""

from __future__ import annotations

import json
import logging
import math
import tempfile
from pathlib import Path

import numpy as np

from pipeline.core.cache import Entry, save_arrays, save_json
from pipeline.core.errors import ConfigError
from pipeline.core.stage import Context, plain_settings

log = logging.getLogger(__name__)

REGIONS = ("dark", "bright")
_HF_SIGMA = 1.0  # pixels: what a blur of this width removes is "high frequency"


def render_settings(cfg) -> dict:
    """``btf.render`` without its switch, checked; the render stages' settings."""
    settings = plain_settings(cfg.btf.render)
    settings.pop("enabled", None)
    for name in ("width", "height", "crop_size"):
        value = settings[name]
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(f"btf.render.{name}={value!r} must be an integer >= 1")
    spp = settings["spp"]
    if isinstance(spp, int):
        spp = [spp]
    if not spp or any(isinstance(s, bool) or not isinstance(s, int) or s < 1 for s in spp):
        raise ConfigError(f"btf.render.spp={settings['spp']!r} must be a list of integers >= 1")
    settings["spp"] = sorted(set(spp))
    if settings["crop_size"] > min(settings["width"], settings["height"]):
        raise ConfigError(
            f"btf.render.crop_size={settings['crop_size']} is larger than the "
            f"{settings['width']}x{settings['height']} frame"
        )
    for region in REGIONS:
        corner = (settings.get("crops") or {}).get(region)
        if corner is not None and (
            len(corner) != 2
            or min(corner) < 0
            or corner[0] + settings["crop_size"] > settings["height"]
            or corner[1] + settings["crop_size"] > settings["width"]
        ):
            raise ConfigError(
                f"btf.render.crops.{region}={corner!r} must be [row, col] of a "
                f"{settings['crop_size']}-pixel window inside the frame"
            )
    return settings


def _scene(settings: dict):
    from pipeline.render.scene import default_scene

    return default_scene(
        settings["width"],
        settings["height"],
        settings["lights"],
        floor=settings["floor"],
        tiles=settings["tiles"],
        resolution=settings["mesh_resolution"],
    )


def _render_every_spp(scene, material, settings: dict, folder: Path, what: str) -> dict:
    """Render at each spp into ``folder`` (``image_spp<N>.npy``, .exr, .png, and the lit
    cloth coverage ``lit_cloth_spp<N>.npy``); returns per-spp seconds and ray counts."""
    from tqdm import tqdm

    from pipeline.render.engine import render_with_stats

    stats = {}
    for spp in tqdm(settings["spp"], desc=f"render {what}", unit="frame", leave=False):
        image, cost = render_with_stats(scene, material, spp, settings["seed"])
        save_arrays(folder, **{f"image_spp{spp}": image, f"lit_cloth_spp{spp}": cost.lit_cloth})
        write_images(folder / f"image_spp{spp}", image, settings["exposure"])
        stats[str(spp)] = {
            "seconds": cost.seconds,
            "rays": cost.rays,
            "material_queries": cost.material_queries,
        }
        log.info(
            "rendered %s at %d spp in %.1f s (%.2f M rays/s)",
            what,
            spp,
            cost.seconds,
            cost.rays_per_second / 1e6,
        )
    return stats


def write_images(stem: Path, image: np.ndarray, exposure: float) -> None:
    """``stem.exr`` (linear, half float) and ``stem.png`` (exposure, then gamma 2.2)."""
    from PIL import Image

    from pipeline.data.images import gamma_encode, quantize_8bit, write_exr

    write_exr(stem.with_suffix(".exr"), image)
    encoded = quantize_8bit(gamma_encode(image * np.float32(exposure)))
    Image.fromarray(encoded).save(stem.with_suffix(".png"))


def choose_crops(reference: np.ndarray, lit_cloth: np.ndarray, size: int,
                 given: dict | None = None) -> dict:
    """Top-left [row, col] of the dark and bright crops of ``reference`` (H, W, 3).

    A crop given in ``given`` is kept; the others are, among the windows of ``size`` pixels
    (on a grid of step size / 4) whose every pixel is wholly on lit cloth (``lit_cloth``
    (H, W), the render's coverage, is 1), the one with the lowest and the highest mean
    luminance.
    """
    given = given or {}
    luminance = reference @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
    lit = (lit_cloth >= 1).astype(np.int64)
    # Summed-area tables: the lit count and the luminance sum of every window at once.
    count = window_sums(lit, size)
    total = window_sums(luminance.astype(np.float64), size)
    step = max(1, size // 4)
    rows = np.arange(0, count.shape[0], step)
    cols = np.arange(0, count.shape[1], step)
    full = count[np.ix_(rows, cols)] == size * size
    chosen = {}
    for region, pick in (("dark", np.argmin), ("bright", np.argmax)):
        if given.get(region) is not None:
            chosen[region] = [int(v) for v in given[region]]
            continue
        if not full.any():
            raise ValueError(
                f"no {size}x{size} window of the reference render is wholly on "
                "lit cloth: lower btf.render.crop_size or give btf.render.crops"
            )
        flat = pick(np.where(full, total[np.ix_(rows, cols)],
                             np.inf if region == "dark" else -np.inf))
        r, c = np.unravel_index(flat, full.shape)
        chosen[region] = [int(rows[r]), int(cols[c])]
    return chosen


def window_sums(values: np.ndarray, size: int) -> np.ndarray:
    """Sum of every size x size window: (H, W) -> (H - size + 1, W - size + 1)."""
    table = np.pad(values.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    return table[size:, size:] - table[:-size, size:] - table[size:, :-size] + table[:-size, :-size]


def high_frequency_energy(image: np.ndarray) -> float:
    """Mean squared difference between ``image`` (h, w, 3) and its Gaussian blur."""
    from scipy.ndimage import gaussian_filter

    image = np.asarray(image, dtype=np.float64)
    blurred = gaussian_filter(image, sigma=(_HF_SIGMA, _HF_SIGMA, 0), mode="reflect")
    return float(np.mean(np.square(image - blurred)))


def compare(model: np.ndarray, reference: np.ndarray, lit_cloth: np.ndarray, crops: dict,
            size: int) -> dict:
    """RMSE and high-frequency energy ratio of ``model`` against ``reference`` in each crop,
    and the RMSE over every pixel wholly on lit cloth (``lit_cloth`` (H, W) is 1)."""
    found = {}
    for region in REGIONS:
        r, c = crops[region]
        a, b = model[r : r + size, c : c + size], reference[r : r + size, c : c + size]
        found[f"rmse_{region}"] = float(np.sqrt(np.mean(np.square(a - b, dtype=np.float64))))
        reference_hf = high_frequency_energy(b)
        found[f"hf_ratio_{region}"] = (
            high_frequency_energy(a) / reference_hf if reference_hf > 0 else math.nan
        )
    lit = lit_cloth >= 1
    found["rmse_cloth"] = float(
        np.sqrt(np.mean(np.square(model[lit] - reference[lit], dtype=np.float64)))
    )
    return found


def reference_stage(ctx: Context, cropped: Entry) -> Entry:
    """Render the measured crop (the reference) at every spp and choose the crops."""
    settings = render_settings(ctx.cfg)

    def compute(folder: Path) -> dict:
        from pipeline.render.materials import MeasuredMaterial

        values = cropped.array("abrdf")
        directions = cropped.array("directions", mmap=False)
        side = math.isqrt(values.shape[0])
        if len(directions) != 81 * 81:
            raise ConfigError(
                f"the render's reference interpolates all 81 x 81 measured directions, but the "
                f"crop has {len(directions)}: render a dataset with every view (dataset.views=null)"
            )
        material = MeasuredMaterial(values, (side, values.shape[0] // side), directions)
        stats = _render_every_spp(_scene(settings), material, settings, folder, "reference")
        top = settings["spp"][-1]
        crops = choose_crops(np.load(folder / f"image_spp{top}.npy"),
                             np.load(folder / f"lit_cloth_spp{top}.npy"),
                             settings["crop_size"], settings.get("crops"))
        save_json(folder, "crops", crops)
        return {"spp": stats, "crops": crops}

    return ctx.run("render_reference", settings, {"crop": cropped}, compute, version="3")


def compressed_material(exported: Entry):
    """The export stage's compressed BTF file (Neural BTF or clustered) as a material."""
    from pipeline.btf.compressed import FILE_NAME
    from pipeline.render.materials import CompressedMaterial

    return CompressedMaterial.from_file(exported.file(FILE_NAME))


def linear_material(fitted: Entry, cropped: Entry, prep: Entry):
    """The linear stage's PCA, as stored, back in linear RGB, as a material."""
    from pipeline.btf.stages import normalization
    from pipeline.render.materials import LinearMaterial

    side = math.isqrt(cropped.manifest["summary"]["M"])  # the crop stage cuts squares
    return LinearMaterial(
        fitted.array("mean", mmap=False),
        fitted.array("basis", mmap=False),
        fitted.array("coefficients", mmap=False),
        (side, side),
        normalization(prep).alpha,
        cropped.array("directions", mmap=False),
    )


def model_stage(ctx: Context, inputs: dict[str, Entry], material, reference: Entry) -> Entry:
    """Render a model at every spp and compare it with the reference.

    ``inputs`` are the entries the model comes from (they key the stage) and ``material()``
    builds it from them, called only when the render is not in the cache.
    """
    settings = render_settings(ctx.cfg)

    def compute(folder: Path) -> dict:
        material_ = material()
        stats = _render_every_spp(_scene(settings), material_, settings, folder, "model")
        crops = reference.json("crops")
        metrics = {}
        for spp in settings["spp"]:
            found = compare(
                np.load(folder / f"image_spp{spp}.npy"),
                reference.array(f"image_spp{spp}", mmap=False),
                reference.array(f"lit_cloth_spp{spp}", mmap=False),
                crops,
                settings["crop_size"],
            )
            metrics.update({f"render_{name}_spp{spp}": value for name, value in found.items()})
            if spp == settings["spp"][-1]:  # the headline: Tables 3 and 4
                metrics.update({f"render_{name}": value for name, value in found.items()})
        top = stats[str(settings["spp"][-1])]
        metrics["render_seconds"] = sum(s["seconds"] for s in stats.values())
        metrics["render_rays_per_second"] = top["rays"] / top["seconds"]
        save_json(folder, "metrics", metrics)
        return {"spp": stats}

    inputs = {**inputs, "render_reference": reference}
    return ctx.run("render", settings, inputs, compute, version="3")


def _entries(ctx: Context, *names: str) -> list[Entry]:
    found = [ctx.cache.lookup(name, ctx.keys[name]) if name in ctx.keys else None
             for name in names]
    if any(entry is None for entry in found):
        raise RuntimeError(f"the render stages need the job's {', '.join(names)} entries, "
                           f"which are not all in the cache {ctx.cache.root}")
    return found


def run(ctx: Context) -> dict[str, float]:
    """Both stages for a method A job that has just run: a compressed model (its ``crop``
    and ``export`` stages are in ``ctx.keys``) or the PCA baseline (``crop``,
    ``preprocess``, ``linear``); logs the images and crops under ``render/`` of the active
    MLflow run and returns the ``render_*`` metrics."""
    import mlflow

    if ctx.cfg.method.name == "pca":
        cropped, prep, fitted = _entries(ctx, "crop", "preprocess", "linear")
        reference = reference_stage(ctx, cropped)
        rendered = model_stage(ctx, {"linear": fitted, "preprocess": prep},
                               lambda: linear_material(fitted, cropped, prep), reference)
    else:
        cropped, exported = _entries(ctx, "crop", "export")
        reference = reference_stage(ctx, cropped)
        rendered = model_stage(ctx, {"export": exported},
                               lambda: compressed_material(exported), reference)
    metrics = rendered.json("metrics")
    if mlflow.active_run() is not None:
        top = render_settings(ctx.cfg)["spp"][-1]
        with tempfile.TemporaryDirectory() as tmp:
            for name, entry in (("model", rendered), ("reference", reference)):
                for suffix in (".png", ".exr"):
                    source = entry.file(f"image_spp{top}{suffix}")
                    (Path(tmp) / f"{name}_spp{top}{suffix}").write_bytes(source.read_bytes())
            for path in rendered.path.glob("image_spp*.png"):
                (Path(tmp) / f"model_{path.stem[len('image_') :]}.png").write_bytes(
                    path.read_bytes()
                )
            (Path(tmp) / "crops.json").write_text(json.dumps(reference.json("crops")))
            mlflow.log_artifacts(tmp, "render")
    return metrics
