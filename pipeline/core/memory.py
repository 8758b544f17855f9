"""Peak resident memory of the process and of each stage (Linux; elsewhere the process peak).

Per-stage peaks reset the kernel's high-water mark (``5`` to ``/proc/self/clear_refs`` sets
``VmHWM`` to the current RSS), which ``getrusage`` reports too, so the process peak is kept
here as the maximum of the marks read before each reset.
"""

from __future__ import annotations

import resource
from contextlib import contextmanager
from pathlib import Path

_STATUS = Path("/proc/self/status")
_CLEAR_REFS = Path("/proc/self/clear_refs")
_process_peak_mb = 0.0


def _hwm_mb() -> float:
    try:
        for line in _STATUS.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB on Linux


def _reset() -> bool:
    try:
        _CLEAR_REFS.write_text("5")
        return True
    except OSError:
        return False


def process_peak_mb() -> float:
    """Peak RSS of this process so far, in MiB."""
    global _process_peak_mb
    _process_peak_mb = max(_process_peak_mb, _hwm_mb())
    return _process_peak_mb


@contextmanager
def stage_peak():
    """``with stage_peak() as peak: ...``, then ``peak["mb"]`` is the block's peak RSS in MiB
    (the process peak so far where the mark cannot be reset)."""
    process_peak_mb()
    _reset()
    result: dict[str, float] = {}
    try:
        yield result
    finally:
        result["mb"] = _hwm_mb()
        process_peak_mb()
