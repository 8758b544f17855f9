"""A small config-hash-keyed artifact cache for pipeline stages.

Every stage's artifacts live in ``<cache root>/<stage>/<key>/`` where ``key`` is the
sha256 of (stage name, the stage's code version, its own resolved settings in canonical
JSON, the keys of the stages it reads). There is no maintained library that does this for
Hydra configs, and the contract is small, so it is written here.

Atomicity: an entry is computed into a temporary sibling folder
``.tmp-<key>-<random>-<pid>@<host>``; a ``manifest.json`` is written last, then the folder
is renamed onto its final name. A folder without a manifest is never read. When two sweep
jobs compute the same key at once, the first rename wins and the loser discards its copy,
so one good entry remains. A killed run leaves only a ``.tmp-*`` folder, which no reader
looks at and :meth:`StageCache.remove_stale_temporaries` removes once its owner is gone.

Integrity: the manifest lists every file with its size and sha256. Each hit checks that
the files are there with their sizes, and their hashes too when the entry holds at most
:data:`HASH_ON_HIT_BYTES`; ``python -m pipeline.cache verify`` checks every hash. A damaged
entry is never read: :meth:`StageCache.run` logs it, removes it and computes it again.
Entries written before sizes and hashes were recorded are checked for presence only.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import logging
import math
import os
import re
import shutil
import socket
import time
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.errors import DataError

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
HASH = "sha256"  # with SHA extensions faster than blake2b; the manifest names it per file
HASH_BLOCK = 4 << 20  # files are hashed in blocks of this many bytes (bounded memory)
# Entries of at most this many bytes have their hashes checked on every hit (a fraction of
# a second); larger ones only their sizes, their hashes by `python -m pipeline.cache verify`.
HASH_ON_HIT_BYTES = 64 << 20
# A temporary folder whose owner cannot be asked (another host, or written before owners
# were recorded) is stale once untouched this long and its key's lock is free.
STALE_AFTER_S = 24 * 3600
TEMPORARY = ".tmp-"
TRASH = (".trash-", ".stale-")  # folders moved aside to be deleted (.stale-: older code)


def canonical(value: Any) -> Any:
    """Return ``value`` in a canonical, JSON-ready form.

    Mappings get sorted string keys, tuples become lists, integral floats become ints (so
    ``1`` and ``1.0`` hash the same), numpy scalars become Python scalars. NaN and infinity
    are rejected: they have no stable meaning as a setting.
    """
    if isinstance(value, Mapping):
        return {str(k): canonical(value[k]) for k in sorted(value, key=str)}
    if isinstance(value, list | tuple):
        return [canonical(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"cannot hash a non-finite setting: {value!r}")
        return int(value) if value.is_integer() else value
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot hash a setting of type {type(value).__name__}: {value!r}")


def canonical_json(value: Any) -> str:
    return json.dumps(canonical(value), sort_keys=True, separators=(",", ":"))


def stage_key(stage: str, version: str, settings: Mapping, inputs: Mapping[str, str]) -> str:
    """The cache key of one stage computation.

    Parameters
    ----------
    stage : name of the stage (``"pca"``).
    version : version string of the stage's code; bump it when its output changes.
    settings : the stage's own resolved settings (only those; not the whole config).
    inputs : ``{input stage name: its key}`` for every stage it reads.
    """
    payload = canonical_json(
        {"stage": stage, "version": version, "settings": settings, "inputs": inputs}
    )
    return hashlib.sha256(payload.encode()).hexdigest()[:20]


@dataclass
class Entry:
    """A complete cache entry: a folder of artifacts plus its manifest."""

    stage: str
    key: str
    path: Path
    hit: bool = False
    seconds: float = 0.0
    manifest: dict = field(default_factory=dict)

    def file(self, name: str) -> Path:
        return self.path / name

    def array(self, name: str, mmap: bool = True) -> np.ndarray:
        """Load ``<name>.npy``, memory-mapped read-only by default."""
        path = self.path / f"{name}.npy"
        try:
            return np.load(path, mmap_mode="r" if mmap else None)
        except (OSError, ValueError, EOFError) as err:
            raise DataError(_unreadable(path, err)) from err

    def json(self, name: str) -> Any:
        path = self.path / f"{name}.json"
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise DataError(_unreadable(path, err)) from err

    def damage(self, hashes: bool | None = None, progress: Callable[[int], Any] | None = None
               ) -> str | None:
        """What is wrong with the entry's files (naming the first bad one), or None.

        Every listed file must exist with its recorded size. ``hashes``: also compare the
        sha256 of every file (None: only when the entry holds at most
        :data:`HASH_ON_HIT_BYTES`). ``progress(n)`` is called with each block's bytes.
        """
        listed = listed_files(self.manifest)
        total = 0
        for name, record in listed.items():
            path = self.path / name
            try:
                size = path.stat().st_size
            except FileNotFoundError:
                return f"{path} is missing"
            total += size
            if "bytes" in record and size != record["bytes"]:
                return f"{path} has {size} bytes, its manifest says {record['bytes']}"
        if hashes is None:
            hashes = total <= HASH_ON_HIT_BYTES
        for name, record in listed.items() if hashes else ():
            path = self.path / name
            if HASH in record and file_digest(path, progress) != record[HASH]:
                return f"{path} has changed: its {HASH} differs from the one in its manifest"
        return None


def _unreadable(path: Path, err: BaseException) -> str:
    return (f"cache file {path} cannot be read ({type(err).__name__}: {err}); the entry is "
            f"damaged: remove it (python -m pipeline.cache verify --fix) and run again")


def listed_files(manifest: Mapping) -> dict[str, dict]:
    """``{relative path: {"bytes": n, "sha256": hex}}`` of an entry's manifest; entries
    written before sizes and hashes were recorded list names only (``{name: {}}``)."""
    files = manifest.get("files", {})
    if isinstance(files, list):
        return {name: {} for name in files}
    return dict(files)


def file_digest(path: Path, progress: Callable[[int], Any] | None = None) -> str:
    """sha256 of a file, read in blocks of :data:`HASH_BLOCK` bytes."""
    digest = hashlib.new(HASH)
    block = bytearray(HASH_BLOCK)
    view = memoryview(block)
    with open(path, "rb", buffering=0) as f:
        while size := f.readinto(block):
            digest.update(view[:size])
            if progress is not None:
                progress(size)
    return digest.hexdigest()


def describe_files(folder: Path) -> dict[str, dict]:
    """Size and sha256 of every file under ``folder`` but its manifest, by relative path."""
    files = {}
    for path in sorted(folder.rglob("*")):
        name = path.relative_to(folder).as_posix()
        if path.is_file() and name != MANIFEST:
            files[name] = {"bytes": path.stat().st_size, HASH: file_digest(path)}
    return files


def folder_bytes(folder: Path) -> int:
    """Total size of the files under ``folder`` (0 when it is gone)."""
    total = 0
    for parent, _dirs, files in os.walk(folder):
        for name in files:
            try:
                total += os.stat(os.path.join(parent, name)).st_size
            except OSError:  # removed meanwhile
                pass
    return total


class StageCache:
    """The on-disk cache: ``root/<stage>/<key>/``."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    def entry_path(self, stage: str, key: str) -> Path:
        return self.root / stage / key

    def stages(self) -> list[str]:
        """The stages that have a folder in the cache."""
        if not self.root.is_dir():
            return []
        return sorted(p.name for p in self.root.iterdir() if p.is_dir() and p.name[0] != ".")

    def keys(self, stage: str) -> list[str]:
        """The keys of the folders under ``stage`` (complete entries or not)."""
        folder = self.root / stage
        if not folder.is_dir():
            return []
        return sorted(p.name for p in folder.iterdir() if p.is_dir() and p.name[0] != ".")

    def check(self, stage: str, key: str, hashes: bool | None = None,
              progress: Callable[[int], Any] | None = None) -> tuple[Entry | None, str | None]:
        """The entry and what is wrong with it: ``(None, None)`` when there is none,
        ``(entry, None)`` when it is intact, ``(entry or None, problem)`` when damaged.
        ``hashes`` and ``progress``: as in :meth:`Entry.damage`."""
        path = self.entry_path(stage, key)
        manifest = path / MANIFEST
        if not path.is_dir():
            return None, None
        if not manifest.is_file():
            return None, f"{path} has no {MANIFEST} (not a complete entry)"
        try:
            content = json.loads(manifest.read_text())
        except (OSError, ValueError) as err:
            return None, f"{manifest} cannot be read ({type(err).__name__}: {err})"
        if not isinstance(content, dict):
            return None, f"{manifest} is not a JSON object"
        entry = Entry(stage, key, path, hit=True, manifest=content)
        return entry, entry.damage(hashes, progress)

    def lookup(self, stage: str, key: str) -> Entry | None:
        """The intact entry, or None (a damaged one is logged and left in place)."""
        entry, problem = self.check(stage, key)
        if problem is not None:
            log.warning("cache entry %s is damaged and not used: %s",
                        self.entry_path(stage, key), problem)
            return None
        return entry

    def run(
        self,
        stage: str,
        version: str,
        settings: Mapping,
        inputs: Mapping[str, str],
        compute: Callable[[Path], Mapping | None],
    ) -> Entry:
        """Return the entry for this stage computation, computing it if absent or damaged.

        ``compute(folder)`` writes the artifacts into ``folder`` (a fresh temporary
        folder) and may return a small JSON-able summary stored in the manifest. If it
        raises, nothing is left behind under the entry's name.
        """
        key = stage_key(stage, version, settings, inputs)
        start = time.perf_counter()
        found, problem = self.check(stage, key)
        if found is not None and problem is None:
            return _hit(found, start, "")

        final = self.entry_path(stage, key)
        final.parent.mkdir(parents=True, exist_ok=True)
        # Jobs of a sweep that need the same entry wait for the one computing it instead of
        # computing it again. The lock is an optimization only: publishing stays atomic
        # without it (file systems where flock does nothing are still safe).
        with open(final.parent / f".lock-{key}", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            found, problem = self.check(stage, key)
            if found is not None and problem is None:
                return _hit(found, start, ", after waiting for another job")
            if problem is not None:
                log.warning("cache entry %s is damaged: %s; computing it again", final, problem)
                discard(final)
            return self._compute(stage, version, settings, inputs, compute, key, final, start)

    def _compute(self, stage, version, settings, inputs, compute, key, final, start) -> Entry:
        tmp = final.parent / temporary_name(key)
        tmp.mkdir()
        try:
            summary = compute(tmp) or {}
            manifest = {
                "stage": stage,
                "version": version,
                "key": key,
                "settings": canonical(settings),
                "inputs": dict(inputs),
                "summary": canonical(summary),
                "files": describe_files(tmp),
                "created": time.time(),
            }
            _write_atomic(tmp / MANIFEST, json.dumps(manifest, indent=1))
            publish(tmp, final)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        seconds = time.perf_counter() - start
        log.info("stage %-16s computed key=%s (%.2f s)", stage, key, seconds)
        return Entry(stage, key, final, hit=False, seconds=seconds, manifest=manifest)

    def remove(self, stage: str, key: str, unless_used_since: float | None = None) -> bool:
        """Delete an entry unless a job holds its key's lock (computing it) or, with
        ``unless_used_since`` (a time.time()), it was used or rewritten since then.
        Returns whether it was removed."""
        path = self.entry_path(stage, key)
        if not path.parent.is_dir():
            return False
        with open(path.parent / f".lock-{key}", "a") as lock:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                return False
            if unless_used_since is not None and last_used(path) >= unless_used_since:
                return False
            return discard(path)

    def temporaries(self) -> list[Path]:
        """The temporary and moved-aside folders of every stage (a glob, nothing more)."""
        patterns = (f"{TEMPORARY}*", *(f"{prefix}*" for prefix in TRASH))
        return sorted(p for pattern in patterns for p in self.root.glob(f"*/{pattern}"))

    def remove_stale_temporaries(self, dry_run: bool = False) -> list[tuple[Path, str]]:
        """Remove the temporary folders of computations that died, and folders left moved
        aside; returns ``(folder, why)`` for each (with ``dry_run``, removes nothing).

        A temporary folder of a process on this host is stale once that process is gone;
        one of another host, or of unknown owner, once nothing in it changed for
        :data:`STALE_AFTER_S` and no job holds its key's lock."""
        removed = []
        for folder in self.temporaries():
            why = _why_stale(folder)
            if why is None:
                continue
            if not dry_run:
                shutil.rmtree(folder, ignore_errors=True)
                if folder.exists():
                    continue
                log.info("removed %s (%s)", folder, why)
            removed.append((folder, why))
        return removed


def _hit(entry: Entry, start: float, note: str) -> Entry:
    entry.seconds = time.perf_counter() - start
    # The manifest's mtime says when the entry was last used (gc keeps what running jobs
    # used); a read-only cache simply does not record it.
    with contextlib.suppress(OSError):
        os.utime(entry.path / MANIFEST)
    log.info("stage %-16s hit      key=%s (%.2f s%s)", entry.stage, entry.key, entry.seconds, note)
    return entry


def last_used(path: Path) -> float:
    """When the entry at ``path`` was published or last hit by :meth:`StageCache.run`
    (its manifest's mtime, a time.time(); 0 when there is none)."""
    try:
        return (path / MANIFEST).stat().st_mtime
    except OSError:
        return 0.0


def temporary_name(key: str) -> str:
    """The name of the folder an entry is computed in: its key and owner (pid@host)."""
    return f"{TEMPORARY}{key}-{uuid.uuid4().hex[:8]}-{os.getpid()}@{_host()}"


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9.-]", "_", socket.gethostname()) or "unknown"


def _why_stale(folder: Path) -> str | None:
    """Why ``folder`` (a temporary or moved-aside folder) may go, or None to keep it."""
    if folder.name.startswith(TRASH):
        return "moved aside to be deleted"
    match = re.fullmatch(rf"{re.escape(TEMPORARY)}([^-]+)-[^-]+(?:-(\d+)@(.+))?", folder.name)
    if match is None:
        return None
    key, pid, host = match.groups()
    if pid is not None and host == _host():
        return None if _alive(int(pid)) else f"its process {pid} on this host is gone"
    age = time.time() - _newest_mtime(folder)
    if age < STALE_AFTER_S:
        return None
    with open(folder.parent / f".lock-{key}", "a") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return None  # a job is computing this key
        fcntl.flock(lock, fcntl.LOCK_UN)
    owner = f"of {pid}@{host}" if pid is not None else "of unknown owner"
    return f"{owner}, untouched for {age / 3600:.0f} h, its key unlocked"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _newest_mtime(folder: Path) -> float:
    newest = 0.0
    for path in [folder, *folder.iterdir()] if folder.is_dir() else []:
        with contextlib.suppress(OSError):
            newest = max(newest, path.stat().st_mtime)
    return newest


def discard(path: Path) -> bool:
    """Move ``path`` aside (atomically: no reader sees half of it) and delete it."""
    trash = path.with_name(f"{TRASH[0]}{path.name}-{uuid.uuid4().hex[:8]}")
    try:
        os.rename(path, trash)
    except FileNotFoundError:
        return False
    shutil.rmtree(trash, ignore_errors=True)
    return True


def publish(tmp: Path, final: Path) -> None:
    """Rename ``tmp`` onto ``final`` unless a complete entry is already there."""
    try:
        os.rename(tmp, final)
        return
    except OSError:
        if (final / MANIFEST).is_file():
            # Another job finished the same key first: its entry is as good as ours.
            shutil.rmtree(tmp, ignore_errors=True)
            return
    # A folder without a manifest under the final name is not an entry (it can only come
    # from outside the cache): move it aside and publish ours.
    discard(final)
    try:
        os.rename(tmp, final)
    except OSError:
        if not (final / MANIFEST).is_file():
            raise
        shutil.rmtree(tmp, ignore_errors=True)


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}")
    tmp.write_text(text)
    os.replace(tmp, path)


def save_arrays(folder: Path, **arrays: np.ndarray) -> None:
    """Write each array as ``<name>.npy`` (memory-mappable)."""
    for name, array in arrays.items():
        np.save(folder / f"{name}.npy", np.asarray(array))


def save_json(folder: Path, name: str, value: Any) -> None:
    (folder / f"{name}.json").write_text(json.dumps(canonical(value), indent=1))
