"""A pytest plugin: where each test worker's time goes (measurement only; it asserts nothing).

    LDAP_JAX_TEST_PROFILE=DIR .venv/bin/python -m pytest -n 2 --dist loadgroup -p scripts.profile_tests

writes one JSON file per worker into DIR at the end of the run:

* JAX's monitoring events: durations summed by name with their counts (compilation, tracing,
  lowering to MLIR, persistent-cache hits), and the events counted;
* per test (setup + call): the wall time, the compile, trace and lowering times, and the number of
  programs compiled (eager operations compile one each);
* Python's garbage collections (time and count per generation), the times of the first and the last
  test, the cache trims of ``tests/conftest.py`` and the largest resident memory;

and ``DIR/docs_cells.tsv``: the wall time of every code cell the docs process runs
(``tests/test_docs.py``'s child, one test's setup in the JSON), a line per cell: document, cell
index, seconds.

The timing lives here, not in the test suite, so that no test reads the clock.
"""

from __future__ import annotations

import gc
import json
import os
import pathlib
import resource
import time

import pytest

import ldap_jax as lj

_STATS: dict = {"trims": 0}


def _listen(event, duration, **kwargs):
    total, count = _STATS.get(event, (0.0, 0))
    _STATS[event] = (total + duration, count + 1)
    if event.startswith("/jax/core/compile/"):
        per_test = _STATS.setdefault("tests", {}).setdefault(_STATS.get("current", ""), {})
        per_test[event] = per_test.get(event, 0.0) + duration
        if event.endswith("backend_compile_duration"):  # how many programs (op by op: many)
            per_test["programs"] = per_test.get("programs", 0) + 1


def _count(event, **kwargs):
    _STATS[event] = _STATS.get(event, 0) + 1


def _collected(phase, info):
    if phase == "start":
        _STATS["gc_started"] = time.perf_counter()
    elif "gc_started" in _STATS:
        key, spent = f"gc{info['generation']}", time.perf_counter() - _STATS.pop("gc_started")
        total, count = _STATS.get(key, (0.0, 0))
        _STATS[key] = (total + spent, count + 1)


def _counting_trims(trim):
    def wrapped(*args, **kwargs):
        trimmed = trim(*args, **kwargs)
        _STATS["trims"] += bool(trimmed)
        return trimmed

    return wrapped


def pytest_configure(config):
    if not os.environ.get("LDAP_JAX_TEST_PROFILE"):
        raise pytest.UsageError("scripts.profile_tests: set LDAP_JAX_TEST_PROFILE=DIR (where to write)")
    from jax._src import monitoring

    monitoring.register_event_duration_secs_listener(_listen)
    monitoring.register_event_listener(_count)
    gc.callbacks.append(_collected)
    lj.trim_compilation_cache = _counting_trims(lj.trim_compilation_cache)  # conftest's calls


def _timed_runner(runner: str) -> str:
    """tests/test_docs.py's runner with each cell's wall time appended to DIR/docs_cells.tsv (an
    absolute path: the child runs in a temporary folder)."""
    folder = pathlib.Path(os.environ["LDAP_JAX_TEST_PROFILE"]).resolve()
    folder.mkdir(parents=True, exist_ok=True)  # the child appends to it before any worker ends
    out = folder / "docs_cells.tsv"
    timed = (
        "started = time.perf_counter(); result = shell.run_cell(source)\n"
        f"            with open({str(out)!r}, 'a') as f:\n"
        "                print(name, i, f'{time.perf_counter() - started:.2f}', sep='\\t', file=f)"
    )
    edits = (("report = {}\n", "report = {}\nimport time\n"), ("result = shell.run_cell(source)", timed))
    if not all(old in runner for old, _ in edits):
        return runner  # another runner: untimed
    for old, new in edits:
        runner = runner.replace(old, new, 1)
    return runner


def pytest_collection_modifyitems(session, config, items):
    for module in {getattr(item, "module", None) for item in items}:
        if isinstance(getattr(module, "RUNNER", None), str):
            module.RUNNER = _timed_runner(module.RUNNER)


def pytest_runtest_setup(item):
    _STATS["current"] = item.nodeid
    _STATS["started"] = time.perf_counter()
    _STATS.setdefault("first_test_at", time.time())


def pytest_runtest_teardown(item, nextitem):
    if "started" in _STATS:
        per_test = _STATS.setdefault("tests", {}).setdefault(item.nodeid, {})
        per_test["wall"] = time.perf_counter() - _STATS.pop("started")
        _STATS["last_test_at"] = time.time()


def pytest_sessionfinish(session, exitstatus):
    out = pathlib.Path(os.environ["LDAP_JAX_TEST_PROFILE"])
    _STATS["max_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{worker}.json").write_text(json.dumps(_STATS, indent=1))


if __name__ == "__main__":  # a pytest plugin, not a program: say how to use it
    import sys

    print(__doc__)
    sys.exit(0 if set(sys.argv[1:]) <= {"-h", "--help"} else 2)
