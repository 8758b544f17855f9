"""Writing files safely: atomically, with a full disk reported as an error naming the file.

- :func:`write_atomic` is the one way the project publishes a file (temporary sibling,
  fsync, rename): a reader sees the old file or the new one, never a 0-byte table.
- A full disk is a :class:`~pipeline.core.errors.DataError` naming the file and the space
  left (:func:`no_space`), whatever library was writing; some lose the errno (numpy, torch),
  so a failed write on a (nearly) full disk counts as one too (:func:`is_disk_full`).
- :func:`reserved_memmap`: a ``.npy`` memory map with its blocks allocated first: a sparse
  file meeting a full disk kills the process with SIGBUS (no cleanup, the run left RUNNING).
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from pipeline.core.errors import DataError

_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
# Their C library texts, which libraries that lose the errno still quote (OpenEXR), and
# SQLite's for SQLITE_FULL, all that reaches MLflow's store from a full disk.
_FULL_TEXTS = (*(os.strerror(number) for number in _FULL_ERRNOS), "database or disk is full")
# A write that failed while less than this is free failed for want of space.
NEARLY_FULL_BYTES = 1 << 20


def human(n: float) -> str:
    """A size in bytes for people.

    >>> human(1536), human(3 << 30)
    ('1.5 KiB', '3.0 GiB')
    """
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"


def free_bytes(path: str | os.PathLike) -> int | None:
    """Bytes free for this user on the file system holding ``path`` (or its nearest
    existing parent); None when that cannot be asked."""
    path = Path(path)
    for folder in (path, *path.parents):
        with contextlib.suppress(OSError):
            if folder.exists():
                return shutil.disk_usage(folder).free
    return None


def error_chain(error: BaseException | None) -> Iterator[BaseException]:
    """``error`` and the exceptions it was raised from (``__cause__``, ``__context__``)."""
    seen: set[int] = set()
    while error is not None and id(error) not in seen:
        seen.add(id(error))
        yield error
        error = error.__cause__ or error.__context__


def is_disk_full(error: BaseException, free: int | None = None) -> bool:
    """Whether ``error`` (raised by a write) means the disk or the quota is full.

    True when it or its causes carry ENOSPC or EDQUOT or quote their text (or SQLite's);
    or when it is an OSError without an errno or a RuntimeError (what libraries that lose
    the errno raise) and ``free``, the bytes free when it was raised, is below
    :data:`NEARLY_FULL_BYTES`.
    """
    for cause in error_chain(error):
        if isinstance(cause, OSError) and cause.errno in _FULL_ERRNOS:
            return True
        if any(text in str(cause) for text in _FULL_TEXTS):
            return True
    errno_lost = isinstance(error, RuntimeError) or (
        isinstance(error, OSError) and error.errno is None
    )
    return errno_lost and free is not None and free < NEARLY_FULL_BYTES


class DiskFullError(DataError):
    """A write the disk (or the quota) could not hold: its ``path``, the bytes it
    ``needed`` when known, the ``free`` bytes measured and what to do (``hint``)."""

    def __init__(self, path: Path, free: int | None, needed: int | None, hint: str):
        if needed is None:
            needs = ""
        elif needed < 1 << 16:
            needs = f"it needs {needed} bytes, "
        else:
            needs = f"it needs {needed / 2**20:.1f} MiB ({needed} bytes), "
        left = "an unknown amount" if free is None else human(free)
        super().__init__(f"no space left for {path}: {needs}{left} free in {path.parent}; {hint}")
        self.path, self.free, self.needed, self.hint = path, free, needed, hint


def no_space(
    path: str | os.PathLike,
    free: int | None = None,
    needed: int | None = None,
    hint: str = "free some space or write elsewhere",
) -> DiskFullError:
    """The error for a write of ``path`` that the disk could not hold (``free``: measured
    now when None).

    >>> str(no_space("/r/tables/t.csv", free=24 << 10, needed=59))
    'no space left for /r/tables/t.csv: it needs 59 bytes, 24.0 KiB free in /r/tables; free some space or write elsewhere'
    """
    path = Path(path)
    return DiskFullError(path, free_bytes(path.parent) if free is None else free, needed, hint)


@contextlib.contextmanager
def disk_full_is_named(
    path: str | os.PathLike, hint: str = "free some space or write elsewhere"
) -> Iterator[None]:
    """Turn a full disk while the block writes ``path`` into :func:`no_space`'s
    :class:`DiskFullError` (other errors pass unchanged). The space it names is measured
    at once: a caller that removes what was written may raise a new one after."""
    try:
        yield
    except Exception as error:
        if isinstance(error, DataError):
            raise
        free = free_bytes(Path(path).parent)
        if is_disk_full(error, free):
            raise no_space(path, free, hint=hint) from error
        raise


def temporary_sibling(path: str | os.PathLike) -> Path:
    """A fresh hidden name in ``path``'s folder that keeps its extension (libraries that
    pick the format from it, such as ``savefig``, still do): ``.t.1a2b3c4d.tmp.csv``."""
    path = Path(path)
    return path.with_name(f".{path.stem}.{uuid.uuid4().hex[:8]}.tmp{path.suffix}")


def write_atomic(
    path: str | os.PathLike,
    content: bytes | str | Callable[[Path], object],
    *,
    sync: bool = True,
    hint: str = "free some space or write elsewhere",
) -> Path:
    """Write a file so that ``path`` holds the old file or the whole new one, never a part:
    a temporary sibling (:func:`temporary_sibling`), synced, renamed onto ``path``; on any
    failure it is removed and ``path`` left as it was.

    Parameters
    ----------
    path : the file to write; returned.
    content : bytes, or str (written as UTF-8), or a callable ``writer(tmp)`` that writes
        the whole file at the path ``tmp`` it is given, e.g.
        ``lambda tmp: fig.savefig(tmp, dpi=110)``.
    sync : fsync the file before the rename (False for files in a staging folder that is
        published as a whole).
    hint : what the disk-full error advises.

    Raises
    ------
    DataError
        Naming ``path`` and the space left, when the disk is full (:func:`is_disk_full`).
    """
    path = Path(path)
    tmp = temporary_sibling(path)
    data = content.encode() if isinstance(content, str) else content
    try:
        if callable(data):
            data(tmp)
        else:
            tmp.write_bytes(data)
        if sync:
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        os.replace(tmp, path)
    except BaseException as error:
        free = free_bytes(path.parent)  # before the temporary file gives its space back
        tmp.unlink(missing_ok=True)
        unnamed = isinstance(error, Exception) and not isinstance(error, DataError)
        if unnamed and is_disk_full(error, free):
            # The space named is what is free once the temporary file is gone.
            raise no_space(path, needed=None if callable(data) else len(data), hint=hint) from error
        raise
    return path


def reserved_memmap(path: str | os.PathLike, shape: tuple[int, ...], dtype) -> np.memmap:
    """``np.lib.format.open_memmap(path, "w+", dtype, shape)`` with every block allocated.

    Raises
    ------
    DataError
        Naming ``path`` and the bytes it needs, when the disk cannot hold it (the
        partial file is removed).
    """
    path = Path(path)
    array = np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=shape)
    size = path.stat().st_size
    fd = os.open(path, os.O_RDWR)
    try:
        os.posix_fallocate(fd, 0, size)
    except OSError as error:
        if error.errno in (errno.EOPNOTSUPP, errno.EINVAL):
            return array  # a file system that cannot reserve: as open_memmap alone
        del array
        path.unlink(missing_ok=True)
        if error.errno in _FULL_ERRNOS:
            raise no_space(
                path, needed=size, hint="free some space or point paths.cache elsewhere"
            ) from None
        raise
    finally:
        os.close(fd)
    return array


def output_array(out: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    """``out`` (a caller's array, e.g. a memory map) checked to be a writeable float32
    array of ``shape``, or a new one when None."""
    from pipeline.core.errors import ConfigError

    if out is None:
        return np.empty(shape, dtype=np.float32)
    if out.shape != shape or out.dtype != np.float32 or not out.flags.writeable:
        raise ConfigError(
            f"out array has shape {out.shape}, dtype {out.dtype}, "
            f"writeable={out.flags.writeable}; need shape {shape}, float32, writeable"
        )
    return out
