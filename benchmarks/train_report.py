"""What ``python -m benchmarks.train`` prints: the training loops' figures as a table of
steps, queries and shares of the machine's peak, the ratios between loops, and the GPU's
figures (:mod:`benchmarks.train_figures` measures them)."""

from __future__ import annotations

import os

from benchmarks.train_child import OPENMP_SPIN_VARIABLES


def _print_training(name: str, row: dict, peak: float, peak_bf16: float | None = None) -> None:
    """One loop's line; a bfloat16 loop gets its share of both peaks (``share_of_peak``
    and ``share_of_bf16_peak`` in the JSON)."""
    row["share_of_peak"] = row["gflops"] / peak
    shares = f"{row['share_of_peak']:.0%} of the float32 peak"
    if peak_bf16 is not None:
        row["share_of_bf16_peak"] = row["gflops"] / peak_bf16
        shares += f", {row['share_of_bf16_peak']:.0%} of the bfloat16 peak"
    print(
        f"training {name}: {row['queries_per_s'] / 1e6:.3f} M queries/s, "
        f"{row['gflops']:.1f} GFLOP/s = {shares}, {row['steps_per_s']:.1f} steps/s"
    )


def _ratio(figures: dict, key: str, faster: str, slower: str, what: str) -> None:
    """``figures[key]``: the queries/s of loop ``faster`` over those of ``slower``."""
    figures[key] = figures[faster]["queries_per_s"] / figures[slower]["queries_per_s"]
    print(f"  {what}: {figures[key]:.3f}x")


def _print_paths(figures: dict, precision: str) -> None:
    """The pipeline's loop at the paper's batch in ``precision``, default and tuned."""
    suffix = "_bf16" if precision == "bfloat16" else ""
    peak = figures["matmul_gflops"]
    peak_bf16 = figures["matmul_gflops_bf16"] if suffix else None
    default, tuned = f"train_default{suffix}", f"train_tuned{suffix}"
    figures[f"train_fused{suffix}"] = figures[default]
    _print_training(
        f"pipeline loop, {precision}, default (5 x all N)", figures[default], peak, peak_bf16
    )
    _ratio(
        figures, f"train_speedup{suffix}", default, "train_naive", "speed-up over the naive loop"
    )
    _print_training(
        f"pipeline loop, {precision}, opt-in tuning (5 x all N)", figures[tuned], peak, peak_bf16
    )
    _ratio(
        figures,
        f"tuning_speedup{suffix}",
        tuned,
        default,
        "what the opt-in tuning buys (tuned / default)",
    )


def print_training(figures: dict, recipe, bf16_skipped: str | None) -> None:
    """The training figures' lines; adds the ratios (``train_speedup``,
    ``tuning_speedup``, ...) and ``train_fused`` (the default path's figures again)."""
    peak, threads, tuning = figures["matmul_gflops"], figures["threads"], figures["tuning"]
    print(
        f"matmul peak: {peak:.1f} GFLOP/s (median of "
        f"{', '.join(f'{p:.1f}' for p in figures['matmul_gflops_rounds'])}, one per round "
        f"of the training loops; {threads} threads, device {figures['device']}; the "
        f"training figures below run on the CPU)"
    )
    ops = "C++ kernels" if figures["kernels"] else "plain torch ops (the kernels did not build)"
    awake = tuning["keep_awake_processes"]
    print(
        f"default path: fused step with {ops}, no machine tuning, libgomp's defaults; "
        f"opt-in tuning: train.keep_awake=true ({awake or 'no'} spinning processes here), "
        f"train.omp_spin_count={tuning['omp_spin_count']}, train.reuse_freed_memory=true"
        f"{'' if tuning['reuse_freed_memory'] else ' (no effect: not glibc)'}"
    )
    if set(os.environ) & set(OPENMP_SPIN_VARIABLES):
        print(
            f"note: {'/'.join(OPENMP_SPIN_VARIABLES)} set in this environment: the loops "
            "run in this process (decoder, recipe, matmul) run with it, the child processes "
            "without"
        )
    _print_training("naive autograd loop (5 x all N)", figures["train_naive"], peak)
    _print_paths(figures, "float32")
    _print_training(
        "pipeline loop, float32, train.backend=autograd (5 x all N)",
        figures["train_autograd"],
        peak,
    )
    _ratio(
        figures,
        "backend_speedup",
        "train_default",
        "train_autograd",
        "the fused backend over the autograd backend, same run",
    )
    if bf16_skipped is None:
        print(
            f"bfloat16 matmul peak: {figures['matmul_gflops_bf16']:.1f} GFLOP/s (median of "
            f"{', '.join(f'{p:.1f}' for p in figures['matmul_gflops_bf16_rounds'])}); "
            f"the CPU's bfloat16 instructions: {figures['cpu_bf16']}"
        )
        _print_paths(figures, "bfloat16")
    else:
        print(f"bfloat16 figures skipped: {bf16_skipped}")
    _print_training("decoder alone, autograd (5 x all N)", figures["decoder_naive"], peak)
    _print_training("decoder alone, fused step (5 x all N)", figures["decoder_fused"], peak)
    _ratio(
        figures,
        "decoder_speedup",
        "decoder_fused",
        "decoder_naive",
        "speed-up of the decoder's step",
    )
    if bf16_skipped is None:
        _print_training(
            "decoder alone, fused step in bfloat16 (5 x all N)",
            figures["decoder_fused_bf16"],
            peak,
            figures["matmul_gflops_bf16"],
        )
        _ratio(
            figures,
            "decoder_speedup_bf16",
            "decoder_fused_bf16",
            "decoder_naive",
            "speed-up of the decoder's step",
        )
    _print_training(
        f"pipeline loop, default, experiment=paper_cpu recipe ({recipe.batch_size} x "
        f"{recipe.queries_per_abrdf})",
        figures["train_paper_recipe"],
        peak,
    )


def print_cuda(figures: dict, recipe) -> None:
    """The GPU's training lines; adds ``backend_speedup`` and ``bf16_speedup``."""
    peak, peak_bf16 = figures["matmul_gflops"], figures["matmul_gflops_bf16"]
    print(
        f"matmul peak on {figures['device']}: float32 {peak:.0f} GFLOP/s, bfloat16 "
        f"{peak_bf16:.0f} GFLOP/s (medians of one per round of the training loops)"
    )
    _print_training(
        "pipeline loop on the GPU, train.backend=autograd, float32 (5 x all N)",
        figures["train_autograd"],
        peak,
    )
    _print_training(
        "pipeline loop on the GPU, train.backend=autograd, bfloat16 (5 x all N)",
        figures["train_autograd_bf16"],
        peak,
        peak_bf16,
    )
    _ratio(
        figures,
        "bf16_speedup",
        "train_autograd_bf16",
        "train_autograd",
        "bfloat16 over float32, autograd backend",
    )
    _print_training(
        "pipeline loop on the GPU, train.backend=fused, float32 (5 x all N)",
        figures["train_fused"],
        peak,
    )
    _ratio(
        figures,
        "backend_speedup",
        "train_fused",
        "train_autograd",
        "the fused backend over the autograd backend, same run",
    )
    _print_training(
        f"pipeline loop on the GPU, experiment=paper_cpu recipe ({recipe.batch_size} x "
        f"{recipe.queries_per_abrdf})",
        figures["train_paper_recipe"],
        peak,
    )
    paper_steps = recipe.epochs * (recipe.epoch_texels // recipe.batch_size)
    print(
        f"  at this rate a paper_cpu model's {paper_steps} steps take "
        f"{paper_steps / figures['train_paper_recipe']['steps_per_s']:.0f} s"
    )
