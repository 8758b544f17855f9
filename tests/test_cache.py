import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.cache import StageCache, canonical_json, publish, save_arrays, stage_key


def test_key_ignores_key_order_and_int_vs_float():
    a = stage_key("pca", "1", {"n_components": 16, "random_state": 0}, {"crop": "abc"})
    b = stage_key("pca", "1", {"random_state": 0.0, "n_components": 16.0}, {"crop": "abc"})
    assert a == b


def test_key_changes_with_own_settings_version_and_inputs():
    base = stage_key("pca", "1", {"n_components": 16}, {"crop": "abc"})
    assert stage_key("pca", "1", {"n_components": 17}, {"crop": "abc"}) != base
    assert stage_key("pca", "2", {"n_components": 16}, {"crop": "abc"}) != base
    assert stage_key("pca", "1", {"n_components": 16}, {"crop": "abd"}) != base
    assert stage_key("kmeans", "1", {"n_components": 16}, {"crop": "abc"}) != base


def test_non_integral_floats_and_nested_values_are_kept():
    assert canonical_json({"a": [1.5, {"y": 2.0, "x": None}]}) == '{"a":[1.5,{"x":null,"y":2}]}'


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_nan_and_inf_settings_are_rejected(bad):
    with pytest.raises(ValueError, match="non-finite"):
        stage_key("pca", "1", {"tol": bad}, {})


def test_second_run_is_a_hit_and_computes_nothing(tmp_path):
    cache = StageCache(tmp_path)
    calls = []

    def compute(folder: Path):
        calls.append(folder)
        save_arrays(folder, x=np.arange(3))
        return {"n": 3}

    first = cache.run("s", "1", {"a": 1}, {}, compute)
    second = cache.run("s", "1", {"a": 1.0}, {}, compute)
    assert len(calls) == 1 and not first.hit and second.hit
    assert second.path == first.path and second.manifest["summary"] == {"n": 3}
    np.testing.assert_array_equal(second.array("x"), np.arange(3))


def test_failed_compute_leaves_nothing(tmp_path):
    cache = StageCache(tmp_path)

    def compute(folder: Path):
        save_arrays(folder, x=np.arange(3))
        raise RuntimeError("killed")

    with pytest.raises(RuntimeError):
        cache.run("s", "1", {}, {}, compute)
    left = [p.name for p in (tmp_path / "s").iterdir() if not p.name.startswith(".lock-")]
    assert left == []


def test_entry_without_manifest_is_never_read(tmp_path):
    """A folder left by a killed run (no manifest written) is recomputed, not read."""
    cache = StageCache(tmp_path)
    key = stage_key("s", "1", {}, {})
    stale = tmp_path / "s" / key
    stale.mkdir(parents=True)
    (stale / "x.npy").write_bytes(b"garbage")
    assert cache.lookup("s", key) is None
    entry = cache.run("s", "1", {}, {}, lambda folder: save_arrays(folder, x=np.arange(2)))
    assert not entry.hit
    np.testing.assert_array_equal(entry.array("x"), np.arange(2))


def test_two_jobs_asking_for_the_same_key_compute_it_once(tmp_path):
    cache = StageCache(tmp_path)
    calls = []
    started = threading.Event()

    def compute(folder: Path):
        calls.append(1)
        started.set()
        time.sleep(0.3)  # the other job arrives while this one computes
        save_arrays(folder, x=np.full(4, 7))

    results = []
    first = threading.Thread(target=lambda: results.append(cache.run("s", "1", {}, {}, compute)))
    first.start()
    started.wait(5)
    results.append(cache.run("s", "1", {}, {}, compute))
    first.join()
    assert len(calls) == 1
    assert sorted(r.hit for r in results) == [False, True]
    assert len({r.path for r in results}) == 1


def test_two_publishers_of_the_same_key_leave_one_good_entry(tmp_path):
    """Without the lock (e.g. flock ignored on a network file system) the rename decides."""
    final = tmp_path / "s" / "key"
    final.parent.mkdir()
    for value in (1, 2):
        tmp = final.parent / f".tmp-key-{value}"
        tmp.mkdir()
        save_arrays(tmp, x=np.full(3, value))
        (tmp / "manifest.json").write_text("{}")
        publish(tmp, final)
    assert [p.name for p in final.parent.iterdir()] == ["key"]
    np.testing.assert_array_equal(np.load(final / "x.npy"), np.full(3, 1))
    assert os.path.isfile(final / "manifest.json")
