"""The decoder step's fused C++ kernels (``kernels.cpp``), built on first use.

Each kernel does in one pass over a chunk's (rows x 106) activations what torch does in
several (``pipeline.btf.fast.fused`` uses them when :func:`available`):

- ``torch.ops.neural_btf.output_layer``: the last layer's forward, the residual and loss,
  and the backward into the last hidden layer (its weight and bias gradients, the gradient
  through its ReLU and that gradient's column sums), which took seven torch calls;
- ``torch.ops.neural_btf.relu_backward_``: a ReLU's gradient in place, with its column
  sums (a bias gradient) or the first layer's weight gradient from its input rows.

They are compiled with ``torch.utils.cpp_extension`` (g++ and ninja, which the project
installs) for this machine's CPU, once per machine (its duration: docs/performance.md):
the build lands under ``TORCH_EXTENSIONS_DIR`` (default ``~/.cache/torch_extensions``).
Where the build fails (no compiler), ``train.backend=auto`` trains with the autograd
backend instead (:mod:`pipeline.btf.backends`) and the fused step, where asked for, falls
back to plain torch ops; a warning says so once. On a CPU with AVX-512 the kernels run on 16-lane vectors (bfloat16 ones also need
its bfloat16 instructions); elsewhere on what the compiler makes of plain loops
(``tests/test_kernels.py`` compares the two).
"""

from __future__ import annotations

import hashlib
import logging
import os
import platform
import sys
import time
from pathlib import Path

import torch

log = logging.getLogger(__name__)

SOURCE = Path(__file__).with_name("kernels.cpp")
FLAGS = ["-O3", "-march=native", "-fopenmp-simd"]
_state: dict = {}


# The /proc/cpuinfo lines that tell CPUs apart (x86: model name, flags; ARM: CPU part,
# Features).
_CPU_LINES = ("model name", "flags", "CPU implementer", "CPU part", "Features")
# A build lock older than this was left by a build that was killed (a build takes far
# less: docs/performance.md).
STALE_LOCK_SECONDS = 600


def cpu_key() -> str:
    """A short hash of the CPU's model and instruction-set flags: ``-march=native`` code
    built on one CPU may not run on another that shares the build folder."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        text = "\n".join(sorted({line for line in lines if line.startswith(_CPU_LINES)}))
    except OSError:
        text = ""
    text += platform.machine() + platform.processor()
    return hashlib.sha256(text.encode()).hexdigest()[:10]


def available() -> bool:
    """Whether the kernels are loaded, building them on the first call in a process."""
    if "ok" not in _state:
        _state["ok"] = _load()
    return _state["ok"]


def _load() -> bool:
    if os.environ.get("PIPELINE_KERNELS") == "0":
        log.info("PIPELINE_KERNELS=0: the decoder step uses plain torch ops")
        return False
    from torch.utils import cpp_extension

    name = f"pipeline_btf_kernels_{cpu_key()}"
    build_dir = Path(cpp_extension._get_build_directory(name, False))
    _remove_stale_lock(build_dir / "lock")
    # ninja comes with the project's environment, whose bin folder may not be on PATH.
    path = os.environ.get("PATH", "")
    os.environ["PATH"] = str(Path(sys.executable).parent) + os.pathsep + path
    try:
        cpp_extension.load(name=name, sources=[str(SOURCE)], extra_cflags=FLAGS,
                           is_python_module=False, verbose=False)
    except Exception as error:  # no compiler, no ninja, or a build error: fall back
        lines = str(error).strip().splitlines() or [type(error).__name__]
        # The compiler's first error, else the last line (ninja's own lines come last).
        reason = next((line for line in lines if "error:" in line), lines[-1])
        log.warning("the decoder's C++ kernels did not build in %s (%s); the fused step "
                    "would use plain torch ops, which are slower", build_dir, reason.strip())
        return False
    finally:
        os.environ["PATH"] = path
    return hasattr(torch.ops.neural_btf, "output_layer")


def _remove_stale_lock(lock: Path) -> None:
    """torch's build lock stays behind when a build is killed, and every later build
    would wait on it forever; one older than :data:`STALE_LOCK_SECONDS` is removed."""
    try:
        age = time.time() - lock.stat().st_mtime
    except OSError:
        return
    if age > STALE_LOCK_SECONDS:
        log.warning("removing %s, left %.0f s ago by a build that did not finish", lock, age)
        lock.unlink(missing_ok=True)
