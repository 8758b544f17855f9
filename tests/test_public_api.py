"""The names a script imports from ``pipeline`` (its docstring lists them): loaded on first
use, so that ``import pipeline`` loads neither torch nor MLflow, and the docstring's
example runs as written from a folder other than the project's."""

from __future__ import annotations

import importlib
import subprocess
import sys
import textwrap

import pytest
from helpers import python_code

import pipeline

HEAVY = ("torch", "mlflow", "hydra", "pandas", "sklearn")


def test_import_pipeline_loads_no_heavy_library(tmp_path):
    probe = (
        f"import sys\nimport pipeline\nprint(sorted(m for m in {HEAVY!r} if m in sys.modules))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


@pytest.mark.parametrize("name", pipeline.__all__)
def test_each_public_name_is_its_module_s_own(name):
    found = getattr(pipeline, name)
    assert found.__module__.startswith("pipeline.")
    assert getattr(importlib.import_module(found.__module__), name) is found
    assert name in dir(pipeline)
    assert f":func:`{name}`" in pipeline.__doc__ or f":class:`{name}`" in pipeline.__doc__


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="'load_compresed'"):
        pipeline.load_compresed  # noqa: B018


def _docstring_example() -> str:
    """The code block of ``pipeline.__doc__`` (the indented lines after its ``::``)."""
    lines = pipeline.__doc__.split("::\n", 1)[1].splitlines()
    block = []
    for line in lines:
        if line.strip() and not line.startswith("    "):
            break
        block.append(line)
    return textwrap.dedent("\n".join(block))


def test_the_docstring_example_loads_a_run_s_model_from_another_folder(smoke_cfg, tmp_path):
    """MLflow looks for ``./mlflow.db`` unless told which store: the example, run in a
    folder without one, must find the run through :func:`pipeline.tracking_uri` and
    leave no empty store behind (what ``runs:/<id>/...`` alone does there)."""
    from pipeline.app import run_job

    cfg = smoke_cfg("train.max_steps=10")  # any model will do
    run_job(cfg)
    code = _docstring_example()
    for old, new in (
        ('runs = "runs"', f"runs = {str(cfg.paths.runs)!r}"),
        ('experiment_names=["btf"]', 'experiment_names=["smoke"]'),
    ):
        assert code.count(old) == 1, old
        code = code.replace(old, new)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "example.py").write_text(code)
    done = python_code("import runpy; runpy.run_path('example.py', run_name='__main__')", elsewhere)
    assert done.returncode == 0, done.stderr[-3000:]
    assert not (elsewhere / "mlflow.db").exists()
    table, array = done.stdout.split("[[", 1)
    assert table.split()[:3] == ["R", "G", "B"]
    # The pyfunc model and the file read without MLflow give the same RGB.
    pyfunc = [[float(v) for v in row.split()[1:]] for row in table.strip().splitlines()[1:]]
    plain = [[float(v) for v in row.strip(" []").split()] for row in array.splitlines()]
    assert len(pyfunc) == len(plain) == 2
    assert sum(pyfunc, []) == pytest.approx(sum(plain, []), rel=1e-5)
