# Two commands on a fresh Debian machine with Python 3.11:
#   make demo   - the main job on the embedded simulated cell
#   make test   - ruff + the test suite (the docs site's strict build among it)
# Both create or refresh .venv and install what they need, system libraries included.

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.scancell-installed

.PHONY: demo test test-fast lint bench docs setup clean

setup: $(STAMP)

$(STAMP): pyproject.toml deploy/install-system-deps.sh tests/js/package-lock.json
	sh deploy/install-system-deps.sh
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,basler,docs]'
	cd tests/js && npm ci --no-audit --no-fund --loglevel=error  # a real Foxglove client for the tests
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/scancell demo

# ruff, then the layer contracts of pyproject.toml [tool.importlinter] (docs/explanation/architecture.md "Layout").
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/lint-imports

# Every tier: unit, process and e2e (markers in pyproject.toml). Files run whole, in
# collection order (tests/conftest.py puts the e2e files first: the longest start first).
test: lint
	$(PY) -m pytest -q -n 3 --dist loadfile --no-loadscope-reorder --durations=30

# The unit tier alone: in-process tests, no sockets to other processes (about a minute and a half).
test-fast: lint
	$(PY) -m pytest -q -n 2 -m unit

# The manual as a site in site/ (open site/index.html); its reference pages and pictures are
# generated from the code as it builds (docsgen/). `make test` builds it with --strict too.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict

bench: $(STAMP)
	sh deploy/install-system-deps.sh --bench || echo "no CloudCompare: bench_metrics runs without its reference"
	$(PY) benchmarks/run_all.py

clean:
	rm -rf $(VENV) build site *.egg-info .pytest_cache .ruff_cache
