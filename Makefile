# Two commands on a fresh machine with only Python and pip:
#   make demo   set up .venv and run the main job on the sample data
#   make test   set up .venv and run the test suite
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
# --no-compile: pip does not byte-compile every installed module (jax, scipy, ...): installs in about
# 60 % of the time, 75 MB smaller. BYTE_COMPILE then imports the packages once with bytecode writing
# on, so the modules a run imports are compiled once, even where PYTHONDONTWRITEBYTECODE is set
# (without bytecode every new process compiles jax's sources again: seconds of start-up).
PIP    := $(PY) -m pip
PIP_INSTALL := $(PIP) install --quiet --disable-pip-version-check --no-compile -c constraints.txt
BYTE_COMPILE := env -u PYTHONDONTWRITEBYTECODE $(PY) -c
# Two stamps: `make demo` installs the core only (no torch, kornia, pyrealsense2, matplotlib);
# `make test` adds the development extras (every backend, pytest) to the same .venv.
CORE_STAMP := $(VENV)/.installed-core
TEST_STAMP := $(VENV)/.installed-test
# `make docs` adds the docs extra (mkdocs, mkdocstrings) to the same .venv.
DOCS_STAMP := $(VENV)/.installed-docs

.PHONY: setup setup-demo test test-fast test-slow test-all demo bench docs clean

$(PY):
	$(PYTHON) -m venv $(VENV)

$(CORE_STAMP): pyproject.toml constraints.txt | $(PY)
	$(PIP_INSTALL) -e .
	$(BYTE_COMPILE) "import softgrip_jax, softgrip_vision, softgrip_calib, softgrip_cli"
	touch $(CORE_STAMP)

$(TEST_STAMP): $(CORE_STAMP)
	$(PIP_INSTALL) -e '.[test]'
	$(BYTE_COMPILE) "import pytest, xdist, hypothesis, beartype, jsonschema, kornia, matplotlib.pyplot, mypy"
	touch $(TEST_STAMP)

setup: $(TEST_STAMP)

setup-demo: $(CORE_STAMP)

# Two worker processes (pytest-xdist), a test file per worker at a time: the suite is mostly XLA
# compilation, which runs on one core per process.
PYTEST := $(PY) -m pytest -n auto --dist loadfile

# `make test` runs every test not marked slow (under 15 minutes on two cores); `make test-slow` the
# slow ones (a fresh-machine install, the reproduction harnesses, refine's compiles); CI runs both.
# The fast set is mostly XLA compilation: it runs with XLA's optimisations off
# (JAX_DISABLE_MOST_OPTIMIZATIONS), which compiles in about 60 % of the time; the slow set, the
# benchmarks and every user run compile the optimised programs users get.
test: $(TEST_STAMP)
	JAX_DISABLE_MOST_OPTIMIZATIONS=1 $(PYTEST) -m "not slow"

test-fast: test

test-slow: $(TEST_STAMP)
	$(PYTEST) -m slow

test-all: $(TEST_STAMP)
	$(PYTEST)

demo: $(CORE_STAMP)
	$(VENV)/bin/softgrip demo

bench: $(TEST_STAMP)
	$(PY) benchmarks/bench_estimate.py

# The documentation site (docs/ and the API reference from the docstrings) into site/; --strict:
# a broken link or a docstring griffe cannot read fails the build.
$(DOCS_STAMP): $(CORE_STAMP)
	$(PIP_INSTALL) -e '.[docs]'
	touch $(DOCS_STAMP)

docs: $(DOCS_STAMP)
	$(PY) -m mkdocs build --strict

clean:
	rm -rf $(VENV) build site *.egg-info
