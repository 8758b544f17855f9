"""Memory-mapped outputs reserve their disk space first: a full disk is an error naming the file."""

import errno
import os

import numpy as np
import pytest

from pipeline.core import files
from pipeline.core.errors import DataError


def test_reserved_memmap_allocates_every_block(tmp_path):
    path = tmp_path / "a.npy"
    array = files.reserved_memmap(path, (64, 1024), np.float32)
    array[:] = 1.0
    array.flush()
    # Allocated, not sparse: the blocks on disk cover the whole file.
    assert os.stat(path).st_blocks * 512 >= os.stat(path).st_size
    np.testing.assert_array_equal(np.load(path), np.ones((64, 1024), np.float32))


def test_a_full_disk_is_an_error_naming_the_file_and_leaves_nothing(tmp_path, monkeypatch):
    def full(fd, offset, length):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(files.os, "posix_fallocate", full)
    path = tmp_path / "abrdf.npy"
    with pytest.raises(DataError, match=rf"no space left for {path}: it needs 0\.3 MiB"):
        files.reserved_memmap(path, (1000, 81, 1), np.float32)
    assert not path.exists()
