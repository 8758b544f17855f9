"""Opt-in machine tuning of a training job (``train.keep_awake``, ``train.omp_spin_count``,
``train.reuse_freed_memory``), all off by default: each changes process-wide state.

- :func:`keep_cpus_awake`: one spinning process per core at ``SCHED_IDLE``, Linux's lowest
  scheduling class, so that a core does not sleep between a step's short parallel phases
  (on virtual machines a woken core ran slower for milliseconds). It only gets a core that
  would otherwise sleep; the price is power. Processes, not threads: a spinning Python
  thread would hold the interpreter's lock the training threads need.
- :func:`set_omp_spin_count`: ``GOMP_SPINCOUNT``, how long OpenMP's idle threads spin
  before they sleep (libgomp's default, 300,000, keeps them on the cores the decoder's
  workers need); set at the start of a job, before torch loads libgomp, which reads it once.
- :func:`reuse_freed_memory`: glibc keeps freed buffers for reuse while training.

What each buys is measured by ``python -m benchmarks.train`` (``docs/performance.md``).
"""

from __future__ import annotations

import ctypes
import logging
import os
import subprocess
import sys
from contextlib import contextmanager, nullcontext
from pathlib import Path

log = logging.getLogger(__name__)

# Spins at SCHED_IDLE on one core until told to stop or its parent (argv[1]) is gone.
_SPINNER = """
import os, sys
parent, cpu = int(sys.argv[1]), int(sys.argv[2])
os.sched_setaffinity(0, {cpu})
os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
os.write(1, b"spinning")
os.close(1)
while os.getppid() == parent:
    for _ in range(100000):
        pass
"""


def set_omp_spin_count(count: int | None) -> None:
    """Set ``GOMP_SPINCOUNT`` for this process (``None``: leave OpenMP's default).

    Takes effect only before torch loads libgomp; where it is loaded already with another
    value, a warning says so and names the environment variable to set instead.
    """
    if count is None:
        return
    if count < 0:
        from pipeline.core.errors import ConfigError

        raise ConfigError(f"train.omp_spin_count={count} must be >= 0 (or null)")
    value = str(int(count))
    if os.environ.get("GOMP_SPINCOUNT") == value:
        return
    if "torch" in sys.modules:
        log.warning(
            "train.omp_spin_count=%s has no effect: torch (and OpenMP) were loaded "
            "before the job started; set GOMP_SPINCOUNT=%s in the environment "
            "instead",
            value,
            value,
        )
        return
    os.environ["GOMP_SPINCOUNT"] = value


# Where a container's CPU quota is set (cgroup v2, then v1).
QUOTA_FILES = (Path("/sys/fs/cgroup/cpu.max"), Path("/sys/fs/cgroup/cpu/cpu.cfs_quota_us"))


def cpu_quota_set() -> bool:
    """Whether this process's cgroup has a CPU quota (``docker --cpus``, a Kubernetes
    limit). Spinners would spend the quota that the job's own threads need, whatever their
    scheduling class."""
    for path in QUOTA_FILES:
        try:
            quota = path.read_text().split()[0]
        except (OSError, IndexError):
            continue
        return quota not in ("max", "-1")
    return False


def can_keep_awake() -> bool:
    return hasattr(os, "SCHED_IDLE") and hasattr(os, "sched_getaffinity") and not cpu_quota_set()


@contextmanager
def keep_cpus_awake(threads: int):
    """Inside the block, one ``SCHED_IDLE`` spinning process per core this process may run
    on, when a job keeps ``threads`` >= 2 threads busy and that is every such core (with
    fewer, which cores it runs on is the scheduler's choice, and spinning on all of them
    would burn the others for nothing); none where the platform has no ``SCHED_IDLE`` or
    a CPU quota is set (:func:`cpu_quota_set`).
    The block starts once they spin (their start-up would compete with the first steps);
    they end with the block, or on their own within milliseconds if this process dies."""
    cpus = sorted(os.sched_getaffinity(0)) if can_keep_awake() else []
    if threads < max(2, len(cpus)):
        cpus = []
    command = [sys.executable, "-S", "-c", _SPINNER, str(os.getpid())]
    pipes = {"stdin": subprocess.DEVNULL, "stdout": subprocess.PIPE, "stderr": subprocess.DEVNULL}
    spinners = [subprocess.Popen([*command, str(cpu)], **pipes) for cpu in cpus]
    try:
        for spinner in spinners:
            spinner.stdout.read()  # "spinning", then end of file
        yield spinners
    finally:
        for spinner in spinners:
            spinner.kill()
        for spinner in spinners:
            spinner.wait()
            spinner.stdout.close()


# glibc's mallopt parameters (malloc.h) and its largest mmap threshold (HEAP_MAX_SIZE / 2 on
# 64-bit), which is also where its dynamic threshold stops growing.
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
_MMAP_THRESHOLD_MAX = 32 << 20


def glibc():
    """The C library as a ``ctypes.CDLL`` where it is glibc (it has ``mallopt``), else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt  # noqa: B018 (musl and others have no mallopt)
        libc.malloc_trim  # noqa: B018
    except (OSError, AttributeError):
        return None
    return libc


@contextmanager
def reuse_freed_memory(trim_threshold: int = 256 << 20):
    """Within the block, glibc's malloc keeps freed buffers of up to 32 MiB for reuse instead
    of returning them to the kernel; on exit, what is free goes back (``malloc_trim``).
    No-op where glibc is not the C library.

    Why: a training step allocates and frees its ~1 MB activations dozens of times, and by
    default glibc returns each one to the kernel, so every step touches fresh pages.
    PyTorch has no caching allocator on the CPU; Intel's tuning guide preloads jemalloc or
    tcmalloc instead, which a pip install cannot do.
    """
    libc = glibc()
    if libc is None:
        yield
        return
    libc.mallopt(M_MMAP_THRESHOLD, _MMAP_THRESHOLD_MAX)
    libc.mallopt(M_TRIM_THRESHOLD, trim_threshold)
    try:
        yield
    finally:
        # Setting either disabled glibc's dynamic thresholds for good; leave them where the
        # dynamic ones stop growing (trim at twice the mmap threshold).
        libc.mallopt(M_TRIM_THRESHOLD, 2 * _MMAP_THRESHOLD_MAX)
        libc.malloc_trim(0)


@contextmanager
def training_tuning(settings, threads: int, on_cpu: bool):
    """The tuning ``settings`` (a :class:`~pipeline.btf.train_settings.TrainSettings`) asks
    for, for the duration of training on ``threads`` threads."""
    with (
        reuse_freed_memory() if settings.reuse_freed_memory and on_cpu else nullcontext(),
        keep_cpus_awake(threads if settings.keep_awake and on_cpu else 0),
    ):
        yield
