"""``python -m pipeline.bench``: throughput figures of method A at the paper's sizes.

Prints, in one run on one machine: the float32 matrix-multiply peak (the yardstick), the
decoder training throughput of a naive loop at the paper's batch (5 ABRDFs x all N
directions per step) and of the configured path, the encoder throughput, and the
reconstruction throughput; the last line is one JSON object, also logged to MLflow
(experiment ``bench``). Timings are medians of repeats; compare figures as ratios within
one run, never across noisy runs. This is a measurement tool, not a test.

    python -m pipeline.bench [--threads 1] [--steps 20] [--runs runs] [--load-size 256]
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np
import torch

from pipeline.btf.model import Decoder, Encoder, parameter_count

N_PAPER = 6561
# Decoder multiply-adds per query: 12*106 + 2*106*106 + 106*3.
DECODER_MACS = 12 * 106 + 2 * 106 * 106 + 106 * 3
TRAIN_FLOPS_PER_QUERY = 3 * 2 * DECODER_MACS  # forward + backward ~ 3x forward


def _median_seconds(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def matmul_peak(size: int = 1024, repeats: int = 5) -> float:
    """GFLOP/s of a float32 square matrix product."""
    a, b = torch.randn(size, size), torch.randn(size, size)
    return 2 * size**3 / _median_seconds(lambda: a @ b, repeats) / 1e9


def train_step_throughput(batch: int, queries: int, steps: int, channels) -> dict:
    """Queries/s of full training steps (encoder + decoder + SGD) on random ABRDFs."""
    torch.manual_seed(0)
    encoder, decoder = Encoder(N_PAPER, channels), Decoder()
    params = list(encoder.parameters()) + list(decoder.parameters())
    optimizer = torch.optim.SGD(params, lr=0.05)
    abrdfs = torch.randn(batch, 3, N_PAPER)
    directions = torch.rand(N_PAPER, 4)
    targets = torch.rand(batch * queries, 3)
    index = torch.randint(0, N_PAPER, (batch * queries,))

    def step():
        for _ in range(steps):
            latents = encoder(abrdfs)
            pred = decoder(latents.repeat_interleave(queries, 0), directions[index])
            loss = torch.nn.functional.mse_loss(pred, targets)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()

    seconds = _median_seconds(step, 3) / steps
    rate = batch * queries / seconds
    return {"queries_per_s": rate, "gflops": rate * TRAIN_FLOPS_PER_QUERY / 1e9,
            "steps_per_s": 1 / seconds}


def encoder_throughput(batch: int, channels) -> float:
    """ABRDFs/s through the encoder, forward and backward."""
    encoder = Encoder(N_PAPER, channels)
    abrdfs = torch.randn(batch, 3, N_PAPER)
    return batch / _median_seconds(lambda: encoder(abrdfs).sum().backward(), 3)


@torch.no_grad()
def reconstruction_throughput(latents: int) -> float:
    """Queries/s of decoding ``latents`` latents at all N directions (chunks of 32)."""
    decoder = Decoder().eval()
    z, directions = torch.randn(latents, 8), torch.rand(N_PAPER, 4)

    def run():
        for start in range(0, latents, 32):
            decoder.decode_grid(z[start : start + 32], directions)

    return latents * N_PAPER / _median_seconds(run, 3)


def load_times(runs: str, size: int) -> dict:
    """Seconds to load a full UBO2003-layout folder (6561 JPEGs of size x size) through the
    load stage: decoded (a cache miss) and again from the stage cache (a hit)."""
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    from pipeline.data.synthetic_btf import write_synthetic_btf
    from pipeline.stages import Context, load

    root = write_synthetic_btf(Path(runs) / "data" / f"bench_ubo2003_{size}", size=size, seed=0)
    conf = Path(__file__).resolve().parents[1] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose("config", overrides=[
            "experiment=smoke", "dataset=ubo2003", f"dataset.root={root}", "dataset.views=null",
            f"paths.runs={runs}", f"paths.cache={Path(runs) / 'bench_cache'}"])
    import shutil

    shutil.rmtree(cfg.paths.cache, ignore_errors=True)
    times = {}
    for name in ("decode", "cached"):
        start = time.perf_counter()
        entry = load(Context.from_config(cfg))
        times[f"load_{name}_s"] = time.perf_counter() - start
    times["load_images"] = int(entry.manifest["summary"]["n_images"])
    return times


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: all)")
    parser.add_argument("--steps", type=int, default=10, help="training steps per timing")
    parser.add_argument("--runs", default="runs", help="paths.runs holding mlflow.db")
    parser.add_argument("--no-mlflow", action="store_true")
    parser.add_argument("--load-size", type=int, default=0,
                        help="also time loading a 6561-file UBO2003 folder of this texture size "
                             "(256 = the real datasets; generated once under --runs)")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    channels = (8, 16, 32)
    figures: dict = {"device": "cpu", "threads": torch.get_num_threads(),
                     "machine": platform.processor() or platform.machine(),
                     "decoder_parameters": parameter_count(Decoder())}
    figures["matmul_gflops"] = matmul_peak()
    print(f"matmul peak: {figures['matmul_gflops']:.1f} GFLOP/s ({figures['threads']} threads)")
    naive = train_step_throughput(5, N_PAPER, args.steps, channels)
    batched = train_step_throughput(32, 256, args.steps, channels)
    for name, row in (("naive (5 x all N)", naive), ("demo (32 x 256)", batched)):
        print(f"training {name}: {row['queries_per_s'] / 1e6:.3f} M queries/s, "
              f"{row['gflops']:.1f} GFLOP/s = {row['gflops'] / figures['matmul_gflops']:.0%} "
              f"of peak, {row['steps_per_s']:.1f} steps/s")
    figures["train_naive"], figures["train_demo"] = naive, batched
    figures["encoder_abrdfs_per_s"] = encoder_throughput(32, channels)
    print(f"encoder: {figures['encoder_abrdfs_per_s']:.0f} ABRDFs/s (forward + backward)")
    figures["reconstruct_queries_per_s"] = reconstruction_throughput(256)
    print(f"reconstruction: {figures['reconstruct_queries_per_s'] / 1e6:.3f} M queries/s "
          f"(Neural BTF all M x N at paper size: "
          f"{10_000 * N_PAPER / figures['reconstruct_queries_per_s']:.0f} s)")
    if args.load_size:
        figures.update(load_times(args.runs, args.load_size))
        print(f"load {figures['load_images']} JPEGs of {args.load_size}^2: decode "
              f"{figures['load_decode_s']:.1f} s, from the stage cache "
              f"{figures['load_cached_s']:.2f} s")
    if not args.no_mlflow:
        import mlflow

        from pipeline.tracking import environment_tags, init_store

        experiment_id = init_store(args.runs, "bench")
        with mlflow.start_run(experiment_id=experiment_id, tags=environment_tags()):
            flat = {k: v for k, v in figures.items() if isinstance(v, int | float)}
            flat.update({f"{name}_{k}": v for name in ("train_naive", "train_demo")
                         for k, v in figures[name].items()})
            mlflow.log_metrics(flat)
            mlflow.log_params({"threads": figures["threads"], "machine": figures["machine"]})
    print(json.dumps(figures))
    return figures


if __name__ == "__main__":
    main()
