"""Keeping a CPU's cores at work between the short parallel phases of a training step.

A training step (``pipeline.btf.train``) alternates phases on both cores (the encoder's
OpenMP threads, the fused decoder's worker threads) with moments where a core waits: for
the other worker, for the main thread's Python, for the optimizer. A core that has nothing
to run sleeps, and on the virtual machine this project is measured on it runs slower for
milliseconds after it wakes (bare metal: not measured). Measured on a 2-core AMX Xeon VM,
the fused decoder step's two halves (5 x 3281 queries each, bfloat16), run in two
processes:

- side by side, never waiting: 12.2-12.4 ms a step each;
- meeting at a blocking barrier every step: 14.4-17.5 ms;
- meeting at a barrier that spins instead of sleeping: 12.3-12.9 ms.

The whole decoder step on two threads (medians of 5 rounds of 20 steps): bfloat16 19.3 ms,
15.2 ms with :func:`keep_cpus_awake`; float32 35.0 against 27.6 ms.

:func:`keep_cpus_awake` runs one spinning process per core at ``SCHED_IDLE``, Linux's
lowest scheduling class: it only ever gets a core that would otherwise sleep, and gives it
up the moment a normal thread wants it. The price is power: the cores never sleep while
it lasts. Spinners are processes, not threads, because a spinning Python thread would hold
the interpreter's lock that the training threads need.

:data:`SPIN_COUNT` is the other half: OpenMP's idle threads (torch's intra-op pool, GNU
libgomp) spin for ``GOMP_SPINCOUNT`` iterations before they sleep, 300,000 by default,
while the decoder's own workers want the same cores. The bfloat16 training loop at the
paper's batch (3 rounds of 60 steps, cores kept awake) took 23.9-26.3 / 23.3-24.0 /
23.4-25.1 / 25.2-26.1 / 28.2-29.9 ms a step at 3,000 / 10,000 / 30,000 / 100,000 /
300,000 (an earlier version of the decoder step). ``import pipeline`` sets the variable
to :data:`SPIN_COUNT` unless ``GOMP_SPINCOUNT`` or ``OMP_WAIT_POLICY`` is set, or
``PIPELINE_OPENMP_DEFAULTS=1`` asks for libgomp's own defaults; libgomp reads it once, when
torch loads, so it has no effect where torch was imported first.
"""

from __future__ import annotations

import os
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path

SPIN_COUNT = "30000"
spin_count_set = False  # whether openmp_defaults() set GOMP_SPINCOUNT in this process

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


def openmp_defaults() -> None:
    """Set ``GOMP_SPINCOUNT`` to :data:`SPIN_COUNT` where nobody chose OpenMP's waiting
    (see the module's docstring); called by ``import pipeline``."""
    global spin_count_set
    if os.environ.get("PIPELINE_OPENMP_DEFAULTS") == "1":
        return
    if "GOMP_SPINCOUNT" not in os.environ and "OMP_WAIT_POLICY" not in os.environ:
        os.environ["GOMP_SPINCOUNT"] = SPIN_COUNT
        spin_count_set = True


def openmp_default_environment() -> dict:
    """This process's environment as a child process with libgomp's own defaults needs it
    (what a plain torch program gets): for timing other code against the pipeline's."""
    env = dict(os.environ, PIPELINE_OPENMP_DEFAULTS="1")
    if spin_count_set:
        env.pop("GOMP_SPINCOUNT", None)
    return env


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
    return (hasattr(os, "SCHED_IDLE") and hasattr(os, "sched_getaffinity")
            and not cpu_quota_set())


@contextmanager
def keep_cpus_awake(threads: int):
    """Inside the block, one ``SCHED_IDLE`` spinning process per core this process may run
    on, when a job keeps ``threads`` >= 2 threads busy and that is every such core (with
    fewer, which cores it runs on is the scheduler's choice, and spinning on all of them
    would burn the others for nothing); none where the platform has no ``SCHED_IDLE`` or
    a CPU quota is set (:func:`cpu_quota_set`).
    The block starts once they spin (their start-up would compete with the first steps);
    they end with the block, or on their own within milliseconds if this process dies."""
    spinners: list[subprocess.Popen] = []
    cpus = sorted(os.sched_getaffinity(0)) if can_keep_awake() else []
    if threads >= max(2, len(cpus)):
        for cpu in cpus:
            spinners.append(subprocess.Popen(
                [sys.executable, "-S", "-c", _SPINNER, str(os.getpid()), str(cpu)],
                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL))
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
