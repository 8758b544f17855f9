"""The kernels' build (pipeline/btf/fast/kernels.py) after a build was killed, while another
is running, and past its time limit: it ends in bounded time, built or fallen back with one
warning, never waiting forever on the lock file torch leaves behind (issue 43). Every child
process runs under a ``timeout`` so that a regression fails instead of hanging."""

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_kernels import PLAIN_FLAGS, PLAIN_PREFIX
from torch.utils import cpp_extension

from pipeline.btf.fast import kernels
from pipeline.core.errors import ConfigError
from pipeline.core.process import kill_tree, process_alive

ROOT = Path(__file__).resolve().parents[1]

# Fake compilers that answer torch's version check. "slow", on a source file, notes its pid
# in ``started`` and compiles for a minute (long enough to be killed midway); "failing"
# fails at once, as g++ without torch's headers would.
_VERSION = """#!/bin/sh
case "$1" in --version|-dumpfullversion|-dumpversion) echo 12.2.0; exit 0;; esac
"""
_COMPILERS = {
    "slow": _VERSION + 'echo $$ > "$(dirname "$0")/started"\nexec sleep 60\n',
    "failing": _VERSION + 'echo "kernels.cpp:16:10: fatal error: ATen/ATen.h: No such file '
    'or directory" >&2\nexit 1\n',
}
_AVAILABLE = """
import logging
logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
from pipeline.btf.fast import kernels
print("available", kernels.available())
"""


def _env(tmp_path: Path, compiler: str | None, **settings: str) -> dict:
    """The environment of a build into ``tmp_path/extensions`` with the fake compiler
    named (None: the real one) and ``settings``."""
    env = {key: value for key, value in os.environ.items() if key != "PIPELINE_KERNELS"}
    env |= {
        "TORCH_EXTENSIONS_DIR": str(tmp_path / "extensions"),
        "TORCH_DONT_CHECK_COMPILER_ABI": "1",
    } | settings
    if compiler is not None:
        folder = tmp_path / f"{compiler}_compiler"
        folder.mkdir(exist_ok=True)
        (folder / "c++").write_text(_COMPILERS[compiler])
        (folder / "c++").chmod(0o755)
        env["CXX"] = str(folder / "c++")
    return env


def _start_slow_build(tmp_path: Path) -> tuple[subprocess.Popen, Path]:
    """A process building the kernels into ``tmp_path/extensions``, once its compiler runs;
    returns it and the build folder."""
    env = _env(tmp_path, "slow")
    started = Path(env["CXX"]).with_name("started")
    build = subprocess.Popen(
        [sys.executable, "-c", _AVAILABLE],
        env=env,
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 120
    while not started.exists():
        if build.poll() is not None or time.monotonic() > deadline:
            _kill_tree(build)
            pytest.fail(f"the build did not reach its compiler: {build.stderr.read()[-2000:]}")
        time.sleep(0.1)
    (folder,) = (tmp_path / "extensions").glob(f"{kernels.PREFIX}_*")
    return build, folder


def _kill_tree(process: subprocess.Popen) -> None:
    """SIGKILL ``process`` and everything it started (as a crash or the OOM killer would)."""
    kill_tree(process.pid)
    process.wait(timeout=30)


def test_extension_name_is_per_source_and_flags(tmp_path):
    """Two checkouts (the same kernels.cpp at another path), another version of it, or
    other flags build into folders of their own; the same inputs into the same one."""
    copy = tmp_path / "kernels.cpp"
    shutil.copy(kernels.SOURCE, copy)
    name = kernels.extension_name()
    assert name == kernels.extension_name() and name.startswith(
        f"pipeline_btf_kernels_{kernels.cpu_key()}_"
    )
    others = {
        kernels.extension_name(source=copy),
        kernels.extension_name(flags=[*kernels.FLAGS, "-DNEURAL_BTF_GENERIC"]),
    }
    copy.write_text(copy.read_text() + "\n// changed\n")
    others.add(kernels.extension_name(source=copy))
    assert len(others) == 3 and name not in others


def test_build_timeout_setting(monkeypatch):
    monkeypatch.delenv("PIPELINE_KERNELS_BUILD_TIMEOUT", raising=False)
    assert kernels.build_timeout() == kernels.BUILD_TIMEOUT_S == 300
    monkeypatch.setenv("PIPELINE_KERNELS_BUILD_TIMEOUT", "2.5")
    assert kernels.build_timeout() == 2.5
    for wrong in ("soon", "0", "-1", "nan"):
        monkeypatch.setenv("PIPELINE_KERNELS_BUILD_TIMEOUT", wrong)
        with pytest.raises(ConfigError, match=f"PIPELINE_KERNELS_BUILD_TIMEOUT='{wrong}' must"):
            kernels.build_timeout()


@pytest.mark.slow
def test_a_killed_build_leaves_no_trap(tmp_path):
    """A build killed midway leaves torch's lock file, which torch would wait on forever;
    the next process, in a fresh interpreter, recognises it as stale (our flock, which the
    killed process held, is free), removes it and builds (here: fails at once and falls
    back to torch ops with one warning)."""
    build, folder = _start_slow_build(tmp_path)
    _kill_tree(build)
    assert (folder / "lock").exists()
    assert (folder / kernels.OWNER_FILE).read_text().startswith(f"{build.pid}@")

    start = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-c", _AVAILABLE],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        env=_env(tmp_path, "failing"),
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.splitlines() == ["available False"]
    assert (
        f"removing {folder / 'lock'}, left by a build of the kernels that did not finish "
        f"(process {build.pid}@" in done.stderr
    )
    assert done.stderr.count("did not build") == 1, done.stderr
    assert "fatal error: ATen/ATen.h" in done.stderr
    assert not (folder / "lock").exists()
    assert time.monotonic() - start < 60


@pytest.mark.slow
def test_a_build_in_progress_is_waited_for_up_to_the_limit(tmp_path):
    """While another process builds, the next one says it waits, for whom, and falls back
    with one warning at the limit (``PIPELINE_KERNELS_BUILD_TIMEOUT``) instead of waiting
    without one."""
    build, folder = _start_slow_build(tmp_path)
    try:
        env = _env(tmp_path, "failing", PIPELINE_KERNELS_BUILD_TIMEOUT="2")
        done = subprocess.run(
            [sys.executable, "-c", _AVAILABLE],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
    finally:
        _kill_tree(build)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.splitlines() == ["available False"]
    assert f"which process {build.pid}@" in done.stderr  # the wait, said before waiting
    assert done.stderr.count("did not build") == 1, done.stderr
    assert (
        f"waited 2 s (PIPELINE_KERNELS_BUILD_TIMEOUT) for the build by process {build.pid}@"
        in done.stderr
    )


@pytest.mark.slow
def test_a_build_past_the_limit_is_stopped(tmp_path):
    """A build that takes longer than the limit is killed, its compiler included, and the
    process falls back with one warning, leaving no lock to wait on."""
    env = _env(tmp_path, "slow", PIPELINE_KERNELS_BUILD_TIMEOUT="3")
    done = subprocess.run(
        [sys.executable, "-c", _AVAILABLE],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.splitlines() == ["available False"]
    assert "building the decoder's C++ kernels in" in done.stderr
    assert done.stderr.count("did not build") == 1, done.stderr
    assert "the build took longer than 3 s (PIPELINE_KERNELS_BUILD_TIMEOUT)" in done.stderr
    compiler = int(Path(env["CXX"]).with_name("started").read_text())
    deadline = time.monotonic() + 10
    while process_alive(compiler) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not process_alive(compiler)
    assert not list((tmp_path / "extensions").glob("*/lock"))


# Holds the build lock of the folder given as it would while building, creates torch's
# lock file as torch's build does, and waits to be killed.
_HOLDER = """
import sys, time
from pathlib import Path
from pipeline.btf.fast import kernels
folder = Path(sys.argv[1])
with kernels._build_lock(folder, time.monotonic() + 60, 60):
    (folder / "lock").touch(exist_ok=False)
    print("holding", flush=True)
    time.sleep(60)
"""
_PLAIN_LOOPS = "from test_kernels import load_plain_loops; print('loaded', load_plain_loops())"


def test_the_plain_loops_fixture_gets_past_a_killed_build(tmp_path):
    """The fixture of tests/test_kernels.py (which hung ``make test``) after a killed
    build of its plain loops: it loads them in bounded time. In this machine's build folder,
    where the kernels are built already (a build here would take a minute)."""
    name = kernels.extension_name(PLAIN_PREFIX, PLAIN_FLAGS)
    folder = Path(cpp_extension._get_build_directory(name, False))
    env = {key: value for key, value in os.environ.items() if key != "PIPELINE_KERNELS"}
    env |= {
        "PIPELINE_KERNELS_BUILD_TIMEOUT": "120",
        "PYTHONPATH": os.pathsep.join([str(ROOT / "tests"), env.get("PYTHONPATH", "")]),
    }
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, str(folder)],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline() == "holding\n", holder.stderr.read()[-2000:]
    finally:
        _kill_tree(holder)
    lock = folder / "lock"
    left = lock.stat().st_ino
    try:
        done = subprocess.run(
            [sys.executable, "-c", _PLAIN_LOOPS],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
        )
    finally:
        # Where a regression left the trap in this machine's build folder, it goes.
        if lock.exists() and lock.stat().st_ino == left:
            lock.unlink(missing_ok=True)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.splitlines() == ["loaded True"], done.stderr[-3000:]
    assert (
        f"left by a build of the kernels that did not finish (process {holder.pid}@" in done.stderr
    )


@pytest.mark.slow
def test_a_real_build_killed_midway_is_built_again(tmp_path):
    """With the real compiler, into an empty folder (two builds: about a minute): the
    build is killed while it compiles, and the next process builds and loads the kernels."""
    if shutil.which("g++") is None and shutil.which("c++") is None:
        pytest.skip("no C++ compiler on this machine")
    env = _env(tmp_path, None)
    build = subprocess.Popen(
        [sys.executable, "-c", _AVAILABLE],
        env=env,
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 120
    while not list((tmp_path / "extensions").glob(f"{kernels.PREFIX}_*/lock")):
        assert build.poll() is None and time.monotonic() < deadline, "the build never started"
        time.sleep(0.1)
    time.sleep(2)  # into the compilation
    _kill_tree(build)
    (lock,) = (tmp_path / "extensions").glob(f"{kernels.PREFIX}_*/lock")

    done = subprocess.run(
        [sys.executable, "-c", _AVAILABLE],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=400,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.splitlines() == ["available True"], done.stderr[-3000:]
    assert f"removing {lock}" in done.stderr and "built the decoder's C++ kernels" in done.stderr
    assert not lock.exists()
