"""Method A's chain: the train and evaluate stages and the job that strings them together.

    load -> crop -> preprocess [-> pca -> kmeans -> representatives] -> train -> evaluate
                                                    (clustered only)

Training writes the decoder and the stored latents; evaluation decodes them, measures the
eq. 10 RMSE, the sizes of Table 1 and, on synthetic data, the interpolation errors.

torch and scikit-learn are imported inside the stages that compute, so that a rerun whose
stages are all cached starts in a fraction of the time.
"""

from __future__ import annotations

import logging
from functools import partial
from pathlib import Path

import numpy as np

from pipeline.btf import interpolation, stages
from pipeline.btf.data_settings import btf_constraints
from pipeline.btf.export import export_stage, log_compressed
from pipeline.btf.models import Model, model_of
from pipeline.btf.stereographic import direction_features
from pipeline.btf.train_settings import TrainSettings
from pipeline.core.cache import Entry, save_arrays, save_json
from pipeline.core.methods import resolve
from pipeline.core.run_log import RunLog
from pipeline.core.settings import SPEED, at_added_default, check_settings, constraints, roles
from pipeline.core.stage import Context, plain_settings

logger = logging.getLogger(__name__)


def check_settings_at_the_door(cfg, model: Model) -> None:
    """Refuse a bad method-A setting before any stage runs, naming it and what it may be:
    ``btf.*`` from :mod:`pipeline.btf.data_settings`, ``model.*`` from the model's declaration."""
    check_settings(cfg, {**btf_constraints(), **constraints(model.config, "model")})
    if model.trains:
        _train_settings(cfg)
    if model.clusters:
        from pipeline.btf.clustering import check_k

        check_k(cfg.model.k, int(cfg.btf.crop.size) ** 2)
    if cfg.btf.render.enabled:
        from pipeline.btf.render.stage import render_settings

        render_settings(cfg)


def check_settings_against_the_data(cfg, loaded: Entry) -> None:
    """Refuse settings that the data's shape rules out, as soon as the load stage knows it
    (for a UBO2014 file: from its header, before anything is decoded): the held-out lights
    must leave lights to train on. (The crop stage, next, checks that the crop fits.)"""
    interpolation.heldout_lights_of(cfg, loaded)


def _train_settings(cfg):
    """``train.*`` as :class:`TrainSettings` (which checks the values; the structured config
    of ``conf/train/default.yaml`` has refused unknown keys); lr null: the model's."""
    settings = plain_settings(cfg.train)
    lr = settings.pop("lr", None)
    return TrainSettings(lr=cfg.model.lr if lr is None else lr, **settings)


# What only changes how fast training runs (up to the order of floating-point sums) is
# not in the train stage's key: the roles TrainSettings declares.
SPEED_ONLY = {
    key.removeprefix("train.")
    for key, role in roles(TrainSettings, "train").items()
    if role == SPEED
}


def keyless(settings: TrainSettings) -> set[str]:
    """The fields of ``settings`` left out of the train stage's key: the speed-only ones,
    and those declared ``added`` that are at their default (the key of the code before)."""
    added = at_added_default(TrainSettings, "train", {"train": settings.__dict__})
    return SPEED_ONLY | {key.removeprefix("train.") for key in added}


def train_stage(
    ctx: Context, cropped: Entry, prep: Entry, clusters: Entry | None, reps: Entry | None
) -> Entry:
    """Train the autoencoder and store decoder weights and latents."""
    cfg = ctx.cfg
    settings = _train_settings(cfg)
    left_out = keyless(settings)
    # Indices into the data's own light set (the 81-grid's canonical order for UBO2003).
    heldout = interpolation.heldout_lights_of(cfg, cropped)
    stage_settings = {
        "method": cfg.model.name,
        "target": cfg.model.get("target", "texel"),
        "train": {k: v for k, v in settings.__dict__.items() if k not in left_out},
        "model": plain_settings(cfg.btf.network),
        "seed": cfg.seed,
        "heldout_lights": heldout.tolist(),
    }
    inputs = {"crop": cropped, "preprocess": prep}
    if clusters is not None:
        inputs.update(kmeans=clusters, representatives=reps)

    def compute(folder: Path) -> dict:
        import torch

        from pipeline.btf.train import encode, train

        abrdf = stages.abrdf(cropped)
        directions = cropped.array("directions", mmap=False)
        norm = stages.normalization(prep)
        if clusters is None:
            sources, source_of_texel = abrdf, np.arange(abrdf.shape[0])
        else:
            sources = np.asarray(reps.array("representatives"))
            source_of_texel = clusters.array("labels", mmap=False).astype(np.int64)

        def on_pass(texel_pass: int, loss: float, step: int) -> None:
            # Keyed by training step, like the curve_* metrics, so that the UI's "Step"
            # axis means one thing; the pass over the texels is the point's index.
            ctx.log.metric("loss", loss, step=step)

        network = cfg.btf.network
        result = train(
            abrdf,
            sources,
            source_of_texel,
            norm,
            direction_features(directions),
            interpolation.training_directions(directions, heldout),
            settings,
            seed=cfg.seed,
            encoder_channels=tuple(network.encoder_channels),
            latent=int(network.latent),
            hidden=int(network.hidden),
            layers=int(network.layers),
            target_from_source=stage_settings["target"] == "representative",
            on_pass=on_pass,
            on_curve=partial(log_curve_point, ctx.log),
        )
        latents = encode(result.encoder, sources, norm)
        torch.save(result.decoder.state_dict(), folder / "decoder.pt")
        torch.save(result.encoder.state_dict(), folder / "encoder.pt")
        save_arrays(folder, latents=latents, latent_of_texel=source_of_texel.astype(np.int32))
        save_json(folder, "losses", result.pass_losses)
        save_json(folder, "curve", result.curve)
        summary = {"steps": result.steps, "seconds": result.seconds, "queries": result.queries}
        return {**summary, "final_loss": result.pass_losses[-1]}

    return ctx.run("train", stage_settings, inputs, compute, version="3")


def log_curve_point(log: RunLog, point: dict) -> None:
    """One point of the RMSE-versus-time curve, as MLflow metrics keyed by step."""
    curve = {f"curve_{name}": point[name] for name in ("rmse", "seconds", "queries")}
    log.metrics(curve, step=point["step"])


def evaluate_stage(ctx: Context, cropped: Entry, prep: Entry, trained: Entry) -> Entry:
    """RMSE (eq. 10), per-direction RMSE, sizes, and interpolation errors, of the model as
    stored: decoder weights and latents rounded to ``btf.sizes.weight_dtype``, the per-texel
    scale to ``extra_dtype``."""
    cfg = ctx.cfg
    clustered = model_of(cfg).clusters
    texel_scale = cfg.model.get("texel_scale", "none")
    settings = {
        "texel_scale": texel_scale,
        "sizes": plain_settings(cfg.btf.sizes),
        "interpolation": plain_settings(cfg.btf.interpolation),
        "dataset": (evaluated_dataset(cfg.dataset) if cfg.dataset.name == "synthetic" else None),
    }

    def compute(folder: Path) -> dict:
        from pipeline.btf import evaluate
        from pipeline.btf.model import load_decoder

        abrdf = stages.abrdf(cropped)
        directions = cropped.array("directions", mmap=False)
        norm = stages.normalization(prep)
        sizes_settings = cfg.btf.sizes
        decoder, latents = evaluate.as_stored(
            load_decoder(trained.file("decoder.pt")),
            trained.array("latents", mmap=False),
            sizes_settings.weight_dtype,
        )
        latent_of_texel = trained.array("latent_of_texel", mmap=False)
        recon = evaluate.reconstruction_error(
            decoder,
            latents,
            latent_of_texel,
            abrdf,
            norm.alpha,
            direction_features(directions),
            texel_scale=texel_scale,
            scale_dtype=sizes_settings.extra_dtype,
        )
        m, n, _ = abrdf.shape
        sizes = evaluate.storage_sizes(
            decoder,
            n_latents=latents.shape[0],
            n_texels=m,
            n_directions=n,
            clustered=clustered,
            weight_dtype=sizes_settings.weight_dtype,
            list_dtype=sizes_settings.list_dtype,
            extra_dtype=sizes_settings.extra_dtype if texel_scale != "none" else None,
            latent_dim=latents.shape[1],
        )
        metrics = {
            "rmse": recon.rmse,
            **sizes,
            "rmse_mean_abrdf": evaluate.mean_abrdf_rmse(abrdf, norm.alpha),
        }
        if recon.rmse_unscaled is not None:
            metrics["rmse_without_texel_scale"] = recon.rmse_unscaled
            metrics["rmse_with_texel_scale"] = recon.rmse_scaled
        heldout = np.asarray(trained.manifest["settings"]["heldout_lights"], dtype=int)
        metrics.update(
            interpolation.measure(
                cfg,
                cropped,
                norm,
                decoder,
                latents,
                latent_of_texel,
                recon.rmse_per_direction,
                heldout,
                recon.texel_scale,
            )
        )
        # rmse is over every direction, held-out ones too; with lights held out the trained
        # ones are rmse_train_dirs and the held-out ones rmse_heldout_model.
        save_arrays(folder, rmse_per_direction=recon.rmse_per_direction)
        if recon.texel_scale is not None:
            save_arrays(folder, texel_scale=recon.texel_scale)
        save_json(folder, "metrics", metrics)
        return {"rmse": recon.rmse}

    inputs = {"crop": cropped, "preprocess": prep, "train": trained}
    return ctx.run("evaluate", settings, inputs, compute, version="6")


def evaluated_dataset(dataset) -> dict:
    """``dataset`` settings as the evaluate stage's key holds them: the generator's
    direction-set settings left out at their defaults
    (:func:`pipeline.btf.synthetic_dataset.generator_settings`)."""
    from pipeline.btf.synthetic_dataset import generator_settings

    settings = plain_settings(dataset)
    return {**settings, "synthetic": generator_settings(settings["synthetic"])}


def _prepared(ctx: Context) -> tuple[Entry, Entry]:
    """The load, crop and preprocess stages every model starts with: (cropped, prep)."""
    loaded = stages.load(ctx)
    check_settings_against_the_data(ctx.cfg, loaded)
    cropped = stages.crop(ctx, loaded)
    return cropped, stages.preprocess(ctx, cropped)


def run(ctx: Context) -> dict[str, float]:
    """The whole chain of the job's model (``model=...``)."""
    model = model_of(ctx.cfg)
    check_settings_at_the_door(ctx.cfg, model)
    if model.stage is None:
        return run_linear(ctx)
    cropped, prep = _prepared(ctx)
    clusters = reps = None
    extra: dict[str, float] = {}
    if model.clusters:
        reduced = stages.pca(ctx, cropped, prep)
        clusters = stages.kmeans(ctx, reduced)
        reps = stages.representatives(ctx, cropped, clusters)
        extra["pca_explained_variance"] = reduced.manifest["summary"]["explained_variance"]
        extra["kmeans_inertia"] = clusters.manifest["summary"]["inertia"]
    trained = resolve(model.stage)(ctx, cropped, prep, clusters, reps)
    if trained.hit and model.trains:
        # A cached model: replay its loss curve so every run shows one, at the steps where
        # train() logged it (the end of each pass over the texels; the last may be cut).
        per_pass = cropped.manifest["summary"]["M"] // ctx.cfg.train.batch_size
        for texel_pass, loss in enumerate(trained.json("losses")):
            step = min((texel_pass + 1) * per_pass, trained.manifest["summary"]["steps"])
            ctx.log.metric("loss", loss, step=step)
        for point in trained.json("curve"):
            log_curve_point(ctx.log, point)
    evaluated = evaluate_stage(ctx, cropped, prep, trained)
    exported = export_stage(ctx, cropped, prep, trained, evaluated)
    summary = trained.manifest["summary"]
    metrics = {
        **evaluated.json("metrics"),
        **extra,
        **truth_metrics(ctx, cropped, prep),
        **{f"train_{key}": summary[key] for key in ("steps", "seconds", "queries")},
        "final_loss": summary["final_loss"],
        **_crop_counts(cropped),
    }
    return _log_results(ctx.log, metrics, evaluated, exported)


def _crop_counts(cropped: Entry) -> dict[str, int]:
    """``n_texels`` (M) and ``n_directions`` (N) of the crop."""
    summary = cropped.manifest["summary"]
    return {"n_texels": summary["M"], "n_directions": summary["N"]}


def _log_results(log: RunLog, metrics: dict, evaluated: Entry, exported: Entry) -> dict:
    """Add ``psnr_db`` and the baseline check to ``metrics``; log them (``metrics.json``),
    the per-direction RMSE (``evaluate/``), the ``stored_as.<part>`` tags (the type each of
    Table 1's parts is stored in, read from what was written: Table 1's captions come from
    them) and the compressed file. Returns ``metrics``."""
    add_psnr(metrics)
    check_against_baseline(log, metrics)
    log.file(evaluated.file("rmse_per_direction.npy"), "evaluate")
    log.json(metrics, "metrics.json")
    stored_as = exported.manifest["summary"]["stored_as"]
    log.tags({f"stored_as.{part}": dtype for part, dtype in stored_as.items()})
    log_compressed(log, exported)
    return metrics


def truth_metrics(ctx: Context, cropped: Entry, prep: Entry) -> dict[str, float]:
    """``rmse_data_vs_truth`` (what a perfect model scores) for the built-in BTF, else {}."""
    floor = stages.truth_floor(ctx, cropped, prep)
    return {} if floor is None else dict(floor.manifest["summary"])


def add_psnr(metrics: dict) -> None:
    """``psnr_db``: 10 log10(1 / MSE) of ``rmse`` (every texel and every direction, held-out
    ones too), in the normalised space where the crop's maximum is 1 (peak 1). The per-image
    MSE of NeuMIP and Neural Biplane (each direction's image over the texels) averages to
    this MSE: every image has M texels."""
    rmse = metrics["rmse"]
    metrics["psnr_db"] = float(-20 * np.log10(rmse)) if rmse > 0 else float("inf")


# A model whose error is within this fraction of the mean-ABRDF baseline, or above it, has
# learnt next to nothing: its training failed, whatever its loss curve says.
NEAR_BASELINE = 0.9


def check_against_baseline(log: RunLog, metrics: dict) -> None:
    """Add ``rmse_ratio_to_mean_abrdf``; warn and tag the run when the model ends within
    10 % of the trivial mean-ABRDF baseline or above it (``tags.training_failed``)."""
    ratio = metrics["rmse"] / metrics["rmse_mean_abrdf"]
    metrics["rmse_ratio_to_mean_abrdf"] = ratio
    if ratio < NEAR_BASELINE:
        return
    message = (
        f"training failed: RMSE {metrics['rmse']:.4g} is {ratio:.2f} x the mean-ABRDF "
        f"baseline ({metrics['rmse_mean_abrdf']:.4g}); check train.* (lr, steps) "
        f"against the crop size"
    )
    logger.warning(message)
    log.tags({"training_failed": message})


def linear_stage(ctx: Context, cropped: Entry, prep: Entry) -> Entry:
    """The PCA baseline: truncated SVD of the normalized ABRDF matrix."""
    from pipeline.btf.evaluate import mean_abrdf_rmse, storage_sizes
    from pipeline.btf.linear import components_for_budget, fit_linear, linear_error, pca_bytes
    from pipeline.btf.model import Decoder

    pca = ctx.cfg.model
    m, n = cropped.manifest["summary"]["M"], cropped.manifest["summary"]["N"]
    n_components = pca.n_components
    if pca.get("match_clustered_k"):
        # What clustered k stores with this run's network and storage settings.
        latent, sizes = int(ctx.cfg.btf.network.latent), ctx.cfg.btf.sizes
        budget = storage_sizes(
            Decoder(latent=latent),
            n_latents=int(pca.match_clustered_k),
            n_texels=m,
            n_directions=n,
            clustered=True,
            weight_dtype=sizes.weight_dtype,
            list_dtype=sizes.list_dtype,
            latent_dim=latent,
        )["bytes_total"]
        n_components = components_for_budget(budget, m, n, pca.dtype)
        if n_components == 0:
            # The smallest PCA model, one component, is over the budget: run it, and say so
            # (its bytes_total is what the tables compare at).
            n_components = 1
            message = (
                f"model.match_clustered_k={pca.match_clustered_k}: its {budget:,} B cannot hold "
                f"one {pca.dtype} component at {m:,} texels x {n:,} directions "
                f"({pca_bytes(1, m, n, pca.dtype):,} B); PCA runs with 1 component, over "
                f"the budget"
            )
            logger.warning(message)
            ctx.log.tags({"over_budget": message})
    settings = {"n_components": n_components, "dtype": pca.dtype, "seed": ctx.cfg.seed}

    def compute(folder: Path) -> dict:
        norm = stages.normalization(prep)
        targets = norm.targets(stages.abrdf(cropped))
        model = fit_linear(targets, n_components, pca.dtype, seed=ctx.cfg.seed)
        rmse, per_direction = linear_error(model, targets)
        arrays = {"mean": model.mean, "basis": model.basis, "coefficients": model.coefficients}
        save_arrays(folder, **arrays, rmse_per_direction=per_direction)
        basis_bytes = model.basis.nbytes + model.mean.nbytes
        total = basis_bytes + model.coefficients.nbytes
        assert total == pca_bytes(n_components, m, n, pca.dtype)
        original = m * n * 3 * 4  # float32 RGB
        metrics = {
            "rmse": rmse,
            "n_components": n_components,
            "bytes_decoder": basis_bytes,
            "bytes_latents": model.coefficients.nbytes,
            "bytes_list": 0,
            "bytes_extra": 0,
            "bytes_original": original,
            "bytes_total": total,
            "compression_ratio": original / total,
            "rmse_mean_abrdf": mean_abrdf_rmse(stages.abrdf(cropped), norm.alpha),
        }
        save_json(folder, "metrics", metrics)
        return {"rmse": rmse}

    return ctx.run("linear", settings, {"crop": cropped, "preprocess": prep}, compute, version="1")


def run_linear(ctx: Context) -> dict[str, float]:
    """``model=pca``: load -> crop -> preprocess -> truncated SVD -> export (its compressed
    file, logged as the other models' are)."""
    from pipeline.btf.export import export_linear_stage

    cropped, prep = _prepared(ctx)
    fitted = linear_stage(ctx, cropped, prep)
    exported = export_linear_stage(ctx, cropped, prep, fitted)
    metrics = {
        **fitted.json("metrics"),
        **_crop_counts(cropped),
        **truth_metrics(ctx, cropped, prep),
    }
    return _log_results(ctx.log, metrics, fitted, exported)
