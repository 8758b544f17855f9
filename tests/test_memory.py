"""Per-stage peak resident memory (pipeline/memory.py)."""

import os
from pathlib import Path

import numpy as np
import pytest

from pipeline.memory import _glibc, process_peak_mb, stage_peak

resettable = pytest.mark.skipif(not os.access("/proc/self/clear_refs", os.W_OK),
                                reason="/proc/self/clear_refs is not writable here")


@resettable
def test_each_stage_reports_its_own_peak():
    with stage_peak() as big:
        block = np.ones(300 * 2**20 // 8)  # 300 MiB, touched
        del block
    with stage_peak() as small:
        np.ones(10)
    assert big["mb"] - small["mb"] > 250
    # The process peak survives the resets.
    assert process_peak_mb() >= big["mb"]


_FAULTS_OF_50_BUFFERS = """
import resource, torch
from pipeline.memory import _M_MMAP_THRESHOLD, _glibc, reuse_freed_memory

def faults_of_50_buffers():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(50):
        torch.empty(1 << 20).fill_(1.0)  # 4 MiB, freed at once
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

_glibc().mallopt(_M_MMAP_THRESHOLD, 128 << 10)  # glibc's default, before it adapts
by_mmap = faults_of_50_buffers()
with reuse_freed_memory():
    faults_of_50_buffers()  # the first buffer's pages
    print(by_mmap, faults_of_50_buffers())
"""


@pytest.mark.skipif(_glibc() is None, reason="reuse_freed_memory acts on glibc's malloc only")
def test_freed_buffers_are_reused_without_page_faults():
    """Allocating, touching and freeing a 4 MiB buffer (1,024 pages) 50 times: served by
    mmap, every buffer faults its pages in again (51,295 measured); inside the block, fewer
    than one buffer's pages fault. In a fresh process: in this one, earlier tests leave
    free heap memory that would serve the buffers either way."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _FAULTS_OF_50_BUFFERS], capture_output=True,
                         text=True, check=True, cwd=Path(__file__).parents[1]).stdout
    by_mmap, reused = map(int, out.split())
    assert by_mmap > 25 * 1024
    assert reused < 1024
