"""How the package's modules import each other: packages depend downwards, the general
renderer imports no method, no import cycle, no private names across modules.

Packages (see ``pipeline/__init__.py``): ``core`` (shared), ``data`` (readers), the general
renderer ``render``, one per method (``btf`` A, ``brdf_map`` B, ``fourier`` C), and the
commands (``__main__``, ``app``, ``tables``, ``cache``).

The rules between modules are import-linter contracts in ``.importlinter`` (run by
:func:`test_import_contracts_hold`). The rest stays here because import-linter cannot say it:

- private names: its graph holds module-to-module edges, not the names taken from a module
  nor attributes read from it, and only the package's modules (not tests/, not other
  libraries'); its ``private_modules`` contract lets a package import its own private
  modules, which this rule refuses;
- cycles: its ``acyclic_siblings`` contract compares the children of each package and so
  misses a cycle through a package's ``__init__`` (``pkg`` imports ``pkg.mod``, which
  imports ``pkg``): the check below runs on import-linter's own graph (grimp) instead;
- conftest.py: what tests import and what conftest defines are not package imports.
"""

from __future__ import annotations

import ast
import graphlib
import os
import subprocess
import sys
from importlib.util import resolve_name
from itertools import pairwise
from pathlib import Path

import grimp
import pytest
from helpers import PACKAGE, ROOT, TESTS, module_name
from helpers import PIPELINE_MODULES as MODULES


def _lint_imports(cwd: Path) -> subprocess.CompletedProcess:
    """``lint-imports`` with the repository's contracts, on the ``pipeline`` found from
    ``cwd``; without a cache, which it would leave in ``cwd``."""
    return subprocess.run(
        [sys.executable, "-c", "from importlinter.cli import lint_imports_command as c; c()"]
        + [str(ROOT / ".importlinter"), "--no-cache", "--no-logo"],
        cwd=cwd,
        env={**os.environ, "COLUMNS": "200"},  # one line per import in the report
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_import_contracts_hold():
    """Every import in the package, wherever it is written (module level, functions, class
    bodies, ``if TYPE_CHECKING:``), keeps the contracts in ``.importlinter``."""
    done = _lint_imports(ROOT)
    assert done.returncode == 0 and " 0 broken." in done.stdout, done.stdout + done.stderr


# A package that looks like the real one, each fault commented with the contract it breaks.
FAULTY_PACKAGE = {
    "__init__.py": "",
    **{f"{command}.py": "" for command in ("__main__", "app", "tables", "cache")},
    "core/__init__.py": "",
    "core/errors.py": "def f():\n    from pipeline import app\n",  # layers
    "data/__init__.py": "import typing\nif typing.TYPE_CHECKING:\n    import pipeline.btf\n",  # layers
    "btf/__init__.py": "",
    "btf/interpolation.py": "import pipeline\n",  # root
    "brdf_map/__init__.py": "class C:\n    from pipeline.render import scene\n",  # renderer-users
    "brdf_map/report.py": "",
    "fourier/__init__.py": "",
    "fourier/series.py": "from ..brdf_map import report\n",  # layers: methods are independent
    "render/__init__.py": "",
    "render/scene.py": (  # renderer (and layers)
        "import numpy\n"
        "from pipeline import btf, core\n"
        "def f():\n"
        "    import pipeline.fourier.series\n"
        "    from ..brdf_map import report\n"
        "class C:\n"
        "    from pipeline.btf.interpolation import Barycentric\n"
    ),
}


def test_import_contracts_catch_every_kind_of_import(tmp_path):
    for name, text in FAULTY_PACKAGE.items():
        (tmp_path / "pipeline" / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "pipeline" / name).write_text(text)
    done = _lint_imports(tmp_path)
    report = done.stdout
    assert done.returncode == 1 and "Contracts: 0 kept, 4 broken." in report, report + done.stderr
    for breach in [
        "pipeline.core.errors -> pipeline.app (l.2)",
        "pipeline.data -> pipeline.btf (l.3)",
        "pipeline.fourier.series -> pipeline.brdf_map.report (l.1)",
        "pipeline.btf.interpolation -> pipeline (l.1)",
        "pipeline.brdf_map -> pipeline.render.scene (l.2)",
        "pipeline.render.scene -> pipeline.btf (l.2)",
        "pipeline.render.scene -> pipeline.fourier.series (l.4)",
        "pipeline.render.scene -> pipeline.brdf_map.report (l.5)",
        "pipeline.render.scene -> pipeline.btf.interpolation (l.7)",
    ]:
        assert breach in report, report


# ---------------------------------------------------------------------------- cycles


def _cycle(graph: grimp.ImportGraph) -> list[str]:
    """One import cycle of ``graph``, an ``importer -> imported (line n)`` per import; [] if
    there is none."""
    imported_by = {m: graph.find_modules_directly_imported_by(m) for m in graph.modules}
    try:
        graphlib.TopologicalSorter(imported_by).prepare()
    except graphlib.CycleError as found:
        chain = found.args[1][::-1]  # graphlib lists each module before its importer
        return [
            f"{a} -> {b} (line {graph.get_import_details(importer=a, imported=b)[0]['line_number']})"
            for a, b in pairwise(chain)
        ]
    return []


def test_no_import_cycle():
    """No cycle among the package's imports, wherever they are written: a cycle at load time
    works or fails depending on which of its modules is imported first, and leaves
    half-initialised modules behind; one closed inside a function works, but should be a
    decision, not an accident (to allow one, remove that import from ``graph`` here and say
    why)."""
    graph = grimp.build_graph("pipeline", cache_dir=None)
    assert _cycle(graph) == []


@pytest.mark.parametrize(
    "files, cycle",
    [
        (  # through a package's __init__ and a function: acyclic_siblings misses this one
            {
                "__init__.py": "from probe import child\n",
                "child.py": "def f():\n    import probe\n",
            },
            ["probe -> probe.child (line 1)", "probe.child -> probe (line 2)"],
        ),
        (  # through a class body and a type-checking block
            {
                "__init__.py": "",
                "a.py": "class C:\n    from probe import b\n",
                "b.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import probe.a\n",
            },
            ["probe.a -> probe.b (line 2)", "probe.b -> probe.a (line 3)"],
        ),
    ],
)
def test_cycle_check_finds_cycles(tmp_path, monkeypatch, files, cycle):
    (tmp_path / "probe").mkdir()
    for name, text in files.items():
        (tmp_path / "probe" / name).write_text(text)
    monkeypatch.syspath_prepend(tmp_path)
    assert sorted(_cycle(grimp.build_graph("probe", cache_dir=None))) == cycle


# --------------------------------------------------------------------- private names


def _imports(path: Path) -> tuple[list[tuple[int, str, tuple[str, ...]]], dict[str, str]]:
    """Every import in the file, wherever it is written: ``(line, module, names taken from
    it)`` (``from m import x``: ``m.x`` if that is a pipeline module, else ``m`` with
    ``x``), and the local names bound to modules."""
    source = module_name(path) if path.is_relative_to(PACKAGE) else path.stem
    found: list[tuple[int, str, tuple[str, ...]]] = []
    bound: dict[str, str] = {}  # local name -> module it refers to
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                found.append((node.lineno, alias.name, ()))
                top = alias.name.split(".")[0]
                bound[alias.asname or top] = alias.name if alias.asname else top
        elif isinstance(node, ast.ImportFrom):
            package = source if path.name == "__init__.py" else source.rpartition(".")[0]
            base = resolve_name("." * node.level + (node.module or ""), package)
            plain = []
            for alias in node.names:
                if f"{base}.{alias.name}" in MODULES:  # a submodule
                    found.append((node.lineno, f"{base}.{alias.name}", ()))
                    bound[alias.asname or alias.name] = f"{base}.{alias.name}"
                else:
                    plain.append(alias.name)
            if plain:
                found.append((node.lineno, base, tuple(plain)))
    return found, bound


def _is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


# Standard-library modules whose names start with "_" but are documented for use
# (docs.python.org/3/library/_thread.html): not private.
DOCUMENTED_STDLIB = {"_thread"}


def _private_uses(path: Path, pipeline_only: bool) -> list[str]:
    """``file:line module.name`` for each private name that ``path`` takes from another
    module: ``from m import _x``, ``import m._x`` and ``module._x`` (a pipeline module's
    attribute; attributes of other libraries' modules are not followed)."""
    source = module_name(path) if path.is_relative_to(PACKAGE) else path.stem
    imports, bound = _imports(path)
    where = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
    out = []
    for line, target, names in imports:
        if target in (source, *DOCUMENTED_STDLIB) or (pipeline_only and target not in MODULES):
            continue
        if any(_is_private(part) for part in target.split(".")):  # a private module
            out.append(f"{where}:{line} {target}")
        out += [f"{where}:{line} {target}.{n}" for n in names if _is_private(n)]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Attribute) and _is_private(node.attr):
            chain, value = [], node.value
            while isinstance(value, ast.Attribute):
                chain.append(value.attr)
                value = value.value
            if isinstance(value, ast.Name) and value.id in bound:
                owner = ".".join([bound[value.id], *reversed(chain)])
                if owner in MODULES:
                    out.append(f"{where}:{node.lineno} {owner}.{node.attr}")
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
    assert sorted(u.split(" ", 1)[1] for u in _private_uses(path, True)) == [
        "pipeline.btf.fast.kernels._cpu_key",
        "pipeline.core.cache._publish",
        "pipeline.core.cache._publish",
        "pipeline.core.cache._write_atomic",
        "pipeline.fourier.quilting._OverlapSearch",
    ]


# ------------------------------------------------------------------------- conftest


def test_tests_take_helpers_from_helpers_and_fixtures_from_conftest():
    """No test imports ``conftest`` (pytest loads it as a plugin; importing it again runs
    it twice under another name); conftest.py defines fixtures (and hooks) only."""
    importers = [
        f"{path.name}:{line}"
        for path in sorted(TESTS.glob("*.py"))
        for line, target, _ in _imports(path)[0]
        if target.split(".")[0] == "conftest"
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
