"""Per-stage peak resident memory (pipeline/core/memory.py)."""

import os

import numpy as np
import pytest

from pipeline.core.memory import process_peak_mb, stage_peak

resettable = pytest.mark.skipif(
    not os.access("/proc/self/clear_refs", os.W_OK),
    reason="/proc/self/clear_refs is not writable here",
)


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
