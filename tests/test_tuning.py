"""pipeline.btf.fast.tuning: the opt-in spinners, OpenMP spin count and freed-memory reuse."""

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

import pipeline.btf.fast.tuning
from pipeline.btf.fast.tuning import can_keep_awake, glibc, keep_cpus_awake, set_omp_spin_count
from pipeline.core.errors import ConfigError

needs_sched_idle = pytest.mark.skipif(
    not can_keep_awake(), reason="no SCHED_IDLE, or a CPU quota: no spinners here"
)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().split(")")[-1].split()[0] != "Z"  # a zombie has ended
    except FileNotFoundError:
        return False


@needs_sched_idle
def test_one_idle_class_spinner_per_core_while_the_block_lasts():
    with keep_cpus_awake(threads=max(2, len(os.sched_getaffinity(0)))) as spinners:
        pids = [s.pid for s in spinners]
        assert len(pids) == len(os.sched_getaffinity(0))
        for pid in pids:
            assert os.sched_getscheduler(pid) == os.SCHED_IDLE
        assert [os.sched_getaffinity(pid) for pid in pids] == [
            {cpu} for cpu in sorted(os.sched_getaffinity(0))
        ]
        assert all(s.poll() is None for s in spinners)
    assert not any(_alive(pid) for pid in pids)


@pytest.mark.parametrize("threads", [0, 1])
def test_nothing_spins_for_a_job_of_one_thread(threads):
    with keep_cpus_awake(threads) as spinners:
        assert spinners == []


@needs_sched_idle
def test_nothing_spins_for_a_job_that_leaves_cores_free():
    cpus = len(os.sched_getaffinity(0))
    if cpus < 3:
        pytest.skip(f"{cpus} CPUs: a job of 2 threads already uses them all")
    with keep_cpus_awake(cpus - 1) as spinners:
        assert spinners == []


@pytest.mark.parametrize(
    ("v2", "v1", "limited"),
    [
        ("max 100000\n", None, False),
        ("200000 100000\n", None, True),
        (None, "-1\n", False),
        (None, "150000\n", True),
        (None, None, False),
    ],
)
def test_no_spinners_under_a_cpu_quota(tmp_path, monkeypatch, v2, v1, limited):
    files = (tmp_path / "cpu.max", tmp_path / "cpu.cfs_quota_us")
    for path, text in zip(files, (v2, v1), strict=True):
        if text is not None:
            path.write_text(text)
    monkeypatch.setattr(pipeline.btf.fast.tuning, "QUOTA_FILES", files)
    assert pipeline.btf.fast.tuning.cpu_quota_set() is limited
    if limited:
        with keep_cpus_awake(threads=max(2, len(os.sched_getaffinity(0)))) as spinners:
            assert spinners == []


_PARENT = """
import os, time
from pipeline.btf.fast.tuning import keep_cpus_awake
with keep_cpus_awake(threads=max(2, len(os.sched_getaffinity(0)))) as spinners:
    print(*[s.pid for s in spinners], flush=True)
    time.sleep(60)
"""


@needs_sched_idle
def test_spinners_end_when_their_parent_is_killed():
    parent = subprocess.Popen([sys.executable, "-c", _PARENT], stdout=subprocess.PIPE, text=True)
    pids = [int(p) for p in parent.stdout.readline().split()]
    assert pids and all(_alive(pid) for pid in pids)
    parent.kill()
    parent.wait()
    deadline = time.monotonic() + 10
    while any(_alive(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(_alive(pid) for pid in pids)


_SPIN_COUNT = """
import logging, os, sys
logging.basicConfig(level=logging.WARNING)
if sys.argv[1] == "torch-first":
    import torch  # noqa: F401
from pipeline.btf.fast.tuning import set_omp_spin_count
set_omp_spin_count(None if sys.argv[2] == "none" else int(sys.argv[2]))
print(os.environ.get("GOMP_SPINCOUNT", "unset"))
"""

BASE = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}


def _spin_count(order: str, count: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", _SPIN_COUNT, order, count],
        env=BASE,
        capture_output=True,
        text=True,
        check=True,
    )


def test_the_spin_count_is_set_only_when_asked_and_before_torch_loads():
    assert _spin_count("pipeline-first", "none").stdout.strip() == "unset"
    assert _spin_count("pipeline-first", "30000").stdout.strip() == "30000"
    late = _spin_count("torch-first", "30000")
    assert late.stdout.strip() == "unset"
    assert "GOMP_SPINCOUNT=30000" in late.stderr


def test_a_negative_spin_count_is_refused():
    with pytest.raises(ConfigError, match="train.omp_spin_count=-1"):
        set_omp_spin_count(-1)


_FAULTS_OF_50_BUFFERS = """
import resource, torch
from pipeline.btf.fast.tuning import M_MMAP_THRESHOLD, glibc, reuse_freed_memory

def faults_of_50_buffers():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(50):
        torch.empty(1 << 20).fill_(1.0)  # 4 MiB, freed at once
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

glibc().mallopt(M_MMAP_THRESHOLD, 128 << 10)  # glibc's default, before it adapts
by_mmap = faults_of_50_buffers()
with reuse_freed_memory():
    faults_of_50_buffers()  # the first buffer's pages
    print(by_mmap, faults_of_50_buffers())
"""


@pytest.mark.skipif(glibc() is None, reason="reuse_freed_memory acts on glibc's malloc only")
def test_freed_buffers_are_reused_without_page_faults():
    """Allocating, touching and freeing a 4 MiB buffer (1,024 pages) 50 times: served by
    mmap, every buffer faults its pages in again; inside the block, fewer than one buffer's
    pages fault. In a fresh process: in this one, earlier tests leave free heap memory
    that would serve the buffers either way."""
    out = subprocess.run(
        [sys.executable, "-c", _FAULTS_OF_50_BUFFERS],
        capture_output=True,
        text=True,
        check=True,
        cwd=Path(__file__).parents[1],
    ).stdout
    by_mmap, reused = map(int, out.split())
    assert by_mmap > 25 * 1024
    assert reused < 1024
