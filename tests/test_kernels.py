"""The fused C++ kernels (pipeline/btf/fast/kernels.py, kernels.cpp) on their own: the build,
its fallback, the ops' checks, and the vector code against the plain loops. The gradients
they make are checked against autograd in tests/test_fused.py."""

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from pipeline.btf.fast import kernels

ROOT = Path(__file__).resolve().parents[1]


def test_kernels_build():
    """Where a C++ compiler is on the machine, the fused kernels must build: a silent
    fallback to torch ops would hide a slower step."""
    if shutil.which("g++") is None and shutil.which("c++") is None:
        pytest.skip("no C++ compiler on this machine; the step falls back to torch ops")
    if os.environ.get("PIPELINE_KERNELS") == "0":
        pytest.skip("PIPELINE_KERNELS=0 turns the kernels off")
    assert kernels.available()


# A compiler that answers torch's version check and fails on every source file, as g++
# without torch's headers would; it notes each compilation in ``compiled``.
_FAILING_COMPILER = """#!/bin/sh
case "$1" in --version|-dumpfullversion|-dumpversion) echo 12.2.0; exit 0;; esac
echo compile >> "$(dirname "$0")/compiled"
echo "kernels.cpp:16:10: fatal error: ATen/ATen.h: No such file or directory" >&2
exit 1
"""

_FALLBACK_SCRIPT = """
import logging, torch
logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
from pipeline.btf.fast import kernels
from pipeline.btf.fast.fused import DecoderStep
from pipeline.btf.model import Decoder
print("available", kernels.available(), kernels.available())
step = DecoderStep(Decoder(), torch.rand(10, 4))
print("fused_kernels", step.fused_kernels)
step.close()
try:
    DecoderStep(Decoder(), torch.rand(10, 4), fused_kernels=True)
except ValueError as error:
    print("refused", error)
"""


def test_a_failed_build_falls_back_to_torch_ops(tmp_path):
    """Where the kernels' build fails (here: the compiler named by ``CXX`` cannot compile,
    into an empty ``TORCH_EXTENSIONS_DIR``), the step says so once, with the compiler's
    error, and runs on torch ops (the same gradient: tests/test_fused.py with
    fused_kernels=False), and refuses to be asked for the kernels."""
    compiler = tmp_path / "c++"
    compiler.write_text(_FAILING_COMPILER)
    compiler.chmod(0o755)
    env = {key: value for key, value in os.environ.items() if key != "PIPELINE_KERNELS"}
    env |= {
        "CXX": str(compiler),
        "TORCH_EXTENSIONS_DIR": str(tmp_path / "extensions"),
        "TORCH_DONT_CHECK_COMPILER_ABI": "1",
    }
    done = subprocess.run(
        [sys.executable, "-c", _FALLBACK_SCRIPT],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    lines = done.stdout.splitlines()
    assert lines[:2] == ["available False False", "fused_kernels False"], done.stdout
    assert re.fullmatch(r"refused fused_kernels=True needs the C\+\+ kernels.*", lines[2])
    # Tried once per process: one compilation, one warning naming the compiler's error.
    assert (tmp_path / "compiled").read_text().splitlines() == ["compile"]
    assert done.stderr.count("did not build") == 1, done.stderr
    assert "fatal error: ATen/ATen.h: No such file" in done.stderr


def test_kernels_refuse_mismatched_inputs():
    if not kernels.available():
        pytest.skip("the fused kernels did not build here (see test_kernels_build)")
    a, w, b, targets = torch.rand(4, 6), torch.rand(3, 6), torch.rand(3), torch.rand(4, 3)
    sums = [torch.zeros(3, 6), torch.zeros(3), torch.zeros(6), torch.zeros((), dtype=torch.float64)]
    output_layer, relu_backward_ = (
        torch.ops.neural_btf.output_layer,
        torch.ops.neural_btf.relu_backward_,
    )
    assert output_layer(a, w, b, targets, 1.0, *sums).shape == (4, 6)
    with pytest.raises(RuntimeError, match="shapes do not match"):
        output_layer(a, torch.rand(3, 5), b, targets, 1.0, *sums)
    with pytest.raises(RuntimeError, match="accumulator type"):
        output_layer(a, w, b, targets.double(), 1.0, *sums)
    with pytest.raises(RuntimeError, match="accumulator type"):
        relu_backward_(torch.rand(4, 6), a, torch.zeros(6, dtype=torch.float64), None, None)
    with pytest.raises(RuntimeError, match="one shape and type"):
        relu_backward_(torch.rand(4, 5), a, None, None, None)
    with pytest.raises(RuntimeError, match="bfloat16, float32 or float64 only"):
        relu_backward_(a.half(), a.half(), None, None, None)


# kernels.cpp with the plain loops only, its ops registered as torch.ops.neural_btf_plain.
PLAIN_PREFIX = "pipeline_btf_kernels_plain"
PLAIN_FLAGS = [*kernels.FLAGS, "-DNEURAL_BTF_GENERIC", "-DNEURAL_BTF_NAMESPACE=neural_btf_plain"]


def load_plain_loops() -> bool:
    """Build (where not built yet) and load the plain loops, after this machine's kernels;
    whether both loaded. Built as the package builds its kernels (:func:`kernels.load`): in
    bounded time, and past a lock that a killed build left (tests/test_kernel_lock.py)."""
    return kernels.available() and kernels.load(PLAIN_PREFIX, PLAIN_FLAGS)


@pytest.fixture(scope="module")
def plain_loops():
    """kernels.cpp built with the plain loops only, as ``torch.ops.neural_btf_plain``."""
    if not load_plain_loops():
        pytest.skip(
            "the fused kernels or their plain loops did not build here (the warning "
            "logged says why; see test_kernels_build)"
        )
    return torch.ops.neural_btf_plain


@pytest.mark.parametrize("rows,hidden", [(37, 106), (8, 33), (1, 16)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16], ids=["float32", "bfloat16"])
def test_vector_code_matches_plain_loops(plain_loops, rows, hidden, dtype):
    """The ops' 16-lane code (this machine's build) against the plain loops that CPUs
    without AVX-512 run: the same values up to the order of float32 sums, for widths of
    whole and partial vectors and an odd number of rows (the output layer takes two rows
    at a time)."""
    torch.manual_seed(4)
    a = torch.relu(torch.randn(rows, hidden)).to(dtype)
    w, b = torch.randn(3, hidden).to(dtype), torch.randn(3).to(dtype)
    targets = torch.rand(rows, 3)
    x = torch.zeros(rows, 9).to(dtype)
    x[:, :4] = torch.rand(rows, 4).to(dtype)
    x[torch.arange(rows), 4 + torch.arange(rows) % 5] = 1
    results = []
    for ops in (torch.ops.neural_btf, plain_loops):
        sums = [
            torch.zeros(3, hidden),
            torch.zeros(3),
            torch.zeros(hidden),
            torch.zeros((), dtype=torch.float64),
        ]
        g = ops.output_layer(a, w, b, targets, 0.01, *sums)
        g_b, g_x, h = torch.zeros(hidden), torch.zeros(9, hidden), g.clone()
        ops.relu_backward_(h, a, g_b, x, g_x)
        results.append([g.float(), h.float(), g_b, g_x] + sums)
    # bfloat16: a sum in another order may round a product's output to the neighbouring
    # bfloat16 (0.4 %), and that moves what follows from it.
    tolerance = 1e-5 if dtype == torch.float32 else 0.02
    for got, want in zip(*results, strict=True):
        assert float((got - want).norm()) <= tolerance * float(want.norm()) + 1e-12
