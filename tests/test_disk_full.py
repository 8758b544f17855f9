"""A full disk is a DataError naming the file and the space left, from every writer, and
leaves no partial file (no 0-byte table): on a real 256 KiB tmpfs with 24 KiB free where
this machine lets a test mount one, and with the writes made to fail by a patch anyway."""

from __future__ import annotations

import errno
import gc
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.core import files
from pipeline.core.cache import StageCache, save_arrays
from pipeline.core.errors import DataError
from pipeline.core.report import write_file, write_table
from pipeline.data.brdf import write_utia_brdf
from pipeline.data.images import write_exr, write_image_8bit

FREE = 24 << 10  # what the tables command had left


def _noise(*shape: int) -> np.ndarray:
    return np.random.default_rng(0).random(shape, dtype=np.float32)


def _table(rows: int) -> pd.DataFrame:
    return pd.DataFrame({"k": np.arange(rows), "rmse": _noise(rows)}).set_index("k")


def _compressed(path: Path) -> Path:
    from pipeline.btf.compressed import write_compressed
    from pipeline.btf.model import Decoder

    return write_compressed(
        path,
        Decoder(hidden=64, layers=2),
        _noise(32 * 32, 8),
        1.0,
        crop_size=(32, 32),
        method="neural_btf",
        dataset="synthetic",
    )


def _stage(folder: Path, compute) -> None:
    StageCache(folder / "cache").run("load", "1", {}, {}, compute)


def _torch_save(folder: Path) -> None:
    import torch

    torch.save({"weight": torch.zeros(100_000)}, folder / "decoder.pt")


# (writer, the path its error must name); each writes more than FREE.
WRITERS = {
    "png": (lambda d: write_image_8bit(d / "fig.png", _noise(128, 128, 3)), "fig.png"),
    "jpeg": (lambda d: write_image_8bit(d / "img.jpg", _noise(256, 256, 3)), "img.jpg"),
    "exr": (lambda d: write_exr(d / "fig.exr", _noise(128, 128, 3)), "fig.exr"),
    "compressed": (lambda d: _compressed(d / "btf.safetensors"), "btf.safetensors"),
    "utia brdf": (
        lambda d: write_utia_brdf(d / "brdf.bin", _noise(6 * 48 * 6 * 48, 3)),
        "brdf.bin",
    ),
    "table": (lambda d: write_table(_table(5000), d, "table2_rmse", "Table 2"), "table2_rmse.csv"),
    "summary.md": (lambda d: write_file(d / "summary.md", "x" * (100 << 10)), "summary.md"),
    # np.save loses the errno ("N requested and M written"): named from the free space
    "stage arrays": (
        lambda d: _stage(d, lambda f: save_arrays(f, images=_noise(100_000))),
        "cache/load/*/images.npy",
    ),
    # torch.save raises RuntimeError("unexpected pos ..."): the entry is named
    "stage torch": (lambda d: _stage(d, _torch_save), "cache/load/*"),
}


def _named(message: str, folder: Path, name: str) -> bool:
    pattern = re.escape(str(folder / name)).replace(r"\*", "[0-9a-f]+")
    return re.search(rf"no space left for {pattern}: .*free in ", message) is not None


def _files(folder: Path) -> list[str]:
    """Every file under ``folder`` (cache locks aside)."""
    return sorted(
        str(p.relative_to(folder))
        for p in folder.rglob("*")
        if p.is_file() and not p.name.startswith(".lock-")
    )


@pytest.fixture
def small_disk(tmp_path):
    """A folder on a fresh 256 KiB tmpfs filled up to :data:`FREE` bytes free."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if shutil.which("mount") is None:
        pytest.skip("no mount command here; test_every_writer_names_a_patched_enospc covers it")
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(disk)],
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        pytest.skip(
            f"cannot mount a tmpfs here ({done.stderr.strip() or done.returncode}); "
            f"test_every_writer_names_a_patched_enospc covers it"
        )
    try:
        (disk / "filler").write_bytes(b"\0" * (shutil.disk_usage(disk).free - FREE))
        assert shutil.disk_usage(disk).free == FREE
        yield disk
    finally:
        subprocess.run(["umount", "--lazy", str(disk)], capture_output=True)


@pytest.mark.parametrize("writer", list(WRITERS))
def test_every_writer_names_a_full_tmpfs_and_leaves_nothing(small_disk, writer):
    write, name = WRITERS[writer]
    with pytest.raises(DataError) as caught:
        write(small_disk)
    message = str(caught.value)
    assert _named(message, small_disk, name), message
    if writer != "stage torch":  # torch's writer, still open in the traceback, holds its bytes
        assert " 24.0 KiB free in " in message
    assert _files(small_disk) == ["filler"]  # no partial, no temporary file
    del caught
    gc.collect()
    assert shutil.disk_usage(small_disk).free == FREE


def test_a_table_on_a_full_tmpfs_keeps_its_previous_version(small_disk):
    write_table(_table(3), small_disk, "table2_rmse", "Table 2")
    before = {name: (small_disk / name).read_bytes() for name in _files(small_disk)}
    with pytest.raises(DataError, match=re.escape(str(small_disk / "table2_rmse.csv"))):
        write_table(_table(5000), small_disk, "table2_rmse", "Table 2")
    assert {name: (small_disk / name).read_bytes() for name in _files(small_disk)} == before
    assert all(len(content) > 0 for content in before.values())


@pytest.mark.parametrize("writer", list(WRITERS))
def test_every_writer_names_a_patched_enospc(tmp_path, monkeypatch, writer):
    """The same without a small disk: the sync of an atomic write fails with ENOSPC; the
    stage writers' libraries fail as they do on a full disk, with 24 KiB left."""
    write, name = WRITERS[writer]

    def enospc(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", enospc)
    if writer.startswith("stage"):
        import torch

        monkeypatch.setattr(files, "free_bytes", lambda path: FREE)
        monkeypatch.setattr(np, "save", lambda *a, **k: enospc())
        monkeypatch.setattr(
            torch,
            "save",
            lambda *a, **k: (_ for _ in ()).throw(
                RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 576")
            ),
        )
    with pytest.raises(DataError) as caught:
        write(tmp_path)
    assert _named(str(caught.value), tmp_path, name), str(caught.value)
    assert _files(tmp_path) == []
