"""Stop signals always stop: wherever SIGTERM lands (imports, stages, training, a
garbage-collection callback), the job ends with status 143 and its run FAILED; a sweep's
workers never outlive their launcher (pipeline.core.stopping, pipeline.core.process)."""

from __future__ import annotations

import gc
import os
import random
import signal
import subprocess
import sys
import textwrap
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from pipeline.core import process, stopping
from pipeline.core.errors import Stopped

ROOT = Path(__file__).resolve().parents[1]

# `python -m pipeline` with garbage collection made frequent and slow while the job runs
# (gc callbacks and __del__ methods that spin), so that many signals land inside them,
# where Python drops exceptions; it reports each stop that landed there (and was raised
# again elsewhere).
GC_PRESSURE = textwrap.dedent("""
    import gc, os, runpy, sys, time
    from pipeline.core import stopping

    def spin(seconds):
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            pass

    class SlowDel:
        def __del__(self):
            if stopping._state.active:
                spin(0.001)

    def callback(phase, info):
        if stopping._state.active:
            if phase == "start":
                spin(0.002)
            else:
                garbage = SlowDel()
                garbage.cycle = garbage  # collected, __del__ and all, by a later pass

    redeliver = stopping._redeliver
    def reporting():
        os.write(2, b"TEST: a stop landed where Python drops exceptions\\n")
        redeliver()

    stopping._redeliver = reporting
    gc.callbacks.append(callback)
    gc.set_threshold(200, 5, 5)
    sys.argv = ["pipeline", *sys.argv[1:]]
    runpy.run_module("pipeline", run_name="__main__", alter_sys=True)
""")


@dataclass
class Outcome:
    returncode: int
    output: str
    statuses: list[str]  # of the store's runs, all experiments
    signalled: bool  # False: the job had ended before the signal was sent


def _statuses(runs: Path) -> list[str]:
    from mlflow.tracking import MlflowClient

    if not (runs / "mlflow.db").is_file():
        return []
    client = MlflowClient(f"sqlite:///{runs / 'mlflow.db'}")
    ids = [e.experiment_id for e in client.search_experiments()]
    return [r.info.status for r in client.search_runs(ids)] if ids else []


def _stop_job(
    runs: Path,
    delay_s: float,
    after: str | None,
    gc_pressure: bool = True,
    signum: int = signal.SIGTERM,
) -> Outcome:
    """Run a smoke job, send ``signum`` ``delay_s`` after the first output line that
    contains ``after`` (None: after the start), and wait for it to end."""
    command = (
        [sys.executable, "-c", GC_PRESSURE] if gc_pressure else [sys.executable, "-m", "pipeline"]
    )
    job = subprocess.Popen(
        [*command, "experiment=smoke", f"paths.runs={runs}"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines: list[str] = []
    seen = threading.Event()
    if after is None:
        seen.set()

    def read() -> None:
        for line in job.stdout:
            lines.append(line)
            if after is not None and after in line:
                seen.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        seen.wait(timeout=300)
        time.sleep(delay_s)
        signalled = job.poll() is None
        if signalled:
            job.send_signal(signum)
        job.wait(timeout=300)
    finally:
        job.kill()
        job.wait()
    reader.join(timeout=10)
    return Outcome(job.returncode, "".join(lines), _statuses(runs), signalled)


def _check(outcome: Outcome, signum: int = signal.SIGTERM) -> None:
    """A stopped job: status 128 + signal, a message that says so, no run left RUNNING,
    its run FAILED (unless the signal came before it was created, or after it ended)."""
    if not outcome.signalled:
        return
    name = signal.Signals(signum).name
    assert outcome.returncode == 128 + signum, outcome.output[-3000:]
    assert f"stopped by signal {signum} ({name})" in outcome.output, outcome.output[-3000:]
    assert "Traceback" not in outcome.output, outcome.output[-3000:]
    assert "RUNNING" not in outcome.statuses
    if "after the job's run had ended" in outcome.output:
        assert outcome.statuses == ["FINISHED"]
    elif "MLflow run" in outcome.output:
        assert outcome.statuses == ["FAILED"], outcome.output[-3000:]


def _leftovers(runs: Path) -> list[Path]:
    return [
        *(runs / "cache").glob("*/.tmp-*"),
        *(runs / "data").glob(".*partial*"),
        *runs.glob(".mlflow.db.partial-*"),
    ]


# --- in this process: the handler's logic --------------------------------------------


@pytest.fixture
def patient(monkeypatch):
    """A watchdog that never ends the test process, however slow the machine."""
    monkeypatch.setattr(stopping, "GRACE_S", 3600.0)


def test_a_stop_dropped_in_a_gc_callback_is_raised_again(patient):
    """The signal lands inside a gc callback, where Python prints and drops exceptions:
    the stop is raised again, outside the callback."""
    sent = []

    def callback(phase, info):
        if phase == "start" and not sent:
            sent.append(True)
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):  # the handler runs, and raises, in here
                pass

    before = signal.getsignal(signal.SIGTERM)
    try:
        with pytest.raises(Stopped) as stopped, stopping.job_scope():
            # Added inside the scope: a collection before it would send the signal to a
            # process whose handler is not installed yet, and end the test's process.
            gc.callbacks.append(callback)
            gc.collect()
            for _ in range(10_000_000):  # Stopped must be raised before this ends
                pass
            pytest.fail("the stop was dropped")
    finally:
        if callback in gc.callbacks:
            gc.callbacks.remove(callback)
    assert stopped.value.code == 128 + signal.SIGTERM
    assert stopping.requested() is None  # a scoped install forgets its stop
    assert signal.getsignal(signal.SIGTERM) is before


def test_another_error_during_a_stop_is_reported_as_the_stop(patient):
    """C code (numpy's buffer-format parser, an import) may turn the stop into another
    error: the job still ends as stopped by the signal."""
    with pytest.raises(Stopped, match=r"signal 15 \(SIGTERM\)"), stopping.job_scope():
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):
                pass
        except Stopped:
            raise ValueError("'O' is not a valid PEP 3118 buffer format string") from None


def test_a_swallowed_stop_ends_the_job_at_its_end(patient):
    with pytest.raises(Stopped), stopping.job_scope():
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):
                pass
        except BaseException:  # code that swallows everything
            pass


def test_outside_a_stop_the_handlers_are_left_as_they_were():
    before = signal.getsignal(signal.SIGTERM)
    with stopping.job_scope():
        assert signal.getsignal(signal.SIGTERM) is not before
    assert signal.getsignal(signal.SIGTERM) is before


# --- in a process of its own: the watchdog --------------------------------------------


def test_the_watchdog_ends_a_job_that_swallows_every_stop(tmp_path):
    """Code that catches the stop and carries on: GRACE_S later the watchdog runs the
    cleanups (here: a file written; a job's: run FAILED, temporary files removed) and
    ends the process with 128 + signal."""
    leftover = tmp_path / ".thing.partial-{pid}-0123abcd"
    script = textwrap.dedent(f"""
        import os, time
        from pathlib import Path
        from pipeline.core import stopping
        stopping.GRACE_S = 1.0
        stopping.install()
        stopping.on_stop(lambda: Path({str(tmp_path / "cleaned")!r}).write_text("yes"))
        Path({str(leftover)!r}.format(pid=os.getpid())).mkdir()
        with stopping.job_scope(leftovers_in=[{str(tmp_path)!r}]):
            while True:
                try:
                    print("ready", flush=True)
                    while True:
                        time.sleep(0.01)
                except BaseException:
                    pass
    """)
    job = subprocess.Popen(
        [sys.executable, "-c", script],
        cwd=ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    assert job.stdout.readline().strip() == "ready"
    started = time.monotonic()
    job.send_signal(signal.SIGTERM)
    output = job.communicate(timeout=60)[0]
    assert job.returncode == 128 + signal.SIGTERM, output
    assert time.monotonic() - started < 30
    assert "did not stop within 1 s" in output
    assert (tmp_path / "cleaned").read_text() == "yes"
    assert not list(tmp_path.glob(".thing.partial-*"))


def test_a_stop_outside_a_job_ends_the_process_at_once():
    """During imports (here: a busy loop where one would be) the handler raises nothing
    that an imported module could turn into its own error: the process ends, saying why."""
    script = (
        "from pipeline.core import stopping\nstopping.install()\nprint('ready', flush=True)\n"
        "while True:\n    pass\n"
    )
    job = subprocess.Popen(
        [sys.executable, "-c", script],
        cwd=ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    assert job.stdout.readline().strip() == "ready"
    job.send_signal(signal.SIGTERM)
    output = job.communicate(timeout=30)[0]
    assert job.returncode == 128 + signal.SIGTERM
    assert "stopped by signal 15 (SIGTERM)" in output
    assert "Traceback" not in output


# --- the real job ---------------------------------------------------------------------


def test_sigterm_during_the_imports_says_it_stopped_the_job(tmp_path):
    outcome = _stop_job(tmp_path / "runs", 0.5, after=None, gc_pressure=False)
    assert outcome.signalled
    _check(outcome)
    assert outcome.statuses == []


def test_sigterm_while_the_job_computes_ends_its_run_failed(tmp_path, mlflow_template):
    """One signal at a random point of the job, with garbage collection busy (the loop
    over many points is the slow test below)."""
    runs = tmp_path / "runs"
    mlflow_template(runs)
    outcome = _stop_job(runs, random.uniform(0.2, 3.0), after="MLflow run")
    assert outcome.signalled
    _check(outcome)
    assert outcome.statuses == ["FAILED"]
    assert not _leftovers(runs)


@pytest.mark.slow
def test_sigterm_at_many_points_always_stops_the_job(tmp_path, mlflow_template):
    """SIGTERM at random delays: during the imports, the stages, training, and inside
    garbage collection (made frequent and slow): always status 143, the run FAILED, no
    temporary file left; at least one stop landed where Python drops exceptions."""
    rng = random.Random(1)
    dropped = 0
    for attempt in range(16):
        runs = tmp_path / f"runs{attempt}"
        mlflow_template(runs)
        after, delay = (
            (None, rng.uniform(0.2, 5.0)) if attempt < 4 else ("MLflow run", rng.uniform(0.0, 6.0))
        )
        outcome = _stop_job(runs, delay, after=after)
        _check(outcome)
        assert not _leftovers(runs)
        landed = outcome.output.count("a stop landed where Python drops exceptions")
        dropped += landed > 0
        print(
            f"{delay:.2f} s after {after or 'the start'}: status {outcome.returncode}, "
            f"runs {outcome.statuses}, {landed} deliveries where exceptions are dropped, "
            f"watchdog: {'did not stop within' in outcome.output}"
        )
    assert dropped > 0


# --- a joblib sweep -------------------------------------------------------------------


def _start_sweep(runs: Path) -> tuple[subprocess.Popen, list[int], list[str]]:
    """A two-job sweep on loky workers, returned once both jobs have opened their runs,
    with the launcher's descendants (workers, loky's resource tracker) at that time."""
    # As from a terminal, where Ctrl-C is not ignored: a suite started in the background
    # of a script inherits SIGINT ignored, and the launcher keeps an ignored signal ignored.
    default_sigint = "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); "
    default_sigint += "os.execv(sys.executable, [sys.executable, *sys.argv[1:]])"
    sweep = subprocess.Popen(
        [
            sys.executable,
            "-c",
            default_sigint,
            "-m",
            "pipeline",
            "-m",
            "experiment=smoke",
            "seed=0,1",
            "hydra/launcher=local",
            "train.threads=1",
            f"paths.runs={runs}",
            "train.max_steps=100000",
            "train.epochs=100",
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines: list[str] = []

    def read() -> None:
        for line in sweep.stdout:
            lines.append(line)

    threading.Thread(target=read, daemon=True).start()
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and sweep.poll() is None:
        if len(_statuses_if_any(runs, "RUNNING")) >= 3:  # the parent and both jobs
            break
        time.sleep(0.5)
    assert sweep.poll() is None, "".join(lines)[-3000:]
    return sweep, process.descendants(sweep.pid), lines


def _statuses_if_any(runs: Path, status: str) -> list[str]:
    try:
        return [s for s in _statuses(runs) if s == status]
    except Exception:  # the store is being created
        return []


def _wait_gone(pids: list[int], timeout_s: float) -> list[int]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        alive = [pid for pid in pids if process.process_alive(pid)]
        if not alive:
            return []
        time.sleep(0.2)
    return alive


@pytest.mark.parametrize(
    "signum",
    [
        pytest.param(signal.SIGKILL, id="kill-9", marks=pytest.mark.slow),
        pytest.param(signal.SIGTERM, id="sigterm", marks=pytest.mark.slow),
        pytest.param(signal.SIGINT, id="sigint", marks=pytest.mark.slow),
    ],
)
def test_a_stopped_sweep_leaves_no_worker_and_no_running_run(tmp_path, mlflow_template, signum):
    runs = tmp_path / "runs"
    mlflow_template(runs)
    sweep, workers, lines = _start_sweep(runs)
    assert len(workers) >= 2
    try:
        sweep.send_signal(signum)
        sweep.wait(timeout=120)
        alive = _wait_gone(workers, 60)
    finally:
        for pid in [sweep.pid, *workers]:
            if process.process_alive(pid):
                os.kill(pid, signal.SIGKILL)
        sweep.wait()
    output = "".join(lines)
    assert not alive, f"workers {alive} outlived the launcher\n{output[-3000:]}"
    assert sweep.returncode in (128 + signum, -signum), output[-3000:]
    statuses = _statuses(runs)
    assert sorted(statuses) == ["FAILED"] * 3, output[-3000:]
    assert not _leftovers(runs)


def test_a_stop_removes_this_process_temporaries_and_no_one_elses(tmp_path):
    """The names the cache, the data generators and the store give their temporaries
    (pipeline.core.cache.temporary_name, pipeline.btf.synthetic, pipeline.core.store)."""
    from pipeline.core.cache import temporary_name

    me, other = os.getpid(), os.getpid() + 1
    (tmp_path / "cache" / "train").mkdir(parents=True)
    ours = [
        tmp_path / "cache" / "train" / temporary_name("0123456789abcdef0123"),
        tmp_path / "data" / f".synthetic_btf.partial-{me}-0a1b2c3d",
        tmp_path / f".mlflow.db.partial-{me}",
        tmp_path / f".mlflow.db.partial-{me}-journal",
    ]
    theirs = [
        tmp_path / "cache" / "train" / f".tmp-0123-0a1b2c3d-{other}@{process.host_name()}",
        tmp_path / "cache" / "train" / f".tmp-0123-0a1b2c3d-{me}@another-host",
        tmp_path / "data" / f".synthetic_btf.partial-{other}-0a1b2c3d",
        tmp_path / "data" / f".synthetic_btf.partial-{me}1-0a1b2c3d",
        tmp_path / f".mlflow.db.partial-{other}",
        tmp_path / "cache" / "train" / "0123456789abcdef0123",
    ]
    for path in ours + theirs:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.mkdir() if "tmp-" in path.name or "btf" in path.name else path.write_text("x")
    removed = process.remove_temporaries([tmp_path, tmp_path / "cache", tmp_path / "data"], [me])
    assert sorted(removed) == sorted(ours)
    assert all(path.exists() for path in theirs)
