# The front door: `make demo` and `make test` work on a fresh machine.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
PYTEST_ARGS ?=

.PHONY: demo test lint bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# Stamp files record which extras are installed; they are rebuilt when pyproject changes.
# The demo installs only what it runs (extra `demo`: formats, simulator, covariance baseline,
# plots, server; no torch, Dask or image stack); `make test` installs everything.
$(VENV)/.demo-installed: pyproject.toml | $(BIN)/python
	@echo "installing semantic3d with the demo's extras (las, ply, viz, sim, ml, server):" \
	  "about 750 MB, a few minutes on a first run"
	$(BIN)/python -m pip install --progress-bar on -e '.[demo]'
	touch $@

$(VENV)/.test-installed: pyproject.toml | $(BIN)/python
	@echo "installing semantic3d with every extra and the test tools (torch included: several GB" \
	  "on a first run)"
	$(BIN)/python -m pip install --progress-bar on -e '.[test]'
	touch $@ $(VENV)/.demo-installed

DEMO_ARGS ?= --serve

demo: $(VENV)/.demo-installed
	$(BIN)/semantic3d demo $(DEMO_ARGS)

# worksteal: a worker that runs out of tests takes the other's queue, so the slowest tests
# (minutes) do not leave one core idle at the end (a clean clone, numba's cache cold: 850 s
# against 928 s with "load", the same day on 2 cores).
test: $(VENV)/.test-installed
	bash scripts/install-server-test-deps.sh
	$(BIN)/python -m pytest -n 2 --dist worksteal $(PYTEST_ARGS)

lint: $(VENV)/.test-installed
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/ruff format --check src tests benchmarks
	$(BIN)/mypy
	$(BIN)/lint-imports

bench: $(VENV)/.test-installed
	for script in benchmarks/bench_*.py; do $(BIN)/python $$script || exit 1; done

clean:
	rm -rf $(VENV) build dist .pytest_cache .ruff_cache .mypy_cache demo-output
