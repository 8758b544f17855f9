"""sha256 records of the files of a cache entry, checked by several threads at once.

A file above :data:`CHUNK_BYTES` gets one sha256 per chunk, so that several threads hash
one large file (hashlib releases the GIL; the time it takes: docs/performance.md).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

HASH = "sha256"  # with SHA extensions faster than blake2b; the manifest names it per file
HASH_BLOCK = 4 << 20  # files are hashed in blocks of this many bytes (bounded memory)
CHUNK_BYTES = 64 << 20
HASH_THREADS = min(8, os.cpu_count() or 1)


def first_changed(
    folder: Path, records: Mapping[str, Mapping], progress: Callable[[int], Any] | None = None
) -> str | None:
    """What differs first between the files under ``folder`` and their ``records``
    (:func:`listed_files`; sizes taken as checked), or None. ``progress(n)`` gets the bytes
    of each file or chunk hashed."""
    pieces = [piece for name, record in records.items() for piece in _pieces(folder / name, record)]
    changed = _first_changed_piece(pieces, progress)
    if changed is None:
        return None
    path, offset, length, _ = changed
    whole = offset == 0 and (length is None or length == path.stat().st_size)
    where = "" if whole else f" of bytes {offset}..{offset + length - 1}"
    return f"{path} has changed: its {HASH}{where} differs from the one in its manifest"


def listed_files(manifest: Mapping) -> dict[str, dict]:
    """``{relative path: record}`` of an entry's manifest. A record is ``{"bytes": n,
    "sha256": hex}``, or for files above :data:`CHUNK_BYTES` ``{"bytes": n, "chunk_bytes":
    c, "sha256_chunks": [hex of bytes 0..c-1, of c..2c-1, ...]}``."""
    return dict(manifest.get("files", {}))


def is_hashed(record: Mapping) -> bool:
    """Whether a file's record (:func:`listed_files`) lets its content be checked."""
    return HASH in record or f"{HASH}_chunks" in record


# A piece of a file to hash: (path, offset, length or None: to the end, expected digest).
Piece = tuple[Path, int, int | None, str | None]


def _pieces(path: Path, record: Mapping) -> list[Piece]:
    """The pieces of a file that its record holds digests of."""
    if f"{HASH}_chunks" in record:
        size, chunk = int(record["bytes"]), int(record["chunk_bytes"])
        return [
            (path, i * chunk, min(chunk, size - i * chunk), digest)
            for i, digest in enumerate(record[f"{HASH}_chunks"])
        ]
    if HASH in record:
        return [(path, 0, record.get("bytes"), record[HASH])]  # no size recorded: to the end
    return []


def range_digest(path: Path, offset: int = 0, length: int | None = None) -> str:
    """sha256 of ``length`` bytes of a file from ``offset`` (None: to its end)."""
    digest = hashlib.new(HASH)
    remaining = float("inf") if length is None else length
    view = memoryview(bytearray(int(min(HASH_BLOCK, max(remaining, 1)))))
    with open(path, "rb", buffering=0) as f:
        f.seek(offset)
        while remaining > 0:
            size = f.readinto(view[: int(min(len(view), remaining))])
            if not size:
                break
            digest.update(view[:size])
            remaining -= size
    return digest.hexdigest()


def _digests(pieces: list[Piece]) -> Iterator[str]:
    """The digest of each piece, in order, computed by up to :data:`HASH_THREADS` threads."""

    def digest(piece: Piece) -> str:
        path, offset, length, _ = piece
        return range_digest(path, offset, length)

    if len(pieces) <= 1 or HASH_THREADS == 1:
        yield from map(digest, pieces)
        return
    pool = ThreadPoolExecutor(HASH_THREADS, thread_name_prefix="cache-hash")
    try:
        yield from pool.map(digest, pieces)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _first_changed_piece(
    pieces: list[Piece], progress: Callable[[int], Any] | None = None
) -> Piece | None:
    """The first piece whose digest differs from the expected one, or None."""
    digests = _digests(pieces)
    with contextlib.closing(digests):  # the threads stop at the first difference
        for piece, found in zip(pieces, digests, strict=False):
            if progress is not None:
                progress(piece[2] or 0)
            if found != piece[3]:
                return piece
    return None


def describe_files(folder: Path, skip: str = "manifest.json") -> dict[str, dict]:
    """The record (:func:`listed_files`) of every file under ``folder`` but ``skip``."""
    sizes = {}
    for path in sorted(folder.rglob("*")):
        name = path.relative_to(folder).as_posix()
        if path.is_file() and name != skip:
            sizes[name] = path.stat().st_size
    pieces = {
        name: [
            (folder / name, offset, min(CHUNK_BYTES, size - offset), None)
            for offset in range(0, max(size, 1), CHUNK_BYTES)
        ]
        for name, size in sizes.items()
    }
    found = iter(list(_digests([piece for name in sizes for piece in pieces[name]])))
    files = {}
    for name, size in sizes.items():
        digests = [next(found) for _ in pieces[name]]
        if size <= CHUNK_BYTES:
            files[name] = {"bytes": size, HASH: digests[0]}
        else:
            files[name] = {"bytes": size, "chunk_bytes": CHUNK_BYTES, f"{HASH}_chunks": digests}
    return files
