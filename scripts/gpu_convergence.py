"""Does doubling the run change the error? Neural BTF and clustered (k = ``--k``), with the
CPU recipe of ``conf/train/converged.yaml`` (Adam, 32 ABRDFs x 256 directions a step,
cosine schedule over the run; ``--lr`` its peak), and the latent texture
(``model=latent_texture``'s defaults) on built-in materials at the paper's size (a
100 x 100 crop, all 81 x 81 directions), each trained at several multiples of its length
and seeds, on the GPU when there is one (where the CPU cannot afford the long runs).

``--data pipeline`` (the default) reads what the pipeline's built-in dataset reads: the
material written as UBO2003 JPEGs (quality 95, a 128 x 128 texture, generator seed 0) by
the project's writer, read back by its reader and cropped at [0, 0], so the RMSEs are those
of docs/results.md's tables. ``--data analytic`` uses the generator's values directly (no
JPEG round trip): lower errors, not comparable with the tables.

Models train in ``--jobs`` processes at once, the longest first: one model's steps leave
the GPU mostly idle, so one GPU serves several, best with CUDA MPS started first
(``nvidia-cuda-mps-control -d``: the processes' kernels then run side by side;
docs/performance.md has figures with and without it). One JSON line per trained model (stdout, and
appended to ``--out`` as each ends: a rerun adds to the file), with the Neural BTF's and
the clustered model's RMSE-versus-steps curve on 256 texels fixed per seed:

    python scripts/gpu_convergence.py --materials plain_weave,corduroy --lengths 1,2,4,8 \
        --jobs 8 --out convergence.jsonl
    python scripts/gpu_convergence.py --size 16 --crop 12 --scale 0.01   # a CPU check
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import multiprocessing
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
import torch

from pipeline.btf.clustering import cluster_medians, kmeans_pp, pca_reduce
from pipeline.btf.latent_texture import train_latent_texture
from pipeline.btf.preprocess import encoder_inputs, fit_normalization
from pipeline.btf.stereographic import direction_features
from pipeline.btf.synthetic import SyntheticBTF
from pipeline.btf.synthetic_dataset import write_synthetic_btf
from pipeline.btf.train import encode, train
from pipeline.btf.train_settings import TrainSettings
from pipeline.core.errors import ConfigError
from pipeline.data.btf import load_btf
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


def material_crop(material: str, size: int, crop: int, data: str, folder: Path):
    """(ABRDFs (M, N, 3), directions (N, 4)) of the crop at [0, 0]."""
    if data == "pipeline":
        root = write_synthetic_btf(folder / material, size=size, material=material, quality=95)
        btf = load_btf(root, progress=False)
        values, directions = btf.images[:, :crop, :crop], btf.directions
    else:
        directions = btf_directions()
        btf = SyntheticBTF(size=size, material=material, seed=0)
        values = btf.evaluate(directions)[:, :crop, :crop]  # (N, crop, crop, 3)
    abrdf = np.ascontiguousarray(values.reshape(len(directions), -1, 3).transpose(1, 0, 2))
    return abrdf.astype(np.float32), np.asarray(directions)


def recipe(task: dict) -> TrainSettings:
    """The Neural BTF's and the clustered model's training settings for ``task``
    (``conf/train/converged.yaml``'s recipe at ``task["epochs"]``); refuses a bad value
    naming the setting (ConfigError)."""
    return TrainSettings(
        optimizer="adam",
        lr=task["lr"],
        batch_size=32,
        queries_per_abrdf=256,
        epochs=task["epochs"],
        epoch_texels=10000,
        schedule="cosine",
        device=task["device"],
        backend=task["backend"] or ("autograd" if task["device"] == "cuda" else "auto"),
        threads=1,
        curve_every=task["curve_every"],
        clip_grad_norm=task["clip"],
    )


def run_task(task: dict) -> dict:
    """Train one model on the crop saved at ``task["path"]``; its result line."""
    torch.set_num_threads(1)
    device = torch.device(task["device"])
    saved = np.load(task["path"])
    abrdf, directions = saved["abrdf"], saved["directions"]
    norm = fit_normalization(abrdf)
    targets = norm.target(abrdf)
    features = direction_features(directions).astype(np.float32)
    every = np.arange(len(directions))
    m = len(abrdf)
    line = {k: task[k] for k in ("material", "data", "crop", "model", "multiple", "seed")}
    line["device"] = str(device)
    line["gpu"] = torch.cuda.get_device_name() if device.type == "cuda" else None
    if task["model"] in ("neural_btf", "clustered"):
        settings = recipe(task)
        line.update(lr=settings.lr, backend=settings.backend, clip=settings.clip_grad_norm)
        if task["model"] == "clustered":
            # As the pipeline's pca, kmeans and representatives stages (btf.pca's 16
            # components, k-means++ seeded by the run's seed, the clusters' medians): the
            # encoder reads a texel's representative and the loss its own ABRDF.
            scores, _ = pca_reduce(encoder_inputs(abrdf, norm), 16, 0)
            labels, _, _ = kmeans_pp(scores, task["k"], seed=task["seed"])
            sources = cluster_medians(abrdf, labels, task["k"])
            source_of_texel = labels.astype(np.int64)
            line["k"] = task["k"]
        else:
            sources, source_of_texel = abrdf, np.arange(m)
        result = train(
            abrdf, sources, source_of_texel, norm, features, every, settings, seed=task["seed"]
        )
        latents = encode(result.encoder.cpu(), sources, norm)[source_of_texel]
        decoder, steps, seconds = result.decoder, result.steps, result.seconds
        curve = [[p["step"], round(p["rmse"], 6)] for p in result.curve]
    else:
        fitted = train_latent_texture(
            targets,
            features,
            every,
            (task["crop"], task["crop"]),
            latent=8,
            levels=1,
            hidden=106,
            layers=3,
            steps=task["steps"],
            batch_texels=64,
            queries_per_texel=64,
            lr=0.01,
            seed=task["seed"],
            device=device.type,
        )
        module = fitted.module
        with torch.no_grad():
            latents = module.texel_latents(torch.arange(m)).numpy()
        decoder, steps, seconds, curve = module.decoder, task["steps"], fitted.seconds, []
    line.update(
        steps=steps,
        seconds=round(seconds, 1),
        steps_per_second=round(steps / seconds, 1),
        rmse=rmse(decoder, latents, targets, features, device),
        curve=curve,
    )
    return line


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--materials", default="corduroy", help="comma-separated")
    parser.add_argument("--data", choices=("pipeline", "analytic"), default="pipeline")
    parser.add_argument("--size", type=int, default=128, help="texture side (texels)")
    parser.add_argument("--crop", type=int, default=100, help="crop side (texels)")
    parser.add_argument("--scale", type=float, default=1.0, help="x every run's length")
    parser.add_argument("--lengths", default="1,2,4", help="multiples of each recipe")
    parser.add_argument("--seeds", default="0", help="comma-separated training seeds")
    parser.add_argument("--models", default="neural_btf,latent_texture")
    parser.add_argument("--k", default="500", help="clustered: k, comma-separated")
    parser.add_argument("--lr", type=float, default=0.002, help="Neural BTF, clustered: peak lr")
    parser.add_argument("--clip", type=float, default=None, help="train.clip_grad_norm")
    parser.add_argument("--backend", default=None, help="train.backend (autograd on CUDA)")
    parser.add_argument("--curve-every", type=int, default=500, help="steps between curve points")
    parser.add_argument("--jobs", type=int, default=1, help="models trained at once")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    device = "cuda" if torch.cuda.is_available() else "cpu"
    try:  # at the door: a bad --lr, --clip or --backend before any crop is written
        recipe(vars(args) | {"device": device, "epochs": 1})
    except ConfigError as error:
        raise SystemExit(f"gpu_convergence.py: {error}") from None
    unknown = set(args.models.split(",")) - {"neural_btf", "clustered", "latent_texture"}
    if unknown:
        raise SystemExit(f"gpu_convergence.py: --models: unknown {', '.join(sorted(unknown))}")
    if args.out and not Path(args.out).resolve().parent.is_dir():
        raise SystemExit(f"gpu_convergence.py: --out {args.out}: its folder does not exist")
    with tempfile.TemporaryDirectory(prefix="gpu_convergence_") as folder:
        failed = train_all(args, device, Path(folder))
    if failed:
        raise SystemExit(f"gpu_convergence.py: {failed} model(s) failed (above)")


def train_all(args: argparse.Namespace, device: str, folder: Path) -> int:
    """Write each material's crop into ``folder`` and queue its models, the longest first,
    so the next material's crop is written while the first one's models train; report each
    model as it ends. Returns how many failed."""
    lengths = [float(v) for v in args.lengths.split(",")]
    seeds = [int(v) for v in args.seeds.split(",")]
    k_values = [int(v) for v in args.k.split(",")]
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    pending = {}
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max(1, args.jobs), mp_context=context) as pool:
        for material in args.materials.split(","):
            clock = time.perf_counter()
            abrdf, directions = material_crop(material, args.size, args.crop, args.data, folder)
            saved = folder / f"{material}.npz"
            np.savez(saved, abrdf=abrdf, directions=directions)
            print(
                json.dumps(
                    {
                        "material": material,
                        "data": args.data,
                        "M": len(abrdf),
                        "N": len(directions),
                        "data_seconds": round(time.perf_counter() - clock, 1),
                    }
                ),
                flush=True,
            )
            tasks = []
            for model, multiple, seed in itertools.product(args.models.split(","), lengths, seeds):
                # k is the clustered model's alone: one task per k for it, one for the others.
                for k in k_values if model == "clustered" else [None]:
                    tasks.append(
                        {
                            "material": material,
                            "path": str(saved),
                            "data": args.data,
                            "crop": args.crop,
                            "model": model,
                            "multiple": multiple,
                            "seed": seed,
                            "device": device,
                            "k": k,
                            "lr": args.lr,
                            "backend": args.backend,
                            "clip": args.clip,
                            "curve_every": args.curve_every,
                            "epochs": max(1, round(24 * multiple * args.scale)),
                            "steps": max(10, round(15000 * multiple * args.scale)),
                        }
                    )
            # The longest first, so the pool's last minutes are not one long model alone.
            tasks.sort(key=lambda t: -t["multiple"] * (2 if t["model"] == "latent_texture" else 1))
            pending.update({pool.submit(run_task, task): task for task in tasks})
        # Lines are written here, in this process: a worker that dies (out of memory, a
        # CUDA fault) fails its own future and the ones still queued, and nothing hangs.
        failed = 0
        for future in as_completed(pending):
            task = pending[future]
            try:
                report(args.out, future.result())
            except Exception as error:  # one model's failure: named and counted, the rest go on
                failed += 1
                named = {k: task[k] for k in ("material", "model", "k", "multiple", "seed")}
                print(f"FAILED {json.dumps(named)}: {type(error).__name__}: {error}", flush=True)
    return failed


def report(out: str | None, line: dict) -> None:
    """Print a finished model's line without its curve; append it whole to ``out``."""
    print(json.dumps({k: v for k, v in line.items() if k != "curve"}), flush=True)
    if out:
        with open(out, "a") as file:
            file.write(json.dumps(line) + "\n")


if __name__ == "__main__":
    main()
