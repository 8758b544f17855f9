"""A stop signal always stops the job, whatever it interrupts.

Python runs a signal handler in the main thread between two bytecodes, wherever that is: in
a ``__del__`` or garbage-collection callback (where its exception is dropped), in an import
(where C code may turn it into another error). So a stop (SIGTERM, SIGINT, SIGHUP) is first
*recorded*, and then:

- **inside a job** (:func:`job_scope`) the handler raises :class:`Stopped`: the stack unwinds
  as for any error (the run ends FAILED, the cache removes its temporary folder) and the
  scope's end ends the process with status 128 + signal. A ``Stopped`` that Python would
  drop is raised again a moment later; any other error surfacing while a stop is pending is
  reported as the stop.
- **outside a job** (imports, Hydra's setup, a launcher waiting for its workers) the main
  thread is held where it is and the stop proceeds at once.
- a **watchdog** thread, woken by the signal itself (``signal.set_wakeup_fd``, even during a
  long C call), ends the process when the main thread has not :data:`GRACE_S` seconds after
  the signal: it runs the :func:`on_stop` cleanups (each for at most :data:`CLEANUP_S`
  seconds), then ``os._exit``.

A sweep's workers stop when their launcher (:data:`LAUNCHER_ENV`) is gone, ``kill -9``
included.
"""

from __future__ import annotations

import _thread  # documented stdlib: interrupt_main has no public twin in threading
import contextlib
import logging
import os
import select
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

from pipeline.core.errors import Stopped
from pipeline.core.process import remove_temporaries

log = logging.getLogger(__name__)

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
GRACE_S = 10.0  # from the signal to os._exit when the job has not stopped by itself
CLEANUP_S = 15.0  # the most one cleanup may take when the process ends
REDELIVER_S = 0.01  # from a dropped stop to its next delivery: time to leave the hook
PARENT_POLL_S = 0.5  # how often a worker checks that its launcher is still there
# "<pid>@<host>" of a sweep's launching process, set there for its workers to watch.
LAUNCHER_ENV = "PIPELINE_SWEEP_LAUNCHER"


class _State:
    """What the handler, the watchdog and the job scope share (no lock: the handler may
    interrupt any code)."""

    def __init__(self) -> None:
        self.pid = os.getpid()  # a forked child is not the process these describe
        self.mode: str | None = None  # None, "process" (for good) or "scoped" (one job)
        self.signum: int | None = None  # the first stop signal
        self.reason = ""  # why, when the signal was sent by this process itself
        self.raised = False  # Stopped raised and not dropped since
        self.redeliver_at: float | None = None  # when to raise a dropped Stopped again
        self.in_handler = False
        self.active = 0  # job scopes entered
        self.jobs_ended = 0  # job scopes left
        self.deadline: float | None = None  # time.monotonic() at which the watchdog ends it
        self.previous: dict[int, object] = {}  # the handlers replaced
        self.previous_wakeup = -1
        self.previous_hook = None
        self.cleanups: dict[int, Callable[[], object]] = {}
        self.next_token = 0
        self.pipe: tuple[int, int] | None = None
        self.watchdog: threading.Thread | None = None
        self.parent_watch: threading.Thread | None = None
        self.finishing = threading.Lock()


_state = _State()


def install() -> bool:
    """Stop on :data:`STOP_SIGNALS` for the rest of this process (ignored signals stay
    ignored). Returns False, doing nothing, outside the main thread."""
    if threading.current_thread() is not threading.main_thread():
        return False
    if _state.mode is None:
        _install()
    _state.mode = "process"
    launcher = _launcher()
    if launcher is not None:
        watch_parent(launcher)
    return True


@contextlib.contextmanager
def job_scope(leftovers_in: Iterable[str | os.PathLike] = ()) -> Iterator[None]:
    """The span of one job: a stop signal raises :class:`Stopped` inside it and ends the
    process at its end (without :func:`install`, as in a test, the handlers last for the
    span and ``Stopped`` is raised instead).

    ``leftovers_in``: folders where this process's temporary files may lie, removed when a
    stop ends it (:func:`~pipeline.core.process.remove_temporaries`)."""
    if _state.mode is None and _launcher() is not None:
        install()  # a sweep's worker: stop for good, and watch the launcher
    if _state.mode is None and threading.current_thread() is not threading.main_thread():
        yield  # only the main thread receives signals
        return
    folders = [Path(folder) for folder in leftovers_in]
    token = on_stop(lambda: remove_temporaries(folders, [os.getpid()]))
    _state.active += 1  # before the handlers: outside a job they would hold the thread
    try:
        if _state.mode is None:
            _install()
            _state.mode = "scoped"
        try:
            yield
        except BaseException as error:
            if _state.signum is None:
                raise
            if not isinstance(error, Stopped):  # C code turned the stop into another error
                log.debug("the stop surfaced as %s: %s", type(error).__name__, error)
            _stop_here()
        if _state.signum is not None:  # it came where nothing could be raised
            _stop_here()
    finally:
        if _state.mode == "scoped":
            _uninstall()
        _state.active -= 1
        _state.jobs_ended += 1
        forget(token)


def check() -> None:
    """A safe point: raise :class:`Stopped` if a stop is pending inside a job (for a loop
    that may have swallowed the first one)."""
    if _state.signum is not None and _state.active and os.getpid() == _state.pid:
        raise Stopped(_state.signum)


def requested() -> int | None:
    """The stop signal received by this process, or None."""
    return _state.signum if os.getpid() == _state.pid else None


def describe(signum: int | None = None) -> str:
    """``"signal 15 (SIGTERM)"``, with the reason when this process sent it itself."""
    signum = signum or _state.signum or signal.SIGTERM
    text = f"signal {signum} ({signal.Signals(signum).name})"
    return f"{text}: {_state.reason}" if _state.reason else text


def on_stop(cleanup: Callable[[], object]) -> int:
    """Run ``cleanup`` when a stop ends this process (at most :data:`CLEANUP_S` seconds,
    the latest registered first). Returns a token for :func:`forget` (a plain number:
    its holders may be pickled)."""
    token = _state.next_token
    _state.next_token += 1
    _state.cleanups[token] = cleanup
    return token


def forget(token: int) -> None:
    """Cancel the cleanup that :func:`on_stop` registered under ``token``."""
    _state.cleanups.pop(token, None)


def watch_parent(pid: int) -> None:
    """Stop this process (as SIGTERM would) once its parent ``pid`` is gone: a sweep's
    worker must not outlive its launcher, even one killed with ``kill -9``."""
    if _state.parent_watch is not None:
        return

    def watch() -> None:
        while os.getppid() == pid:
            time.sleep(PARENT_POLL_S)
        _state.reason = f"the sweep's launching process {pid} is gone"
        os.kill(os.getpid(), signal.SIGTERM)

    _state.parent_watch = threading.Thread(target=watch, name="watch-launcher", daemon=True)
    _state.parent_watch.start()


# --- the handler, the watchdog and the end --------------------------------------------


def _install() -> None:
    _state.pid = os.getpid()
    _state.previous = {}
    for signum in STOP_SIGNALS:
        current = signal.getsignal(signum)
        if current == signal.SIG_IGN:  # nohup, or a background job of a script
            continue
        _state.previous[signum] = current
        signal.signal(signum, _handle)
    if _state.pipe is None:
        read, write = os.pipe()
        os.set_blocking(write, False)
        _state.pipe = (read, write)
    _state.previous_wakeup = signal.set_wakeup_fd(_state.pipe[1], warn_on_full_buffer=False)
    _state.previous_hook = sys.unraisablehook
    sys.unraisablehook = _unraisable
    if _state.watchdog is None:
        _state.watchdog = threading.Thread(target=_watch, name="stop-watchdog", daemon=True)
        _state.watchdog.start()


def _uninstall() -> None:
    """Undo a scoped install, and forget a stop that the scope raised."""
    _restore(_state.previous_wakeup)
    _state.signum, _state.reason, _state.raised, _state.deadline = None, "", False, None
    _state.redeliver_at = None


def _restore(wakeup_fd: int) -> None:
    """Put back the handlers and hook that :func:`_install` replaced."""
    for signum, previous in _state.previous.items():
        signal.signal(signum, previous)
    signal.set_wakeup_fd(wakeup_fd)
    sys.unraisablehook = _state.previous_hook or sys.__unraisablehook__
    _state.mode = None


def _handle(signum: int, frame) -> None:
    if os.getpid() != _state.pid:  # a forked child, without the watchdog: the default
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)
        return
    if _state.signum is None:
        _state.signum = signum
    if _state.in_handler:  # a signal while the handler runs: that one decides
        return
    _state.in_handler = True
    try:
        if _state.active:
            if _state.deadline is None:
                _state.deadline = time.monotonic() + GRACE_S
            if _dropped_there(frame):
                _redeliver()
            elif not _state.raised:  # a repeated signal must not interrupt the unwinding
                _state.raised = True
                raise Stopped(_state.signum)
            return
    finally:
        _state.in_handler = False
    # Outside a job: nothing to unwind. Hold the main thread here (it may hold the import
    # lock, or sit in joblib's loop) and let the watchdog end the process now.
    _state.deadline = time.monotonic()
    while True:
        time.sleep(60)


def _unraisable(unraisable) -> None:
    """A ``Stopped`` that Python dropped (raised in a ``__del__`` or callback) is raised
    again: the watchdog delivers the signal anew once this hook has returned."""
    if isinstance(unraisable.exc_value, Stopped) and os.getpid() == _state.pid:
        _redeliver()
        return
    (_state.previous_hook or sys.__unraisablehook__)(unraisable)


def _redeliver() -> None:
    """Have the watchdog deliver the stop signal again :data:`REDELIVER_S` from now."""
    _state.raised = False
    _state.redeliver_at = time.monotonic() + REDELIVER_S


_NO_RAISE = {_unraisable.__code__, _redeliver.__code__}


def _dropped_there(frame) -> bool:
    """Whether an exception raised in ``frame`` would be dropped: it runs inside a
    ``__del__`` or inside the hook that raises dropped stops again."""
    while frame is not None:
        if frame.f_code in _NO_RAISE or frame.f_code.co_name == "__del__":
            return True
        frame = frame.f_back
    return False


def _watch() -> None:
    read = _state.pipe[0]
    while True:
        wait = 0.2 if _state.redeliver_at is None else REDELIVER_S / 2
        if select.select([read], [], [], wait)[0]:
            for signum in os.read(read, 512):
                # A byte read after a scoped job ended (its handlers uninstalled) is a
                # stop that scope already raised, not a new one.
                if signum in _state.previous and _state.signum is None and _state.mode:
                    _state.signum = signum  # the handler has not run yet
        if _state.signum is not None and _state.deadline is None and _state.mode:
            _state.deadline = time.monotonic() + GRACE_S
        if _state.redeliver_at is not None and time.monotonic() >= _state.redeliver_at:
            _state.redeliver_at = None
            if _state.signum is not None and _state.active and not _state.raised:
                # The handler again, in the main thread, without a real signal (which would
                # come back through the wakeup pipe as a new request).
                _thread.interrupt_main(_state.signum)
        if _state.deadline is not None and time.monotonic() >= _state.deadline:
            message = f"stopped by {describe()}"
            if _state.active:
                message += (
                    f": the job did not stop within {GRACE_S:.0f} s (the signal landed where "
                    f"it could not interrupt it); its run is marked FAILED and the process ends"
                )
            elif _state.jobs_ended:
                message += " after the job's run had ended"
            _finish(message)
            time.sleep(60)  # the main thread is ending the process: give it time
            os._exit(128 + (_state.signum or signal.SIGTERM))


def _stop_here() -> None:
    """The safe point at a job's end, in the main thread."""
    _state.raised = True  # a repeated signal must not interrupt what follows
    log.error("stopped by %s: the job's run ends FAILED", describe())
    if _state.mode == "scoped":
        raise Stopped(_state.signum) from None
    _finish("")


def _finish(message: str) -> None:
    """Run the cleanups, flush the logs, end the process with status 128 + signal."""
    if not _state.finishing.acquire(blocking=False):
        if threading.current_thread() is threading.main_thread():
            while True:  # the watchdog is ending the process
                time.sleep(60)
        return
    _state.raised = True
    if message:
        _bounded(lambda: log.error(message), 2.0, fallback=message)
    for cleanup in reversed(list(_state.cleanups.values())):
        _bounded(cleanup, CLEANUP_S)
    _bounded(_flush, 2.0)
    os._exit(128 + (_state.signum or signal.SIGTERM))


def _bounded(function: Callable[[], object], timeout_s: float, fallback: str = "") -> None:
    """Call ``function`` in its own thread for at most ``timeout_s``: whatever lock the
    interrupted main thread holds, the process still ends."""
    done = threading.Event()

    def call() -> None:
        try:
            function()
        except BaseException as error:  # a cleanup that fails must not stop the others
            with contextlib.suppress(BaseException):
                log.warning("cleanup %r failed: %s: %s", function, type(error).__name__, error)
        finally:
            done.set()

    threading.Thread(target=call, name="stop-cleanup", daemon=True).start()
    if not done.wait(timeout_s):
        note = fallback or f"cleanup {function!r} did not end within {timeout_s:.0f} s"
        with contextlib.suppress(OSError):
            os.write(2, f"{note}\n".encode())


def _flush() -> None:
    for handler in logging.getLogger().handlers:
        handler.flush()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()


def _launcher() -> int | None:
    """The pid of the sweep's launching process when it is this process's parent (a
    joblib worker; not a SLURM task, whose parent is SLURM's)."""
    pid, _, host = os.environ.get(LAUNCHER_ENV, "").partition("@")
    if not pid.isdigit() or host != socket.gethostname() or int(pid) != os.getppid():
        return None
    return int(pid)


def _forget_in_child() -> None:
    """After ``fork`` without ``exec``: the child has no watchdog and must not write to
    the parent's wakeup pipe; it gets the handlers that were there before."""
    if _state.mode is None or threading.current_thread() is not threading.main_thread():
        return
    _restore(-1)


os.register_at_fork(after_in_child=_forget_in_child)
