"""Files written through memory maps, with their disk space reserved first.

A ``.npy`` opened with ``np.lib.format.open_memmap(mode="w+")`` is a sparse file: its blocks
are only allocated when a page is first written through the mapping, and if the disk is
full then, the kernel kills the process with SIGBUS (no exception, no cleanup, the MLflow
run left RUNNING). Reserving the blocks up front (``posix_fallocate``) turns a full disk
into an ordinary error that names the file.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np

from pipeline.core.errors import DataError


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
        if error.errno in (errno.ENOSPC, errno.EDQUOT):
            raise DataError(
                f"no space left for {path}: it needs {size / 2**20:.1f} MiB "
                f"({size} bytes); free some space or point paths.cache elsewhere"
            ) from None
        raise
    finally:
        os.close(fd)
    return array
