"""A damaged cache entry is found and computed again; ``python -m pipeline.cache`` lists,
verifies and collects the cache; stale temporary folders go; dataset renames count."""

from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import os
import re
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import pipeline_command
from omegaconf import OmegaConf

from pipeline import cache as command
from pipeline.core import cache as cache_module
from pipeline.core import digests
from pipeline.core.cache import MANIFEST, StageCache, save_arrays, save_json, temporary_name
from pipeline.core.errors import DataError
from pipeline.core.stage import Context, folder_fingerprint


class Counting:
    """A stage's compute that writes fixed arrays and counts its calls."""

    def __init__(self, **arrays: np.ndarray):
        self.arrays = arrays
        self.calls = 0

    def __call__(self, folder: Path):
        self.calls += 1
        save_arrays(folder, **self.arrays)
        save_json(folder, "meta", {"n": 3})


def _entry(cache: StageCache, stage: str = "s", inputs: dict | None = None, value: float = 1.0):
    compute = Counting(x=np.full(16, value), y=np.arange(4))
    return cache.run(stage, "1", {"value": value}, inputs or {}, compute), compute


def _change_a_value(path: Path) -> None:
    """Same size, one value different (what a bad disk or a stray write does)."""
    array = np.load(path, mmap_mode="r+")
    array[3] += 1
    array.flush()
    del array


# ------------------------------------------------------------------------- damaged entries


def test_changed_values_of_a_small_entry_are_found_on_hit_and_recomputed(tmp_path, caplog):
    cache = StageCache(tmp_path)
    first, _ = _entry(cache)
    assert first.manifest["files"]["x.npy"]["bytes"] == (first.path / "x.npy").stat().st_size
    _change_a_value(first.path / "x.npy")
    compute = Counting(x=np.full(16, 1.0), y=np.arange(4))
    with caplog.at_level(logging.WARNING, logger="pipeline.core.cache"):
        again = cache.run("s", "1", {"value": 1.0}, {}, compute)
    assert compute.calls == 1 and not again.hit and again.key == first.key
    np.testing.assert_array_equal(again.array("x"), np.full(16, 1.0))
    assert str(first.path / "x.npy") in caplog.text and "sha256" in caplog.text
    assert cache.run("s", "1", {"value": 1.0}, {}, compute).hit


LARGE = (64 << 20) + (2 << 20)  # two chunks of digests.CHUNK_BYTES, hashed apart


def _stages(cache: StageCache, big: np.ndarray, value: float = 1.0) -> tuple[list, list]:
    """load (``big``) -> crop -> evaluate, as the runners pass inputs; returns the entries
    and their computes (each counts its calls)."""
    load = Counting(images=big)
    crop = Counting(x=np.full(16, value))
    evaluate = Counting(y=np.arange(4))
    loaded = cache.run("load", "1", {"value": value}, {}, load)
    cropped = cache.run("crop", "1", {}, {"load": loaded.key}, crop)
    evaluated = cache.run("evaluate", "1", {}, {"crop": cropped.key, "load": loaded.key}, evaluate)
    return [loaded, cropped, evaluated], [load, crop, evaluate]


def _flip_bytes(path: Path, offset: int, n: int = 12) -> None:
    """Change ``n`` bytes in place from ``offset`` (same size, same mtime kept or not)."""
    with open(path, "r+b") as f:
        f.seek(offset)
        old = f.read(n)
        f.seek(offset)
        f.write(bytes(b ^ 0x5A for b in old))


def test_a_large_entry_changed_in_place_is_recomputed_with_its_descendants(tmp_path, caplog):
    cache = StageCache(tmp_path)
    big = np.zeros(LARGE, np.uint8)
    first, _ = _stages(cache, big)
    record = first[0].manifest["files"]["images.npy"]
    assert len(record["sha256_chunks"]) == 2 and record["bytes"] > digests.CHUNK_BYTES
    assert first[1].manifest["parents"] == {
        first[0].key: {"stage": "load", "id": first[0].manifest["id"]}
    }
    images = first[0].path / "images.npy"
    _flip_bytes(images, offset=LARGE - 100)  # in the second chunk
    with caplog.at_level(logging.WARNING, logger="pipeline.core.cache"):
        again, computes = _stages(cache, big)
    assert [c.calls for c in computes] == [1, 1, 1] and not any(e.hit for e in again)
    assert [e.key for e in again] == [e.key for e in first]
    assert f"{images} has changed: its sha256 of bytes {64 << 20}.." in caplog.text
    assert (
        f"{first[1].path} was computed from {first[0].path}, which has been computed "
        f"again since" in caplog.text
    )
    np.testing.assert_array_equal(again[0].array("images"), big)
    # Recomputed once: the next run hits all three.
    hits, computes = _stages(cache, big)
    assert all(e.hit for e in hits) and [c.calls for c in computes] == [0, 0, 0]


def test_verify_fix_removes_a_damaged_large_entry_and_its_descendants(tmp_path, capsys):
    cache = StageCache(tmp_path)
    big = np.zeros(LARGE, np.uint8)
    first, _ = _stages(cache, big)
    other, _ = _stages(cache, big[:1000], value=2.0)  # another chain, intact
    _flip_bytes(first[0].path / "images.npy", offset=5000)
    assert command.main(["verify", f"paths.cache={tmp_path}"]) == 1
    out = capsys.readouterr().out
    assert f"damaged {first[0].path}: {first[0].path / 'images.npy'} has changed" in out
    for child in first[1:]:
        assert f"damaged {child.path}: computed from the damaged entry" in out
    assert "verified 6 entries" in out and "3 damaged" in out
    assert all(e.path.is_dir() for e in first)  # without fix=true nothing is removed
    assert command.main(["verify", "fix=true", f"paths.cache={tmp_path}"]) == 1
    assert not any(e.path.exists() for e in first) and all(e.path.is_dir() for e in other)
    assert command.main(["verify", f"paths.cache={tmp_path}"]) == 0
    again, computes = _stages(cache, big)
    assert [c.calls for c in computes] == [1, 1, 1]


def test_an_entry_whose_input_was_computed_again_or_is_gone_is_not_used(tmp_path, capsys):
    cache = StageCache(tmp_path)
    big = np.arange(100, dtype=np.uint8)
    first, _ = _stages(cache, big)
    # Recomputed (by verify fix=true and another job, say): crop was made from the old one.
    cache.remove("load", first[0].key)
    cache.run("load", "1", {"value": 1.0}, {}, Counting(images=big))
    assert cache.lookup("crop", first[1].key) is None
    assert command.main(["verify", f"paths.cache={tmp_path}"]) == 1
    out = capsys.readouterr().out
    for child in first[1:]:  # both read load
        assert f"damaged {child.path}: {child.path} was computed from {first[0].path}" in out
    # Gone: the descendants cannot be checked against it.
    cache.remove("load", first[0].key)
    entry, problem = cache.check("evaluate", first[2].key)
    assert entry is not None and f"{first[0].path}, which is gone" in problem


def test_chunks_of_a_file_are_hashed_by_several_threads(tmp_path, monkeypatch):
    monkeypatch.setattr(digests, "CHUNK_BYTES", 1000)
    monkeypatch.setattr(digests, "HASH_THREADS", 3)
    threads = set()
    real = digests.range_digest

    def recording(*args):
        threads.add(threading.current_thread().name)
        return real(*args)

    monkeypatch.setattr(digests, "range_digest", recording)
    cache = StageCache(tmp_path)
    entry, _ = _entry(cache)
    save_arrays(entry.path, z=np.arange(2500, dtype=np.uint8))
    record = digests.describe_files(entry.path)["z.npy"]
    assert record["bytes"] == 2500 + 128 and len(record["sha256_chunks"]) == 3
    whole = (entry.path / "z.npy").read_bytes()
    assert record["sha256_chunks"][1] == hashlib.sha256(whole[1000:2000]).hexdigest()
    assert all(name.startswith("cache-hash") for name in threads)
    entry.manifest["files"]["z.npy"] = record
    assert entry.damage() is None
    _flip_bytes(entry.path / "z.npy", offset=2600, n=1)
    hashed = []
    assert entry.damage(progress=hashed.append).endswith(
        "z.npy has changed: its sha256 of bytes 2000..2627 differs from the one in its manifest"
    )
    assert hashed[-3:] == [1000, 1000, 628]


def test_missing_or_truncated_file_is_recomputed(tmp_path, caplog):
    cache = StageCache(tmp_path)
    first, _ = _entry(cache)
    (first.path / "y.npy").unlink()
    with caplog.at_level(logging.WARNING, logger="pipeline.core.cache"):
        again, compute = _entry(cache)
    assert compute.calls == 1 and not again.hit
    assert f"{first.path / 'y.npy'} is missing" in caplog.text
    with open(first.path / "x.npy", "r+b") as f:
        f.truncate(100)
    again, compute = _entry(cache)
    assert compute.calls == 1 and not again.hit
    np.testing.assert_array_equal(again.array("x"), np.full(16, 1.0))


@pytest.mark.parametrize("mmap", [True, False])
def test_a_truncated_array_is_a_data_error_naming_its_path(tmp_path, mmap):
    entry, _ = _entry(StageCache(tmp_path))
    path = entry.path / "x.npy"
    with open(path, "r+b") as f:
        f.truncate(path.stat().st_size - 8)
    with pytest.raises(DataError, match=re.escape(str(path))):
        entry.array("x", mmap=mmap)


def test_a_corrupt_json_is_a_data_error_naming_its_path(tmp_path):
    entry, _ = _entry(StageCache(tmp_path))
    path = entry.path / "meta.json"
    path.write_text('{"n": ')
    with pytest.raises(DataError, match=re.escape(str(path))):
        entry.json("meta")


def test_lookup_of_a_damaged_entry_is_none_with_a_warning(tmp_path, caplog):
    cache = StageCache(tmp_path)
    entry, _ = _entry(cache)
    (entry.path / MANIFEST).write_text('{"files": ')
    with caplog.at_level(logging.WARNING, logger="pipeline.core.cache"):
        assert cache.lookup("s", entry.key) is None
    assert str(entry.path) in caplog.text and MANIFEST in caplog.text
    assert entry.path.is_dir()  # lookup leaves it; the next run replaces it


@pytest.mark.parametrize(
    "strip, said",
    [
        (lambda m: m.update(files=sorted(m["files"])), "records no size and sha256 of each file"),
        (lambda m: m["files"]["x.npy"].pop("sha256"), "records no size and sha256 of each file"),
        (lambda m: m.pop("parents"), "records no parents"),
        (lambda m: m.pop("id"), "records no id"),
    ],
)
def test_a_manifest_without_hashes_or_lineage_is_not_read(tmp_path, capsys, strip, said):
    """Every manifest this code writes has them: one without is damage, never a hit."""
    cache = StageCache(tmp_path)
    entry, _ = _entry(cache)
    manifest = json.loads((entry.path / MANIFEST).read_text())
    strip(manifest)
    (entry.path / MANIFEST).write_text(json.dumps(manifest))
    assert command.main(["verify", f"paths.cache={tmp_path}"]) == 1
    assert f"damaged {entry.path}: {entry.path / MANIFEST} {said}" in capsys.readouterr().out
    again, compute = _entry(cache)
    assert not again.hit and compute.calls == 1 and again.key == entry.key
    assert cache.lookup("s", entry.key) is not None


# ---------------------------------------------------------------------- dataset fingerprint


def test_renaming_a_dataset_file_changes_the_fingerprint(tmp_path):
    folder = tmp_path / "tv000_pv000"
    folder.mkdir()
    for name in ("tl000_pl000.png", "tl015_pl000.png"):
        (folder / name).write_bytes(b"0123456789")
    before = folder_fingerprint(tmp_path)
    assert folder_fingerprint(tmp_path) == before
    os.rename(folder / "tl015_pl000.png", folder / "tl015_pl060.png")  # same size and mtime
    after = folder_fingerprint(tmp_path)
    assert {k: after[k] for k in ("files", "bytes", "mtime_ns")} == {
        k: before[k] for k in ("files", "bytes", "mtime_ns")
    }
    assert after["names"] != before["names"]


# --------------------------------------------------------------------- stale temporaries


def _dead_pid() -> int:
    child = subprocess.Popen(["true"])
    child.wait()
    return child.pid


def test_temporary_of_a_dead_process_is_removed_a_live_ones_kept(tmp_path):
    stage = tmp_path / "s"
    stage.mkdir()
    live = stage / temporary_name("k1")
    dead = stage / live.name.replace(f"-{os.getpid()}@", f"-{_dead_pid()}@").replace("k1", "k2", 1)
    elsewhere = stage / ".tmp-k3-0000abcd-12@another-host"
    old_elsewhere = stage / ".tmp-k4-0000abcd-12@another-host"
    old_locked = stage / ".tmp-k5-0000abcd-12@another-host"
    not_ours = stage / ".tmp-k6-0000abcd"  # not named by temporary_name: left alone
    for folder in (live, dead, elsewhere, old_elsewhere, old_locked, not_ours):
        folder.mkdir()
        save_arrays(folder, x=np.arange(2))
    day_ago = time.time() - cache_module.STALE_AFTER_S - 60
    for folder in (old_elsewhere, old_locked, not_ours):
        for path in (folder / "x.npy", folder):
            os.utime(path, (day_ago, day_ago))
    with open(stage / ".lock-k5", "w") as lock:  # a job computing k5 holds its lock
        fcntl.flock(lock, fcntl.LOCK_EX)
        Context.from_config(OmegaConf.create({"paths": {"cache": str(tmp_path)}}))
    left = sorted(p.name for p in stage.iterdir() if not p.name.startswith(".lock-"))
    assert left == sorted([live.name, elsewhere.name, old_locked.name, not_ours.name])


# ------------------------------------------------------------------------------ the command


@pytest.fixture
def store(tmp_path, mlflow_template, monkeypatch):
    """A runs folder with an empty MLflow store; returns (runs, client, experiment id)."""
    from mlflow.tracking import MlflowClient

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    runs = tmp_path / "runs"
    mlflow_template(runs)
    client = MlflowClient(f"sqlite:///{runs / 'mlflow.db'}")
    return runs, client, client.get_experiment_by_name("Default").experiment_id


def _chain(cache: StageCache) -> dict[str, Path]:
    """a -> b (used by a finished run); c -> d (used by no finished run)."""
    a, _ = _entry(cache, "a")
    b, _ = _entry(cache, "b", {"a": a.key})
    c, _ = _entry(cache, "c", value=3.0)
    d, _ = _entry(cache, "d", {"c": c.key})
    cache.release()  # as a job does when it ends: nothing is held in use
    return {"a": a, "b": b, "c": c, "d": d}


def _finish(client, experiment: str, status: str, **tags: str) -> None:
    run = client.create_run(experiment, tags={f"cache.{s}": k for s, k in tags.items()})
    client.set_terminated(run.info.run_id, status)


def test_gc_keeps_what_finished_runs_use_and_their_inputs(store, capsys):
    runs, client, experiment = store
    cache = StageCache(runs / "cache")
    entries = _chain(cache)
    _finish(client, experiment, "FINISHED", b=entries["b"].key)
    _finish(client, experiment, "FAILED", d=entries["d"].key)
    stale = runs / "cache" / "c" / ".tmp-k9-0000abcd-1@x"
    stale.mkdir()
    old = time.time() - 2 * cache_module.STALE_AFTER_S
    os.utime(stale, (old, old))

    assert command.main(["gc", "dry_run=true", f"paths.runs={runs}"]) == 0
    out = capsys.readouterr().out
    for name in "cd":
        assert f"would remove {entries[name].path}" in out
    assert f"would remove {stale}" in out and "would be freed" in out
    assert all(e.path.is_dir() for e in entries.values()) and stale.is_dir()

    assert command.main(["gc", f"paths.runs={runs}"]) == 0
    out = capsys.readouterr().out
    assert "removed 2 entries and 1 temporary folders" in out
    assert [name for name, e in entries.items() if e.path.is_dir()] == ["a", "b"]
    assert not stale.exists()

    assert command.main(["ls", "entries=true", f"paths.runs={runs}"]) == 0
    out = capsys.readouterr().out
    assert f"{entries['b'].key}" in out and "used by a finished run" in out
    assert f"input of b {entries['b'].key}" in out


def test_gc_keeps_what_was_used_since_a_running_run_started(store, capsys):
    runs, client, experiment = store
    cache = StageCache(runs / "cache")
    entries = _chain(cache)
    _finish(client, experiment, "FINISHED", b=entries["b"].key)
    client.create_run(experiment)  # a job in progress records its keys when it ends
    assert command.main(["gc", f"paths.runs={runs}"]) == 0
    assert all(e.path.is_dir() for e in entries.values())
    assert "a run is still RUNNING" in capsys.readouterr().out


def test_gc_refuses_without_a_store_or_when_it_knows_no_entry(tmp_path, store, capsys):
    runs, _, _ = store
    lone = tmp_path / "elsewhere"
    entries = _chain(StageCache(lone / "cache"))
    assert command.main(["gc", f"paths.runs={lone}"]) == 2
    assert "no MLflow store" in capsys.readouterr().err
    assert command.main(["gc", f"paths.runs={runs}", f"paths.cache={lone / 'cache'}"]) == 2
    assert "nothing removed" in capsys.readouterr().err
    assert all(e.path.is_dir() for e in entries.values())


def test_ls_prints_each_stage(tmp_path, capsys):
    _chain(StageCache(tmp_path / "runs" / "cache"))
    assert command.main(["ls", f"paths.runs={tmp_path / 'runs'}"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[:2] for line in lines[1:]] == [
        ["a", "1"],
        ["b", "1"],
        ["c", "1"],
        ["d", "1"],
        ["total", "4"],
    ]


def test_command_runs_as_a_module(tmp_path):
    _entry(StageCache(tmp_path / "cache"), "load")
    done = pipeline_command("ls", f"paths.runs={tmp_path}", module="pipeline.cache")
    assert done.returncode == 0, done.stderr
    assert re.search(r"^load\s+1\s", done.stdout, re.MULTILINE)


def _age(entry, days: float) -> None:
    """Make ``entry`` last used ``days`` ago (its manifest's mtime)."""
    when = time.time() - days * 86400
    os.utime(entry.path / cache_module.MANIFEST, (when, when))


def test_gc_by_age_reads_no_store_and_takes_what_was_computed_from_an_entry(tmp_path, capsys):
    cache = StageCache(tmp_path / "cache")
    entries = _chain(cache)
    _age(entries["a"], 40)  # b was computed from a: without it b is of no use
    for name, days in (("b", 1), ("c", 2), ("d", 3)):
        _age(entries[name], days)
    settings = [f"paths.runs={tmp_path / 'no_store_here'}", f"paths.cache={tmp_path / 'cache'}"]
    assert command.main(["gc", "unused_days=30", "dry_run=true", *settings]) == 0
    out = capsys.readouterr().out
    assert "not used for 40 days" in out and f"computed from {entries['a'].key}" in out
    assert all(e.path.is_dir() for e in entries.values())
    assert command.main(["gc", "unused_days=30", *settings]) == 0
    assert [name for name, e in entries.items() if e.path.is_dir()] == ["c", "d"]
    assert "removed 2 entries" in capsys.readouterr().out


def test_gc_by_size_removes_the_least_recently_used_first(tmp_path, capsys):
    from pipeline.cache import scan

    cache = StageCache(tmp_path / "cache")
    entries = _chain(cache)
    for name, days in (("a", 2), ("b", 1), ("c", 5), ("d", 4)):
        _age(entries[name], days)
    rows = {row.key: row for row in scan(cache)}
    keep = rows[entries["a"].key].bytes + rows[entries["b"].key].bytes
    assert command.main(["gc", f"max_gb={keep / 1e9}", f"paths.cache={tmp_path / 'cache'}"]) == 0
    assert [name for name, e in entries.items() if e.path.is_dir()] == ["a", "b"]
    assert "least recently used" in capsys.readouterr().out
    assert command.main(["gc", "max_gb=0", f"paths.cache={tmp_path / 'cache'}"]) == 0
    assert not any(e.path.is_dir() for e in entries.values())


def test_gc_keeps_what_a_running_job_was_handed_and_a_lock_being_computed(tmp_path, capsys):
    """A job handed c (a hit) holds it until it ends, however old its last use; d is
    being computed (its key's lock); a's age alone would have it go."""
    cache = StageCache(tmp_path / "cache")
    entries = _chain(cache)
    for entry in entries.values():
        _age(entry, 40)
    job = StageCache(tmp_path / "cache")  # a running job's cache
    _entry(job, "c", value=3.0)
    _age(entries["c"], 40)  # the hit touched it: old again, and still held
    d = entries["d"]
    settings = ["unused_days=30", f"paths.cache={tmp_path / 'cache'}"]
    with open(d.path.parent / f".lock-{d.key}", "w") as lock:  # a job computing d
        fcntl.flock(lock, fcntl.LOCK_EX)
        assert command.main(["gc", *settings]) == 0
    out = capsys.readouterr().out
    assert [name for name, e in entries.items() if e.path.is_dir()] == ["c", "d"]
    assert f"kept {entries['c'].path}: used or locked" in out
    job.release()  # the job ends: its entries may go
    assert command.main(["gc", *settings]) == 0
    assert not any(e.path.is_dir() for e in entries.values())
