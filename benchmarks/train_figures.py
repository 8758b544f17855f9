"""``python -m benchmarks.train``: speed and memory figures of method A at the paper's sizes.

Prints, in one run on one machine:

- the float32 matrix-multiply peak (the yardstick), at the threads the figures use;
- training throughput at the paper's batch (5 ABRDFs x all 6561 directions per step) of a
  naive autograd loop and of ``pipeline.btf.train.train`` on its default path (the fused,
  chunked, threaded step with its C++ kernels, no machine tuning), with the opt-in
  tuning (``train.keep_awake``, ``train.omp_spin_count``, ``train.reuse_freed_memory``:
  :mod:`pipeline.btf.fast.tuning`), and with ``train.backend=autograd`` (the plain
  PyTorch step, :mod:`pipeline.btf.backends`), each in a child process of its own
  (:mod:`benchmarks.train_child`; the loops: :mod:`benchmarks.train_loops`),
  in queries/s, GFLOP/s, steps/s and as a share of the peak, and the two backends' ratio;
  the default path at the recipe ``experiment=paper_cpu`` uses (``conf/train/cpu.yaml``:
  32 ABRDFs x 256 directions); the decoder alone (autograd against the fused step, no
  encoder);
- the same in bfloat16 (``train.precision=bfloat16``), where oneDNN supports bfloat16 on
  this CPU (AVX-512 or AMX); elsewhere its products take emulated code paths far slower
  than float32's, and the bench skips them and says so;
- encoder throughput (ABRDFs/s, forward and backward);
- reconstruction throughput: Neural BTF (all M x N) and clustered (k x N decoded once);
- with ``paper_run=STEPS``: time and peak resident memory of every stage of a paper-size run
  on the synthetic BTF (one Neural BTF and one clustered job, each in its own process);
- with ``load_size=256``: loading a 6561-file UBO2003 folder, decoded and cached.

With ``device=cuda``, only the training loops, on the GPU: ``pipeline.btf.train.train`` at
the paper's batch with the autograd backend in float32 and in bfloat16 (autocast) and with
the fused step (torch ops, one chunk), and at ``experiment=paper_cpu``'s batch, against
the GPU's matmul peaks; then
``paper_run`` and ``load_size`` when asked.

The last line is one JSON object, also logged to MLflow (experiment ``bench`` under
``paths.runs``). Timings are medians of repeats; compare them as ratios within one run, never
across runs on a shared machine. A measurement tool, not a test. Its keys:

- ``matmul_gflops`` (``_rounds``: each round's), ``matmul_gflops_bf16`` (``_rounds``);
- each loop's ``queries_per_s``, ``gflops``, ``steps_per_s``, ``share_of_peak`` (and
  ``share_of_bf16_peak`` for bfloat16 loops), under ``train_naive``, ``train_default``
  (``train_fused``: the same figures), ``train_tuned``, ``train_autograd``,
  ``train_paper_recipe``, ``decoder_naive``, ``decoder_fused``, and with ``_bf16``
  ``train_default_bf16`` (``train_fused_bf16``), ``train_tuned_bf16``,
  ``decoder_fused_bf16``; with ``device=cuda`` ``train_autograd``,
  ``train_autograd_bf16``, ``train_fused`` and ``train_paper_recipe`` only;
- the ratios ``train_speedup`` (default / naive), ``tuning_speedup`` (tuned / default),
  ``decoder_speedup`` (fused / autograd), each also with ``_bf16``, ``backend_speedup``
  (fused backend / autograd backend); with ``device=cuda`` ``backend_speedup`` and
  ``bf16_speedup`` (autograd bfloat16 / float32);
- ``tuning``: what the opt-in tuning does here (``keep_awake_processes``, spinning
  processes, 0 where none start; ``omp_spin_count``; ``reuse_freed_memory``: glibc found);
  ``kernels``: whether the C++ kernels built; ``cpu_bf16``: the CPU's native bfloat16
  instructions (``amx_bf16``, ``avx512_bf16`` or ``none``); ``bf16_skipped``: why the
  ``_bf16`` keys are missing, where they are;
- ``encoder_abrdfs_per_s``, ``reconstruct_queries_per_s``, ``reconstruct_neural_btf_s``,
  ``reconstruct_clustered_k2000_s``; ``paper_run.<variant>.*`` and ``load_*`` with
  ``paper_run`` and ``load_size``; ``device``, ``threads``, ``machine``, ``torch``,
  ``decoder_parameters``, ``encoder_channels``.

    python -m benchmarks.train [threads=2] [steps=30] [device=cuda] [paper_run=200]
                               [load_size=256] [paths.runs=runs] [mlflow=false]

Its settings (``python -m benchmarks.train --help``) are read without torch:
:mod:`benchmarks.train_settings`.
"""

from __future__ import annotations

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

from benchmarks.train_child import TUNED, Isolated
from benchmarks.train_loops import N_PAPER, decoder_training, paper_channels, pipeline_training
from benchmarks.train_report import print_cuda, print_training
from benchmarks.train_settings import DECODER_MACS, PROG, BenchSettings
from pipeline.btf.fast import kernels
from pipeline.btf.model import Decoder, Encoder, parameter_count
from pipeline.core.methods import CONF_DIR

M_PAPER = 10_000
TRAIN_FLOPS_PER_QUERY = 3 * 2 * DECODER_MACS  # forward + backward ~ 3x forward


def _median_seconds(fn, repeats: int, device: str = "cpu") -> float:
    def timed():
        fn()
        if device == "cuda":  # the work queued on the GPU, not just its launch
            torch.cuda.synchronize()

    timed()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        timed()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def matmul_peak(
    size: int | None = None, repeats: int = 5, dtype=torch.float32, device: str = "cpu"
) -> float:
    """GFLOP/s of a square matrix product (float32, or bfloat16 for the bfloat16 loops) on
    ``device``; ``size`` None: 2048 on the CPU, 8192 on CUDA (a GPU needs the larger to
    reach its peak)."""
    size = size or (8192 if device == "cuda" else 2048)
    a = torch.randn(size, size, dtype=dtype, device=device)
    b = torch.randn(size, size, dtype=dtype, device=device)
    return 2 * size**3 / _median_seconds(lambda: a @ b, repeats, device) / 1e9


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
    return {
        "queries_per_s": rate,
        "gflops": rate * TRAIN_FLOPS_PER_QUERY / 1e9,
        "steps_per_s": 1 / seconds_per_step,
    }


def interleaved(
    loops: dict,
    queries_per_step: dict,
    steps: int,
    bf16: bool,
    rounds: int = 3,
    device: str = "cpu",
) -> dict:
    """Time the loops in turn, ``rounds`` times after one warm-up each, so that a machine
    that slows down or speeds up meanwhile affects all of them alike; medians per loop.
    The float32 matmul peak (and with ``bf16`` the bfloat16 one) is measured in every round
    too (``matmul_gflops``, ``matmul_gflops_bf16``: the medians; ``..._rounds``: each
    round's), so the shares of them compare like with like; on ``device``."""
    for run in loops.values():
        run()
    times = {name: [] for name in loops}
    peaks = {"matmul_gflops": []} | ({"matmul_gflops_bf16": []} if bf16 else {})
    for _ in range(rounds):
        for key, rounds_of_key in peaks.items():
            rounds_of_key.append(
                matmul_peak(dtype=torch.bfloat16 if "bf16" in key else torch.float32, device=device)
            )
        for name, run in loops.items():
            times[name].append(run() / steps)
    figures = {
        name: _rates(queries_per_step[name], float(np.median(t))) for name, t in times.items()
    }
    for key, rounds_of_key in peaks.items():
        figures |= {key: float(np.median(rounds_of_key)), f"{key}_rounds": rounds_of_key}
    return figures


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


def paper_run(runs: str, steps: int, threads: int, device: str = "cpu") -> dict:
    """Per-stage seconds and peak RSS of paper-size jobs on the synthetic BTF (128 x 128,
    crop 100 x 100), one process per job, with ``steps`` training steps each on
    ``device`` (``train.device``; the backend: ``train.backend=auto``'s)."""
    import mlflow

    from pipeline.core.store import use_store

    root = Path(runs) / "bench_paper"
    figures: dict = {}
    for variant, model in (
        ("neural_btf", ["model=neural_btf"]),
        ("k1000", ["model=clustered", "model.k=1000"]),
    ):
        command = [
            sys.executable,
            "-m",
            "pipeline",
            "experiment=paper",
            *model,
            f"train.max_steps={steps}",
            f"train.threads={threads}",
            f"train.device={device}",
            f"paths.runs={root}",
            "tracking.experiment=bench_paper",
        ]
        start = time.perf_counter()
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - start
        use_store(str(root))
        run = mlflow.search_runs(
            experiment_names=["bench_paper"],
            output_format="list",
            order_by=["attributes.start_time DESC"],
            max_results=1,
        )[0]
        metrics = run.data.metrics
        row = {
            "wall_s": wall,
            "peak_rss_mb": metrics["memory/peak_rss_mb"],
            "train_queries_per_s": metrics["train_queries"] / metrics["train_seconds"],
        }
        for name, value in metrics.items():  # time/<stage>_seconds, memory/<stage>_peak_rss_mb
            group, _, stage_metric = name.partition("/")
            if group in ("time", "memory") and stage_metric != "peak_rss_mb":
                row[stage_metric] = value
        figures[variant] = row
    return figures


def load_times(runs: str, size: int) -> dict:
    """Seconds to load a full UBO2003-layout folder (6561 JPEGs of size x size) through the
    load stage: decoded (a cache miss) and again from the stage cache (a hit)."""
    import shutil

    from hydra import compose, initialize_config_dir

    from pipeline.btf.stages import load
    from pipeline.btf.synthetic_dataset import write_synthetic_btf
    from pipeline.core.stage import Context

    root = write_synthetic_btf(Path(runs) / "data" / f"bench_ubo2003_{size}", size=size, seed=0)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                "experiment=smoke",
                "dataset=ubo2003",
                f"dataset.root={root}",
                "dataset.views=null",
                f"paths.runs={runs}",
                f"paths.cache={Path(runs) / 'bench_cache'}",
            ],
        )
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


def bfloat16_skip_reason() -> str | None:
    """Why this CPU gets no bfloat16 figures, or None where oneDNN supports bfloat16 here
    (AVX-512 or AMX): elsewhere its bfloat16 products take emulated code paths, orders of
    magnitude slower than float32's, which would stretch the bench to hours."""
    if torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported():
        return None
    return (
        "oneDNN does not support bfloat16 on this CPU (torch.ops.mkldnn."
        "_is_mkldnn_bf16_supported() is False; native bfloat16 instructions: "
        f"{cpu_bfloat16_support()}): its bfloat16 products would take slow emulated paths"
    )


def tuning_in_effect(threads: int) -> dict:
    """What :data:`~benchmarks.train_child.TUNED` does on this machine at ``threads``
    threads: the spinning processes ``keep_awake`` starts (none under a CPU quota, or with
    fewer threads than cores: :func:`pipeline.btf.fast.tuning.keep_cpus_awake`), the spin
    count, and whether glibc's malloc is there to keep freed memory."""
    from pipeline.btf.fast.tuning import can_keep_awake, glibc

    cpus = len(os.sched_getaffinity(0)) if can_keep_awake() else 0
    return {
        "keep_awake_processes": cpus if cpus and threads >= max(2, cpus) else 0,
        "omp_spin_count": TUNED["omp_spin_count"],
        "reuse_freed_memory": glibc() is not None,
    }


def training_figures(steps: int, threads: int, channels, recipe, bf16: bool) -> dict:
    """Every training loop's figures, timed in turn (:func:`interleaved`). The naive loops
    and the pipeline's loop at the paper's batch, default and tuned, run in child processes
    (:class:`~benchmarks.train_child.Isolated`); the recipe's loop and the fused
    decoder step in this one."""
    paper = {
        "train_naive": Isolated("naive", steps, threads),
        "train_default": Isolated("train", steps, threads),
        "train_tuned": Isolated("train", steps, threads, tuned=True),
        "train_autograd": Isolated("train", steps, threads, backend="autograd"),
    }
    if bf16:
        paper |= {
            "train_default_bf16": Isolated("train", steps, threads, precision="bfloat16"),
            "train_tuned_bf16": Isolated("train", steps, threads, tuned=True, precision="bfloat16"),
        }
    children = paper | {"decoder_naive": Isolated("decoder_naive", steps, threads)}
    loops = children | {"decoder_fused": decoder_training(True, steps, threads)}
    if bf16:
        loops["decoder_fused_bf16"] = decoder_training(True, steps, threads, "bfloat16")
    loops["train_paper_recipe"] = pipeline_training(
        recipe.batch_size,
        recipe.queries_per_abrdf,
        steps,
        channels,
        threads,
        optimizer=recipe.optimizer,
        lr=recipe.lr,
    )
    queries = {name: 5 * N_PAPER for name in loops}
    queries["train_paper_recipe"] = recipe.batch_size * recipe.queries_per_abrdf
    try:
        return interleaved(loops, queries, steps, bf16)
    finally:
        for child in children.values():
            child.close()


def cuda_figures(steps: int, channels, recipe) -> dict:
    """``pipeline.btf.train.train`` on the GPU, timed in turn (:func:`interleaved`): at the
    paper's batch the autograd backend in float32 and in bfloat16 (autocast) and the fused
    step (torch ops, one chunk), and the autograd backend at ``experiment=paper_cpu``'s
    batch (``recipe``), against the GPU's matmul peaks."""
    loops = {
        "train_autograd": pipeline_training(
            5, -1, steps, channels, 1, backend="autograd", device="cuda"
        ),
        "train_autograd_bf16": pipeline_training(
            5, -1, steps, channels, 1, precision="bfloat16", backend="autograd", device="cuda"
        ),
        "train_fused": pipeline_training(5, -1, steps, channels, 1, backend="fused", device="cuda"),
        "train_paper_recipe": pipeline_training(
            recipe.batch_size,
            recipe.queries_per_abrdf,
            steps,
            channels,
            1,
            optimizer=recipe.optimizer,
            lr=recipe.lr,
            backend="autograd",
            device="cuda",
        ),
    }
    queries = dict.fromkeys(loops, 5 * N_PAPER)
    queries["train_paper_recipe"] = recipe.batch_size * recipe.queries_per_abrdf
    return interleaved(loops, queries, steps, bf16=True, device="cuda")


def run(settings: BenchSettings) -> dict:
    """Measure, print and record the figures (the module's docstring); returns them."""
    if settings.threads:
        torch.set_num_threads(settings.threads)
    threads = torch.get_num_threads()
    channels = paper_channels()
    on_cuda = settings.device == "cuda"
    if on_cuda and not torch.cuda.is_available():
        print(f"{PROG}: error: device=cuda but torch sees no CUDA device", file=sys.stderr)
        raise SystemExit(2)
    bf16_skipped = None if on_cuda else bfloat16_skip_reason()
    figures: dict = {
        "device": f"cuda ({torch.cuda.get_device_name()})" if on_cuda else "cpu",
        "threads": threads,
        "machine": platform.processor() or platform.machine(),
        "torch": torch.__version__,
        "cpu_bf16": cpu_bfloat16_support(),
        "decoder_parameters": parameter_count(Decoder()),
        "encoder_channels": list(channels),
    }
    recipe = OmegaConf.load(CONF_DIR / "train" / "cpu.yaml")
    if on_cuda:
        figures |= cuda_figures(settings.steps, channels, recipe)
        print_cuda(figures, recipe)
    else:
        # Built here, once, before the child processes load them.
        figures |= {"kernels": kernels.available(), "tuning": tuning_in_effect(threads)}
        if bf16_skipped is not None:
            figures["bf16_skipped"] = bf16_skipped
        figures |= training_figures(settings.steps, threads, channels, recipe, bf16_skipped is None)
        print_training(figures, recipe, bf16_skipped)
        other_figures(figures, channels)
    if settings.paper_run:
        figures["paper_run"] = paper_run(
            settings.runs, settings.paper_run, threads, settings.device
        )
        for variant, row in figures["paper_run"].items():
            print(
                f"paper-size run, {variant} ({settings.paper_run} training steps on "
                f"{settings.device}): {row['wall_s']:.0f} s wall, peak RSS "
                f"{row['peak_rss_mb']:.0f} MiB, training {row['train_queries_per_s'] / 1e6:.3f}"
                " M queries/s"
            )
            for stage in (
                "load",
                "crop",
                "preprocess",
                "pca",
                "kmeans",
                "representatives",
                "train",
                "evaluate",
            ):
                if f"{stage}_seconds" in row:
                    print(
                        f"  {stage:16s} {row[f'{stage}_seconds']:8.1f} s "
                        f"{row[f'{stage}_peak_rss_mb']:8.0f} MiB"
                    )
    if settings.load_size:
        figures.update(load_times(settings.runs, settings.load_size))
        cold = "cold page cache" if figures["load_cold"] else "page cache NOT dropped"
        print(
            f"load {figures['load_images']} JPEGs of {settings.load_size}^2: decode "
            f"{figures['load_decode_s']:.1f} s ({cold}), from the stage cache "
            f"{figures['load_cached_s']:.2f} s"
        )
    if settings.mlflow:
        _record(settings.runs, figures)
    print(json.dumps(figures))
    return figures


def other_figures(figures: dict, channels) -> None:
    """The encoder's and the reconstruction's throughput on the CPU, added and printed."""
    figures["encoder_abrdfs_per_s"] = encoder_throughput(32, channels)
    print(f"encoder: {figures['encoder_abrdfs_per_s']:.0f} ABRDFs/s (forward + backward)")
    seconds = reconstruction_seconds(256)
    figures["reconstruct_queries_per_s"] = 256 * N_PAPER / seconds
    figures["reconstruct_neural_btf_s"] = M_PAPER * N_PAPER / figures["reconstruct_queries_per_s"]
    figures["reconstruct_clustered_k2000_s"] = reconstruction_seconds(2000, repeats=1)
    print(
        f"reconstruction: {figures['reconstruct_queries_per_s'] / 1e6:.3f} M queries/s; "
        f"Neural BTF, all {M_PAPER} x {N_PAPER}: {figures['reconstruct_neural_btf_s']:.0f} s; "
        f"clustered k = 2000 (decoded once): {figures['reconstruct_clustered_k2000_s']:.1f} s"
    )


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

    from pipeline.core.run import environment_tags
    from pipeline.core.store import init_store

    experiment_id = init_store(runs, "bench")
    with mlflow.start_run(experiment_id=experiment_id, tags=environment_tags()):
        mlflow.log_metrics(_flatten(figures))
        mlflow.log_params({k: figures[k] for k in ("threads", "machine", "device", "torch")})
