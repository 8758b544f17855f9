"""``python -m pipeline.cache``: list, verify and clean up the stage cache.

    python -m pipeline.cache ls [entries=true]    # entries and size per stage (entries: each)
    python -m pipeline.cache verify [fix=true]    # every file's hash; exit status 1 if any damaged
    python -m pipeline.cache gc [dry_run=true]    # remove what no finished run uses
    python -m pipeline.cache gc unused_days=30    # remove what no job used for 30 days
    python -m pipeline.cache gc max_gb=50         # the least recently used, down to 50 GB

Settings are ``key=value`` after the command (:data:`KEYS`): ``paths.runs`` (default
``runs``) is where the MLflow store is (``MLFLOW_TRACKING_URI`` wins, as for the jobs),
``paths.cache`` (default ``<paths.runs>/cache``) where the cache is. An unknown key is
refused, naming the closest real one; the command line is read before MLflow, Hydra or
pandas is imported.

``gc`` keeps every entry whose key a FINISHED run records (its tags ``cache.<stage>``), the
entries those were computed from, and anything used since the oldest RUNNING run started (a
job records its keys when it ends; :class:`~pipeline.core.cache.StageCache` marks each hit
on the manifest's mtime). Keys are matched whatever the stage. It removes
nothing when the store cannot be read or knows none of the entries (the wrong
``paths.runs``). A RUNNING run whose process is gone from this machine is marked FAILED
first (``ls`` and ``dry_run`` only leave it out).

The cache is a memo (tables are drawn from what the runs logged), so ``gc unused_days=D``
and ``gc max_gb=G`` clear it by age or size without reading the store; an entry goes with
every entry computed from it, never one a running job holds or used since ``gc`` started.
"""

from __future__ import annotations

import sys
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.core import cli
from pipeline.core.errors import ConfigError
from pipeline.core.settings import OneOf, Real

if TYPE_CHECKING:
    from pipeline.core.cache import StageCache

# Hosts of a shared cache may disagree on the time by this much (seconds).
CLOCK_SKEW_S = 600
IN_PROGRESS = ("RUNNING", "SCHEDULED")


@dataclass
class Usage:
    """What the MLflow store says about cache keys."""

    uri: str
    finished: set[str] = field(default_factory=set)  # keys recorded by FINISHED runs
    n_finished: int = 0
    running_since: float | None = None  # start (time.time()) of the oldest RUNNING run
    dead: list[str] = field(default_factory=list)  # RUNNING runs whose process is gone


@dataclass
class Row:
    """One folder under a stage of the cache."""

    stage: str
    key: str
    path: Path
    bytes: int
    created: float | None  # None: no readable manifest
    used: float  # published or last hit (time.time())
    inputs: list[str]


def read_usage(runs: Path, fail_dead: bool = False) -> Usage:
    """The keys that FINISHED runs of the store of ``runs`` record, over all experiments.
    RUNNING runs whose process is gone count as ended (``fail_dead``: marked FAILED)."""
    from pipeline.core.errors import StoreError
    from pipeline.core.store import (
        all_pages,
        check_sqlite_store,
        fail_dead_runs,
        process_gone,
        sqlite_path,
        tracking_uri,
    )

    uri = tracking_uri(runs)
    db = sqlite_path(uri)
    if db is not None:
        if not db.is_file():  # MLflow would create an empty store, which uses nothing
            raise StoreError(f"there is no MLflow store at {db} (see paths.runs)")
        check_sqlite_store(db)  # nor may it write its tables into another program's file
    try:
        from mlflow.entities import ViewType
        from mlflow.tracking import MlflowClient

        client = MlflowClient(uri)
        active = ViewType.ACTIVE_ONLY
        found = all_pages(client.search_experiments, view_type=active)
        experiments = [e.experiment_id for e in found]
        usage = Usage(uri)
        if not experiments:
            return usage
        if fail_dead:
            gone = "its process was gone at a cache gc"
            usage.dead = fail_dead_runs(client, experiments, ended_by=gone)
        starts = []
        for run in all_pages(client.search_runs, experiment_ids=experiments, run_view_type=active):
            if run.info.status == "FINISHED":
                usage.n_finished += 1
                usage.finished |= {
                    value for name, value in run.data.tags.items() if name.startswith("cache.")
                }
            elif run.info.status in IN_PROGRESS and process_gone(run):
                usage.dead.append(run.info.run_id)
            elif run.info.status in IN_PROGRESS:
                starts.append(run.info.start_time / 1000)
    except Exception as err:  # any failure of the store or its client: delete nothing
        raise StoreError(
            f"cannot read the MLflow store {uri} ({type(err).__name__}: {err})"
        ) from err
    usage.running_since = min(starts, default=None)
    return usage


def scan(cache: StageCache) -> list[Row]:
    """Every folder under a stage of ``cache``, with its size and manifest's facts."""
    from pipeline.core.cache import folder_bytes, last_used

    rows = []
    for stage in cache.stages():
        for key in cache.keys(stage):
            entry, _ = cache.read(stage, key)  # the manifest only: no file is checked
            manifest = entry.manifest if entry is not None else {}
            path = cache.entry_path(stage, key)
            rows.append(
                Row(
                    stage,
                    key,
                    path,
                    folder_bytes(path),
                    manifest.get("created") if entry is not None else None,
                    last_used(path),
                    list(manifest.get("inputs", {}).values()),
                )
            )
    return rows


def kept(rows: list[Row], usage: Usage) -> dict[str, str]:
    """``{key: why it is kept}`` for the entries gc keeps (see the module's docstring)."""
    by_key = {row.key: row for row in rows}
    todo = deque((key, "used by a finished run") for key in sorted(usage.finished & set(by_key)))
    if usage.running_since is not None:
        since = usage.running_since - CLOCK_SKEW_S
        todo += [(row.key, "used since a RUNNING run started") for row in rows if row.used >= since]
    why: dict[str, str] = {}
    while todo:
        key, reason = todo.popleft()
        if key in why:
            continue
        why[key] = reason
        row = by_key[key]
        todo += [(k, f"input of {row.stage} {key}") for k in row.inputs if k in by_key]
    return why


def _when(seconds: float | None) -> str:
    if seconds is None:
        return "no manifest    "
    return time.strftime("%Y-%m-%d %H:%M", time.localtime(seconds))


def ls(cache: StageCache, runs: Path, entries: bool) -> int:
    from pipeline.core.cache import folder_bytes
    from pipeline.core.errors import StoreError
    from pipeline.core.files import human

    rows = scan(cache)
    why: dict[str, str] | None = None
    if entries and rows:
        try:
            why = kept(rows, read_usage(runs))
        except StoreError as err:
            print(f"ls: {err}; whether runs use the entries is unknown (?)", file=sys.stderr)
    print(f"{'stage':<24} {'entries':>7} {'size':>10}   cache {cache.root}")
    for stage in sorted({row.stage for row in rows}):
        mine = [row for row in rows if row.stage == stage]
        print(f"{stage:<24} {len(mine):>7} {human(sum(r.bytes for r in mine)):>10}")
        for row in mine if entries else ():
            used = "?" if why is None else why.get(row.key, "no finished run uses it")
            print(f"  {row.key}  {human(row.bytes):>10}  {_when(row.created)}  {used}")
    print(f"{'total':<24} {len(rows):>7} {human(sum(r.bytes for r in rows)):>10}")
    temporaries = cache.temporaries()
    if temporaries:
        size = human(sum(folder_bytes(t) for t in temporaries))
        print(
            f"{'temporary folders':<24} {len(temporaries):>7} {size:>10}   (computing, or "
            f"left by killed jobs: gc removes those)"
        )
    return 0


def verify(cache: StageCache, fix: bool) -> int:
    """Check every entry's files and lineage; an entry computed from a damaged one is
    damaged too. ``fix``: remove them (unless a job is computing them again)."""
    from tqdm import tqdm

    from pipeline.core.cache import folder_bytes
    from pipeline.core.files import human

    started = time.time()
    folders = [(stage, key) for stage in cache.stages() for key in cache.keys(stage)]
    total = sum(folder_bytes(cache.entry_path(*f)) for f in folders)
    problems: dict[str, str] = {}
    children: dict[str, list[str]] = {}
    with tqdm(
        total=total,
        unit="B",
        unit_scale=True,
        unit_divisor=1024,
        desc="verify",
        file=sys.stderr,
        disable=not sys.stderr.isatty(),
    ) as bar:
        for stage, key in folders:
            entry, problem = cache.check(stage, key, hashes=True, progress=bar.update)
            if problem is not None:
                problems[key] = problem
            if entry is None:
                continue
            for parent in (entry.manifest.get("inputs") or {}).values():
                children.setdefault(parent, []).append(key)
    todo = sorted(problems)
    stage_of = {key: stage for stage, key in folders}
    while todo:  # descendants of damaged entries, whatever their own state
        parent = todo.pop()
        for child in children.get(parent, []):
            if child not in problems:
                damaged = cache.entry_path(stage_of[parent], parent)
                problems[child] = f"computed from the damaged entry {damaged}"
                todo.append(child)
    damaged = [(stage, key) for stage, key in folders if key in problems]
    for stage, key in damaged:
        print(f"damaged {cache.entry_path(stage, key)}: {problems[key]}")
        if fix:
            removed = cache.remove(stage, key, unless_used_since=started, even_in_use=True)
            print("  removed" if removed else "  kept: a job is computing it again")
    print(
        f"verified {len(folders)} entries ({human(total)}) in {time.time() - started:.1f} s: "
        f"{len(damaged)} damaged" + (" (removed)" if fix and damaged else "")
    )
    return 1 if damaged else 0


def stale(
    rows: list[Row], unused_days: float | None, max_gb: float | None, now: float
) -> dict[str, str]:
    """``{key: why}`` of the entries to remove by age (unused for ``unused_days``) or size
    (least recently used first, down to ``max_gb``), each with those computed from it."""
    children: dict[str, list[Row]] = {}
    for row in rows:
        for key in row.inputs:
            children.setdefault(key, []).append(row)
    why: dict[str, str] = {}

    def remove(row: Row, reason: str) -> int:
        """Mark ``row`` and every entry computed from it; the bytes newly marked."""
        freed, todo = 0, [(row, reason)]
        while todo:
            found, because = todo.pop()
            if found.key in why:
                continue
            why[found.key] = because
            freed += found.bytes
            todo += [(child, f"computed from {found.key}") for child in children.get(found.key, [])]
        return freed

    oldest_first = sorted(rows, key=lambda r: r.used)
    if unused_days is not None:
        for row in oldest_first:
            if now - row.used > unused_days * 86400:
                remove(row, f"not used for {(now - row.used) / 86400:.0f} days")
    if max_gb is not None:
        kept = sum(r.bytes for r in rows if r.key not in why)
        for row in oldest_first:
            if kept <= max_gb * 1e9:
                break
            kept -= remove(
                row, f"least recently used ({_when(row.used)}), the cache above {max_gb:g} GB"
            )
    return why


def gc_by_age_or_size(
    cache: StageCache, unused_days: float | None, max_gb: float | None, dry_run: bool
) -> int:
    """``gc unused_days=… max_gb=…``: the store is not read (see the module's docstring)."""
    from pipeline.core.files import human

    started = time.time()
    rows = scan(cache)
    why = stale(rows, unused_days, max_gb, started)
    verb = "would remove" if dry_run else "removed"
    doomed = [row for row in sorted(rows, key=lambda r: r.used) if row.key in why]
    # Used since gc started (on any host whose clock is within CLOCK_SKEW_S): kept.
    freed, n_removed = _remove(cache, doomed, started - CLOCK_SKEW_S, dry_run, why)
    kept_bytes = sum(r.bytes for r in rows if r.key not in why)
    print(
        f"{verb} {n_removed} entries: {human(freed)} {'would be ' if dry_run else ''}freed; "
        f"{len(rows) - len(why)} entries ({human(kept_bytes)}) kept"
    )
    return 0


def _remove(
    cache: StageCache, rows: list[Row], since: float, dry_run: bool, why: dict | None = None
) -> tuple[int, int]:
    """Remove ``rows`` but those used since ``since``, a line for each (with ``why`` its
    reason); returns the bytes freed and the entries removed."""
    from pipeline.core.files import human

    verb = "would remove" if dry_run else "removed"
    freed, n_removed = 0, 0
    for row in rows:
        if dry_run or cache.remove(row.stage, row.key, unless_used_since=since):
            reason = f"; {why[row.key]}" if why else ""
            print(f"{verb} {row.path} ({human(row.bytes)}{reason})")
            freed, n_removed = freed + row.bytes, n_removed + 1
        else:
            print(f"kept {row.path}: used or locked by a job meanwhile")
    return freed, n_removed


def gc(cache: StageCache, runs: Path, dry_run: bool) -> int:
    from pipeline.core.cache import folder_bytes
    from pipeline.core.errors import StoreError
    from pipeline.core.files import human

    started = time.time()
    try:
        usage = read_usage(runs, fail_dead=not dry_run)
    except StoreError as err:
        print(f"gc: {err}; nothing removed", file=sys.stderr)
        return 2
    if usage.dead:
        print(
            f"{'would mark' if dry_run else 'marked'} {len(usage.dead)} RUNNING runs FAILED: "
            f"their processes on this host are gone ({', '.join(usage.dead)})"
        )
    rows = scan(cache)
    why = kept(rows, usage)
    if rows and not why:
        print(
            f"gc: no finished run in {usage.uri} ({usage.n_finished} finished) uses any of "
            f"the {len(rows)} entries under {cache.root}; nothing removed (is paths.runs right? "
            f"to empty the cache, delete the folder)",
            file=sys.stderr,
        )
        return 2
    verb = "would remove" if dry_run else "removed"
    doomed = [row for row in rows if row.key not in why]
    freed, n_removed = _remove(cache, doomed, started, dry_run)
    sizes = {folder: folder_bytes(folder) for folder in cache.temporaries()}
    stale = cache.remove_stale_temporaries(dry_run=dry_run)
    for folder, reason in stale:
        print(f"{verb} {folder} ({human(sizes.get(folder, 0))}; {reason})")
        freed += sizes.get(folder, 0)
    running = ""
    if usage.running_since is not None:
        running = f", and what was used since {_when(usage.running_since)} (a run is still RUNNING)"
    print(
        f"kept {len(why)} entries ({human(sum(r.bytes for r in rows if r.key in why))}): those "
        f"of {usage.n_finished} finished runs and their inputs{running}"
    )
    print(
        f"{verb} {n_removed} entries and {len(stale)} temporary folders: "
        f"{human(freed)} {'would be ' if dry_run else ''}freed"
    )
    return 0


# ------------------------------------------------------------------ the command line

PROG = "python -m pipeline.cache"
COMMANDS = {
    "ls": "entries and size per stage",
    "verify": "check every file's hash",
    "gc": "remove entries no finished run uses (or by unused_days, max_gb)",
}


@dataclass(frozen=True)
class CacheSettings:
    """The command and its settings; :data:`KEYS` describes each."""

    command: str = "ls"
    runs: str = "runs"
    cache: str | None = None
    entries: bool = False
    fix: bool = False
    dry_run: bool = False
    unused_days: float | None = None
    max_gb: float | None = None

    @property
    def cache_dir(self) -> Path:
        """``paths.cache``, by default ``<paths.runs>/cache``."""
        return Path(self.cache) if self.cache is not None else Path(self.runs) / "cache"


BOOLEAN = OneOf(True, False)
# Each key of the command line: its field, what it may be, and what it sets.
KEYS = {
    "paths.runs": ("runs", cli.Text(), "the runs folder (MLflow store: <runs>/mlflow.db)"),
    "paths.cache": (
        "cache",
        cli.Text(optional=True),
        "the cache folder (null: <paths.runs>/cache)",
    ),
    "entries": (
        "entries",
        BOOLEAN,
        "ls: one line per entry (key, size, created, whether a run uses it)",
    ),
    "fix": ("fix", BOOLEAN, "verify: remove the damaged entries"),
    "dry_run": ("dry_run", BOOLEAN, "gc: list what would be removed, remove nothing"),
    "unused_days": (
        "unused_days",
        Real(0, optional=True),
        "gc: remove entries no job used for this many days (the store is not read)",
    ),
    "max_gb": (
        "max_gb",
        Real(0, optional=True),
        "gc: remove the least recently used entries down to this many GB (the store is not read)",
    ),
}
# key -> its one command
ONLY_FOR = {"entries": "ls", "fix": "verify", "dry_run": "gc", "unused_days": "gc", "max_gb": "gc"}

COMMAND = cli.Command(
    PROG,
    KEYS,
    CacheSettings,
    "\n".join(f"  {name:<6} {text}" for name, text in COMMANDS.items())
    + "\n\nSettings and their defaults:",
    synopsis=f"{{{','.join(COMMANDS)}}} [key=value ...]",
)


def parse(argv: list[str]) -> CacheSettings:
    """:class:`CacheSettings` from the command and its ``key=value`` arguments; raises
    :class:`ConfigError` naming the first bad one."""
    command, rest = cli.command_of(argv, list(COMMANDS))
    given = cli.read(rest, KEYS, f"the {command} command")
    for key, only in ONLY_FOR.items():
        if KEYS[key][0] in given and command != only:
            raise ConfigError(f"{key} is a setting of {only}, not of {command}")
    return CacheSettings(command, **given)


def main(argv: list[str] | None = None) -> int:
    """Run the command; a bad command line prints one line and exits 2."""
    args = COMMAND.parse_args(argv, parse)
    from pipeline.core.cache import StageCache

    cache = StageCache(args.cache_dir)
    if args.command == "ls":
        return ls(cache, Path(args.runs), args.entries)
    if args.command == "verify":
        return verify(cache, args.fix)
    if args.unused_days is not None or args.max_gb is not None:
        return gc_by_age_or_size(cache, args.unused_days, args.max_gb, args.dry_run)
    return gc(cache, Path(args.runs), args.dry_run)


if __name__ == "__main__":
    sys.exit(main())
