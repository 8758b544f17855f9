"""The train stage of ``model=latent_texture`` (:mod:`pipeline.btf.latent_texture`): a
NeuMIP-style latent texture and decoder fitted directly to the crop, stored as Neural BTF
stores its model (the pyramid folded into one latent per texel, so the bytes are Neural
BTF's at the same latent size and decoder) so that the evaluate and export stages are the
same.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.btf import interpolation, stages
from pipeline.btf.stereographic import direction_features
from pipeline.core.cache import Entry, save_arrays, save_json
from pipeline.core.stage import Context, plain_settings


def train_stage(
    ctx: Context, cropped: Entry, prep: Entry, clusters: Entry | None, reps: Entry | None
) -> Entry:
    """Fit the latent texture; write ``decoder.pt``, ``latents.npy`` (M, latent),
    ``latent_of_texel.npy`` (texel t has latent t), ``losses.json`` and ``curve.json``.
    ``clusters`` and ``reps`` (None: this model does not cluster) keep the train stages'
    common signature."""
    cfg = ctx.cfg
    heldout = interpolation.heldout_lights_of(cfg, cropped)
    model = plain_settings(cfg.model)
    network = plain_settings(cfg.btf.network)
    settings = {
        "model": model,
        "seed": cfg.seed,
        "heldout_lights": heldout.tolist(),
        "network": {key: network[key] for key in ("latent", "hidden", "layers") if key in network},
    }

    def compute(folder: Path) -> dict:
        import torch

        from pipeline.btf.latent_texture import train_latent_texture

        abrdf = stages.abrdf(cropped)
        directions = cropped.array("directions", mmap=False)
        norm = stages.normalization(prep)
        size = int(cfg.btf.crop.size)
        result = train_latent_texture(
            norm.targets(abrdf),  # normalised where read, a batch at a time
            direction_features(directions).astype(np.float32),
            interpolation.training_directions(directions, heldout),
            (size, size),
            latent=int(network["latent"]),
            levels=model["levels"],
            hidden=int(network.get("hidden", 106)),
            layers=int(network.get("layers", 3)),
            steps=model["steps"],
            batch_texels=model["batch_texels"],
            queries_per_texel=model["queries_per_texel"],
            lr=model["lr"],
            seed=cfg.seed,
        )
        module = result.module
        with torch.no_grad():
            latents = module.texel_latents(torch.arange(size * size)).numpy()
        torch.save(module.decoder.state_dict(), folder / "decoder.pt")
        latent_of_texel = np.arange(size * size, dtype=np.int32)
        save_arrays(folder, latents=latents.astype(np.float32), latent_of_texel=latent_of_texel)
        losses = [point["loss"] for point in result.curve]
        save_json(folder, "losses", losses)
        save_json(folder, "curve", [])  # no RMSE-versus-time curve (train.curve_every)
        queries = result.steps * model["batch_texels"] * model["queries_per_texel"]
        summary = {"steps": result.steps, "seconds": result.seconds, "queries": queries}
        return {**summary, "final_loss": losses[-1] if losses else float("nan")}

    # The same stage name as the autoencoder's: its entry holds the same files, which the
    # evaluate and export stages and the job's Fig. 7 read (the settings tell them apart).
    return ctx.run("train", settings, {"crop": cropped, "preprocess": prep}, compute, version="1")
