"""Processes of this machine: whether one is alive, a process's children, and the
temporary files a process names after itself (what a killed one leaves behind)."""

from __future__ import annotations

import contextlib
import logging
import os
import re
import shutil
import signal
import socket
import time
from collections.abc import Iterable
from pathlib import Path

log = logging.getLogger(__name__)

CHILDREN_GRACE_S = 10.0  # from SIGTERM to SIGKILL for a sweep's workers


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` of this machine exists and has not ended (a zombie has)."""
    if pid <= 0:  # os.kill(0, ...) would address the process group
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    state = _proc_stat(pid)
    return state is None or state[0] not in ("Z", "X")


def children(pid: int | None = None) -> list[int]:
    """The processes whose parent is ``pid`` (default: this process), from ``/proc``."""
    pid = os.getpid() if pid is None else pid
    found = []
    with contextlib.suppress(OSError):
        for entry in os.scandir("/proc"):
            if entry.name.isdigit():
                stat = _proc_stat(int(entry.name))
                if stat is not None and stat[1] == pid:
                    found.append(int(entry.name))
    return found


def descendants(pid: int | None = None) -> list[int]:
    """Children, their children, and so on (those alive now)."""
    found, todo = [], children(pid)
    while todo:
        child = todo.pop()
        found.append(child)
        todo += children(child)
    return found


def stop_children(
    leftovers_in: Iterable[str | os.PathLike] = (), grace_s: float = CHILDREN_GRACE_S
) -> list[int]:
    """SIGTERM this process's children (a sweep's workers: their runs end FAILED), SIGKILL
    what is left of their trees after ``grace_s``, then remove their temporary files under
    ``leftovers_in`` (:func:`remove_temporaries`). Children that ignore SIGTERM (loky's
    resource tracker) are left. Returns the pids signalled."""
    workers = [pid for pid in children() if not _ignores(pid, signal.SIGTERM)]
    tree = workers + [d for pid in workers for d in descendants(pid)]
    _signal_all(workers, signal.SIGTERM)
    _wait(workers, grace_s)
    left = [pid for pid in tree if process_alive(pid)]
    _signal_all(left, signal.SIGKILL)
    if left:
        log.warning("killed processes %s: still running %.0f s after SIGTERM", left, grace_s)
    _wait(left, 5.0)
    # A worker killed before its own cleanup ran (loky kills the others once one is gone).
    remove_temporaries([Path(folder) for folder in leftovers_in], tree)
    return workers


def kill_tree(pid: int) -> None:
    """SIGKILL process ``pid`` and its descendants, ``pid`` last. ninja starts each
    compiler in a process group of its own, which a signal to the build's group would
    miss; each is stopped first, so that none starts another while the tree is listed."""
    tree: list[int] = []
    while found := [p for p in [pid, *descendants(pid)] if p not in tree]:
        _signal_all([p for p in found if p != os.getpid()], signal.SIGSTOP)
        tree += found
    _signal_all(reversed(tree), signal.SIGKILL)


def _signal_all(pids: Iterable[int], signum: int) -> None:
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signum)


def _wait(pids: list[int], timeout_s: float) -> None:
    """Wait until ``pids`` have all ended, for at most ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while any(map(process_alive, pids)) and time.monotonic() < deadline:
        time.sleep(0.05)


def remove_temporaries(folders: Iterable[Path], pids: Iterable[int]) -> list[Path]:
    """Remove the temporary files and folders of processes ``pids`` of this machine, one or
    two levels under ``folders``: hidden names that carry the pid as their owner
    (``.tmp-<key>-<random>-<pid>@<host>``, ``.<name>.partial-<pid>-<random>``,
    ``.mlflow.db.partial-<pid>-journal``). Returns what was removed."""
    host = re.escape(host_name())
    owners = "|".join(str(pid) for pid in pids)
    if not owners:
        return []
    pattern = re.compile(
        rf"\..*-(?:{owners})(?:@{host})?(?:-[0-9a-f]{{8}})?(?:-journal|-wal|-shm)?"
    )
    removed = []
    for folder in folders:
        for path in [*folder.glob(".*"), *folder.glob("*/.*")]:
            if not pattern.fullmatch(path.name):
                continue
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            else:
                with contextlib.suppress(OSError):
                    path.unlink()
            if not path.exists():
                removed.append(path)
    if removed:
        log.info("removed temporary files %s", [str(p) for p in removed])
    return removed


def _proc_stat(pid: int) -> tuple[str, int] | None:
    """(state letter, parent pid) of ``pid`` from ``/proc``; None when unreadable."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return fields[0], int(fields[1])
    except (OSError, IndexError, ValueError):
        return None


def _ignores(pid: int, signum: int) -> bool:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("SigIgn:"):
                return bool(int(line.split()[1], 16) >> (signum - 1) & 1)
    except (OSError, ValueError, IndexError):
        pass
    return False


def host_name() -> str:
    """The host as the cache writes it in temporary names (``pipeline.core.cache``)."""
    return re.sub(r"[^A-Za-z0-9.-]", "_", socket.gethostname()) or "unknown"
