"""The decoder step's fused C++ kernels (``kernels.cpp``), built on first use.

Each of the two ops, ``torch.ops.neural_btf.output_layer`` and ``relu_backward_`` (the
top of kernels.cpp says what they compute), does in one pass over a chunk's (rows x 106)
activations what torch does in several; :mod:`pipeline.btf.fast.fused` uses them when
:func:`available`.

``torch.utils.cpp_extension`` (g++ and ninja, which the project installs) compiles them
for this machine's CPU once per machine and checkout (how long: docs/performance.md), under
``TORCH_EXTENSIONS_DIR`` (default ``~/.cache/torch_extensions``) in a folder named by
:func:`extension_name`. The build runs in a child process under a lock of our own
(:func:`load`), so that a killed build leaves nothing to wait on, and is given up after
``PIPELINE_KERNELS_BUILD_TIMEOUT`` seconds (default :data:`BUILD_TIMEOUT_S`), waiting for
another process's build included. Where it fails (no compiler) or times out,
``train.backend=auto`` trains with autograd (:mod:`pipeline.btf.backends`) and the fused
step, where asked for, falls back to plain torch ops; a warning says so once. On a CPU with
AVX-512 the kernels run on 16-lane vectors (bfloat16 ones also need its bfloat16
instructions), elsewhere on what the compiler makes of plain loops
(``tests/test_kernels.py`` compares the two).
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import hashlib
import logging
import math
import os
import platform
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import torch

from pipeline.core.errors import ConfigError
from pipeline.core.process import host_name, kill_tree

log = logging.getLogger(__name__)

SOURCE = Path(__file__).with_name("kernels.cpp")
FLAGS = ["-O3", "-march=native", "-fopenmp-simd"]
PREFIX = "pipeline_btf_kernels"
# A build takes 10-90 s (docs/performance.md); the limit leaves room for a busy machine.
BUILD_TIMEOUT_S = 300.0
TIMEOUT_VARIABLE = "PIPELINE_KERNELS_BUILD_TIMEOUT"
# Our lock in the build folder, held (flock) around the whole build and load; it names
# its holder, "pid@host", while held.
OWNER_FILE = "pipeline_build.lock"
_POLL_S = 0.2

# The /proc/cpuinfo lines that tell CPUs apart (x86: model name, flags; ARM: CPU part,
# Features).
_CPU_LINES = ("model name", "flags", "CPU implementer", "CPU part", "Features")

# What the child process runs: torch's build (which also loads the library: harmless). It
# kills itself, compilers included, after the seconds it is given: a build orphaned by a
# killed parent still ends, and with it our lock, which it inherited.
_BUILD_SCRIPT = """
import os, signal, sys
seconds, name, build_dir, source, *flags = sys.argv[1:]
def stop(*_):
    from pipeline.core.process import kill_tree
    kill_tree(os.getpid())
signal.signal(signal.SIGALRM, stop)
signal.alarm(int(seconds))
from torch.utils import cpp_extension
cpp_extension.load(name=name, sources=[source], extra_cflags=flags, build_directory=build_dir,
                   is_python_module=False, verbose=False)
"""


class _NotBuilt(Exception):
    """Why the kernels are not loaded, in one line."""


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


def extension_name(
    prefix: str = PREFIX, flags: Sequence[str] = FLAGS, source: Path = SOURCE
) -> str:
    """``<prefix>_<cpu_key()>_<build key>``, the extension's name and build folder's.

    The build key hashes what torch's ``build.ninja`` depends on: the source's contents and
    path, the flags, and the torch and Python that compile it. Two checkouts (or two
    versions of kernels.cpp) thus build into folders of their own instead of rebuilding
    each other's kernels on every run: ninja rebuilds when a path in its command changes.
    """
    source = Path(source).resolve()
    digest = hashlib.sha256(source.read_bytes())
    for part in (str(source), *flags, torch.__version__, torch.__file__, sys.version):
        digest.update(b"\0" + part.encode())
    return f"{prefix}_{cpu_key()}_{digest.hexdigest()[:10]}"


def build_timeout() -> float:
    """Seconds a build may take, waiting for another process's build included:
    ``PIPELINE_KERNELS_BUILD_TIMEOUT``, default :data:`BUILD_TIMEOUT_S`."""
    text = os.environ.get(TIMEOUT_VARIABLE, "").strip()
    if not text:
        return BUILD_TIMEOUT_S
    try:
        seconds = float(text)
    except ValueError:
        seconds = float("nan")
    if not seconds > 0:
        raise ConfigError(f"{TIMEOUT_VARIABLE}={text!r} must be a number of seconds > 0")
    return seconds


@functools.cache
def available() -> bool:
    """Whether the kernels are loaded, building them on the first call in a process."""
    if os.environ.get("PIPELINE_KERNELS") == "0":
        log.info("PIPELINE_KERNELS=0: the decoder step uses plain torch ops")
        return False
    return load() and hasattr(torch.ops.neural_btf, "output_layer")


def load(prefix: str = PREFIX, flags: Sequence[str] = FLAGS) -> bool:
    """Build kernels.cpp with ``flags`` where not built yet, and load it into torch.

    Parameters
    ----------
    prefix : the start of the extension's name (:func:`extension_name`); a variant built
        with other flags (``tests/test_kernels.py``'s plain loops) takes its own.
    flags : the compiler's flags.

    Returns
    -------
    bool : whether the library is loaded. Where not (no compiler, a build error, or no
        build within :func:`build_timeout` seconds), a warning says why.
    """
    from torch.utils import cpp_extension

    name = extension_name(prefix, flags)
    build_dir = Path(cpp_extension._get_build_directory(name, False))
    timeout = build_timeout()
    deadline = time.monotonic() + timeout
    # ninja comes with the project's environment, whose bin folder may not be on PATH.
    path = os.environ.get("PATH", "")
    env = os.environ | {"PATH": str(Path(sys.executable).parent) + os.pathsep + path}
    try:
        with _build_lock(build_dir, deadline, timeout) as lock_fd:
            library = build_dir / f"{name}{cpp_extension.LIB_EXT}"
            if not library.exists():
                _build_in_child(name, flags, build_dir, env, lock_fd, deadline, timeout)
            # Built: torch's own load finds it so (ninja has nothing to do) and loads it.
            os.environ["PATH"] = env["PATH"]
            try:
                cpp_extension.load(
                    name=name,
                    sources=[str(SOURCE)],
                    extra_cflags=list(flags),
                    build_directory=str(build_dir),
                    is_python_module=False,
                    verbose=False,
                )
            except Exception as error:  # a library that does not load, say
                raise _NotBuilt(_first_error(str(error), type(error).__name__)) from None
            finally:
                os.environ["PATH"] = path
    except _NotBuilt as error:
        log.warning(
            "the decoder's C++ kernels did not build in %s (%s); the fused step "
            "would use plain torch ops, which are slower",
            build_dir,
            error,
        )
        return False
    return True


@contextlib.contextmanager
def _build_lock(build_dir: Path, deadline: float, timeout: float) -> Iterator[int]:
    """Hold our lock on ``build_dir`` (an flock on :data:`OWNER_FILE`, which names its
    holder) until ``deadline`` at the latest; yields the lock's file descriptor.

    The operating system releases an flock when its holder dies, however it dies. Every
    build of the kernels runs inside this lock, so torch's own lock file (``lock``, which
    torch waits on without a limit) found while we hold ours was left by a build that was
    killed, and is removed.
    """
    lock_path = build_dir / OWNER_FILE
    try:
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as error:  # a build folder we may not write to
        raise _NotBuilt(f"cannot open {lock_path}: {error.strerror}") from None
    try:
        _acquire(fd, lock_path, deadline, timeout)
        dead_owner = _owner(fd)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}@{host_name()}\n".encode(), 0)
        torch_lock = build_dir / "lock"
        if torch_lock.exists():
            _tell(
                "removing %s, left by a build of the kernels that did not finish (%s)",
                torch_lock,
                f"process {dead_owner}" if dead_owner else "owner not recorded",
            )
            torch_lock.unlink(missing_ok=True)
        try:
            yield fd
        finally:
            os.ftruncate(fd, 0)  # released in order: no dead owner for the next holder
    finally:
        os.close(fd)  # releases the flock


def _acquire(fd: int, lock_path: Path, deadline: float, timeout: float) -> None:
    """Take the flock on ``fd``, saying once that we wait, or raise :class:`_NotBuilt`
    at ``deadline``."""
    told = False
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            pass
        except OSError as error:  # a file system without locks: no safe way to build
            raise _NotBuilt(f"cannot lock {lock_path}: {error.strerror}") from None
        owner = _owner(fd)
        holder = f"process {owner}" if owner else "another process"
        left = deadline - time.monotonic()
        if left <= 0:
            raise _NotBuilt(
                f"waited {timeout:.0f} s ({TIMEOUT_VARIABLE}) for the build "
                f"by {holder}, which holds {lock_path}"
            )
        if not told:
            _tell(
                "waiting up to %.0f s for the decoder's C++ kernels, which %s is building "
                "(it holds %s)",
                left,
                holder,
                lock_path,
            )
            told = True
        time.sleep(min(_POLL_S, left))


def _owner(fd: int) -> str:
    """The ``pid@host`` the lock's holder wrote, or ""."""
    return os.pread(fd, 300, 0).decode(errors="replace").strip()


def _build_in_child(
    name: str,
    flags: Sequence[str],
    build_dir: Path,
    env: dict,
    lock_fd: int,
    deadline: float,
    timeout: float,
) -> None:
    """Run torch's build in a child process, killed with its compilers at ``deadline``
    (a build in this process could not be stopped). The child inherits our lock, which
    thus stays held while it runs, even if this process is killed."""
    left = deadline - time.monotonic()
    if left <= 0:
        raise _NotBuilt(f"no time left to build within {timeout:.0f} s ({TIMEOUT_VARIABLE})")
    _tell(
        "building the decoder's C++ kernels in %s (first use of this version on this "
        "machine; docs/performance.md says how long it takes)...",
        build_dir,
    )
    start = time.monotonic()
    seconds = str(math.ceil(left) + 1)  # the child's own limit (its SIGALRM)
    command = [sys.executable, "-c", _BUILD_SCRIPT, seconds, name, str(build_dir), str(SOURCE)]
    child = subprocess.Popen(
        [*command, *flags],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        pass_fds=(lock_fd,),
    )
    try:
        output, _ = child.communicate(timeout=left)
    except subprocess.TimeoutExpired:
        raise _NotBuilt(
            f"the build took longer than {timeout:.0f} s ({TIMEOUT_VARIABLE}) and was stopped"
        ) from None
    finally:
        if child.poll() is None:  # timed out, or this process was interrupted
            kill_tree(child.pid)
            child.communicate()
            # Torch's lock, left by the killed build: ours is still held, so it is stale.
            (build_dir / "lock").unlink(missing_ok=True)
    if child.returncode != 0:
        raise _NotBuilt(_first_error(output, f"the build exited with {child.returncode}"))
    _tell("built the decoder's C++ kernels in %.0f s", time.monotonic() - start)


def _first_error(output: str, otherwise: str) -> str:
    """The compiler's first error in ``output``, else its last line (ninja's own lines and
    a traceback's come last), else ``otherwise``."""
    lines = [line.strip() for line in output.strip().splitlines() if line.strip()]
    return next((line for line in lines if "error:" in line), lines[-1] if lines else otherwise)


def _tell(message: str, *args) -> None:
    """Log at INFO where INFO reaches the terminal (Hydra's apps), else at WARNING: a
    first build makes the user wait, and a plain script shows warnings only."""
    log.log(logging.INFO if log.isEnabledFor(logging.INFO) else logging.WARNING, message, *args)
