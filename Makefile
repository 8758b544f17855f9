# The two commands of the README. Each creates the virtual environment and installs the
# project into it first, so that a fresh machine needs nothing else.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test test-slow tables

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	# torch first, on its own: the pinned CPU build, never the CUDA one.
	$(PY) -m pip install --quiet torch==2.13.0 2>&1 | grep -v "is ignored" || true
	$(PY) -m pip install --quiet -e '.[dev]' 2>&1 | grep -v "is ignored" || true
	$(PY) -c "import pipeline, torch, hydra, mlflow, OpenEXR"
	# method A's C++ kernels, built now rather than by the first job that trains (without
	# a compiler it warns, and training uses torch's own operators)
	$(PY) -c "from pipeline.btf.fast import kernels; kernels.available()"
	touch $(STAMP)

demo: $(STAMP)  ## the main job: default experiment on the built-in synthetic BTF
	$(PY) -m pipeline

test: $(STAMP)  ## the default (fast) test suite: lint, format, pytest
	$(PY) -m ruff check pipeline benchmarks tests hydra_plugins scripts
	$(PY) -m ruff format --check pipeline benchmarks tests hydra_plugins scripts
	$(PY) -m pytest -q -n 2 --dist worksteal  # two workers (pytest-xdist), the machine's two cores; an idle one takes queued tests from the other

test-slow: $(STAMP)  ## the tests marked slow: paper size, real interpreters and sweeps
	$(PY) -m pytest -q -n 2 --dist worksteal -m slow

tables: $(STAMP)
	$(PY) -m pipeline.tables
