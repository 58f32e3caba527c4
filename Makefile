# Two commands do all the set-up: `make demo` and `make test` (each creates .venv if needed).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PYTEST_ARGS ?=

.PHONY: demo test lint format clean

# The venv is made without pip (0.1 s, against 3.2 s with ensurepip's), and uv installs pip into it
# with the package.
$(VENV)/bin/python:
	$(PYTHON) -m venv --without-pip $(VENV)

# uv, from PyPI into the venv: by $(PYTHON)'s own pip (pip >= 22.3 installs into another
# environment: 1.7 s), else by the venv's pip after ensurepip.
get_uv = $(PYTHON) -m pip --python $(PY) install -q uv 2>/dev/null \
	|| { $(PY) -m ensurepip >/dev/null && $(PY) -m pip install -q uv; }

# The package and an extra, installed by uv: measured on a fresh venv, 13-18 s against 26-36 s for
# pip with its upgrade. Where uv cannot be had, pip installs. With PYTHONDONTWRITEBYTECODE set, as on
# some machines (the one these were measured on), no process would write bytecode and each would
# compile its imports again (6.5 s of imports instead of 3.5 s): the demo's install compiles every
# installed module (uv's --compile-bytecode: 7 s); the tests' compiles only what their processes
# import, by importing it once with the variable unset, in two processes (4 s; a fresh install took
# 9.0 and 14.7 s against 15.2 and 19.1 s, alternating).
install = { $(get_uv); } && $(VENV)/bin/uv pip install -q --python $(PY) $(2) -e '.[$(1)]' pip \
	|| { $(PY) -m ensurepip >/dev/null; $(PY) -m pip install -q -e '.[$(1)]'; }
compile_imports = env -u PYTHONDONTWRITEBYTECODE $(PY) -c 'import $(1)'
# a test worker's imports, and those of the processes the tests start (notebooks, typing, plots)
WORKER_IMPORTS = ldap_jax.control, ldap_jax.study, ldap_jax.plotting, diffrax, jaxlie, pytest, xdist.plugin
CHILD_IMPORTS = matplotlib.pyplot, IPython, beartype, jaxtyping, PIL.Image, scipy.linalg

$(VENV)/.installed: pyproject.toml | $(VENV)/bin/python
	$(call install,bench,--compile-bytecode)
	touch $@

# the tests need no benchmark extras (CasADi): `make demo` installs them when it runs
$(VENV)/.installed-dev: pyproject.toml | $(VENV)/bin/python
	$(call install,dev)
	$(call compile_imports,$(WORKER_IMPORTS)) & $(call compile_imports,$(CHILD_IMPORTS)) && wait $$!
	touch $@

# The main results at quick settings (a few minutes on 2 cores): one line per stage, then a table of
# what was written under results/ and the headline numbers. `make demo DEMO_ARGS=--full` runs the
# paper-size versions; `python scripts/demo.py --list` shows the stages.
DEMO_ARGS ?=
demo: $(VENV)/.installed
	$(PY) scripts/demo.py --out results $(DEMO_ARGS)

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
