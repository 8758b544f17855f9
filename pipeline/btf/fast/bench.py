"""``python -m pipeline.btf.fast.bench``: speed and memory figures of method A at the paper's sizes.

Prints, in one run on one machine:

- the float32 matrix-multiply peak (the yardstick), at the threads the figures use;
- decoder training throughput at the paper's batch (5 ABRDFs x all 6561 directions per
  step) of a naive autograd loop and of ``pipeline.btf.train.train`` (the fused, chunked,
  threaded step), in queries/s, GFLOP/s and as a share of the peak, and of the recipe
  ``experiment=paper_cpu`` uses (``conf/train/cpu.yaml``: 32 ABRDFs x 256 directions);
  the same for the decoder alone (autograd against the fused step, no encoder);
- encoder throughput (ABRDFs/s, forward and backward);
- reconstruction throughput: Neural BTF (all M x N) and clustered (k x N decoded once);
- with ``--paper-run``: time and peak resident memory of every stage of a paper-size run
  on the synthetic BTF (one Neural BTF and one clustered job, each in its own process);
- with ``--load-size 256``: loading a 6561-file UBO2003 folder, decoded and cached.

The last line is one JSON object (keys in README.md), also logged to MLflow (experiment
``bench`` under ``--runs``). Timings are medians of repeats; compare them as ratios within
one run, never across runs on a shared machine. A measurement tool, not a test.

    python -m pipeline.btf.fast.bench [--threads 2] [--paper-run] [--load-size 256] [--runs runs]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from pipeline.btf.model import Decoder, Encoder, parameter_count

N_PAPER = 6561
M_PAPER = 10_000
CONF = Path(__file__).resolve().parents[1] / "conf"
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


def paper_channels() -> tuple[int, ...]:
    return tuple(OmegaConf.load(CONF / "btf" / "default.yaml").model.encoder_channels)


def matmul_peak(size: int = 2048, repeats: int = 5, dtype=torch.float32) -> float:
    """GFLOP/s of a square matrix product (float32, or bfloat16 for the bfloat16 loops)."""
    a, b = torch.randn(size, size, dtype=dtype), torch.randn(size, size, dtype=dtype)
    return 2 * size**3 / _median_seconds(lambda: a @ b, repeats) / 1e9


def cpu_bfloat16_support() -> str:
    """The CPU's native bfloat16 instructions from /proc/cpuinfo (``amx_bf16``,
    ``avx512_bf16``), or ``none``: without them bfloat16 products take oneDNN's slower
    code paths, and ``train.precision=bfloat16`` may not pay."""
    try:
        flags = set(Path("/proc/cpuinfo").read_text().split())
    except OSError:
        return "unknown"
    found = [f for f in ("amx_bf16", "avx512_bf16") if f in flags]
    return ",".join(found) or "none"


def _rates(queries_per_step: float, seconds_per_step: float) -> dict:
    rate = queries_per_step / seconds_per_step
    return {"queries_per_s": rate, "gflops": rate * TRAIN_FLOPS_PER_QUERY / 1e9,
            "steps_per_s": 1 / seconds_per_step}


def naive_training(steps: int, channels):
    """A plain autograd loop at the paper's batch: each step encodes 5 ABRDFs, repeats each
    latent for all N directions, concatenates the direction inputs and backpropagates.
    Returns a callable that runs ``steps`` steps and returns their seconds."""
    torch.manual_seed(0)
    encoder, decoder = Encoder(N_PAPER, channels), Decoder()
    # The blocks as a plain implementation would write them, conv -> ReLU -> torch's
    # MaxPool1d -> batch-norm on (batch, C, L) tensors (Encoder.reference), not the
    # pipeline's faster equivalents (model.MaxPool3 first, the channels-last forward).
    for block in range(0, len(encoder.features), 4):
        encoder.features[block + 1] = torch.nn.ReLU()
        encoder.features[block + 2] = torch.nn.MaxPool1d(kernel_size=3, stride=3)
    params = list(encoder.parameters()) + list(decoder.parameters())
    optimizer = torch.optim.SGD(params, lr=0.05)
    abrdfs = torch.randn(5, 3, N_PAPER)
    directions = torch.rand(N_PAPER, 4)
    targets = torch.rand(5 * N_PAPER, 3)
    index = torch.arange(N_PAPER).repeat(5)

    def run() -> float:
        start = time.perf_counter()
        for _ in range(steps):
            latents = encoder.reference(abrdfs)
            pred = decoder(latents.repeat_interleave(N_PAPER, 0), directions[index])
            loss = torch.nn.functional.mse_loss(pred, targets)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        return time.perf_counter() - start

    return run


class Isolated:
    """A plain PyTorch loop (``naive`` or ``decoder_naive``) timed in a child process that
    runs with libgomp's default settings, as a user's own program would: ``import
    pipeline`` lowers OpenMP's spin-waiting for the pipeline's loops
    (``pipeline.btf.fast.tuning.SPIN_COUNT``). On a 2-core AMX Xeon a spin count of 10,000 made the
    naive loop slower (75 against 64 ms a step; at 30,000: 59-63 ms, no slower). Calling it
    runs ``steps`` steps there and returns their seconds, like the other loops'
    callables."""

    def __init__(self, kind: str, steps: int, threads: int):
        from pipeline.btf.fast.tuning import openmp_default_environment

        self.process = subprocess.Popen(
            [sys.executable, "-m", "pipeline.btf.fast.bench", "--serve", kind, "--steps", str(steps),
             "--threads", str(threads)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
            env=openmp_default_environment())

    def __call__(self) -> float:
        self.process.stdin.write("run\n")
        self.process.stdin.flush()
        while line := self.process.stdout.readline():
            if line.startswith("seconds "):
                return float(line.split()[1])
        raise RuntimeError(f"the bench's child process ended (exit {self.process.wait()})")

    def close(self) -> None:
        self.process.stdin.close()
        self.process.wait()


def _serve(kind: str, steps: int) -> None:
    """The child's side of :class:`Isolated`: a timing per line read from stdin."""
    run = (naive_training(steps, paper_channels()) if kind == "naive"
           else decoder_training(False, steps, torch.get_num_threads()))
    for _ in sys.stdin:
        print(f"seconds {run()!r}", flush=True)


def decoder_training(fused: bool, steps: int, threads: int, precision: str = "float32"):
    """The decoder alone at the paper's batch (5 fixed latents x all N directions): autograd
    on the concatenated (latent, direction) rows, or the pipeline's fused step
    (``pipeline.btf.fast.fused.DecoderStep``) with its default chunk, in ``precision``. Both
    compute the latents' gradient and take an SGD step on the decoder, so the two differ only
    in how the decoder's forward and backward are computed. The fused step runs with the
    cores kept awake, as in training (``pipeline.btf.fast.tuning.keep_cpus_awake``). Returns a callable
    that runs ``steps`` steps and returns their seconds."""
    from pipeline.btf.fast.fused import Batch, DecoderStep
    from pipeline.btf.fast.tuning import keep_cpus_awake

    torch.manual_seed(0)
    decoder = Decoder()
    optimizer = torch.optim.SGD(decoder.parameters(), lr=1e-3)
    latents = torch.randn(5, 8, requires_grad=True)
    features = torch.rand(N_PAPER, 4)
    targets = torch.rand(5, N_PAPER, 3)
    directions = torch.arange(N_PAPER).repeat(5, 1)
    step = (DecoderStep(decoder, features, workers=threads, precision=precision)
            if fused else None)

    def one_step() -> None:
        optimizer.zero_grad(set_to_none=True)
        if fused:
            torch.set_num_threads(1)  # as in training: one op per thread, chunks side by side
            step.assign(step(Batch(latents.detach(), directions, targets)))
            torch.set_num_threads(threads)
        else:
            pred = decoder(latents.repeat_interleave(N_PAPER, 0),
                           features[directions.reshape(-1)])
            torch.nn.functional.mse_loss(pred, targets.reshape(-1, 3)).backward()
        optimizer.step()

    def run() -> float:
        with keep_cpus_awake(threads if fused else 0):
            one_step()  # untimed warm-up
            start = time.perf_counter()
            for _ in range(steps):
                one_step()
            return time.perf_counter() - start

    return run


def pipeline_training(batch: int, queries: int, steps: int, channels, threads: int,
                      precision: str = "float32", optimizer: str = "sgd", lr: float = 0.05):
    """The project's training loop (``pipeline.btf.train.train``) on random ABRDFs: data
    handling, normalization, encoder, fused decoder step and optimizer (by default the
    paper's plain SGD, as in the naive loop), as in a real run. Returns a callable that runs
    ``steps`` steps and returns their training seconds."""
    from pipeline.btf.preprocess import fit_normalization
    from pipeline.btf.train import train
    from pipeline.btf.train_settings import TrainSettings

    rng = np.random.default_rng(0)
    m = max(2 * batch, 64)
    abrdf = rng.random((m, N_PAPER, 3), dtype=np.float32)
    norm = fit_normalization(abrdf)
    features = rng.random((N_PAPER, 4), dtype=np.float32) * 2 - 1
    settings = TrainSettings(epochs=10**6, batch_size=batch, queries_per_abrdf=queries,
                             max_steps=steps, optimizer=optimizer, lr=lr, threads=threads,
                             device="cpu", precision=precision)

    def run() -> float:
        return train(abrdf, abrdf, np.arange(m), norm, features, np.arange(N_PAPER), settings,
                     seed=0, encoder_channels=channels).seconds

    return run


def interleaved(loops: dict, queries_per_step: dict, steps: int, rounds: int = 3) -> dict:
    """Time the loops in turn, ``rounds`` times after one warm-up each, so that a machine
    that slows down or speeds up meanwhile affects all of them alike; medians per loop.
    The float32 and bfloat16 matmul peaks are measured in every round too
    (``matmul_gflops`` and ``matmul_gflops_bf16``, the medians; ``..._rounds``, each
    round's), so the shares of them compare like with like."""
    for run in loops.values():
        run()
    times = {name: [] for name in loops}
    peaks, peaks_bf16 = [], []
    for _ in range(rounds):
        peaks.append(matmul_peak())
        peaks_bf16.append(matmul_peak(dtype=torch.bfloat16))
        for name, run in loops.items():
            times[name].append(run() / steps)
    figures = {name: _rates(queries_per_step[name], float(np.median(t)))
               for name, t in times.items()}
    return figures | {"matmul_gflops": float(np.median(peaks)), "matmul_gflops_rounds": peaks,
                      "matmul_gflops_bf16": float(np.median(peaks_bf16)),
                      "matmul_gflops_bf16_rounds": peaks_bf16}


def encoder_throughput(batch: int, channels) -> float:
    """ABRDFs/s through the encoder, forward and backward."""
    encoder = Encoder(N_PAPER, channels)
    abrdfs = torch.randn(batch, 3, N_PAPER)
    return batch / _median_seconds(lambda: encoder(abrdfs).sum().backward(), 3)


def reconstruction_seconds(latents: int, repeats: int = 3) -> float:
    """Seconds to decode ``latents`` latents at all N directions with the evaluate stage's
    ``decode_all`` (chunks of 32 latents)."""
    from pipeline.btf.evaluate import decode_all

    decoder = Decoder().eval()
    z = np.random.default_rng(0).standard_normal((latents, 8)).astype(np.float32)
    directions = np.random.default_rng(1).random((N_PAPER, 4), dtype=np.float32)
    return _median_seconds(lambda: decode_all(decoder, z, directions), repeats)


def paper_run(runs: str, steps: int, threads: int) -> dict:
    """Per-stage seconds and peak RSS of paper-size jobs on the synthetic BTF (128 x 128,
    crop 100 x 100), one process per job, with ``steps`` training steps each."""
    import mlflow

    from pipeline.core.tracking import use_store

    root = Path(runs) / "bench_paper"
    figures: dict = {}
    for variant in ("neural_btf", "k1000"):
        command = [sys.executable, "-m", "pipeline", "experiment=paper", f"variant={variant}",
                   f"train.max_steps={steps}", f"train.threads={threads}",
                   f"paths.runs={root}", "tracking.experiment=bench_paper"]
        start = time.perf_counter()
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - start
        use_store(str(root))
        run = mlflow.search_runs(experiment_names=["bench_paper"], output_format="list",
                                 order_by=["attributes.start_time DESC"], max_results=1)[0]
        metrics = run.data.metrics
        row = {"wall_s": wall, "peak_rss_mb": metrics["peak_rss_mb"],
               "train_queries_per_s": metrics["train_queries"] / metrics["train_seconds"]}
        for name, value in metrics.items():
            for prefix in ("seconds_", "peak_rss_mb_"):
                if name.startswith(prefix):
                    row[f"{name[len(prefix):]}_{prefix.rstrip('_')}"] = value
        figures[variant] = row
    return figures


def load_times(runs: str, size: int) -> dict:
    """Seconds to load a full UBO2003-layout folder (6561 JPEGs of size x size) through the
    load stage: decoded (a cache miss) and again from the stage cache (a hit)."""
    import shutil

    from hydra import compose, initialize_config_dir

    from pipeline.btf.stages import Context, load
    from pipeline.btf.synthetic import write_synthetic_btf

    root = write_synthetic_btf(Path(runs) / "data" / f"bench_ubo2003_{size}", size=size, seed=0)
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=[
            "experiment=smoke", "dataset=ubo2003", f"dataset.root={root}", "dataset.views=null",
            f"paths.runs={runs}", f"paths.cache={Path(runs) / 'bench_cache'}"])
    shutil.rmtree(cfg.paths.cache, ignore_errors=True)
    times = {"load_cold": _drop_page_cache()}
    for name in ("decode", "cached"):
        start = time.perf_counter()
        entry = load(Context.from_config(cfg))
        times[f"load_{name}_s"] = time.perf_counter() - start
    times["load_images"] = int(entry.manifest["summary"]["n_images"])
    return times


def _drop_page_cache() -> bool:
    """Empty the OS page cache so that the first load reads from disk (root on Linux
    only); returns whether it could."""
    os.sync()
    try:
        Path("/proc/sys/vm/drop_caches").write_text("3")
        return True
    except OSError:
        return False


def _print_training(name: str, row: dict, peak: float, peak_bf16: float | None = None) -> None:
    """One loop's line; a bfloat16 loop gets its share of both peaks (``share_of_peak``
    and ``share_of_bf16_peak`` in the JSON)."""
    row["share_of_peak"] = row["gflops"] / peak
    shares = f"{row['share_of_peak']:.0%} of the float32 peak"
    if peak_bf16 is not None:
        row["share_of_bf16_peak"] = row["gflops"] / peak_bf16
        shares += f", {row['share_of_bf16_peak']:.0%} of the bfloat16 peak"
    print(f"training {name}: {row['queries_per_s'] / 1e6:.3f} M queries/s, "
          f"{row['gflops']:.1f} GFLOP/s = {shares}, {row['steps_per_s']:.1f} steps/s")


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=None, help="CPU threads (default: all)")
    parser.add_argument("--steps", type=int, default=30, help="training steps per timing")
    parser.add_argument("--runs", default="runs", help="paths.runs holding mlflow.db")
    parser.add_argument("--no-mlflow", action="store_true")
    parser.add_argument("--paper-run", type=int, default=0, metavar="STEPS",
                        help="also run paper-size jobs with this many training steps and "
                             "report each stage's time and peak RSS")
    parser.add_argument("--load-size", type=int, default=0,
                        help="also time loading a 6561-file UBO2003 folder of this texture size "
                             "(256 = the real datasets; generated once under --runs)")
    parser.add_argument("--serve", choices=("naive", "decoder_naive"),
                        help=argparse.SUPPRESS)  # the child of Isolated
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.serve:
        _serve(args.serve, args.steps)
        return {}
    threads = torch.get_num_threads()
    channels = paper_channels()
    device = "cuda" if torch.cuda.is_available() else "cpu"
    figures: dict = {"device": f"{device} ({torch.cuda.get_device_name()})" if device == "cuda"
                     else "cpu", "threads": threads,
                     "machine": platform.processor() or platform.machine(),
                     "torch": torch.__version__, "cpu_bf16": cpu_bfloat16_support(),
                     "decoder_parameters": parameter_count(Decoder()),
                     "encoder_channels": list(channels)}
    recipe = OmegaConf.load(CONF / "train" / "cpu.yaml")
    naive = {"train_naive": Isolated("naive", args.steps, threads),
             "decoder_naive": Isolated("decoder_naive", args.steps, threads)}
    figures |= interleaved(
        {"train_naive": naive["train_naive"],
         "train_fused": pipeline_training(5, -1, args.steps, channels, threads),
         "train_paper_recipe": pipeline_training(recipe.batch_size, recipe.queries_per_abrdf,
                                                 args.steps, channels, threads,
                                                 optimizer=recipe.optimizer, lr=recipe.lr),
         "train_fused_bf16": pipeline_training(5, -1, args.steps, channels, threads,
                                               precision="bfloat16"),
         "decoder_naive": naive["decoder_naive"],
         "decoder_fused": decoder_training(True, args.steps, threads),
         "decoder_fused_bf16": decoder_training(True, args.steps, threads, "bfloat16")},
        {"train_naive": 5 * N_PAPER, "train_fused": 5 * N_PAPER,
         "train_paper_recipe": recipe.batch_size * recipe.queries_per_abrdf,
         "train_fused_bf16": 5 * N_PAPER, "decoder_naive": 5 * N_PAPER,
         "decoder_fused": 5 * N_PAPER, "decoder_fused_bf16": 5 * N_PAPER},
        args.steps)
    for child in naive.values():
        child.close()
    peak = figures["matmul_gflops"]
    print(f"matmul peak: {peak:.1f} GFLOP/s (median of "
          f"{', '.join(f'{p:.1f}' for p in figures['matmul_gflops_rounds'])}, one per round "
          f"of the training loops; {threads} threads, device {figures['device']}; the "
          f"training figures below run on the CPU)")
    _print_training("naive autograd loop (5 x all N)", figures["train_naive"], peak)
    _print_training("pipeline loop (5 x all N)", figures["train_fused"], peak)
    figures["train_speedup"] = (figures["train_fused"]["queries_per_s"]
                                / figures["train_naive"]["queries_per_s"])
    print(f"  speed-up over the naive loop: {figures['train_speedup']:.2f}x")
    peak_bf16 = figures["matmul_gflops_bf16"]
    print(f"bfloat16 matmul peak: {peak_bf16:.1f} GFLOP/s (median of "
          f"{', '.join(f'{p:.1f}' for p in figures['matmul_gflops_bf16_rounds'])}); the CPU's "
          f"bfloat16 instructions: {figures['cpu_bf16']}")
    _print_training("pipeline loop, train.precision=bfloat16 (5 x all N)",
                    figures["train_fused_bf16"], peak, peak_bf16)
    figures["train_speedup_bf16"] = (figures["train_fused_bf16"]["queries_per_s"]
                                     / figures["train_naive"]["queries_per_s"])
    print(f"  speed-up over the naive loop: {figures['train_speedup_bf16']:.2f}x")
    _print_training("decoder alone, autograd (5 x all N)", figures["decoder_naive"], peak)
    _print_training("decoder alone, fused step (5 x all N)", figures["decoder_fused"], peak)
    figures["decoder_speedup"] = (figures["decoder_fused"]["queries_per_s"]
                                  / figures["decoder_naive"]["queries_per_s"])
    print(f"  speed-up of the decoder's step: {figures['decoder_speedup']:.2f}x")
    _print_training("decoder alone, fused step in bfloat16 (5 x all N)",
                    figures["decoder_fused_bf16"], peak, peak_bf16)
    figures["decoder_speedup_bf16"] = (figures["decoder_fused_bf16"]["queries_per_s"]
                                       / figures["decoder_naive"]["queries_per_s"])
    print(f"  speed-up of the decoder's step: {figures['decoder_speedup_bf16']:.2f}x")
    _print_training(f"pipeline loop, experiment=paper_cpu recipe ({recipe.batch_size} x "
                    f"{recipe.queries_per_abrdf})", figures["train_paper_recipe"], peak)
    figures["encoder_abrdfs_per_s"] = encoder_throughput(32, channels)
    print(f"encoder: {figures['encoder_abrdfs_per_s']:.0f} ABRDFs/s (forward + backward)")
    seconds = reconstruction_seconds(256)
    figures["reconstruct_queries_per_s"] = 256 * N_PAPER / seconds
    figures["reconstruct_neural_btf_s"] = M_PAPER * N_PAPER / figures["reconstruct_queries_per_s"]
    figures["reconstruct_clustered_k2000_s"] = reconstruction_seconds(2000, repeats=1)
    print(f"reconstruction: {figures['reconstruct_queries_per_s'] / 1e6:.3f} M queries/s; "
          f"Neural BTF, all {M_PAPER} x {N_PAPER}: {figures['reconstruct_neural_btf_s']:.0f} s; "
          f"clustered k = 2000 (decoded once): {figures['reconstruct_clustered_k2000_s']:.1f} s")
    if args.paper_run:
        figures["paper_run"] = paper_run(args.runs, args.paper_run, threads)
        for variant, row in figures["paper_run"].items():
            print(f"paper-size run, {variant} ({args.paper_run} training steps): "
                  f"{row['wall_s']:.0f} s wall, peak RSS {row['peak_rss_mb']:.0f} MiB")
            for stage in ("load", "crop", "preprocess", "pca", "kmeans", "representatives",
                          "train", "evaluate"):
                if f"{stage}_seconds" in row:
                    print(f"  {stage:16s} {row[f'{stage}_seconds']:8.1f} s "
                          f"{row[f'{stage}_peak_rss_mb']:8.0f} MiB")
    if args.load_size:
        figures.update(load_times(args.runs, args.load_size))
        cold = "cold page cache" if figures["load_cold"] else "page cache NOT dropped"
        print(f"load {figures['load_images']} JPEGs of {args.load_size}^2: decode "
              f"{figures['load_decode_s']:.1f} s ({cold}), from the stage cache "
              f"{figures['load_cached_s']:.2f} s")
    if not args.no_mlflow:
        _record(args.runs, figures)
    print(json.dumps(figures))
    return figures


def _flatten(figures: dict, prefix: str = "") -> dict:
    flat = {}
    for key, value in figures.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}_"))
        elif isinstance(value, int | float) and not isinstance(value, bool):
            flat[f"{prefix}{key}"] = value
    return flat


def _record(runs: str, figures: dict) -> None:
    import mlflow

    from pipeline.core.tracking import environment_tags, init_store

    experiment_id = init_store(runs, "bench")
    with mlflow.start_run(experiment_id=experiment_id, tags=environment_tags()):
        mlflow.log_metrics(_flatten(figures))
        mlflow.log_params({k: figures[k] for k in ("threads", "machine", "device", "torch")})


if __name__ == "__main__":
    main()
