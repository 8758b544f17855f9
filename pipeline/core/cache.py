"""A config-hash-keyed artifact cache for pipeline stages: ``<root>/<stage>/<key>/``, where
``key`` hashes the stage's name, code version, own resolved settings and its inputs' keys.

Atomicity: an entry is computed into a temporary sibling ``.tmp-<key>-<random>-<pid>@<host>``,
its ``manifest.json`` written last, then renamed onto its name; a folder without a manifest
is never read. Of two jobs computing one key, the first rename wins. A killed run leaves only
a ``.tmp-*`` folder, removed once its owner is gone
(:meth:`StageCache.remove_stale_temporaries`).

Integrity: the manifest records every file's size and sha256 (per 64 MiB chunk for large
files: :mod:`pipeline.core.digests`), and every hit checks every byte. A damaged entry, or
one whose manifest lacks those records, an ``id`` or ``parents``, is logged, removed and
computed again.

Lineage: ``parents`` records each entry the stage read with the ``id`` it had. An entry
whose parent is gone or was computed again since is not a hit, nor are its descendants.
An ancestor's files are hashed when its own stage is hit, which a runner does before
reading it (so :meth:`StageCache.lineage_problem` checks only their sizes);
``verify fix=true`` removes a damaged entry with its descendants.
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
import time
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.digests import describe_files, first_changed, is_hashed, listed_files
from pipeline.core.errors import DataError
from pipeline.core.files import DiskFullError, disk_full_is_named, no_space, write_atomic
from pipeline.core.process import host_name, process_alive

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
# What a full disk while a stage writes its entry advises.
CACHE_HINT = "free some space (python -m pipeline.cache gc) or point paths.cache elsewhere"
# A temporary folder whose owner cannot be asked (a process of another host) is stale once
# untouched this long and its key's lock is free.
STALE_AFTER_S = 24 * 3600
TEMPORARY = ".tmp-"
TRASH = ".trash-"  # folders moved aside to be deleted


def canonical(value: Any) -> Any:
    """``value`` in a canonical, JSON-ready form: mappings with sorted string keys, tuples
    as lists, integral floats as ints (``1`` and ``1.0`` hash the same), numpy scalars as
    Python's. NaN and infinity, with no stable meaning as a setting, are refused."""
    if isinstance(value, Mapping):
        return {str(k): canonical(value[k]) for k in sorted(value, key=str)}
    if isinstance(value, list | tuple):
        return [canonical(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, bool | int | str):
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
    version : the stage's code version; bump it when its output changes.
    settings : the stage's own resolved settings (not the whole config).
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

    def damage(
        self, hashes: bool = True, progress: Callable[[int], Any] | None = None
    ) -> str | None:
        """What is wrong with the entry's own files (naming the first bad one), or None:
        each must have its recorded size and, with ``hashes``, sha256 (``progress``: as
        in :func:`~pipeline.core.digests.first_changed`)."""
        listed = listed_files(self.manifest)
        for name, record in listed.items():
            path = self.path / name
            try:
                size = path.stat().st_size
            except FileNotFoundError:
                return f"{path} is missing"
            if size != record["bytes"]:
                return f"{path} has {size} bytes, its manifest says {record['bytes']}"
        return first_changed(self.path, listed, progress) if hashes else None


def _manifest_problem(manifest: Any) -> str | None:
    """What a manifest lacks of what :meth:`StageCache.run` writes, or None."""
    if not isinstance(manifest, dict):
        return "is not a JSON object"
    if not isinstance(manifest.get("id"), str):
        return "records no id"
    parents = manifest.get("parents")
    if not isinstance(parents, dict) or not all(
        isinstance(p, dict) and isinstance(p.get("stage"), str) and isinstance(p.get("id"), str)
        for p in parents.values()
    ):
        return "records no parents (each one's stage and id)"
    files = manifest.get("files")
    if not isinstance(files, dict) or not all(
        isinstance(r, dict) and isinstance(r.get("bytes"), int) and is_hashed(r)
        for r in files.values()
    ):
        return "records no size and sha256 of each file"
    return None


def _unreadable(path: Path, err: BaseException) -> str:
    return (
        f"cache file {path} cannot be read ({type(err).__name__}: {err}); the entry is "
        f"damaged: remove it (python -m pipeline.cache verify fix=true) and run again"
    )


def folder_bytes(folder: Path) -> int:
    """Total size of the files under ``folder`` (0 when it is gone)."""
    total = 0
    for parent, _dirs, files in os.walk(folder):
        for name in files:
            with contextlib.suppress(OSError):  # removed meanwhile
                total += os.stat(os.path.join(parent, name)).st_size
    return total


class StageCache:
    """The on-disk cache: ``root/<stage>/<key>/``.

    Every entry it hands out is held in use until :meth:`release` (or this object goes): a
    shared lock on ``<stage>/.inuse-<key>``, which :meth:`remove` (``gc``) respects, so a
    job's inputs stay while it runs (on this host, and on file systems whose locks reach
    other hosts)."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        # The entries run() returned, by key: a stage computed from them records their ids.
        self._handed_out: dict[str, Entry] = {}
        self._in_use: dict[str, Any] = {}  # key -> the open file holding its shared lock

    def entry_path(self, stage: str, key: str) -> Path:
        return self.root / stage / key

    def stages(self) -> list[str]:
        """The stages that have a folder in the cache."""
        return _subfolders(self.root)

    def keys(self, stage: str) -> list[str]:
        """The keys of the folders under ``stage`` (complete entries or not)."""
        return _subfolders(self.root / stage)

    def read(self, stage: str, key: str) -> tuple[Entry | None, str | None]:
        """The entry with its manifest, files unchecked: ``(None, None)`` when there is
        none, ``(None, problem)`` when its manifest is missing or unreadable."""
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
        problem = _manifest_problem(content)
        if problem is not None:
            return None, f"{manifest} {problem}"
        return Entry(stage, key, path, hit=True, manifest=content), None

    def check(
        self,
        stage: str,
        key: str,
        hashes: bool = True,
        progress: Callable[[int], Any] | None = None,
    ) -> tuple[Entry | None, str | None]:
        """The entry and what is wrong with it: ``(None, None)`` when there is none,
        ``(entry, None)`` when it can be used, ``(entry or None, problem)`` when not.

        Checked: its files' sizes, its lineage (:meth:`lineage_problem`), then, with
        ``hashes``, its files' hashes (:meth:`Entry.damage`)."""
        entry, problem = self.read(stage, key)
        if entry is None:
            return None, problem
        problem = (
            entry.damage(hashes=False)
            or self.lineage_problem(entry)
            or (entry.damage(True, progress) if hashes else None)
        )
        return entry, problem

    def lineage_problem(self, entry: Entry) -> str | None:
        """Why ``entry`` must not be used for what it was computed from, or None: each
        ancestor must still be there, complete, with the id it had when its child was
        computed and its files at their recorded sizes."""
        seen: set[str] = set()
        todo = [entry]
        while todo:
            child = todo.pop()
            for key, recorded in sorted(child.manifest["parents"].items()):
                if key in seen:
                    continue
                seen.add(key)
                parent, problem = self.read(recorded["stage"], key)
                where = self.entry_path(recorded["stage"], key)
                if parent is None:
                    return f"{child.path} was computed from {where}, which {problem or 'is gone'}"
                if parent.manifest["id"] != recorded["id"]:
                    return (
                        f"{child.path} was computed from {where}, which has been computed "
                        f"again since"
                    )
                problem = parent.damage(hashes=False)
                if problem is not None:
                    return f"{child.path} was computed from {where}, which is damaged: {problem}"
                todo.append(parent)
        return None

    def _stage_of(self, key: str, hint: str | None = None) -> str | None:
        """The stage whose folder holds the entry ``key`` (each key is of one stage), or None."""
        for stage in ([hint] if hint else []) + self.stages():
            if (self.entry_path(stage, key) / MANIFEST).is_file():
                return stage
        return None

    def lookup(self, stage: str, key: str) -> Entry | None:
        """The entry if it can be used, or None (a damaged one is logged and left)."""
        entry, problem = self.check(stage, key)
        if problem is not None:
            log.warning("cache entry %s cannot be used: %s", self.entry_path(stage, key), problem)
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
        """The entry for this stage computation, computed if absent, damaged or computed
        from inputs that have been computed again since.

        ``inputs`` maps a name to the key of each entry the stage reads. ``compute(folder)``
        writes the artifacts into a fresh temporary ``folder`` and may return a small
        JSON-able summary for the manifest; if it raises, nothing is left behind.

        A full disk is a DataError naming the file (or the entry) and the space left.
        """
        key = stage_key(stage, version, settings, inputs)
        start = time.perf_counter()
        found, problem = self.check(stage, key)
        if found is not None and problem is None:
            return self._hand_out(_hit(found, start, ""))

        final = self.entry_path(stage, key)
        final.parent.mkdir(parents=True, exist_ok=True)
        # Jobs needing the same entry wait for the one computing it. An optimization only:
        # publishing stays atomic where flock does nothing.
        with open(final.parent / f".lock-{key}", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            found, problem = self.check(stage, key)
            if found is not None and problem is None:
                return self._hand_out(_hit(found, start, ", after waiting for another job"))
            if problem is not None:
                log.warning("cache entry %s cannot be used: %s; computing it again", final, problem)
                discard(final)
            entry = self._compute(stage, version, settings, inputs, compute, key, final, start)
            return self._hand_out(entry)

    def _hand_out(self, entry: Entry) -> Entry:
        self._handed_out[entry.key] = entry
        if entry.key not in self._in_use:
            # Held open: the lock lasts as long as the file does.
            handle = open(entry.path.parent / f".inuse-{entry.key}", "a")
            try:
                fcntl.flock(handle, fcntl.LOCK_SH | fcntl.LOCK_NB)
                self._in_use[entry.key] = handle
            except OSError:  # a gc is removing it this very moment: nothing to hold
                handle.close()
        return entry

    def release(self) -> None:
        """Stop holding the entries handed out (:class:`StageCache`): a job has ended."""
        for handle in self._in_use.values():
            handle.close()
        self._in_use.clear()

    def _lineage(self, inputs: Mapping[str, str]) -> dict[str, dict]:
        """``{key: {"stage", "id"}}`` of the entries behind ``inputs``: those this cache
        handed out, else those on disk now."""
        parents = {}
        for name, key in sorted(inputs.items()):
            parent = self._handed_out.get(key)
            if parent is None:
                stage = self._stage_of(key, name)
                parent = self.read(stage, key)[0] if stage else None
            if parent is not None:
                parents[key] = {"stage": parent.stage, "id": parent.manifest["id"]}
        return parents

    def _compute(self, stage, version, settings, inputs, compute, key, final, start) -> Entry:
        tmp = final.parent / temporary_name(key)
        tmp.mkdir()
        try:
            parents = self._lineage(inputs)
            # numpy and torch lose a full disk's errno: name the entry and the space left.
            with disk_full_is_named(final, CACHE_HINT):
                summary = compute(tmp) or {}
                manifest = {
                    "stage": stage,
                    "version": version,
                    "key": key,
                    "id": uuid.uuid4().hex,
                    "settings": canonical(settings),
                    "inputs": dict(inputs),
                    "parents": parents,
                    "summary": canonical(summary),
                    "files": describe_files(tmp, skip=MANIFEST),
                    "created": time.time(),
                }
                # No fsync: a crash that left the entry short fails its manifest's checks.
                text = json.dumps(manifest, indent=1)
                write_atomic(tmp / MANIFEST, text, sync=False, hint=CACHE_HINT)
            if not publish(tmp, final):
                # Another job published the same key first: hand out its entry (its id).
                entry, _ = self.read(stage, key)
                manifest = entry.manifest if entry is not None else manifest
        except BaseException as error:
            shutil.rmtree(tmp, ignore_errors=True)
            if not isinstance(error, DiskFullError):
                raise
            # Named as the entry's file, with the space free once the partial entry is gone.
            named = Path(str(error.path).replace(str(tmp), str(final)))
            raise no_space(named, needed=error.needed, hint=error.hint) from error
        seconds = time.perf_counter() - start
        log.info("stage %-16s computed key=%s (%.2f s)", stage, key, seconds)
        return Entry(stage, key, final, hit=False, seconds=seconds, manifest=manifest)

    def remove(
        self,
        stage: str,
        key: str,
        unless_used_since: float | None = None,
        even_in_use: bool = False,
    ) -> bool:
        """Delete an entry unless a job computes it (its key's lock), holds it in use
        (unless ``even_in_use``: a damaged entry goes all the same) or, with
        ``unless_used_since`` (a time.time()), used it since. Returns whether it went."""
        path = self.entry_path(stage, key)
        if not path.parent.is_dir():
            return False
        held = self._in_use.pop(key, None)
        if held is not None:  # this cache's own hold does not keep the entry from itself
            held.close()
        with (
            open(path.parent / f".lock-{key}", "a") as lock,
            open(path.parent / f".inuse-{key}", "a") as in_use,
        ):
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                if not even_in_use:
                    fcntl.flock(in_use, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                return False
            if unless_used_since is not None and last_used(path) >= unless_used_since:
                return False
            return discard(path)

    def temporaries(self) -> list[Path]:
        """The temporary and moved-aside folders of every stage."""
        return sorted(p for prefix in (TEMPORARY, TRASH) for p in self.root.glob(f"*/{prefix}*"))

    def remove_stale_temporaries(self, dry_run: bool = False) -> list[tuple[Path, str]]:
        """Remove the temporary folders of computations that died (:func:`_why_stale`) and
        folders left moved aside; returns ``(folder, why)`` for each (``dry_run``: of those
        it would remove)."""
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
    # The manifest's mtime records the last use, for gc (not in a read-only cache).
    with contextlib.suppress(OSError):
        os.utime(entry.path / MANIFEST)
    log.info("stage %-16s hit      key=%s (%.2f s%s)", entry.stage, entry.key, entry.seconds, note)
    return entry


def last_used(path: Path) -> float:
    """When the entry at ``path`` was published or last hit (its manifest's mtime; 0 when
    there is none)."""
    try:
        return (path / MANIFEST).stat().st_mtime
    except OSError:
        return 0.0


def temporary_name(key: str) -> str:
    """The name of the folder an entry is computed in: its key and owner (pid@host)."""
    return f"{TEMPORARY}{key}-{uuid.uuid4().hex[:8]}-{os.getpid()}@{host_name()}"


def _why_stale(folder: Path) -> str | None:
    """Why ``folder`` (a temporary or moved-aside folder) may go, or None to keep it: a
    temporary folder of this host once its process is gone, of another host once untouched
    for :data:`STALE_AFTER_S` with its key's lock free."""
    if folder.name.startswith(TRASH):
        return "moved aside to be deleted"
    match = re.fullmatch(rf"{re.escape(TEMPORARY)}([^-]+)-[^-]+-(\d+)@(.+)", folder.name)
    if match is None:
        return None  # not named by temporary_name: not the cache's to remove
    key, pid, host = match.groups()
    if host == host_name():
        return None if process_alive(int(pid)) else f"its process {pid} on this host is gone"
    age = time.time() - _newest_mtime(folder)
    if age < STALE_AFTER_S:
        return None
    with open(folder.parent / f".lock-{key}", "a") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return None  # a job is computing this key
        fcntl.flock(lock, fcntl.LOCK_UN)
    return f"of {pid}@{host}, untouched for {age / 3600:.0f} h, its key unlocked"


def _newest_mtime(folder: Path) -> float:
    newest = 0.0
    for path in [folder, *folder.iterdir()] if folder.is_dir() else []:
        with contextlib.suppress(OSError):
            newest = max(newest, path.stat().st_mtime)
    return newest


def _subfolders(folder: Path) -> list[str]:
    """The names of ``folder``'s subfolders, hidden ones left out (none when it is gone)."""
    if not folder.is_dir():
        return []
    return sorted(p.name for p in folder.iterdir() if p.is_dir() and p.name[0] != ".")


def discard(path: Path) -> bool:
    """Move ``path`` aside (atomically: no reader sees half of it) and delete it."""
    trash = path.with_name(f"{TRASH}{path.name}-{uuid.uuid4().hex[:8]}")
    try:
        os.rename(path, trash)
    except FileNotFoundError:
        return False
    shutil.rmtree(trash, ignore_errors=True)
    return True


def publish(tmp: Path, final: Path) -> bool:
    """Rename ``tmp`` onto ``final`` unless a complete entry is already there; returns
    whether ``tmp`` became the entry (False: another job's entry was kept)."""
    with contextlib.suppress(OSError):
        os.rename(tmp, final)
        return True
    if not (final / MANIFEST).is_file():
        # A folder without a manifest is no entry (it came from outside): move it aside.
        discard(final)
        try:
            os.rename(tmp, final)
            return True
        except OSError:
            if not (final / MANIFEST).is_file():
                raise
    # Another job finished the same key first: its entry is as good as ours.
    shutil.rmtree(tmp, ignore_errors=True)
    return False


def save_arrays(folder: Path, **arrays: np.ndarray) -> None:
    """Write each array as ``<name>.npy`` (memory-mappable); a full disk is a
    :class:`DataError` naming the file."""
    for name, array in arrays.items():
        path = folder / f"{name}.npy"
        with disk_full_is_named(path, CACHE_HINT):
            np.save(path, np.asarray(array))


def save_json(folder: Path, name: str, value: Any) -> None:
    """Write ``value`` as ``<name>.json`` (canonical: sorted keys, 1.0 as 1); a full disk
    is a :class:`DataError` naming the file."""
    path = folder / f"{name}.json"
    with disk_full_is_named(path, CACHE_HINT):
        path.write_text(json.dumps(canonical(value), indent=1))
