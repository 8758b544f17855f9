"""The MLflow store: where it is, its creation, its checks, and the runs whose process died.

The store is SQLite at ``${paths.runs}/mlflow.db`` (artifacts in ``${paths.runs}/artifacts``)
unless ``MLFLOW_TRACKING_URI`` names a server. MLflow creates its schema on first use, and
processes doing that at once crash ("duplicate column"): :func:`init_store` creates it under
a file lock. A run records its ``host`` and ``pid`` tags, so that a later start, ``cache gc``
and a stopping sweep mark FAILED the RUNNING runs whose process is gone. A full disk met
writing the store is one error naming its ``mlflow.db`` and the space left
(:func:`store_full`).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import logging
import os
import re
import socket
import sqlite3
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from pipeline.core import stopping
from pipeline.core.errors import DataError, StoreError
from pipeline.core.files import DiskFullError, error_chain, is_disk_full, no_space
from pipeline.core.process import process_alive

log = logging.getLogger(__name__)

_OWN_URI = "PIPELINE_TRACKING_URI_SET_BY_PIPELINE"
DB_NAME = "mlflow.db"
# MLflow 3's UI opens an experiment of this kind on its runs view (not the GenAI overview).
EXPERIMENT_KIND_TAG = "mlflow.experimentKind"
EXPERIMENT_KIND = (EXPERIMENT_KIND_TAG, "custom_model_development")
NOTE_TAG = "mlflow.note.content"  # the run's description in the UI (Markdown)
ENDED_BY_TAG = "ended_by"  # why a run ended FAILED when its own process did not say
ERROR_TAG = "error"  # the refused setting's or file's message, on a run that ended FAILED for it
MLFLOW_TABLES = {"experiments", "alembic_version"}  # what makes a SQLite file a store
_PARTIAL = re.compile(rf"\.{re.escape(DB_NAME)}\.partial-(\d+)(?:-journal|-wal|-shm)?")


def tracking_uri(runs: str | os.PathLike, must_exist: bool = True) -> str:
    """The tracking URI: ``MLFLOW_TRACKING_URI`` if set, else SQLite under ``runs`` (the
    jobs' ``paths.runs``, a relative one taken from the current folder).

    Raises
    ------
    StoreError
        When ``must_exist`` and ``runs`` holds no ``mlflow.db``: MLflow would create an
        empty one and find no run (a typo). Only a job creates a store (:func:`init_store`).
    """
    env = os.environ.get("MLFLOW_TRACKING_URI")
    # mlflow.set_tracking_uri exports MLFLOW_TRACKING_URI: our own value is no user's choice.
    if env and env != os.environ.get(_OWN_URI):
        return env
    uri = _sqlite_uri(runs)
    db = sqlite_path(uri)
    if must_exist and not db.is_file():
        relative = "" if Path(runs).is_absolute() else f" ({str(runs)!r} from {Path.cwd()})"
        raise StoreError(
            f"no MLflow store at {db}{relative}: give the jobs' paths.runs, "
            f"as an absolute path or from the folder they ran in"
        )
    return uri


def _sqlite_uri(runs: str | os.PathLike) -> str:
    return f"sqlite:///{Path(runs).resolve() / DB_NAME}"


def use_store(runs: str | os.PathLike, must_exist: bool = True) -> str:
    """Point this process's MLflow client at the store of ``runs`` (:func:`tracking_uri`);
    returns the URI."""
    import mlflow

    uri = tracking_uri(runs, must_exist)
    mlflow.set_tracking_uri(uri)
    logging.getLogger("mlflow.store.db.utils").addFilter(_no_full_disk_traceback)  # once
    # MLflow draws a bar per artifact copied, which buries the job's own progress.
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    if uri == _sqlite_uri(runs):
        os.environ[_OWN_URI] = uri
    else:  # the user's server: it stays the choice for every later call and subprocess
        os.environ.pop(_OWN_URI, None)
    return uri


def _no_full_disk_traceback(record: logging.LogRecord) -> bool:
    """False for MLflow's traceback of an SQL statement failed for a full disk (the job
    says it in one line: :func:`store_full`)."""
    error = record.exc_info[1] if record.exc_info else None
    return error is None or not is_disk_full(error)


def init_store(
    runs: str | os.PathLike, experiment: str, job: DictConfig | None = None, note: str | None = None
) -> str:
    """Create (or upgrade) the store and the experiment once; return the experiment id.

    The experiment's note is ``note``, or one written from the job's config ``job``
    (:func:`describe_experiment`). A new SQLite store is built under another name and
    renamed into place, so a killed process never leaves a half-made ``mlflow.db``. Runs
    left RUNNING by a process of this machine that no longer exists are marked FAILED.

    Raises
    ------
    StoreError
        Naming the store, when it cannot be opened, is empty, or holds another program's
        tables.
    DataError
        Naming the store and the space left, when the disk is full (:func:`store_full`).
    """
    from mlflow.tracking import MlflowClient

    runs = Path(runs).resolve()
    runs.mkdir(parents=True, exist_ok=True)
    uri = use_store(runs, must_exist=False)  # the one place a store is created
    with open(runs / ".mlflow.lock", "w") as lock, _store_full_is_named(uri):
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            db = sqlite_path(uri)
            if db is not None and db == runs / DB_NAME:
                remove_partial_stores(runs)
                if not db.exists():
                    _create_sqlite_store(db)
            if db is not None and db.exists():
                check_sqlite_store(db)
            try:
                client = MlflowClient(uri)
                found = client.get_experiment_by_name(experiment)
                fail_dead_runs(client)
            except Exception as error:  # SQLAlchemy's and MLflow's errors alike
                if is_disk_full(error):
                    raise  # the store is sound, the disk full: _store_full_is_named says so
                raise StoreError(
                    f"the MLflow store {uri} cannot be opened ({type(error).__name__}: "
                    f"{error}); move it aside to start a new one (artifacts stay in "
                    f"{runs / 'artifacts'})"
                ) from error
            if found is not None:
                if EXPERIMENT_KIND_TAG not in found.tags:
                    client.set_experiment_tag(found.experiment_id, *EXPERIMENT_KIND)
                experiment_id, tags = found.experiment_id, found.tags
            else:
                location = (runs / "artifacts").as_uri() if uri.startswith("sqlite:") else None
                experiment_id = client.create_experiment(
                    experiment, artifact_location=location, tags=dict([EXPERIMENT_KIND])
                )
                tags = {}
            describe_experiment(client, experiment_id, experiment, tags, job, note)
            return experiment_id
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


DESCRIBED_TAG = "pipeline.described"  # JSON: the methods and presets its note names


def describe_experiment(
    client,
    experiment_id: str,
    name: str,
    tags: Mapping[str, str],
    job: DictConfig | None = None,
    note: str | None = None,
) -> None:
    """Set the experiment's note (shown above its runs): ``note``, or one written from a
    job's config (:func:`experiment_note`), which a later job of another method or preset
    extends. A note someone edited in the UI is left as it is.
    """
    if note is not None:
        if tags.get(NOTE_TAG) != note:
            client.set_experiment_tag(experiment_id, NOTE_TAG, note)
        return
    if job is None or job.get("method") is None:
        return
    from pipeline.core.methods import method_of

    old = json.loads(tags.get(DESCRIBED_TAG, '{"methods": {}, "presets": []}'))
    if NOTE_TAG in tags and tags[NOTE_TAG] != experiment_note(name, old):
        return  # the user's own words
    method = method_of(job)
    bold = re.match(r"\*\*(.+?)\*\*", method.description)
    preset = _experiment_preset(job)
    title = bold.group(1).rstrip(".") if bold else method.name
    methods = {**old["methods"], method.name: {"title": title, "headline": list(method.headline)}}
    presets = sorted(set(old["presets"]) | ({preset} if preset else set()))
    new = {"methods": methods, "presets": presets}
    if new == old and NOTE_TAG in tags:
        return
    client.set_experiment_tag(experiment_id, NOTE_TAG, experiment_note(name, new))
    client.set_experiment_tag(experiment_id, DESCRIBED_TAG, json.dumps(new, sort_keys=True))


def experiment_note(name: str, described: Mapping) -> str:
    """The note of experiment ``name`` whose jobs ran the methods and presets of
    ``described`` (``{"methods": {name: {"title", "headline"}}, "presets": [...]}``)."""
    methods = described["methods"]
    presets = ", ".join(f"`experiment={p}`" for p in described["presets"])
    lines = [
        f"**Experiment `{name}`**: runs of "
        + "; ".join(f"{m['title']} (`method={key}`)" for key, m in methods.items())
        + (f", from {presets}" if presets else "")
        + "."
    ]
    lines += [
        f"Read first: {', '.join(f'`{h}`' for h in m['headline'])}"
        + (f" ({m['title']})" if len(methods) > 1 else "")
        + "."
        for m in methods.values()
    ]
    lines.append(
        "A sweep's parent run (`sweep <time>`) says what the sweep found and holds "
        "its tables (`tables/summary.html`); each job is a child run. "
        f"`python -m pipeline.tables tables.experiments=[{name}]` rebuilds the "
        "tables from the finished runs."
    )
    return "\n\n".join(lines)


def _experiment_preset(job: DictConfig) -> str | None:
    """The ``experiment=`` preset of a job or a sweep's config; None outside Hydra."""
    hydra_cfg = job.get("hydra") or hydra_config()
    choices = OmegaConf.select(hydra_cfg, "runtime.choices") if hydra_cfg is not None else None
    preset = choices.get("experiment") if choices is not None else None
    return None if preset in (None, "none") else str(preset)


def sqlite_path(uri: str) -> Path | None:
    """The database file of a ``sqlite:///`` tracking URI, else None."""
    prefix = "sqlite:///"
    return Path(uri[len(prefix) :].split("?", 1)[0]) if uri.startswith(prefix) else None


STORE_FULL_HINT = "free some space, or point paths.runs (or MLFLOW_TRACKING_URI) elsewhere"


def store_full(
    error: BaseException, uri: str, run_id: str | None = None, status: str | None = None
) -> DiskFullError | None:
    """The one-line error for ``error`` when it is a full disk met while MLflow wrote the
    SQLite store of ``uri`` (SQLite's "database or disk is full", or ENOSPC for an
    artifact); None for any other error, a DataError (already named) or a server's store.

    It names the file (``mlflow.db``, or the artifact when the OSError says which), the
    space left and, given ``run_id``, whether that run ended FAILED (``status``) or is left
    RUNNING for the next start to mark FAILED.
    """
    db = sqlite_path(uri)
    if db is None or isinstance(error, DataError) or not is_disk_full(error):
        return None
    hint = STORE_FULL_HINT
    if run_id is not None:
        fate = (
            "ended FAILED"
            if status == "FAILED"
            else "is left RUNNING: the next start marks it FAILED"
        )
        hint += f"; its run {run_id} {fate}"
    return no_space(_file_written(error) or db, hint=hint)


def _file_written(error: BaseException) -> Path | None:
    """The file an ENOSPC in ``error``'s chain was writing, when it says (a copy's
    destination is its ``filename2``)."""
    for cause in error_chain(error):
        if isinstance(cause, OSError) and cause.errno in (errno.ENOSPC, errno.EDQUOT):
            name = cause.filename2 or cause.filename
            if name:
                return Path(os.fsdecode(name))
    return None


@contextmanager
def _store_full_is_named(uri: str) -> Iterator[None]:
    """Raise :func:`store_full`'s error for a full disk met in the block."""
    try:
        yield
    except Exception as error:
        full = store_full(error, uri)
        if full is None:
            raise
        raise full from error


def _create_sqlite_store(db: Path) -> None:
    """Let MLflow create its tables in a temporary file, renamed to ``db``."""
    from mlflow.tracking import MlflowClient

    partial = db.with_name(f".{db.name}.partial-{os.getpid()}")
    partial.unlink(missing_ok=True)
    uri = f"sqlite:///{partial}"
    try:
        MlflowClient(uri).search_experiments(max_results=1)
        os.replace(partial, db)
    finally:
        _close_engine(uri)
        partial.unlink(missing_ok=True)
        partial.with_name(f"{partial.name}-journal").unlink(missing_ok=True)


def _close_engine(uri: str) -> None:
    """Close the SQLAlchemy engine MLflow keeps for ``uri`` (a private map of MLflow 3):
    its pooled connection would keep a removed partial store's space taken."""
    from mlflow.store.tracking.sqlalchemy_store import SqlAlchemyStore

    engine = getattr(SqlAlchemyStore, "_engine_map", {}).pop(uri, None)
    if engine is not None:
        engine.dispose()


def remove_partial_stores(runs: Path) -> list[Path]:
    """Remove the half-made stores (``.mlflow.db.partial-<pid>``, its ``-journal``) of
    killed processes. Call it holding the store's lock, under which alone they are made."""
    removed = []
    for path in sorted(runs.glob(f".{DB_NAME}.partial-*")):
        match = _PARTIAL.fullmatch(path.name)
        if match is None or int(match[1]) == os.getpid():
            continue
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
            removed.append(path)
    if removed:
        log.info(
            "removed %s: left by processes killed while they created the store",
            ", ".join(p.name for p in removed),
        )
    return removed


def check_sqlite_store(db: Path) -> None:
    """Refuse a file at ``db`` that is not an MLflow store (empty, not SQLite, or holding
    none of :data:`MLFLOW_TABLES`) before MLflow writes its tables into it.

    Raises
    ------
    StoreError
        Naming ``db``, what is wrong and what to do.
    """
    aside = (
        "move it aside (or point paths.runs, or MLFLOW_TRACKING_URI, elsewhere) and "
        "a new store is created"
    )
    if db.stat().st_size == 0:
        raise StoreError(
            f"the MLflow store {db} is an empty file (0 bytes: a copy or a write cut short?); "
            f"delete it to start a new store, or put the real store in its place"
        )
    with open(db, "rb") as head:
        if head.read(16) != b"SQLite format 3\x00":
            raise StoreError(f"the MLflow store {db} is not a SQLite database; {aside}")
    try:
        # Not read-only: a journal left by a killed writer must be rolled back first.
        with contextlib.closing(sqlite3.connect(db, timeout=30)) as connection:
            query = "SELECT name FROM sqlite_master WHERE type = 'table'"
            tables = {name for (name,) in connection.execute(query)}
    except sqlite3.Error as error:
        raise StoreError(
            f"the MLflow store {db} cannot be read ({type(error).__name__}: {error}); {aside}"
        ) from error
    if not tables:
        raise StoreError(
            f"the MLflow store {db} is a SQLite database without tables, "
            f"not an MLflow store; {aside}"
        )
    if not MLFLOW_TABLES <= tables:
        listed = ", ".join(sorted(tables)[:8]) + (", ..." if len(tables) > 8 else "")
        raise StoreError(
            f"the MLflow store {db} holds another program's tables ({listed}), not MLflow's "
            f"(no {' or '.join(sorted(MLFLOW_TABLES - tables))} table); {aside}"
        )


def process_gone(run) -> bool:
    """Whether ``run`` (an MLflow Run) was started by a process of this machine (tags
    ``host``, ``pid``) that no longer exists."""
    tags = run.data.tags
    if tags.get("host") != socket.gethostname() or not tags.get("pid", "").isdigit():
        return False
    return not process_alive(int(tags["pid"]))


def fail_dead_runs(
    client,
    experiment_ids: list[str] | None = None,
    *,
    ended_by: str = "its process was gone at a later start",
    also_pid: int | None = None,
) -> list[str]:
    """Mark FAILED the RUNNING runs (of all experiments unless ``experiment_ids`` says
    which) whose process is gone from this machine, and those of ``also_pid`` (this one, as
    it stops); returns their ids."""
    if experiment_ids is None:
        experiment_ids = [e.experiment_id for e in all_pages(client.search_experiments)]
    if not experiment_ids:
        return []
    host = socket.gethostname()
    ended = []
    for run in all_pages(
        client.search_runs,
        experiment_ids=experiment_ids,
        filter_string="attributes.status = 'RUNNING'",
    ):
        tags = run.data.tags
        own = also_pid is not None and tags.get("host") == host and tags.get("pid") == str(also_pid)
        if not (own or process_gone(run)):
            continue
        client.set_tag(run.info.run_id, ENDED_BY_TAG, ended_by)
        client.set_terminated(run.info.run_id, status="FAILED")
        why = f" ({ended_by})" if own else f": its process {tags['pid']} is gone"
        log.warning("marked run %s FAILED%s", run.info.run_id, why)
        ended.append(run.info.run_id)
    return ended


def all_pages(search, **kwargs) -> list:
    """Every item of a paged MLflow search (``client.search_runs`` and the like)."""
    found, token = [], None
    while True:
        page = search(**kwargs, page_token=token)
        found += list(page)
        token = page.token
        if not token:
            return found


_STOP_CLEANUPS: dict[str, int] = {}  # tracking URI -> its cleanup's token (one per store)


def fail_runs_at_stop(uri: str) -> None:
    """At a stop, end FAILED the runs of this store that this process (or a dead one) left
    RUNNING; registered once per store."""
    if uri in _STOP_CLEANUPS:
        return

    def fail_runs() -> None:
        from mlflow.tracking import MlflowClient

        stopped = f"stopped by {stopping.describe()}"
        fail_dead_runs(MlflowClient(uri), ended_by=stopped, also_pid=os.getpid())

    _STOP_CLEANUPS[uri] = stopping.on_stop(fail_runs)


def hydra_config():
    """Hydra's config of this job, or None outside a Hydra app (a test, a notebook)."""
    try:
        from hydra.core.hydra_config import HydraConfig

        return HydraConfig.get()
    except (ImportError, ValueError):
        return None


# A shared view of the UI's runs table (an experiment tag read for ?viewStateShareKey=...).
RESULTS_VIEW = "results"


def share_results_view(experiment_id: str, headline: list[str], cfg: DictConfig) -> None:
    """Set the experiment's shared view :data:`RESULTS_VIEW`: the headline metrics, the
    model and the seed as columns, sorted by the first headline (:func:`results_url`)."""
    import mlflow

    if not headline:
        return
    columns = [f"metrics.`{name}`" for name in headline]
    columns += [
        f"params.`{key}`"
        for key in ("model.name", "seed")
        if OmegaConf.select(cfg, key) is not None
    ]
    state = {"selectedColumns": columns, "orderByKey": columns[0], "orderByAsc": True}
    key = f"mlflow.sharedViewState.{RESULTS_VIEW}"
    client = mlflow.MlflowClient()
    if client.get_experiment(experiment_id).tags.get(key) != json.dumps(state):
        client.set_experiment_tag(experiment_id, key, json.dumps(state))


def results_url(experiment_id: str, port: int = 5000) -> str:
    """The address of the results view in ``mlflow ui`` (``workflowType``: not the GenAI
    pages)."""
    return (
        f"http://127.0.0.1:{port}/#/experiments/{experiment_id}/runs"
        f"?viewStateShareKey={RESULTS_VIEW}&workflowType=machine_learning"
    )
