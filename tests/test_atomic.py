"""``write_atomic``: the file is whole or absent, its temporary name goes, a full disk is
named; images are written through it, and an image the decoder rejects is named."""

from __future__ import annotations

import errno
import os
import re

import numpy as np
import pandas as pd
import pytest

from pipeline.core import files
from pipeline.core.errors import DataError
from pipeline.core.report import write_table
from pipeline.data.images import image_size, read_image_8bit, write_image_8bit


def _left(folder) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


@pytest.mark.parametrize("content", [b"\x00\x01abc", "table ± text"])
def test_bytes_and_text_are_written_and_synced(tmp_path, monkeypatch, content):
    synced = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: synced.append(fd) or real_fsync(fd))
    path = files.write_atomic(tmp_path / "a.csv", content)
    expected = content.encode() if isinstance(content, str) else content
    assert path.read_bytes() == expected and len(synced) == 1
    assert _left(tmp_path) == ["a.csv"]
    files.write_atomic(path, b"new", sync=False)
    assert path.read_bytes() == b"new" and len(synced) == 1


def test_a_writer_gets_a_temporary_path_with_the_same_extension(tmp_path):
    seen = []

    def writer(tmp):
        seen.append(tmp)
        np.save(tmp, np.arange(3))  # np.save appends .npy to a name without it

    files.write_atomic(tmp_path / "x.npy", writer)
    assert seen[0].parent == tmp_path and seen[0].suffix == ".npy" and seen[0].name[0] == "."
    np.testing.assert_array_equal(np.load(tmp_path / "x.npy"), np.arange(3))
    assert _left(tmp_path) == ["x.npy"]


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "t.md"
    path.write_text("old")

    def half_then_fail(tmp):
        tmp.write_text("half")
        raise RuntimeError("the writer broke")

    with pytest.raises(RuntimeError, match="the writer broke"):
        files.write_atomic(path, half_then_fail)
    assert path.read_text() == "old" and _left(tmp_path) == ["t.md"]


def test_enospc_is_a_data_error_naming_the_file_and_the_space_left(tmp_path, monkeypatch):
    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    monkeypatch.setattr(files, "free_bytes", lambda path: 24 << 10)
    path = tmp_path / "table2_rmse.csv"
    with pytest.raises(DataError) as caught:
        files.write_atomic(path, "x" * 59)
    assert str(caught.value) == (
        f"no space left for {path}: it needs 59 bytes, 24.0 KiB free "
        f"in {tmp_path}; free some space or write elsewhere"
    )
    assert isinstance(caught.value.__cause__, OSError)
    assert _left(tmp_path) == []


@pytest.mark.parametrize(
    "error, free, full",
    [
        (OSError(errno.EDQUOT, os.strerror(errno.EDQUOT)), 1 << 30, True),
        (RuntimeError('Failed to write "x.exr". No space left on device.'), 1 << 30, True),
        # numpy and torch lose the errno: a failed write on a full disk is one all the same
        (OSError("400000 requested and 131056 written"), 0, True),
        (RuntimeError("unexpected pos 576 vs 534"), 4096, True),
        (OSError("400000 requested and 131056 written"), 1 << 30, False),
        (ValueError("not a number"), 0, False),
        (PermissionError(errno.EACCES, "Permission denied"), 0, False),  # an errno, not ENOSPC
    ],
)
def test_what_counts_as_a_full_disk(error, free, full):
    assert files.is_disk_full(error, free) is full


def test_a_cause_carrying_enospc_counts():
    try:
        try:
            raise OSError(errno.ENOSPC, "full")
        except OSError as inner:
            raise RuntimeError("iostream error") from inner
    except RuntimeError as outer:
        assert files.is_disk_full(outer, free=1 << 30)


def test_write_table_replaces_each_file_whole(tmp_path, monkeypatch):
    table = pd.DataFrame({"k": [500, 1000], "rmse": [0.1625, 0.17]}).set_index("k")
    markdown = write_table(table, tmp_path, "table2_rmse", "Table 2", note="n")
    assert _left(tmp_path) == ["table2_rmse.csv", "table2_rmse.md", "table2_rmse.tex"]
    assert (tmp_path / "table2_rmse.csv").read_text() == "k,rmse\n500,0.1625\n1000,0.17\n"
    assert (tmp_path / "table2_rmse.md").read_text() == markdown
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(DataError, match=re.escape(str(tmp_path / "table2_rmse.csv"))):
        write_table(table.iloc[:1], tmp_path, "table2_rmse", "Table 2")
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


# ------------------------------------------------------------------------------- images


def _image(folder, name: str):
    path = folder / name
    write_image_8bit(path, np.random.default_rng(0).random((16, 16, 3)))
    return path


@pytest.mark.parametrize("name", ["a.png", "a.jpg"])
def test_an_image_write_that_fails_leaves_the_old_image(tmp_path, monkeypatch, name):
    path = _image(tmp_path, name)
    before = path.read_bytes()

    def fail(fd):
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(os, "fsync", fail)
    with pytest.raises(OSError, match="Input/output error"):
        write_image_8bit(path, np.zeros((16, 16, 3)))
    assert path.read_bytes() == before and _left(tmp_path) == [name]


def _damaged(path, how: str) -> None:
    data = bytearray(path.read_bytes())
    if how == "truncated":
        data = data[: len(data) // 2]
    elif how == "flipped":  # a bit in the compressed data: PNG's CRC finds it
        data[len(data) // 2] ^= 0x10
    else:  # a JPEG header claiming 65535 x 65535 pixels (Pillow: DecompressionBombError)
        at = data.find(b"\xff\xc0") + 5
        data[at : at + 4] = b"\xff\xff\xff\xff"
    path.write_bytes(bytes(data))


@pytest.mark.parametrize(
    "name, how",
    [("a.png", "truncated"), ("a.jpg", "truncated"), ("a.png", "flipped"), ("a.jpg", "huge")],
)
def test_an_image_the_decoder_rejects_is_a_data_error_naming_it(tmp_path, name, how):
    path = _image(tmp_path, name)
    _damaged(path, how)
    for read in (read_image_8bit, image_size):
        if read is image_size and how in ("truncated", "flipped"):
            continue  # the header is intact: only decoding finds it
        with pytest.raises(DataError, match=re.escape(str(path))):
            read(path)
