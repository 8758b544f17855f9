"""Method A's render stages: Fig. 8 and Tables 3-4 of the clustering paper.

    crop   -> render_reference   the measured BTF, interpolated between its directions (L x V)
    crop   -> render_truth       the built-in material's analytic generator (when the data is
                                 the built-in synthetic BTF): the truth, at every direction
    export -> render             the run's compressed BTF (Neural BTF or clustered), scored
                                 against the reference (and the truth): same scene, samples, seed
    linear -> render             or the PCA baseline, interpolated like the measured BTF

Each renders :func:`pipeline.render.scene.default_scene` with the crop tiled over the sheet,
once per entry of ``btf.render.spp`` (say 1, 16 and 128 samples per pixel), so that the
graininess of a reconstruction can be followed as the samples average over each pixel.

Scoring (:func:`scores`). A dark and a bright crop of the frame and every pixel wholly on
lit cloth are compared at every spp (Tables 3 and 4 at the largest): the RMSE of linear
radiance, and the ratio of high-frequency energy (the image minus its Gaussian blur, sigma
1 pixel) of the model's crop to the target's, above 1 where the model adds grain. The
metrics, each also per spp with ``_spp<N>`` (``<name>``: ``rmse_dark``, ``rmse_bright``,
``rmse_cloth``, ``hf_ratio_dark``, ``hf_ratio_bright``, or over the frame as displayed
``flip``, ``ssim``, ``psnr_db``):

- ``render_<name>``: the model against the measured reference render;
- ``render_truth_<name>``: the model against the truth render (built-in material only);
- ``render_reference_truth_<name>``: the reference itself against the truth: how far
  scoring against the reference is itself off;
- ``render_beyond_grid_share`` and ``render_beyond_grid_share_{dark,bright}``: the share
  of the (camera sample, light) pairs on the lit cloth and in each crop whose light or
  view lies beyond the measured grid, at the largest spp (:func:`beyond_grid_shares`).

Unless given (``btf.render.crops``), the crops are chosen (:func:`choose_crops`) on the
truth when there is one, else on the reference, at the largest spp; the same crops score
every comparison of a run.

Directions beyond the grid (:mod:`pipeline.btf.render.surfaces` says why): without a truth,
every model is queried through :class:`~pipeline.btf.render.surfaces.GridClamped`, so that
a render differs from the reference by its reconstruction of the measured domain only;
samples beyond the grid stay in the crops and the cloth RMSE (leaving them out would move
the dark crop, which is dark because its light grazes) and their share is reported. With a
truth, each model is queried as it is and the truth, unclamped, scores it.

The stages' code versions (``version=`` below) cover the general renderer
(:mod:`pipeline.render.scene`, ``engine``, ``materials``) and method A's materials
(:mod:`pipeline.btf.render.surfaces`) too: bump them when a change there alters the images.

Units: the key light gives irradiance 1 at the sheet's centre, so radiance is in the BTF's
own units (the data's linear RGB), and the RMSE is comparable with eq. 10's un-normalised.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from pipeline.core.cache import Entry, save_arrays, save_json
from pipeline.core.errors import ConfigError, DataError
from pipeline.core.stage import Context, plain_settings

log = logging.getLogger(__name__)

REGIONS = ("dark", "bright")
_HF_SIGMA = 1.0  # pixels: what a blur of this width removes is "high frequency"


def render_settings(cfg) -> dict:
    """``btf.render`` without its switch: the render stages' settings, spp sorted. Each value
    is checked at the door (:class:`pipeline.btf.data_settings.RenderSettings`); this checks
    the crops against the frame (also at the door, when rendering is on)."""
    settings = plain_settings(cfg.btf.render)
    settings.pop("enabled", None)
    settings["spp"] = sorted(set(settings["spp"]))
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
        rate = cost.rays_per_second / 1e6
        log.info("rendered %s at %d spp in %.1f s (%.2f M rays/s)", what, spp, cost.seconds, rate)
    return stats


def write_images(stem: Path, image: np.ndarray, exposure: float) -> None:
    """``stem.exr`` (linear, half float) and ``stem.png`` (exposure, then gamma 2.2)."""
    from PIL import Image

    from pipeline.data.images import gamma_encode, quantize_8bit, write_exr

    write_exr(stem.with_suffix(".exr"), image)
    encoded = quantize_8bit(gamma_encode(image * np.float32(exposure)))
    Image.fromarray(encoded).save(stem.with_suffix(".png"))


def choose_crops(
    target: np.ndarray, lit_cloth: np.ndarray, size: int, given: dict | None = None
) -> dict:
    """Top-left [row, col] of the dark and bright crops of ``target`` (H, W, 3), the render
    that scores the models (the truth, else the reference).

    A crop given in ``given`` is kept; the others are, among the windows of ``size`` pixels
    (on a grid of step size / 4) whose every pixel is wholly on lit cloth (``lit_cloth``
    (H, W), the render's coverage, is 1), the one with the lowest and the highest mean
    luminance.
    """
    given = given or {}
    luminance = target @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
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
                f"no {size}x{size} window of the render is wholly on "
                "lit cloth: lower btf.render.crop_size or give btf.render.crops"
            )
        flat = pick(
            np.where(full, total[np.ix_(rows, cols)], np.inf if region == "dark" else -np.inf)
        )
        r, c = np.unravel_index(flat, full.shape)
        chosen[region] = [int(rows[r]), int(cols[c])]
    return chosen


def window_sums(values: np.ndarray, size: int) -> np.ndarray:
    """Sum of every size x size window: (H, W) -> (H - size + 1, W - size + 1)."""
    table = np.pad(values.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    return table[size:, size:] - table[:-size, size:] - table[size:, :-size] + table[:-size, :-size]


def high_pass(image: np.ndarray) -> np.ndarray:
    """``image`` (h, w, 3) minus its Gaussian blur of :data:`_HF_SIGMA` pixels, float64."""
    from scipy.ndimage import gaussian_filter

    image = np.asarray(image, dtype=np.float64)
    return image - gaussian_filter(image, sigma=(_HF_SIGMA, _HF_SIGMA, 0), mode="reflect")


def high_frequency_energy(image: np.ndarray) -> float:
    """Mean squared difference between ``image`` (h, w, 3) and its Gaussian blur."""
    return float(np.mean(np.square(high_pass(image))))


def compare(
    model: np.ndarray,
    target: np.ndarray,
    lit_cloth: np.ndarray,
    crops: dict,
    size: int,
    exposure: float = 1.0,
) -> dict:
    """RMSE, high-frequency energy ratio and RMSE of the high-pass parts (the detail in
    place, :func:`high_pass`) of ``model`` against ``target`` (both (H, W, 3)) in each crop,
    and the RMSE over every pixel wholly on lit cloth (``lit_cloth`` (H, W) is 1); over the
    whole frame as displayed (``exposure``, gamma 2.2, clipped to [0, 1], the PNG's values),
    LDR-FLIP (mean), SSIM and PSNR (:mod:`pipeline.core.image_metrics`)."""
    from pipeline.core.image_metrics import flip, psnr, ssim
    from pipeline.data.images import gamma_encode

    shown = [
        np.clip(gamma_encode(np.asarray(image, np.float32) * np.float32(exposure)), 0, 1)
        for image in (target, model)
    ]
    shown = [image.astype(np.float64) for image in shown]
    found = {"flip": flip(*shown), "ssim": ssim(*shown), "psnr_db": psnr(*shown)}
    for region in REGIONS:
        r, c = crops[region]
        a, b = model[r : r + size, c : c + size], target[r : r + size, c : c + size]
        found[f"rmse_{region}"] = float(np.sqrt(np.mean(np.square(a - b, dtype=np.float64))))
        target_hf = high_frequency_energy(b)
        found[f"hf_ratio_{region}"] = (
            high_frequency_energy(a) / target_hf if target_hf > 0 else math.nan
        )
        # The ratio compares amounts of fine detail, so detail in the wrong place (grain)
        # can score 1; the RMSE of the high-pass parts is 0 only where the detail matches.
        found[f"hf_rmse_{region}"] = float(np.sqrt(np.mean(np.square(high_pass(a) - high_pass(b)))))
    lit = lit_cloth >= 1
    found["rmse_cloth"] = float(
        np.sqrt(np.mean(np.square(model[lit] - target[lit], dtype=np.float64)))
    )
    return found


def scores(
    model: np.ndarray,
    reference: np.ndarray,
    lit_cloth: np.ndarray,
    crops: dict,
    size: int,
    truth: np.ndarray | None = None,
    exposure: float = 1.0,
) -> dict:
    """:func:`compare` of a model's render (H, W, 3) with the reference's (``render_*``) and,
    given the truth's, with it (``render_truth_*``), and of the reference with the truth
    (``render_reference_truth_*``); same crops and lit cloth for all."""
    pairs = [("render_", model, reference)]
    if truth is not None:
        pairs += [("render_truth_", model, truth), ("render_reference_truth_", reference, truth)]
    return {
        f"{prefix}{name}": value
        for prefix, image, target in pairs
        for name, value in compare(image, target, lit_cloth, crops, size, exposure).items()
    }


def beyond_grid_shares(
    indicator: np.ndarray, lit_cloth: np.ndarray, crops: dict, size: int
) -> dict:
    """Share of the samples beyond the measured grid, over the lit cloth and in each crop:
    ``beyond_grid_share`` (lit cloth), ``beyond_grid_share_dark`` and ``_bright``, in [0, 1];
    NaN where no pixel counts.

    Parameters
    ----------
    indicator : ndarray of shape (H, W, 3)
        A render of :class:`pipeline.btf.render.surfaces.BeyondGridIndicator`: channel 0
        sums the (sample, light) pairs whose light or view is beyond the grid, channel 2
        all pairs, each weighted by the light's irradiance.
    lit_cloth : ndarray of shape (H, W)
        The render's coverage: the pixels where it is 1 count (those of the cloth RMSE).
    crops : ``{"dark": [row, col], "bright": [row, col]}``, windows of ``size`` pixels.
    """
    lit = lit_cloth >= 1

    def share(window: np.ndarray, counted: np.ndarray) -> float:
        total = float(window[..., 2][counted].sum())
        return float(window[..., 0][counted].sum()) / total if total > 0 else math.nan

    found = {"beyond_grid_share": share(indicator, lit)}
    for region in REGIONS:
        r, c = crops[region]
        found[f"beyond_grid_share_{region}"] = share(
            indicator[r : r + size, c : c + size], lit[r : r + size, c : c + size]
        )
    return found


def has_truth(cfg) -> bool:
    """Whether the run's data has an analytic truth: the built-in synthetic BTF
    (``dataset.name`` synthetic, generated because ``dataset.root`` is null)."""
    return cfg.dataset.name == "synthetic" and cfg.dataset.get("root") is None


def reference_stage(ctx: Context, cropped: Entry) -> Entry:
    """Render the measured crop (the reference) at every spp, and at the largest spp the
    :class:`~pipeline.btf.render.surfaces.BeyondGridIndicator` (``beyond_grid_spp<N>.npy``)."""
    settings = render_settings(ctx.cfg)

    def compute(folder: Path) -> dict:
        from pipeline.btf.render.surfaces import BeyondGridIndicator, MeasuredMaterial
        from pipeline.btf.stages import abrdf
        from pipeline.render.engine import render_with_stats

        values = np.asarray(abrdf(cropped))  # pairs of (texel, direction) are looked up
        directions = cropped.array("directions", mmap=False)
        side = math.isqrt(values.shape[0])
        crop_size = (side, values.shape[0] // side)
        try:
            reference = MeasuredMaterial(values, crop_size, directions)
        except DataError as error:
            raise DataError(
                f"the render's reference interpolates the crop's {len(directions)} "
                f"measured direction pairs, but: {error}"
            ) from None
        scene = _scene(settings)
        stats = _render_every_spp(scene, reference, settings, folder, "reference")
        top = settings["spp"][-1]
        indicator, _ = render_with_stats(
            scene, BeyondGridIndicator(crop_size, directions), top, settings["seed"]
        )
        save_arrays(folder, **{f"beyond_grid_spp{top}": indicator})
        return {"spp": stats}

    return ctx.run("render_reference", settings, {"crop": cropped}, compute, version="4")


def truth_stage(ctx: Context, cropped: Entry) -> Entry:
    """Render the built-in material's generator over the run's crop (the truth,
    :class:`~pipeline.btf.render.surfaces.AnalyticMaterial`) at every spp."""
    settings = render_settings(ctx.cfg)
    generator = plain_settings(ctx.cfg.dataset.synthetic)
    own = {
        **settings,
        "generator": {name: generator[name] for name in ("size", "seed", "material")},
        "crop": plain_settings(ctx.cfg.btf.crop),
    }

    def compute(folder: Path) -> dict:
        from pipeline.btf.render.surfaces import AnalyticMaterial

        material = AnalyticMaterial.from_config(ctx.cfg)
        if material.n_texels != cropped.manifest["summary"]["M"]:
            raise ConfigError(
                f"the truth's crop btf.crop={own['crop']} has {material.n_texels} texels, the "
                f"measured crop {cropped.manifest['summary']['M']}"
            )
        return {"spp": _render_every_spp(_scene(settings), material, settings, folder, "truth")}

    return ctx.run("render_truth", own, {"crop": cropped}, compute, version="1")


def compressed_material(exported: Entry):
    """The export stage's compressed BTF file (Neural BTF or clustered) as a material."""
    from pipeline.btf.compressed import FILE_NAME, load_compressed
    from pipeline.btf.render.surfaces import CompressedMaterial

    return CompressedMaterial(load_compressed(exported.file(FILE_NAME)))


def linear_material(fitted: Entry, cropped: Entry, prep: Entry):
    """The linear stage's PCA, as stored, back in linear RGB, as a material."""
    from pipeline.btf.render.surfaces import LinearMaterial
    from pipeline.btf.stages import normalization

    side = math.isqrt(cropped.manifest["summary"]["M"])  # the crop stage cuts squares
    return LinearMaterial(
        fitted.array("mean", mmap=False),
        fitted.array("basis", mmap=False),
        fitted.array("coefficients", mmap=False),
        (side, side),
        normalization(prep).alpha,
        cropped.array("directions", mmap=False),
    )


def model_stage(
    ctx: Context,
    cropped: Entry,
    inputs: dict[str, Entry],
    material,
    reference: Entry,
    truth: Entry | None = None,
) -> Entry:
    """Render a model at every spp and score it against the reference, and the truth when
    given (:func:`scores`); the crops are chosen on the truth, else on the reference.

    ``inputs`` are the entries the model comes from (they key the stage) and ``material()``
    builds it from them, called only when the render is not in the cache. Without a truth,
    the model is queried through :class:`~pipeline.btf.render.surfaces.GridClamped`, at the
    edge of the crop's (``cropped``) measured directions.
    """
    settings = render_settings(ctx.cfg)
    beyond = "as is" if truth is not None else "clamped to the grid"

    def compute(folder: Path) -> dict:
        from pipeline.btf.render.surfaces import GridClamped

        queried = material()
        if truth is None:
            queried = GridClamped(queried, cropped.array("directions", mmap=False))
        stats = _render_every_spp(_scene(settings), queried, settings, folder, "model")
        top = settings["spp"][-1]
        target = truth if truth is not None else reference
        crops = choose_crops(
            target.array(f"image_spp{top}", mmap=False),
            target.array(f"lit_cloth_spp{top}", mmap=False),
            settings["crop_size"],
            settings.get("crops"),
        )
        save_json(folder, "crops", crops)
        metrics = {}
        for spp in settings["spp"]:
            found = scores(
                np.load(folder / f"image_spp{spp}.npy"),
                reference.array(f"image_spp{spp}", mmap=False),
                reference.array(f"lit_cloth_spp{spp}", mmap=False),
                crops,
                settings["crop_size"],
                None if truth is None else truth.array(f"image_spp{spp}", mmap=False),
                settings["exposure"],
            )
            metrics.update({f"{name}_spp{spp}": value for name, value in found.items()})
            if spp == top:  # the headline: Tables 3 and 4
                metrics.update(found)
        shares = beyond_grid_shares(
            reference.array(f"beyond_grid_spp{top}", mmap=False),
            reference.array(f"lit_cloth_spp{top}", mmap=False),
            crops,
            settings["crop_size"],
        )
        metrics.update({f"render_{name}": value for name, value in shares.items()})
        metrics["render_seconds"] = sum(s["seconds"] for s in stats.values())
        metrics["render_rays_per_second"] = stats[str(top)]["rays"] / stats[str(top)]["seconds"]
        save_json(folder, "metrics", metrics)
        return {"spp": stats, "crops": crops, "beyond_grid": beyond}

    inputs = {**inputs, "render_reference": reference}
    if truth is not None:
        inputs["render_truth"] = truth
    return ctx.run("render", {**settings, "beyond_grid": beyond}, inputs, compute, version="6")


def _entries(ctx: Context, *names: str) -> list[Entry]:
    found = [ctx.cache.lookup(name, ctx.keys[name]) if name in ctx.keys else None for name in names]
    if any(entry is None for entry in found):
        raise RuntimeError(
            f"the render stages need the job's {', '.join(names)} entries, "
            f"which are not all in the cache {ctx.cache.root}"
        )
    return found


def run(ctx: Context) -> dict[str, float]:
    """The render stages for a method A job that has just run: a compressed model (its
    ``crop`` and ``export`` stages are in ``ctx.keys``) or the PCA baseline (``crop``,
    ``preprocess``, ``linear``), with the reference and, for the built-in material, the
    truth; logs the images and crops under ``render/`` of the job's MLflow run and returns
    the ``render_*`` metrics."""
    from pipeline.btf.models import model_of

    if model_of(ctx.cfg).stage is None:  # the linear chain
        cropped, prep, fitted = _entries(ctx, "crop", "preprocess", "linear")
        inputs = {"linear": fitted, "preprocess": prep}

        def material():
            return linear_material(fitted, cropped, prep)
    else:
        cropped, exported = _entries(ctx, "crop", "export")
        inputs = {"export": exported}

        def material():
            return compressed_material(exported)

    reference = reference_stage(ctx, cropped)
    truth = truth_stage(ctx, cropped) if has_truth(ctx.cfg) else None
    rendered = model_stage(ctx, cropped, inputs, material, reference, truth)
    metrics = rendered.json("metrics")
    top = render_settings(ctx.cfg)["spp"][-1]
    shown = [("model", rendered), ("reference", reference)]
    if truth is not None:
        shown.append(("truth", truth))
    named = {
        f"{name}_spp{top}{suffix}": entry.file(f"image_spp{top}{suffix}")
        for name, entry in shown
        for suffix in (".png", ".exr")
    }
    for path in rendered.path.glob("image_spp*.png"):
        named[f"model_{path.stem[len('image_') :]}.png"] = path
    ctx.log.files(named, "render")
    ctx.log.json(rendered.json("crops"), "render/crops.json")
    if ctx.log.on:  # reads every spp's image: only for a run to keep
        ctx.log.arrays(fig8_data(shown, rendered.json("crops"), ctx.cfg), f"render/{FIG8_DATA}")
    return metrics


FIG8_DATA = "fig8_data.npz"  # logged under render/: what the tables draw Fig. 8 from


def fig8_data(shown: list[tuple[str, Entry]], crops: dict, cfg) -> dict[str, np.ndarray]:
    """What Fig. 8 shows of one job's renders: ``<name>_image`` (H, W, 3) at the largest spp
    and ``<name>_crops`` (spp levels, regions, size, size, 3), for ``shown``'s names (model,
    reference, truth); ``spp``; ``crops`` (regions, 2: the top-left pixels)."""
    settings = render_settings(cfg)
    levels, size = list(settings["spp"]), int(settings["crop_size"])
    corners = np.array([crops[region] for region in REGIONS], dtype=np.int64)
    data = {"spp": np.array(levels, dtype=np.int64), "crops": corners}
    for name, entry in shown:
        data[f"{name}_image"] = entry.array(f"image_spp{levels[-1]}", mmap=False)
        per_spp = []
        for spp in levels:
            image = entry.array(f"image_spp{spp}", mmap=False)
            per_spp.append(np.stack([image[r : r + size, c : c + size] for r, c in corners]))
        data[f"{name}_crops"] = np.stack(per_spp).astype(np.float32)
    return data
