# crater_thermal: `make run` and `make test` each work on a fresh machine.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: run test lint docs install thesis bench clean

# constraints.txt pins the versions the benchmarks were measured with (numba/numpy set the speed figures).
$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt -e ".[viz,distributed,test,docs]"
	touch $(STAMP)

install: $(STAMP)

# Runs the small default case and writes results/default/ (run.nc, replay.nc, report/).
run: $(STAMP)
	$(VENV)/bin/crater-thermal run cases/default.toml -o results/default/run.nc --overwrite
	$(VENV)/bin/crater-thermal replay results/default/run.nc --profile 1300/1800 --profile 800/1100 --profile rock -o results/default/replay.nc --overwrite
	$(VENV)/bin/crater-thermal report results/default/run.nc results/default/replay.nc -o results/default/report --overwrite
	@echo "open results/default/report/report.html"

# Lint (ruff, config in pyproject.toml) and the import contracts (layering, [tool.importlinter]).
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/lint-imports

# The documentation (Sphinx + MyST, docs/conf.py) into docs/_build/html/. Strict: any warning, an unresolved
# cross-reference included (-n), fails the build; -E re-reads every page and docstring each time.
docs: $(STAMP)
	$(VENV)/bin/sphinx-build -W --keep-going -n -E -q -b html docs docs/_build/html
	@echo "open docs/_build/html/index.html"

test: lint docs
	$(PY) -m pytest -q tests

thesis: $(STAMP)
	$(VENV)/bin/crater-thermal sweep cases/thesis/*.toml -o results/thesis

bench: $(STAMP)
	$(PY) bench/conduction.py
	$(PY) bench/viewfactors.py
	$(PY) bench/thesis.py

clean:
	rm -rf $(VENV) results .pytest_cache docs/_build docs/_generated
