"""The paper experiment at full size (M = 10000, N = 6561) on the synthetic BTF (slow), and
the sizes that ``python -m benchmarks.train`` counts its figures with."""

import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import torch
from helpers import compose_config

from pipeline.btf.model import Decoder
from pipeline.data.directions import N_DIRECTIONS

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_paper_experiment_produces_table1_with_the_papers_bytes(tmp_path):
    runs = tmp_path / "runs"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "pipeline",
            "-m",
            "experiment=paper",
            "train.max_steps=10",
            "btf.interpolation.offgrid=4",
            f"paths.runs={runs}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=3600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    sizes = pd.read_csv(runs / "tables" / "paper" / "table1_sizes.csv").set_index("model")
    neural = ["Neural BTF", "k = 500", "k = 1000", "k = 2000"]
    # Each clustered model has a second row: its bytes with a per-texel scale stored.
    scaled = [m for m in sizes.index if m.endswith(" + per-texel scale")]
    assert scaled == [f"{k} + per-texel scale" for k in neural[1:]]
    assert set(sizes.loc[scaled, "per-texel scale [B]"]) == {40_000}  # M float32
    plain = [m for m in sizes.index if m not in scaled]
    assert plain[:4] == neural and len(plain) == 5 and plain[4].startswith("PCA c = ")
    assert sizes.loc[plain[4], "total [B]"] <= sizes.loc["k = 1000", "total [B]"]  # matched
    sizes = sizes.loc[neural]
    assert set(sizes["decoder [B]"]) == {97_532}
    assert list(sizes["latents [B]"]) == [320_000, 16_000, 32_000, 64_000]
    assert list(sizes["list [B]"]) == [0, 40_000, 40_000, 40_000]
    assert set(sizes["original [B]"]) == {787_320_000}


@pytest.mark.slow
def test_bench_prints_its_figures_as_json(capsys):
    import json

    from benchmarks.train import main

    figures = main(["steps=2", "mlflow=false"])
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert json.loads(last) == json.loads(json.dumps(figures))
    assert figures["decoder_parameters"] == 24_383
    assert figures["encoder_channels"] == [16, 32, 64]

    def rate(key):
        return figures[key]["queries_per_s"]

    # The default training path (train_fused is its figures again) against the opt-in tuning,
    # each timed in a child process of its own; bfloat16 only where oneDNN supports it.
    bf16 = "bf16_skipped" not in figures
    suffixes = ["", "_bf16"] if bf16 else [""]
    keys = ["train_naive", "train_autograd", "train_paper_recipe", "decoder_naive", "decoder_fused"]
    for suffix in suffixes:
        keys += [f"train_default{suffix}", f"train_tuned{suffix}", f"train_fused{suffix}"]
    if bf16:
        keys.append("decoder_fused_bf16")
    # Queries per step from the configs, not from the bench: the paper's batch of ABRDFs
    # at all 81 x 81 directions, and the CPU recipe's batch for its own loop; the FLOPs
    # per query from the decoder's layers.
    per_step = {
        key: compose_config("experiment=paper").train.batch_size * N_DIRECTIONS**2 for key in keys
    }
    recipe = compose_config("experiment=paper_cpu").train
    per_step["train_paper_recipe"] = recipe.batch_size * recipe.queries_per_abrdf
    flops_per_query = 3 * 2 * _decoder_multiply_adds()  # backward ~ twice the forward
    for key in keys:
        row = figures[key]
        assert rate(key) > 0 and row["share_of_peak"] > 0, key
        assert row["steps_per_s"] * per_step[key] == pytest.approx(rate(key)), key
        assert row["gflops"] * 1e9 == pytest.approx(rate(key) * flops_per_query), key
        if key.endswith("_bf16"):
            assert row["share_of_bf16_peak"] > 0, key
    ratios = ["decoder_speedup", "backend_speedup"] + [
        f"{name}_speedup{suffix}" for suffix in suffixes for name in ("train", "tuning")
    ]
    if bf16:
        ratios.append("decoder_speedup_bf16")
    assert all(figures[name] > 0 for name in ratios)
    for suffix in suffixes:
        assert figures[f"train_fused{suffix}"] == figures[f"train_default{suffix}"]
    assert figures["tuning"]["omp_spin_count"] == 30_000
    assert figures["tuning"]["keep_awake_processes"] >= 0
    if not bf16:
        assert "train_tuned_bf16" not in figures and "matmul_gflops_bf16" not in figures
    assert figures["cpu_bf16"] in (
        "amx_bf16,avx512_bf16",
        "amx_bf16",
        "avx512_bf16",
        "none",
        "unknown",
    )
    # Every texel of the paper's crop at every direction.
    texels = compose_config("experiment=paper").btf.crop.size ** 2
    assert figures["reconstruct_neural_btf_s"] == pytest.approx(
        texels * N_DIRECTIONS**2 / figures["reconstruct_queries_per_s"]
    )


def _decoder_multiply_adds() -> int:
    """Multiply-adds per query of the decoder the pipeline trains: its layers' weights."""
    return sum(
        layer.weight.numel() for layer in Decoder().modules() if isinstance(layer, torch.nn.Linear)
    )


def test_bench_counts_the_decoders_flops_and_the_papers_sizes():
    """Catches the bench's written-out multiply-adds or paper sizes drifting from the
    decoder and the paper's config: every GFLOP/s and reconstruction time would be off."""
    from benchmarks.train_figures import DECODER_MACS, M_PAPER, TRAIN_FLOPS_PER_QUERY
    from benchmarks.train_loops import N_PAPER

    assert DECODER_MACS == _decoder_multiply_adds()
    assert TRAIN_FLOPS_PER_QUERY == 3 * 2 * _decoder_multiply_adds()
    assert M_PAPER == compose_config("experiment=paper").btf.crop.size ** 2
    assert N_PAPER == N_DIRECTIONS**2


def test_the_gpu_figures_print_on_a_machine_without_one(capsys):
    """``device=cuda``'s printing runs only on a GPU: fed made-up figures here, it prints
    every loop, the ratios and the time a paper_cpu model's steps take at its rate."""
    from omegaconf import OmegaConf

    from benchmarks.train_report import print_cuda
    from pipeline.core.methods import CONF_DIR as CONF

    recipe = OmegaConf.load(CONF / "train" / "cpu.yaml")

    def loop(steps_per_s, queries):
        return {
            "queries_per_s": steps_per_s * queries,
            "gflops": 1000.0,
            "steps_per_s": steps_per_s,
        }

    paper = 5 * N_DIRECTIONS**2
    figures = {
        "device": "cuda (test)",
        "matmul_gflops": 50000.0,
        "matmul_gflops_bf16": 700000.0,
        "train_autograd": loop(200.0, paper),
        "train_autograd_bf16": loop(100.0, paper),
        "train_fused": loop(400.0, paper),
        "train_paper_recipe": loop(7488 / 30, recipe.batch_size * recipe.queries_per_abrdf),
    }
    print_cuda(figures, recipe)
    out = capsys.readouterr().out
    assert figures["bf16_speedup"] == pytest.approx(0.5)
    assert figures["backend_speedup"] == pytest.approx(2.0)
    assert "bfloat16 over float32, autograd backend: 0.500x" in out
    assert "a paper_cpu model's 7488 steps take 30 s" in out
