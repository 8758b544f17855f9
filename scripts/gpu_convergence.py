"""Does doubling the run change the error? Neural BTF (the CPU recipe of
``conf/train/converged.yaml``: Adam, 32 ABRDFs x 256 directions a step, cosine schedule over
the run) and the latent texture (``model=latent_texture``'s defaults) on one built-in
material at the paper's size (a 100 x 100 crop, all 81 x 81 directions), each trained at 1x,
2x and 4x its length, on the GPU when there is one (where the CPU cannot afford 4x).

The data is the material's analytic values (no JPEG round trip, unlike the pipeline's
built-in dataset), so the RMSEs are not those of docs/results.md's tables; the ratios
between lengths are the point. One JSON line per trained model (stdout, and ``--out``):

    python scripts/gpu_convergence.py --material corduroy --out convergence.jsonl
    python scripts/gpu_convergence.py --size 16 --crop 12 --scale 0.01   # a CPU check
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
import torch

from pipeline.btf.latent_texture import train_latent_texture
from pipeline.btf.preprocess import fit_normalization
from pipeline.btf.stereographic import direction_features
from pipeline.btf.synthetic import SyntheticBTF
from pipeline.btf.train import encode, train
from pipeline.btf.train_settings import TrainSettings
from pipeline.data.directions import btf_directions


def rmse(
    decoder, latents: np.ndarray, targets: np.ndarray, features: np.ndarray, device: torch.device
) -> float:
    """Eq. 10 over every texel and direction, in the normalised space, accumulated in
    float64 chunk by chunk."""
    decoder = decoder.to(device).eval()
    feats = torch.from_numpy(features).float().to(device)
    total = 0.0
    with torch.no_grad():
        for start in range(0, len(latents), 256):
            z = torch.from_numpy(latents[start : start + 256]).to(device)
            out = decoder.decode_grid(z, feats)
            target = torch.from_numpy(targets[start : start + 256]).to(device)
            total += torch.sum(torch.square(out - target), dtype=torch.float64).item()
    return math.sqrt(total / targets.size)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--material", default="corduroy")
    parser.add_argument("--size", type=int, default=128, help="texture side (texels)")
    parser.add_argument("--crop", type=int, default=100, help="crop side (texels)")
    parser.add_argument("--scale", type=float, default=1.0, help="x every run's length")
    parser.add_argument("--lengths", default="1,2,4", help="multiples of each recipe")
    parser.add_argument("--models", default="neural_btf,latent_texture")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    clock = time.perf_counter()
    directions = btf_directions()
    btf = SyntheticBTF(size=args.size, material=args.material, seed=0)
    values = btf.evaluate(directions)[:, : args.crop, : args.crop]  # (N, crop, crop, 3)
    abrdf = np.ascontiguousarray(values.reshape(len(directions), -1, 3).transpose(1, 0, 2))
    norm = fit_normalization(abrdf)
    targets = norm.target(abrdf)
    features = direction_features(directions).astype(np.float32)
    every = np.arange(len(directions))
    m = len(abrdf)
    common = {
        "material": args.material,
        "crop": args.crop,
        "device": str(device),
        "gpu": torch.cuda.get_device_name() if device.type == "cuda" else None,
    }
    print(
        json.dumps(
            {
                **common,
                "data_seconds": round(time.perf_counter() - clock, 1),
                "M": m,
                "N": len(directions),
            }
        ),
        flush=True,
    )
    lines = []
    for multiple in (float(v) for v in args.lengths.split(",")):
        models = args.models.split(",")
        epochs = max(1, round(24 * multiple * args.scale))
        settings = TrainSettings(
            optimizer="adam",
            lr=0.002,
            batch_size=32,
            queries_per_abrdf=256,
            epochs=epochs,
            epoch_texels=10000,
            schedule="cosine",
            device=device.type,
            backend="autograd" if device.type == "cuda" else "auto",
            threads=1,
        )
        if "neural_btf" in models:
            result = train(abrdf, abrdf, np.arange(m), norm, features, every, settings, seed=0)
            latents = encode(result.encoder.cpu(), abrdf, norm)
            lines.append(
                {
                    **common,
                    "model": "neural_btf",
                    "multiple": multiple,
                    "steps": result.steps,
                    "seconds": round(result.seconds, 1),
                    "steps_per_second": round(result.steps / result.seconds, 1),
                    "rmse": rmse(result.decoder, latents, targets, features, device),
                }
            )
            print(json.dumps(lines[-1]), flush=True)
        if "latent_texture" not in models:
            continue
        steps = max(10, round(15000 * multiple * args.scale))
        fitted = train_latent_texture(
            targets,
            features,
            every,
            (args.crop, args.crop),
            latent=8,
            levels=1,
            hidden=106,
            layers=3,
            steps=steps,
            batch_texels=64,
            queries_per_texel=64,
            lr=0.01,
            seed=0,
            device=device.type,
        )
        module = fitted.module
        with torch.no_grad():
            latents = module.texel_latents(torch.arange(m)).numpy()
        lines.append(
            {
                **common,
                "model": "latent_texture",
                "multiple": multiple,
                "steps": steps,
                "seconds": round(fitted.seconds, 1),
                "steps_per_second": round(steps / fitted.seconds, 1),
                "rmse": rmse(module.decoder, latents, targets, features, device),
            }
        )
        print(json.dumps(lines[-1]), flush=True)
        if args.out:
            with open(args.out, "w") as out:
                out.write("".join(json.dumps(line) + "\n" for line in lines))


if __name__ == "__main__":
    main()
