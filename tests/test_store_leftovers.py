"""What a start finds next to the store: half-made stores of killed processes are
removed; an empty file, or another program's SQLite database, is refused by name."""

from __future__ import annotations

import hashlib
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline import cache as cache_command
from pipeline.core.errors import StoreError
from pipeline.core.store import init_store


def _dead_pid() -> int:
    gone = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        capture_output=True,
        text=True,
        check=True,
    )
    return int(gone.stdout)


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(autouse=True)
def _own_store(monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)


@pytest.mark.parametrize("existing_store", [True, False], ids=["existing", "new"])
def test_partial_stores_of_killed_processes_are_removed_at_the_next_start(
    tmp_path, mlflow_template, existing_store
):
    if existing_store:
        mlflow_template(tmp_path)
    dead = _dead_pid()
    leftovers = [
        tmp_path / f".mlflow.db.partial-{dead}",
        tmp_path / f".mlflow.db.partial-{dead}-journal",
        tmp_path / ".mlflow.db.partial-1",
    ]  # an old pid, reused since
    for path in leftovers:
        path.write_bytes(b"SQLite format 3\x00 half made")
    unrelated = tmp_path / ".mlflow.db.partial-notes.txt"
    unrelated.write_text("not ours")

    init_store(tmp_path, "btf")
    assert not [path for path in leftovers if path.exists()]
    assert unrelated.exists()
    assert sorted(p.name for p in tmp_path.glob(".mlflow.db*")) == [unrelated.name]


def test_an_empty_store_file_is_refused(tmp_path):
    db = tmp_path / "mlflow.db"
    db.touch()
    with pytest.raises(StoreError, match="empty") as refused:
        init_store(tmp_path, "btf")
    assert str(db) in str(refused.value) and "delete it" in str(refused.value)
    assert db.stat().st_size == 0  # left as it was


def test_another_programs_sqlite_database_is_refused_and_left_untouched(tmp_path):
    db = tmp_path / "mlflow.db"
    with sqlite3.connect(db) as connection:
        connection.execute("CREATE TABLE photos (id INTEGER, path TEXT)")
        connection.execute("CREATE TABLE albums (id INTEGER, name TEXT)")
    connection.close()
    before = _digest(db)
    with pytest.raises(StoreError, match=r"another program's tables \(albums, photos\)") as refused:
        init_store(tmp_path, "btf")
    assert str(db) in str(refused.value) and "move it aside" in str(refused.value)
    assert _digest(db) == before  # MLflow wrote none of its tables into it


def test_a_sqlite_database_without_tables_is_refused(tmp_path):
    db = tmp_path / "mlflow.db"
    with sqlite3.connect(db) as connection:
        connection.execute("PRAGMA user_version = 7")  # a real, non-empty database file
    connection.close()
    assert db.stat().st_size > 0
    with pytest.raises(StoreError, match="without tables"):
        init_store(tmp_path, "btf")


def test_a_store_missing_one_of_mlflows_tables_is_refused(tmp_path, mlflow_template):
    mlflow_template(tmp_path)
    with sqlite3.connect(tmp_path / "mlflow.db") as connection:
        connection.execute("DROP TABLE alembic_version")
    connection.close()
    with pytest.raises(StoreError, match="no alembic_version table"):
        init_store(tmp_path, "btf")


def test_cache_gc_refuses_a_foreign_store_and_leaves_it_untouched(tmp_path, capsys):
    runs = tmp_path / "runs"
    runs.mkdir()
    db = runs / "mlflow.db"
    with sqlite3.connect(db) as connection:
        connection.execute("CREATE TABLE inventory (item TEXT)")
    connection.close()
    before = _digest(db)
    assert cache_command.main(["gc", f"paths.runs={runs}"]) == 2
    err = capsys.readouterr().err
    assert str(db) in err and "another program's tables (inventory)" in err
    assert "nothing removed" in err
    assert _digest(db) == before


def test_a_good_store_still_opens(tmp_path, mlflow_template):
    mlflow_template(tmp_path)
    first = init_store(tmp_path, "btf")
    assert init_store(tmp_path, "btf") == first
    assert os.path.getsize(tmp_path / "mlflow.db") > 0
