"""Per-stage peak resident memory (pipeline/memory.py)."""

import os

import numpy as np
import pytest

from pipeline.memory import _glibc, process_peak_mb, reuse_freed_memory, stage_peak

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


@pytest.mark.skipif(_glibc() is None, reason="reuse_freed_memory acts on glibc's malloc only")
def test_freed_buffers_are_reused_without_page_faults():
    """Allocating, touching and freeing a 4 MiB buffer (1,024 pages) 50 times: when glibc
    serves each buffer by mmap (threshold at its 128 KiB default, set here), every buffer
    faults its pages in again; inside the block, fewer than one buffer's pages fault."""
    import resource

    import torch

    from pipeline.memory import _M_MMAP_THRESHOLD

    def faults_of_50_buffers() -> int:
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for _ in range(50):
            torch.empty(1 << 20).fill_(1.0)  # 4 MiB, freed at once
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

    _glibc().mallopt(_M_MMAP_THRESHOLD, 128 << 10)
    assert faults_of_50_buffers() > 25 * 1024
    with reuse_freed_memory():
        faults_of_50_buffers()  # the first buffer's pages
        assert faults_of_50_buffers() < 1024
