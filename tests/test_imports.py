"""How the package's modules import each other: no private names across modules, no
cycles but the listed ones, packages depend downwards, and the general renderer imports no
method.

Packages (see ``pipeline/__init__.py``): ``core`` (shared), ``data`` (readers), one per
method (``btf`` A, ``brdf_map`` B, ``fourier`` C), and the commands (``__main__``,
``app``, ``tables``, ``bench``).
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from functools import cache
from pathlib import Path

from helpers import PACKAGE, ROOT, module_name
from helpers import PIPELINE_MODULES as MODULES

TESTS = ROOT / "tests"


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
    source = module_name(path) if path.is_relative_to(PACKAGE) else path.stem
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
                visit(
                    child,
                    deferred
                    or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda),
                )

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
    importers = [
        f"{path.name}:{imp.line}"
        for path in sorted(TESTS.glob("*.py"))
        for imp in _imports(path)[0]
        if imp.target.split(".")[0] == "conftest"
    ]
    assert importers == []
    tree = ast.parse((TESTS / "conftest.py").read_text())
    plain = [
        node.name
        for node in tree.body
        if isinstance(node, ast.FunctionDef | ast.ClassDef)
        and not node.name.startswith("pytest_")
        and not any("fixture" in ast.unparse(d) for d in node.decorator_list)
    ]
    assert plain == [], "move these to tests/helpers.py"


def _graph(include_deferred: bool) -> dict[str, dict[str, int]]:
    """module -> {imported pipeline module: line}. An edge goes to the module named in the
    import only, not to the packages above it (whose ``__init__`` Python runs first)."""
    graph: dict[str, dict[str, int]] = {name: {} for name in MODULES}
    for name, path in MODULES.items():
        for imp in _imports(path)[0]:
            if (
                imp.target in MODULES
                and imp.target != name
                and (include_deferred or not imp.deferred)
            ):
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
    return [
        f"{a} -> {b} (line {graph[a][b]})"
        for component in components
        for a in component
        for b in graph[a]
        if b in component
    ]


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
    assert new == [], "import cycles closed inside functions: " + "; ".join(_describe(graph, new))
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
    assert found == [
        ("os", False),
        ("typing", False),
        ("json", True),
        ("math", False),
        ("re", True),
        ("pipeline.core.errors", True),
    ]


def test_cycle_finder_finds_cycles():
    graph = {"a": {"b": 1}, "b": {"c": 2}, "c": {"a": 3, "d": 4}, "d": {}}
    assert _cycles(graph) == [["a", "b", "c"]]
    assert _describe(graph, _cycles(graph)) == [
        "a -> b (line 1)",
        "b -> c (line 2)",
        "c -> a (line 3)",
    ]


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
        "    return kernels._cpu_key(), c._publish, pipeline.core.cache._write_atomic\n"
    )
    uses = _private_uses(path, True)
    imports, _ = _imports(path)
    assert sorted(u.split(" ", 1)[1] for u in uses) == [
        "pipeline.btf.fast.kernels._cpu_key",
        "pipeline.core.cache._publish",
        "pipeline.core.cache._publish",
        "pipeline.core.cache._write_atomic",
        "pipeline.fourier.quilting._OverlapSearch",
    ]
    assert [(i.target, i.deferred) for i in imports if i.target.startswith("pipeline.f")] == [
        ("pipeline.fourier.quilting", True)
    ]


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
    renderer = {
        name: path
        for name, path in MODULES.items()
        if name == "pipeline.render" or name.startswith("pipeline.render.")
    }
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
        "    from pipeline.btf.interpolation import Barycentric, ProductInterpolator\n"
    )
    found = _method_imports(path, "pipeline.render.probe")
    assert [hit.split(" ", 1)[1] for hit in found] == [
        "pipeline.btf",
        "pipeline.fourier.series",
        "pipeline.brdf_map",
        "pipeline.btf.interpolation",
    ]
