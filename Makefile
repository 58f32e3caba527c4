# Two commands do all the set-up: `make demo` and `make test` (each creates .venv if needed).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PYTEST_ARGS ?=

.PHONY: demo test lint format clean

$(VENV)/bin/python:
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

$(VENV)/.installed: pyproject.toml | $(VENV)/bin/python
	$(PY) -m pip install -q -e '.[bench]'
	touch $@

# the tests need no benchmark extras (CasADi): `make demo` installs them when it runs
$(VENV)/.installed-dev: pyproject.toml | $(VENV)/bin/python
	$(PY) -m pip install -q -e '.[dev]'
	touch $@

# The main job at quick settings; figures and tables under results/.
demo: $(VENV)/.installed
	$(PY) scripts/demo.py --quick --out results
	$(PY) scripts/sweep.py --quick --out results
	$(PY) scripts/optimize.py --model car --task parallel_park --quick --out results
	$(PY) scripts/optimize.py --model snakeboard --task forward_gait --quick --out results
	$(PY) scripts/bench.py --quick --out results
	$(PY) scripts/bench_control.py --quick --out results

# The test suite (2 workers); pytest's "no tests collected" (exit 5) is a failure here.
test: $(VENV)/.installed-dev
	@$(PY) -m pytest -n 2 --dist loadgroup --durations=15 $(PYTEST_ARGS); rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests"; exit 1; fi; exit $$rc

lint: $(VENV)/.installed-dev
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: $(VENV)/.installed-dev
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

clean:
	rm -rf $(VENV) results .pytest_cache
