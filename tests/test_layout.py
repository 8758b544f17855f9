"""The project's shape: what importing it does, how its packages depend on each other,
that every experiment composes, and that the examples in its docstrings run.

Packages (see ``pipeline/__init__.py``): ``core`` (shared), ``data`` (readers), one per
method (``btf`` A, ``brdf_map`` B, ``fourier`` C), and the commands (``__main__``,
``app``, ``tables``, ``bench``).
"""

from __future__ import annotations

import ast
import doctest
import importlib
import io
import json
import re
import subprocess
import sys
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import pytest
from helpers import CONF_DIR, ROOT, compose_config
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import OmegaConf

PACKAGE = ROOT / "pipeline"
TESTS = ROOT / "tests"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


# Every module of the package, from the files on disk (``pipeline/__main__.py`` included).
MODULES = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _fresh_python(code: str, timeout: float = 300) -> dict:
    """Run ``code`` in a new interpreter (this one's environment); it prints one JSON line."""
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)
    assert done.returncode == 0, done.stderr[-4000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------- importing has no effects

# Third-party libraries that change os.environ when imported (pinned versions, pyproject):
# they are imported before the snapshot, so that what remains is pipeline's own doing.
#   sklearn/__init__.py: os.environ.setdefault("KMP_DUPLICATE_LIB_OK", "True") and
#                        os.environ.setdefault("KMP_INIT_AT_FORK", "FALSE")
#   mlflow/__init__.py:  set_telemetry_client() sets _MLFLOW_TELEMETRY_SESSION_ID
#                        (mlflow/telemetry/client.py), unless telemetry is disabled
# torch, numpy, scipy, matplotlib, hydra, omegaconf, pandas, OpenEXR, PIL set nothing.
LIBRARY_ENV = {
    "sklearn": {"KMP_DUPLICATE_LIB_OK", "KMP_INIT_AT_FORK"},
    "mlflow": {"_MLFLOW_TELEMETRY_SESSION_ID"},
}

IMPORT_PROBE = r"""
import importlib, json, os, pkgutil, sys, traceback

LIBRARIES = __LIBRARIES__
SPAWNS = {"subprocess.Popen", "os.system", "os.fork", "os.forkpty", "os.posix_spawn",
          "os.spawn", "os.exec"}
phase = ["libraries"]
env_writes, spawns, watched = [], [], []


def origin():
    # Innermost frame outside this probe and the os/subprocess modules, and the innermost
    # frame in pipeline/ (what imported the library that did it, when one did).
    frames = [f for f in traceback.extract_stack()[:-2]
              if f.filename not in ("<string>", "<frozen os>")
              and not f.filename.endswith(("/os.py", "/subprocess.py"))]
    inner = frames[-1] if frames else None
    own = [f for f in frames if "/pipeline/" in f.filename]
    fmt = lambda f: f"{f.filename}:{f.lineno}" if f else None
    return fmt(inner), fmt(own[-1] if own else None)


def audit(event, args):
    if event in ("os.putenv", "os.unsetenv"):
        key = args[0].decode() if isinstance(args[0], bytes) else str(args[0])
        env_writes.append([phase[0], event, key, *origin()])
    elif event in SPAWNS:
        spawns.append([phase[0], event, repr(args)[:200], *origin()])


class Watch:
    # Records who imports matplotlib.pyplot; finds nothing itself.
    def find_spec(self, name, path=None, target=None):
        if name == "matplotlib.pyplot":
            watched.append([phase[0], name, *origin()])
        return None


sys.addaudithook(audit)
sys.meta_path.insert(0, Watch())

import matplotlib

def backend():
    rc = matplotlib.rcParams
    getter = getattr(rc, "_get_backend_or_none", None)  # never resolves the backend
    return getter() if getter else dict.__getitem__(rc, "backend")

uses = []
real_use = matplotlib.use
def use(*args, **kwargs):
    uses.append([phase[0], repr(args), *origin()])
    return real_use(*args, **kwargs)
matplotlib.use = use

env_start = dict(os.environ)
for name in LIBRARIES:
    importlib.import_module(name)
env_libraries = dict(os.environ)
backend_before = backend()
pyplot_before = "matplotlib.pyplot" in sys.modules

phase[0] = "pipeline"
import pipeline

def fail(name):
    raise ImportError(f"walk_packages could not import {name}")

walked = [m.name for m in pkgutil.walk_packages(pipeline.__path__, "pipeline.", onerror=fail)
          if m.name.rsplit(".", 1)[-1] != "__main__"]
for name in walked:
    importlib.import_module(name)
phase[0] = "done"

me = os.getpid()
children = []
for entry in os.listdir("/proc"):
    if entry.isdigit():
        try:
            stat = open(f"/proc/{entry}/stat").read()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == me:
            children.append(stat[:100])

diff = lambda a, b: {k: [a.get(k), b.get(k)] for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)}
print(json.dumps({
    "walked": walked,
    "library_env": diff(env_start, env_libraries),
    "pipeline_env": diff(env_libraries, dict(os.environ)),
    "env_writes": env_writes,
    "spawns": spawns,
    "children": children,
    "backend": [backend_before, backend()],
    "pyplot": [pyplot_before, "matplotlib.pyplot" in sys.modules],
    "pyplot_importers": watched,
    "use_calls": uses,
}))
"""


@pytest.fixture(scope="module")
def import_probe() -> dict:
    """Every pipeline module imported, one after another, in a fresh interpreter."""
    code = IMPORT_PROBE.replace("__LIBRARIES__", repr(sorted(LIBRARY_ENV)))
    return _fresh_python(code)


def test_every_module_is_imported_by_the_walk(import_probe):
    """The walk reaches every file under pipeline/ (a folder without ``__init__.py``
    would hide its modules from it, and from setuptools' package list)."""
    on_disk = {name for name in MODULES if name != "pipeline" and not name.endswith("__main__")}
    assert set(import_probe["walked"]) == on_disk


def test_importing_pipeline_leaves_the_environment_alone(import_probe):
    """os.environ is unchanged by importing every module, once the libraries that set
    variables themselves (:data:`LIBRARY_ENV`) are loaded; those set only what is listed."""
    for key in import_probe["library_env"]:
        assert any(key in keys for keys in LIBRARY_ENV.values()), (
            f"a library set {key}; add it to LIBRARY_ENV with where it is set",
            import_probe["env_writes"])
    writes = [w for w in import_probe["env_writes"] if w[0] == "pipeline"]
    assert import_probe["pipeline_env"] == {}, writes
    # Set and restored again counts too: nothing writes the environment while importing.
    assert writes == [], "phase, event, key, where, pipeline frame"


def test_importing_pipeline_starts_no_process(import_probe):
    spawns = [s for s in import_probe["spawns"] if s[0] == "pipeline"]
    assert spawns == [], "phase, event, args, where, pipeline frame"
    assert import_probe["children"] == []


def test_importing_pipeline_leaves_matplotlib_alone(import_probe):
    """No module picks a backend or loads pyplot (which picks one) when imported: a
    figure is drawn with ``matplotlib.figure.Figure`` where it is made."""
    assert import_probe["use_calls"] == []
    assert import_probe["backend"][1] == import_probe["backend"][0]
    assert import_probe["pyplot"] == [False, False], import_probe["pyplot_importers"]


TORCH_PROBE = r"""
import importlib, json, sys, traceback

importers = []

class Watch:
    def find_spec(self, name, path=None, target=None):
        if name == "torch":
            importers.append([f"{f.filename}:{f.lineno}" for f in traceback.extract_stack()
                              if "/pipeline/" in f.filename])
        return None

sys.meta_path.insert(0, Watch())
loaded = {}
for name in __MODULES__:
    importlib.import_module(name)
    loaded[name] = "torch" in sys.modules
print(json.dumps({"loaded": loaded, "importers": importers}))
"""


def test_commands_start_without_torch():
    """``import pipeline``, the job (``python -m pipeline``: ``pipeline.__main__``,
    ``pipeline.app``) and ``python -m pipeline.tables`` do not load torch: a rerun whose
    stages are all cached starts in a second or two. (Each name is imported in turn, in
    one fresh interpreter; torch is imported inside the stages that compute.)"""
    names = ["pipeline", "pipeline.tables", "pipeline.app", "pipeline.__main__"]
    probe = _fresh_python(TORCH_PROBE.replace("__MODULES__", repr(names)))
    assert probe["loaded"] == dict.fromkeys(names, False), probe["importers"]


# ------------------------------------------------------------------ experiments compose

EXPERIMENTS = sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml"))
METHOD_A = {"neural_btf", "clustered", "pca"}


def _sweep_points(experiment: str) -> list[list[str]]:
    """The experiment alone, then each value of each of its sweep's parameters alone."""
    cfg = compose_config(f"experiment={experiment}", return_hydra_config=True)
    params = OmegaConf.select(cfg, "hydra.sweeper.params") or {}
    parser = OverridesParser.create()
    points = [[]]
    for key, values in params.items():
        override = parser.parse_override(f"{key}={values}")
        points += [[f"{key}={value}"] for value in override.sweep_string_iterator()]
    return points


def test_experiments_are_found():
    assert {"default", "smoke", "brdf_map", "fourier"} <= set(EXPERIMENTS)


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_experiment_composes_with_its_methods_settings_only(experiment):
    """Each experiment (and each point of its sweep) composes with the real config;
    method A's settings (``btf.*``, ``train.*``) are there for A and absent from B and C."""
    for point in _sweep_points(experiment):
        cfg = compose_config(f"experiment={experiment}", *point)
        where = f"experiment={experiment} {' '.join(point)}".strip()
        if cfg.method.name in METHOD_A:
            assert isinstance(OmegaConf.select(cfg, "btf.crop.size"), int), where
            assert "train" in cfg, where
        else:
            assert {"btf", "train"} & set(cfg) == set(), where
        OmegaConf.to_container(cfg, resolve=True)  # every interpolation resolves


# --------------------------------------------------------- imports: privacy and cycles


@dataclass(frozen=True)
class Import:
    """One import statement's target, as written in a file."""

    source: str  # the importing module
    target: str  # the module imported (for ``from m import x``: ``m.x`` if a module, else ``m``)
    names: tuple[str, ...]  # for ``from m import x, y``: the names taken from ``target``
    line: int
    deferred: bool  # inside a function (runs when called) or ``if TYPE_CHECKING:``


def _resolve(source: str, is_package: bool, module: str | None, level: int) -> str:
    if level == 0:
        return module or ""
    base = source.split(".") if is_package else source.split(".")[:-1]
    base = base[: len(base) - (level - 1)]
    return ".".join(base + ([module] if module else []))


@cache
def _imports(path: Path) -> tuple[list[Import], list[tuple[str, int]]]:
    """The file's imports, and the private attributes it reads from pipeline modules
    (``module._name`` where ``module`` was imported as a pipeline module)."""
    source = _module_name(path) if path.is_relative_to(PACKAGE) else path.stem
    tree = ast.parse(path.read_text(), str(path))
    found: list[Import] = []
    bound: dict[str, str] = {}  # local name -> pipeline module it refers to

    def visit(body: list[ast.stmt] | ast.AST, deferred: bool) -> None:
        for child in body if isinstance(body, list) else ast.iter_child_nodes(body):
            if isinstance(child, ast.Import):
                for alias in child.names:
                    found.append(Import(source, alias.name, (), child.lineno, deferred))
                    if alias.asname:
                        bound[alias.asname] = alias.name
                    else:
                        top = alias.name.split(".")[0]
                        bound[top] = top
            elif isinstance(child, ast.ImportFrom):
                base = _resolve(source, path.name == "__init__.py", child.module, child.level)
                plain = []
                for alias in child.names:
                    full = f"{base}.{alias.name}"
                    if full in MODULES:  # a submodule
                        found.append(Import(source, full, (), child.lineno, deferred))
                        bound[alias.asname or alias.name] = full
                    else:
                        plain.append(alias.name)
                if plain:
                    found.append(Import(source, base, tuple(plain), child.lineno, deferred))
            elif isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                visit(child.body, True)  # read by type checkers only
                visit(child.orelse, deferred)
            else:
                visit(child, deferred or isinstance(
                    child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda))

    visit(tree, False)

    private_reads = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and _is_private(node.attr):
            chain, value = [], node.value
            while isinstance(value, ast.Attribute):
                chain.append(value.attr)
                value = value.value
            if isinstance(value, ast.Name) and value.id in bound:
                owner = ".".join([bound[value.id], *reversed(chain)])
                if owner in MODULES:
                    private_reads.append((f"{owner}.{node.attr}", node.lineno))
    return found, private_reads


def _is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


# Standard-library modules whose names start with "_" but are documented for use
# (docs.python.org/3/library/_thread.html): not private.
DOCUMENTED_STDLIB = {"_thread"}


def _private_uses(path: Path, pipeline_only: bool) -> list[str]:
    """``file:line module.name`` for each private name that ``path`` takes from another
    module: ``from m import _x``, ``import m._x`` and ``module._x`` (a pipeline module's
    attribute; attributes of other libraries' modules are not followed)."""
    imports, reads = _imports(path)
    where = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
    out = []
    for imp in imports:
        if imp.target == imp.source or (pipeline_only and imp.target not in MODULES):
            continue
        if imp.target in DOCUMENTED_STDLIB:
            continue
        if any(_is_private(part) for part in imp.target.split(".")):  # a private module
            out.append(f"{where}:{imp.line} {imp.target}")
        out += [f"{where}:{imp.line} {imp.target}.{n}" for n in imp.names if _is_private(n)]
    out += [f"{where}:{line} {name}" for name, line in reads]
    return out


def test_no_module_uses_another_modules_private_names():
    """A leading underscore means "this module only": no pipeline module takes one from
    another module, whether imported at module level or inside a function, or read as an
    attribute of an imported pipeline module. Other libraries' private names may not be
    imported either (their attributes, e.g. ``cpp_extension._get_build_directory``, are
    not followed)."""
    offenders = [use for path in MODULES.values() for use in _private_uses(path, False)]
    assert offenders == []


def test_tests_use_only_public_names():
    """The same rule for tests/ (names of pipeline modules)."""
    found = [use for path in sorted(TESTS.glob("*.py")) for use in _private_uses(path, True)]
    assert found == []


def test_tests_take_helpers_from_helpers_and_fixtures_from_conftest():
    """No test imports ``conftest`` (pytest loads it as a plugin; importing it again runs
    it twice under another name); conftest.py defines fixtures (and hooks) only."""
    importers = [f"{path.name}:{imp.line}" for path in sorted(TESTS.glob("*.py"))
                 for imp in _imports(path)[0] if imp.target.split(".")[0] == "conftest"]
    assert importers == []
    tree = ast.parse((TESTS / "conftest.py").read_text())
    plain = [node.name for node in tree.body
             if isinstance(node, ast.FunctionDef | ast.ClassDef)
             and not node.name.startswith("pytest_")
             and not any("fixture" in ast.unparse(d) for d in node.decorator_list)]
    assert plain == [], "move these to tests/helpers.py"


def _graph(include_deferred: bool) -> dict[str, dict[str, int]]:
    """module -> {imported pipeline module: line}. An edge goes to the module named in the
    import only, not to the packages above it (whose ``__init__`` Python runs first)."""
    graph: dict[str, dict[str, int]] = {name: {} for name in MODULES}
    for name, path in MODULES.items():
        for imp in _imports(path)[0]:
            if imp.target in MODULES and imp.target != name and (
                    include_deferred or not imp.deferred):
                graph[name].setdefault(imp.target, imp.line)
    return graph


def _cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    components: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while (w := stack.pop()) != v:
                component.append(w)
            if component:
                components.append(sorted([v, *component]))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return components


def _describe(graph, components) -> list[str]:
    return [f"{a} -> {b} (line {graph[a][b]})"
            for component in components for a in component for b in graph[a] if b in component]


def test_no_import_cycle():
    """No cycle among the imports that run when a module is loaded (module level, class
    bodies included; ``if TYPE_CHECKING:`` blocks excluded): such a cycle works or fails
    depending on which of its modules is imported first, and leaves half-initialised
    modules behind. Edges go to the module an import names (``from pkg import mod``:
    ``pkg.mod``; ``from mod import name``: ``mod``)."""
    graph = _graph(include_deferred=False)
    assert _cycles(graph) == [], _describe(graph, _cycles(graph))


# Cycles that close only through an import inside a function, each with why it is there:
# Python resolves them (the inner import runs when the function is called, once both
# modules are loaded), e.g. a module and the child-process entry point that calls back
# into it, but each should be a decision, not an accident. Across packages they are
# refused anyway by test_packages_depend_downwards (one edge then points up a layer).
DEFERRED_CYCLES: dict[frozenset[str], str] = {}


def test_import_cycles_through_functions_are_the_listed_ones():
    """Catches a new cycle through a function-level import (add it to DEFERRED_CYCLES
    with its reason if it is meant), and a listed one that is gone."""
    graph = _graph(include_deferred=True)
    loaded = {frozenset(c) for c in _cycles(_graph(include_deferred=False))}
    deferred = [c for c in _cycles(graph) if frozenset(c) not in loaded]
    new = [c for c in deferred if frozenset(c) not in DEFERRED_CYCLES]
    assert new == [], "import cycles closed inside functions: " + "; ".join(
        _describe(graph, new))
    gone = set(DEFERRED_CYCLES) - {frozenset(c) for c in deferred}
    assert gone == set(), f"listed in DEFERRED_CYCLES but no longer there: {gone}"


def test_imports_inside_functions_and_type_checking_blocks_are_deferred(tmp_path):
    """Catches the import scanner that the cycle tests rely on taking a function's or a
    type-checking block's import for one that runs at load time, or the reverse."""
    module = tmp_path / "scanned.py"
    module.write_text(
        "import os\n"
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n"
        "    import json\n"
        "class Loaded:\n"
        "    import math\n"
        "def later():\n"
        "    import re\n"
        "    return lambda: __import__('glob')\n"
        "async def later_too():\n"
        "    from pipeline.core import errors\n"
    )
    found = [(imp.target, imp.deferred) for imp in _imports(module)[0]]
    assert found == [("os", False), ("typing", False), ("json", True), ("math", False),
                     ("re", True), ("pipeline.core.errors", True)]


def test_cycle_finder_finds_cycles():
    graph = {"a": {"b": 1}, "b": {"c": 2}, "c": {"a": 3, "d": 4}, "d": {}}
    assert _cycles(graph) == [["a", "b", "c"]]
    assert _describe(graph, _cycles(graph)) == [
        "a -> b (line 1)", "b -> c (line 2)", "c -> a (line 3)"]


# What each package may import (imports inside functions included); the commands
# (pipeline.__main__, app, tables, bench) may import anything, and only they import them.
ALLOWED = {
    "core": {"core"},
    "data": {"core", "data"},
    "btf": {"core", "data", "btf", "render"},  # btf.render: A's materials on the renderer
    "render": {"core", "data", "render"},  # the general renderer, a library below the methods
    "brdf_map": {"core", "data", "brdf_map"},
    "fourier": {"core", "data", "fourier"},
}


def test_packages_depend_downwards():
    """core <- data <- each method <- the commands; the methods do not import each other."""
    wrong = []
    for name, targets in _graph(include_deferred=True).items():
        part = name.split(".")[1] if "." in name else ""
        for target, line in targets.items():
            to = target.split(".")[1] if "." in target else ""
            if part in ALLOWED and to not in ALLOWED[part]:
                wrong.append(f"{name}:{line} imports {target}")
    assert wrong == []


def test_private_name_rules_see_every_kind_of_use(tmp_path):
    path = tmp_path / "test_probe.py"
    path.write_text(
        "import pipeline.core.cache\n"
        "from pipeline.core import cache as c\n"
        "from pipeline.core.cache import _publish, stage_key\n"
        "from pipeline.btf.fast import kernels\n"
        "def f():\n"
        "    from pipeline.fourier.quilting import _OverlapSearch\n"
        "    return kernels._cpu_key(), c._publish, pipeline.core.cache._write_atomic\n")
    uses = _private_uses(path, True)
    imports, _ = _imports(path)
    assert sorted(u.split(" ", 1)[1] for u in uses) == [
        "pipeline.btf.fast.kernels._cpu_key", "pipeline.core.cache._publish",
        "pipeline.core.cache._publish", "pipeline.core.cache._write_atomic",
        "pipeline.fourier.quilting._OverlapSearch"]
    assert [(i.target, i.deferred) for i in imports if i.target.startswith("pipeline.f")] == [
        ("pipeline.fourier.quilting", True)]


# ------------------------------------------------------------------------ command line


def test_a_stage_runs_only_with_its_code_version(tmp_path):
    """An unknown stage (no ``version=``) is an error, not version "1"; nothing runs."""
    from pipeline.core.cache import StageCache
    from pipeline.core.stage import Context

    ctx = Context(OmegaConf.create({}), StageCache(tmp_path / "cache"))
    calls = []

    def compute(folder):
        calls.append(folder)

    with pytest.raises(TypeError):
        ctx.run("new_stage", {}, {}, compute)
    for version in (None, "", 1):
        with pytest.raises(TypeError, match="version"):
            ctx.run("new_stage", {}, {}, compute, version=version)
    assert calls == [] and ctx.keys == {}
    assert not (tmp_path / "cache").exists()
    entry = ctx.run("new_stage", {}, {}, compute, version="1")
    assert len(calls) == 1 and ctx.keys == {"new_stage": entry.key}


# --------------------------------------------------------------------------- doctests

# Modules with examples, found by reading the files (only these are imported here).
EXAMPLES = sorted(name for name, path in MODULES.items()
                  if re.search(r"^\s*>>> ", path.read_text(), re.MULTILINE))
# The examples in these must run (not all be skipped).
MUST_RUN = {"pipeline.btf.synthetic", "pipeline.fourier.series", "pipeline.fourier.quilting"}
# Examples that fail because of a mistake in pipeline/ (reported; strict: remove the
# entry once fixed).
BROKEN_EXAMPLES: dict[str, str] = {}


def test_examples_are_found():
    assert MUST_RUN <= set(EXAMPLES)


@pytest.mark.parametrize("name", [
    pytest.param(name, marks=pytest.mark.xfail(reason=BROKEN_EXAMPLES[name], strict=True))
    if name in BROKEN_EXAMPLES else name for name in EXAMPLES])
def test_docstring_examples(name):
    """The ``>>>`` examples of the module run and print what they show (doctest, with
    pytest's default ELLIPSIS; ``pytest --doctest-modules pipeline`` runs the same)."""
    module = importlib.import_module(name)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS)
    report = io.StringIO()
    for test in doctest.DocTestFinder().find(module, name):
        runner.run(test, out=report.write)
    results = runner.summarize(verbose=False)
    assert results.failed == 0, report.getvalue()
    if name in MUST_RUN:
        assert results.attempted > 0


# ------------------------------------------------------- the renderer imports no method

METHOD_PACKAGES = ("pipeline.btf", "pipeline.brdf_map", "pipeline.fourier")


def _method_imports(path: Path, module: str) -> list[str]:
    """``file:line target`` for each import in ``path`` (module ``module``) that names a
    method package or a module in one, wherever it is: module level, functions, classes,
    ``if TYPE_CHECKING:``; relative imports resolved."""
    tree = ast.parse(path.read_text(), str(path))

    def is_method(target: str) -> bool:
        return any(target == p or target.startswith(p + ".") for p in METHOD_PACKAGES)

    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(module, path.name == "__init__.py", node.module, node.level)
            # ``from pipeline import btf`` names the method in the imported names.
            targets = [base] if is_method(base) else [f"{base}.{a.name}" for a in node.names]
        else:
            continue
        found += [(node.lineno, t) for t in targets if is_method(t)]
    where = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path.name
    return [f"{where}:{line} {target}" for line, target in sorted(found)]


def test_the_general_renderer_imports_no_method_package():
    """``pipeline/render/`` (scene, tracer, the material interface) is a library that any
    method can build on: none of its modules imports a method package, not even inside a
    function. A method's materials, render stages and reports live in its own package
    (method A's in ``pipeline/btf/render/``)."""
    renderer = {name: path for name, path in MODULES.items()
                if name == "pipeline.render" or name.startswith("pipeline.render.")}
    assert {"pipeline.render", "pipeline.render.engine", "pipeline.render.scene"} <= set(renderer)
    assert set(METHOD_PACKAGES) <= set(MODULES)  # the names checked are the real packages
    found = [hit for name, path in renderer.items() for hit in _method_imports(path, name)]
    assert found == []


def test_the_method_import_check_sees_every_kind_of_import(tmp_path):
    path = tmp_path / "probe.py"
    path.write_text(
        "import numpy\n"
        "from pipeline.render.scene import Scene\n"
        "from pipeline import btf, core\n"
        "def f():\n"
        "    import pipeline.fourier.series\n"
        "    from ..brdf_map import report\n"
        "    return 1\n"
        "class C:\n"
        "    from pipeline.btf.interpolation import Barycentric, ProductInterpolator\n")
    found = _method_imports(path, "pipeline.render.probe")
    assert [hit.split(" ", 1)[1] for hit in found] == [
        "pipeline.btf", "pipeline.fourier.series", "pipeline.brdf_map",
        "pipeline.btf.interpolation"]
