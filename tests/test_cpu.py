"""pipeline.cpu: the spinning idle-class processes and the OpenMP spin-count default."""

import os
import subprocess
import sys
import time

import pytest

import pipeline.cpu
from pipeline.cpu import SPIN_COUNT, can_keep_awake, keep_cpus_awake, openmp_default_environment

needs_sched_idle = pytest.mark.skipif(not can_keep_awake(),
                                      reason="no SCHED_IDLE, or a CPU quota: no spinners here")


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
            {cpu} for cpu in sorted(os.sched_getaffinity(0))]
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


@pytest.mark.parametrize(("v2", "v1", "limited"), [
    ("max 100000\n", None, False), ("200000 100000\n", None, True),
    (None, "-1\n", False), (None, "150000\n", True), (None, None, False)])
def test_no_spinners_under_a_cpu_quota(tmp_path, monkeypatch, v2, v1, limited):
    files = (tmp_path / "cpu.max", tmp_path / "cpu.cfs_quota_us")
    for path, text in zip(files, (v2, v1), strict=True):
        if text is not None:
            path.write_text(text)
    monkeypatch.setattr(pipeline.cpu, "QUOTA_FILES", files)
    assert pipeline.cpu.cpu_quota_set() is limited
    if limited:
        with keep_cpus_awake(threads=max(2, len(os.sched_getaffinity(0)))) as spinners:
            assert spinners == []


_PARENT = """
import os, time
from pipeline.cpu import keep_cpus_awake
with keep_cpus_awake(threads=max(2, len(os.sched_getaffinity(0)))) as spinners:
    print(*[s.pid for s in spinners], flush=True)
    time.sleep(60)
"""


@needs_sched_idle
def test_spinners_end_when_their_parent_is_killed():
    parent = subprocess.Popen([sys.executable, "-c", _PARENT], stdout=subprocess.PIPE,
                              text=True)
    pids = [int(p) for p in parent.stdout.readline().split()]
    assert pids and all(_alive(pid) for pid in pids)
    parent.kill()
    parent.wait()
    deadline = time.monotonic() + 10
    while any(_alive(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(_alive(pid) for pid in pids)


def _spin_count(env: dict, child_env: bool = False) -> str:
    """GOMP_SPINCOUNT in a fresh process after ``import pipeline`` (or in the environment
    it would give a child timed with libgomp's defaults)."""
    code = ("import os, pipeline, pipeline.cpu\n"
            f"env = pipeline.cpu.openmp_default_environment() if {child_env} else os.environ\n"
            "print(env.get('GOMP_SPINCOUNT', 'unset'))")
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, check=True).stdout.strip()


BASE = {k: v for k, v in os.environ.items()
        if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY", "PIPELINE_OPENMP_DEFAULTS")}


def test_import_sets_the_spin_count_unless_openmp_waiting_was_chosen():
    assert _spin_count(BASE) == SPIN_COUNT
    assert _spin_count(BASE | {"GOMP_SPINCOUNT": "5"}) == "5"
    assert _spin_count(BASE | {"OMP_WAIT_POLICY": "passive"}) == "unset"
    assert _spin_count(BASE | {"PIPELINE_OPENMP_DEFAULTS": "1"}) == "unset"


def test_the_default_environment_undoes_only_the_pipelines_own_setting():
    assert _spin_count(BASE, child_env=True) == "unset"
    assert _spin_count(BASE | {"GOMP_SPINCOUNT": "5"}, child_env=True) == "5"
    assert openmp_default_environment()["PIPELINE_OPENMP_DEFAULTS"] == "1"
