"""The paper experiment at full size (M = 10000, N = 6561) on the synthetic BTF. Slow."""

import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_paper_experiment_produces_table1_with_the_papers_bytes(tmp_path):
    runs = tmp_path / "runs"
    done = subprocess.run(
        [sys.executable, "-m", "pipeline", "-m", "experiment=paper", "train.max_steps=10",
         "btf.interpolation.offgrid=4", f"paths.runs={runs}"],
        cwd=ROOT, capture_output=True, text=True, timeout=3600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    sizes = pd.read_csv(runs / "tables" / "table1_sizes.csv").set_index("model")
    neural = ["Neural BTF", "k = 500", "k = 1000", "k = 2000"]
    assert list(sizes.index[:4]) == neural and sizes.index[4].startswith("PCA c = ")
    assert sizes.iloc[4]["total [B]"] <= sizes.loc["k = 1000", "total [B]"]  # matched bytes
    sizes = sizes.loc[neural]
    assert set(sizes["decoder [B]"]) == {97_532}
    assert list(sizes["latents [B]"]) == [320_000, 16_000, 32_000, 64_000]
    assert list(sizes["list [B]"]) == [0, 40_000, 40_000, 40_000]
    assert set(sizes["original [B]"]) == {787_320_000}


@pytest.mark.slow
def test_bench_prints_its_figures_as_json(capsys):
    import json

    from pipeline.btf.fast.bench import main

    figures = main(["--steps", "2", "--no-mlflow"])
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
    keys = ["train_naive", "train_paper_recipe", "decoder_naive", "decoder_fused"]
    for suffix in suffixes:
        keys += [f"train_default{suffix}", f"train_tuned{suffix}", f"train_fused{suffix}"]
    if bf16:
        keys.append("decoder_fused_bf16")
    for key in keys:
        assert rate(key) > 0 and figures[key]["gflops"] > 0, key
    for suffix in suffixes:
        assert figures[f"train_fused{suffix}"] == figures[f"train_default{suffix}"]
        assert figures[f"train_speedup{suffix}"] == pytest.approx(
            rate(f"train_default{suffix}") / rate("train_naive"))
        assert figures[f"tuning_speedup{suffix}"] > 0
        assert figures[f"tuning_speedup{suffix}"] == pytest.approx(
            rate(f"train_tuned{suffix}") / rate(f"train_default{suffix}"))
    assert figures["tuning"]["omp_spin_count"] == 30_000
    assert figures["tuning"]["keep_awake_processes"] >= 0
    assert figures["decoder_speedup"] == pytest.approx(
        rate("decoder_fused") / rate("decoder_naive"))
    if bf16:
        assert figures["decoder_speedup_bf16"] == pytest.approx(
            rate("decoder_fused_bf16") / rate("decoder_naive"))
        row = figures["decoder_fused_bf16"]
        assert row["share_of_bf16_peak"] == pytest.approx(
            row["gflops"] / figures["matmul_gflops_bf16"])
    else:
        assert "train_tuned_bf16" not in figures and "matmul_gflops_bf16" not in figures
    row = figures["decoder_fused"]
    assert row["share_of_peak"] == pytest.approx(row["gflops"] / figures["matmul_gflops"])
    assert figures["cpu_bf16"] in ("amx_bf16,avx512_bf16", "amx_bf16", "avx512_bf16", "none",
                                   "unknown")
    assert figures["reconstruct_neural_btf_s"] == pytest.approx(
        10_000 * 6561 / figures["reconstruct_queries_per_s"])
