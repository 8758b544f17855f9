"""A small config-hash-keyed artifact cache for pipeline stages.

Every stage's artifacts live in ``<cache root>/<stage>/<key>/`` where ``key`` is the
sha256 of (stage name, the stage's code version, its own resolved settings in canonical
JSON, the keys of the stages it reads). There is no maintained library that does this for
Hydra configs, and the contract is small, so it is written here.

Atomicity: an entry is computed into a temporary sibling folder ``.tmp-<key>-<random>``;
a ``manifest.json`` is written last, then the folder is renamed onto its final name. A
folder without a manifest is never read. When two sweep jobs compute the same key at once,
the first rename wins and the loser discards its copy, so one good entry remains. A killed
run leaves only a ``.tmp-*`` folder, which no reader looks at.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import math
import os
import shutil
import time
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"


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
        return np.load(self.path / f"{name}.npy", mmap_mode="r" if mmap else None)

    def json(self, name: str) -> Any:
        return json.loads((self.path / f"{name}.json").read_text())


class StageCache:
    """The on-disk cache: ``root/<stage>/<key>/``."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    def entry_path(self, stage: str, key: str) -> Path:
        return self.root / stage / key

    def lookup(self, stage: str, key: str) -> Entry | None:
        path = self.entry_path(stage, key)
        manifest = path / MANIFEST
        if not manifest.is_file():
            return None
        return Entry(stage, key, path, hit=True, manifest=json.loads(manifest.read_text()))

    def run(
        self,
        stage: str,
        version: str,
        settings: Mapping,
        inputs: Mapping[str, str],
        compute: Callable[[Path], Mapping | None],
    ) -> Entry:
        """Return the entry for this stage computation, computing it if absent.

        ``compute(folder)`` writes the artifacts into ``folder`` (a fresh temporary
        folder) and may return a small JSON-able summary stored in the manifest. If it
        raises, nothing is left behind under the entry's name.
        """
        key = stage_key(stage, version, settings, inputs)
        start = time.perf_counter()
        found = self.lookup(stage, key)
        if found is not None:
            found.seconds = time.perf_counter() - start
            log.info("stage %-16s hit      key=%s (%.2f s)", stage, key, found.seconds)
            return found

        final = self.entry_path(stage, key)
        final.parent.mkdir(parents=True, exist_ok=True)
        # Jobs of a sweep that need the same entry wait for the one computing it instead of
        # computing it again. The lock is an optimization only: publishing stays atomic
        # without it (file systems where flock does nothing are still safe).
        with open(final.parent / f".lock-{key}", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            found = self.lookup(stage, key)
            if found is not None:
                found.seconds = time.perf_counter() - start
                log.info(
                    "stage %-16s hit      key=%s (%.2f s, after waiting for another job)",
                    stage,
                    key,
                    found.seconds,
                )
                return found
            return self._compute(stage, version, settings, inputs, compute, key, final, start)

    def _compute(self, stage, version, settings, inputs, compute, key, final, start) -> Entry:
        tmp = final.parent / f".tmp-{key}-{uuid.uuid4().hex[:8]}"
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
                "files": sorted(p.name for p in tmp.iterdir()),
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
    stale = final.with_name(f".stale-{final.name}-{uuid.uuid4().hex[:8]}")
    os.rename(final, stale)
    shutil.rmtree(stale, ignore_errors=True)
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
