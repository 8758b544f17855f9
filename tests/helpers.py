"""Plain helpers shared by the tests (fixtures live in ``conftest.py``).

Tests import from here (``from helpers import compose_config``): pytest's default
"prepend" import mode puts ``tests/`` (a folder without ``__init__.py``) at the front of
``sys.path`` before it imports a test module, so ``helpers`` is found there.
"""

from __future__ import annotations

import copy
import functools
import json
import re
import subprocess
import sys
from pathlib import Path

from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf

ROOT = Path(__file__).resolve().parents[1]  # the repository
CONF_DIR = ROOT / "pipeline" / "conf"
SHARED = ROOT.parent / "shared"  # real datasets, where the checkout has them
PACKAGE = ROOT / "pipeline"
TESTS = ROOT / "tests"
# Tests that check the wiring, not what training reaches, stop the smoke recipe's 300
# steps at this many (``train.max_steps``); tests/test_smoke_quality.py trains the recipe
# as the demo does.
WIRING_STEPS = 30


@functools.cache
def _register_schemas() -> None:
    """The structured configs in Hydra's ConfigStore, once per process (it keeps them)."""
    from pipeline.core.methods import register_schemas

    register_schemas()


# ``paths.<name>=<folder>`` with nothing Hydra's override grammar would read differently.
_PLAIN_FOLDER = re.compile(r"paths\.\w+=[\w./-]+")


def compose_config(*overrides: str, return_hydra_config: bool = False) -> DictConfig:
    """Compose ``conf/config.yaml`` exactly as ``python -m pipeline`` would (with the
    ``hydra`` section too if asked: its sweeper's parameters, for instance).

    The tests compose the same settings hundreds of times, each in another temporary
    folder, and a Hydra compose costs far more than a copy (docs/performance.md): the
    settings other than plain ``paths.*=folder`` are composed once per process, and the
    folders are set on a copy (as a ``paths.*`` override would: they are leaves that
    others interpolate)."""
    folders, rest = [], []
    for override in overrides:
        (folders if _PLAIN_FOLDER.fullmatch(override) else rest).append(override)
    cfg = copy.deepcopy(hydra_compose(tuple(rest), return_hydra_config))
    for override in folders:
        key, value = override.split("=", 1)
        OmegaConf.update(cfg, key, value)
    return cfg


@functools.lru_cache(maxsize=256)
def hydra_compose(overrides: tuple[str, ...], return_hydra_config: bool = False) -> DictConfig:
    """Hydra's own compose of ``overrides``, once per process (do not change the result:
    :func:`compose_config` hands out copies)."""
    _register_schemas()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(
            config_name="config", overrides=list(overrides), return_hydra_config=return_hydra_config
        )


def check_one_line_refusal(done: subprocess.CompletedProcess, named: str) -> None:
    """A refusal (``pipeline/core/refusal.py``): exit status 2, no traceback, and one
    ``error: `` line on stderr that holds ``named``."""
    output = done.stdout + done.stderr
    assert done.returncode == 2, output[-2000:]
    assert "Traceback" not in output and "HYDRA_FULL_ERROR" not in output, output[-2000:]
    errors = [line for line in done.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and named in errors[0], done.stderr[-2000:]


def recipe_tags(params: dict) -> dict[str, str]:
    """The ``recipe`` and ``render_recipe`` tags a job with these flattened settings logs
    (:func:`pipeline.core.run.job_run`): hand-made runs need them to be tabled."""
    from pipeline.core.recipe import recipe_id, render_recipe_id

    return {"recipe": recipe_id(params), "render_recipe": render_recipe_id(params)}


def exits_before_torch(calls: list[tuple[str, list[str]]]) -> tuple[list, bool, str]:
    """Call each command's ``main(argv)`` (``calls``: ``("module", argv)``) in one fresh
    interpreter; returns each call's exit code, whether torch was imported by then, and
    the calls' stderr: a bad argument must be answered before torch loads."""
    import json
    import subprocess
    import sys

    code = (
        "import importlib, json, sys\n"
        f"calls = {calls!r}\n"
        "codes = []\n"
        "for module, argv in calls:\n"
        "    try:\n"
        "        importlib.import_module(module).main(argv)\n"
        "    except SystemExit as stop:\n"
        "        codes.append(stop.code)\n"
        "print(json.dumps({'codes': codes, 'torch': 'torch' in sys.modules}))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout.strip().splitlines()[-1])
    return result["codes"], result["torch"], done.stderr


def module_name(path: Path) -> str:
    """The dotted name of a module file under the repository (``pipeline/a/__init__.py``:
    ``pipeline.a``)."""
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


# Every module of the package, from the files on disk (``pipeline/__main__.py`` included).
PIPELINE_MODULES = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def fresh_python(code: str, timeout: float = 300) -> dict:
    """Run ``code`` in a new interpreter (this one's environment); it prints one JSON line."""
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=timeout
    )
    assert done.returncode == 0, done.stderr[-4000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


# ``python -m pipeline`` without paying its imports for every call: a fork server that
# imported the package's heavy modules once forks a fresh process per command, which then
# runs ``pipeline/__main__.py`` as ``__main__`` exactly as the command line does. The
# child is a new process (its own signal handlers, store, torch threads), forked from a
# single-threaded server that never computed anything, so nothing leaks between commands.
# What a job imports on its way (torch's optimisers bring torch._dynamo; MLflow's store
# SQLAlchemy; the tags GitPython), imported without creating anything: no thread starts.
_PRELOAD = [
    "torch",
    "torch._dynamo",
    "sklearn.cluster",
    "mlflow",
    "mlflow.pyfunc",
    "mlflow.store.tracking.sqlalchemy_store",
    "git",
    "hydra",
    "matplotlib.pyplot",
    "pipeline.app",
    "pipeline.__main__",
    "pipeline.btf.runner",
    "pipeline.btf.train",
    "pipeline.tables",
]


@functools.cache
def _fork_server():
    """This worker's fork server (started at its first command)."""
    import multiprocessing

    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(_PRELOAD)
    return context


def _run_command(
    module: str | None, code: str | None, arguments: list, cwd: str, env: dict, out: str, err: str
):
    import atexit
    import os
    import runpy

    os.chdir(cwd)
    os.environ.clear()
    os.environ.update(env)
    for fd, path in ((1, out), (2, err)):
        file = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
        os.dup2(file, fd)
        os.close(file)
    try:
        if module is not None:
            sys.argv = [module, *arguments]
            runpy.run_module(module, run_name="__main__", alter_sys=True)
        else:  # as ``python -c``: the current folder first on the path, not tests/
            import types

            sys.argv = ["-c", *arguments]
            sys.path[:] = ["", *(p for p in sys.path if Path(p or ".").resolve() != TESTS)]
            main = sys.modules["__main__"] = types.ModuleType("__main__")
            exec(compile(code, "<string>", "exec"), main.__dict__)
    finally:  # the exit handlers (MLflow's, joblib's) run as at the interpreter's exit
        atexit._run_exitfuncs()


def _forked(
    module: str | None, code: str | None, arguments: list, cwd: Path, env: dict | None, timeout
) -> subprocess.CompletedProcess:
    import os
    import tempfile

    shown = [module or "-c", *arguments]
    with tempfile.TemporaryDirectory() as folder:
        out, err = os.path.join(folder, "out"), os.path.join(folder, "err")
        child = _fork_server().Process(
            target=_run_command,
            args=(module, code, arguments, str(cwd), {**os.environ, **(env or {})}, out, err),
        )
        child.start()
        child.join(timeout)
        if child.exitcode is None:
            child.kill()
            child.join()
            raise subprocess.TimeoutExpired(shown, timeout)
        return subprocess.CompletedProcess(
            shown,
            child.exitcode,
            Path(out).read_text(errors="replace"),
            Path(err).read_text(errors="replace"),
        )


def pipeline_command(
    *arguments: str,
    module: str = "pipeline",
    cwd: Path = ROOT,
    env: dict | None = None,
    timeout: float = 600,
) -> subprocess.CompletedProcess:
    """``python -m <module> arguments`` in ``cwd``, with ``env`` added to this process's
    environment: its exit status, stdout and stderr."""
    return _forked(module, None, list(arguments), cwd, env, timeout)


def python_code(code: str, cwd: Path = ROOT, timeout: float = 600) -> subprocess.CompletedProcess:
    """``python -c code`` in ``cwd``, forked as :func:`pipeline_command` is (for the
    examples the docs give, run from another folder): its exit status, stdout and stderr.
    The package is already imported: whether it imports from another folder is
    tests/test_install.py's question, in a new interpreter."""
    return _forked(None, code, [], cwd, None, timeout)
