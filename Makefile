# Everything a fresh clone needs: `make demo` and `make test` create .venv themselves.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
# The demo needs the core only; the tests add the extra [test].
CORE := $(VENV)/.installed-core
STAMP := $(VENV)/.installed

DOCS := $(VENV)/.installed-docs

.PHONY: demo test test-fast test-docs bench docs clean device-wheels

$(CORE): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e .
	touch $(CORE)

$(STAMP): $(CORE)
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

demo: $(CORE)
	$(BIN)/emccdcal demo

# One pytest worker per core (pytest-xdist), each taking whole test files, so that a
# file's module-scoped fixtures are built once.
PARALLEL := -n auto --dist loadfile

# The package's modules compiled once: every command a test starts imports them, and a
# shell with PYTHONDONTWRITEBYTECODE set would otherwise compile them in each (~0.2 s).
COMPILED := $(BIN)/python -m compileall -q src

test: $(STAMP)
	$(COMPILED)
	$(BIN)/python -m pytest -q $(PARALLEL) -m "not docs_examples"

# The quick loop while developing: everything but the tests marked slow and the files
# that run verbs end to end (tests/conftest.py's END_TO_END); the target is 90 s on 2
# cores, docs/benchmarks.md has what it takes now.
test-fast: $(STAMP)
	$(COMPILED)
	$(BIN)/python -m pytest -q -m "not slow and not docs_examples" $(PARALLEL)

# Every command and Python example of README.md and docs/ run as written, each page in
# a copy of a small simulated world (tests/test_docs_examples.py; a few minutes).
test-docs: $(STAMP)
	$(COMPILED)
	$(BIN)/python -m pytest -q -n auto --dist load -m docs_examples tests/test_docs_examples.py

$(DOCS): $(CORE)
	$(BIN)/python -m pip install --quiet -e '.[docs]'
	touch $(DOCS)

# The site, from the pages in docs/, the docstrings, the parsers and the gallery's scripts
# (executed); any warning fails the build. Open docs/_build/html/index.html.
docs: $(DOCS)
	$(BIN)/python -m sphinx -W --keep-going -q -b html docs docs/_build/html

# What the GPU machine (no network) lacks of the core, and emccdcal itself, as wheels in
# .whl/ for benchmarks/device_check.sh (docs/benchmarks.md, "On a GPU").
DEVICE_WHEELS := array-api-compat h5netcdf emcee tomli-w
device-wheels: $(CORE)
	rm -rf .whl && mkdir -p .whl
	$(BIN)/python -m pip wheel --quiet --no-deps -w .whl .
	$(BIN)/python -m pip download --quiet --no-deps --only-binary=:all: \
		--python-version 3.12 --implementation cp --platform manylinux2014_x86_64 \
		-d .whl $(DEVICE_WHEELS)

bench: $(STAMP)
	for b in benchmarks/bench_*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) build src/*.egg-info .pytest_cache .whl docs/_build docs/generated \
		docs/auto_examples docs/sg_execution_times.rst
