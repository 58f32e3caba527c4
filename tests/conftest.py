import gc
import os
import pathlib
import subprocess
import sys

import pytest

# XLA's CPU code generation for every program the tests compile (their own jax.jit too), set before
# JAX starts its backend: the loop emitters the library's entry points compile with
# (lj.compiler_options()) and, since the tests time nothing, LLVM at -O0 without its expensive
# passes: compilation 0.57x of LLVM -O2 (a DLA rollout 9.1 -> 5.2 s; -O1 gives 7.7 s; the
# suite 28 -> 25 min on 2 cores). On top of these, XLA's fast-compile preset and one LLVM module
# per program instead of 32 compiled on threads (the two test workers already fill both cores):
# measured on a quiet 2-core machine, full runs of the suite, XLA's backend compilation summed over
# both workers 490 s -> 398 s with the preset, -> 308 s with both; pytest 8:45 -> 7:42 -> 6:21.
# For users neither helps (at -O2, on a single solve program, the preset changed nothing and one
# module compiled 1.3x longer), so the library does not set them. Nearly all of the suite's time is
# compilation and tracing. Test workers and the processes the tests start (notebooks, scripts)
# inherit the flags. An XLA that does not know a flag aborts the process, so a child process tries
# them first (once per test worker): all of them, else the older set, else none.
#
# At -O0 the same operation can round differently in a vectorised and a scalar loop: `a * b + c`
# is fused into one rounding (FMA) in one and not the other (258 of 1001 random values differ
# between a vectorised map and a scan; tanh 434), which XLA's default code generation does not do.
# A test that asserts bit-for-bit agreement between two compiled programs must therefore compare
# programs that vectorise alike; the one such test (test_simulate's save options: one trajectory,
# the same step in every program) holds at this code generation too, and runs in the worker.
_OPTIONS = {
    "xla_llvm_disable_expensive_passes": True,
    "xla_backend_optimization_level": 0,
}
_NEWER = {"xla_cpu_opt_preset": "CPU_OPT_PRESET_FAST_COMPILE", "xla_cpu_parallel_codegen_split_count": 1}


def _flags(options: dict) -> str:
    return " ".join(f"--{k}={str(v).lower() if isinstance(v, bool) else v}" for k, v in options.items())


# XLA reads XLA_FLAGS when its first client starts: jaxlib's CPU client alone (0.2 s) aborts on an
# unknown flag as JAX's start does (1.2 s, measured); each test worker probes once, the processes
# it starts inherit the result
_PROBE = """
try:
    from jaxlib.xla_client import make_cpu_client as start
except ImportError:
    import jax
    def start():
        jax.jit(lambda x: x + 1)(1.0)
start()
"""


def _xla_accepts(flags: str) -> bool:
    env = dict(os.environ, XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} {flags}".strip())
    probe = [sys.executable, "-c", _PROBE]
    return subprocess.run(probe, env=env, capture_output=True, timeout=300).returncode == 0


def _controller(config) -> bool:
    """True in pytest-xdist's controller, which runs no test: it imports neither JAX nor the
    library (1.8 s before the workers could start); each worker sets itself up."""
    return not hasattr(config, "workerinput") and config.pluginmanager.has_plugin("dsession")


@pytest.hookimpl(trylast=True)  # after pytest-xdist's, which registers its controller
def pytest_configure(config):
    if _controller(config):
        return
    from ldap_jax._compilation_cache import FAST_COMPILE_OPTIONS

    if "LDAP_JAX_TEST_FLAGS" not in os.environ:
        options = {**FAST_COMPILE_OPTIONS, **_OPTIONS}
        candidates = (_flags({**options, **_NEWER}), _flags(options))
        os.environ["LDAP_JAX_TEST_FLAGS"] = next((f for f in candidates if _xla_accepts(f)), "")
    if os.environ["LDAP_JAX_TEST_FLAGS"] not in os.environ.get("XLA_FLAGS", ""):
        merged = f"{os.environ.get('XLA_FLAGS', '')} {os.environ['LDAP_JAX_TEST_FLAGS']}"
        os.environ["XLA_FLAGS"] = merged.strip()

    import jax

    import ldap_jax as lj  # importing does not start JAX's backend

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_numpy_dtype_promotion", "strict")
    jax.config.update("jax_numpy_rank_promotion", "raise")
    # Compiled programs are shared between the test workers and kept for the next run (tests
    # compile the same rollouts in several files); the cache is keyed by program, JAX version and
    # device. Programs that compile in under a second are not stored: storing all
    # (LDAP_JAX_TEST_CACHE_MIN_SECONDS=0) measured 3005 hits of 6595 compilations in a full run,
    # saving 21 s of compilation for 19 s of reading.
    cache_min = os.environ.get("LDAP_JAX_TEST_CACHE_MIN_SECONDS", "1.0")
    cache = lj.enable_compilation_cache(
        os.environ.get("LDAP_JAX_TEST_CACHE") or pathlib.Path(__file__).parent.parent / ".cache" / "xla",
        min_compile_seconds=float(cache_min),
    )
    # ... and with the processes the tests start (the notebooks, scripts, the README's sharded
    # example). A full run that stored every program (1473) saved the notebooks nothing, though:
    # they compile programs no test compiles.
    os.environ["JAX_COMPILATION_CACHE_DIR"] = cache
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = cache_min
    os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"
    # lc.solve's quick first compilation of a new export (LLVM unoptimised, then the optimised
    # program behind it) is a second compilation at the suite's code generation, already
    # unoptimised: off here and in the processes the tests start (tests/test_export.py turns it
    # on for its own test of it)
    os.environ["LDAP_JAX_QUICK_FIRST"] = "0"

    # A test worker's heap grows to millions of objects (JAX's caches of traced and compiled
    # programs), and each of Python's full collections then walks all of them: measured 20-22 full
    # collections of 0.5-0.8 s each per worker on four test files, 33 s per worker in a full run.
    # The objects made by the imports are never garbage (frozen out of the collector), and the
    # young generation is collected every 50000 allocations instead of 700: measured in a full
    # run, 3-5 full collections per worker (0.2-0.3 s) instead of 39-49 (32-34 s).
    gc.freeze()
    gc.set_threshold(50_000, 20, 100)

    from jax._src import monitoring

    monitoring.register_event_duration_secs_listener(_count_programs)


#: Tests that read the same per-worker results (tests/helpers.py's caches, a module's cached runs)
#: run on the same xdist worker (``--dist loadgroup``): module file name -> group.
_GROUPS = {
    "test_convergence.py": "convergence",  # helpers.convergence_case / convergence_runs
    "test_dla_gni.py": "convergence",
    "test_closed_form.py": "closed_form",  # its kernel and Newton runs, helpers.sleigh_newton_run
}


#: The gait tests, the car's solutions of test_control and the documents of tests/test_docs.py's
#: ``CHAIN`` (its second child process) solve the same problems (the drive gait of notebook 05,
#: the control guide and the README; parallel parking and the U-turn at N = 120 of notebook 03 and
#: the guide), and a cold solve compiles for tens of seconds. On one worker and in this order, the
#: child reads the tests' compiled and exported programs from the shared persistent cache; on two
#: workers at once each compiled them (measured under load: notebook 05 alone 710 s, after
#: test_gaits 68 s). test_docs.py marks its chain documents with this group itself.
_DOCS_CHAIN = "gaits"


def _chain_rank(item) -> int:
    """0 for the tests whose solves the chain's documents repeat, 1 for those documents, 2 for
    every other test (their order kept)."""
    if item.path.name == "test_gaits.py" or "car_solutions" in getattr(item, "fixturenames", ()):
        return 0
    groups = {m.args[0] for m in item.iter_markers("xdist_group") if m.args}
    return 1 if item.path.name == "test_docs.py" and _DOCS_CHAIN in groups else 2


def _module_fixtures(item) -> list[str]:
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return []
    return sorted(name for name, defs in info.name2fixturedefs.items() if defs and defs[-1].scope == "module")


@pytest.hookimpl(hookwrapper=True)
def pytest_collection_modifyitems(config, items):
    """Marks the tests that share results with their ``xdist_group`` (before any other
    implementation of the hook runs, xdist's included); afterwards, in a ``--dist loadgroup``
    worker, checks that every grouped test carries its group in its node id (xdist's side channel
    to the scheduler). With pytest 9.2, xdist 3.8 cannot set it (pytest-xdist#1386): every test was
    scheduled on its own, without an error, and both workers computed every shared result; hence
    the ``pytest<9.2`` pin, and this check so that it cannot happen silently again."""
    for item in items:
        group = _GROUPS.get(item.path.name)
        if item.path.name == "test_general.py" and item.name == "test_sleigh_energy_and_momentum_equation":
            group = "closed_form"  # helpers.sleigh_newton_run
        if _chain_rank(item) == 0:
            group = _DOCS_CHAIN
        # a module-scoped fixture is computed once per worker: keep its users together (unless the
        # test names its group itself: pytest-xdist would join both names into a third group)
        scoped = _module_fixtures(item)
        if group is None and scoped and item.get_closest_marker("xdist_group") is None:
            group = f"{item.path.stem}:{','.join(scoped)}"
        if group is not None:
            item.add_marker(pytest.mark.xdist_group(group))
    items.sort(key=_chain_rank)  # stable: the gait tests, the documents, then the rest in order
    yield
    if os.environ.get("PYTEST_XDIST_WORKER") and config.getvalue("loadgroup"):
        lost = [i.nodeid for i in items if i.get_closest_marker("xdist_group") and "@" not in i.nodeid]
        if lost:
            raise pytest.UsageError(
                f"--dist loadgroup: {len(lost)} grouped tests lost their xdist group (e.g. {lost[0]}); "
                "this pytest-xdist does not work with this pytest (pytest-xdist#1386)"
            )


# Where a worker's time goes is measured by a plugin outside the suite (no test reads the clock):
# LDAP_JAX_TEST_PROFILE=DIR python -m pytest -n 2 --dist loadgroup -p scripts.profile_tests


#: programs lowered (compiled, or read from the persistent cache) since the mappings were counted
_NEW_PROGRAMS = [0]


def _count_programs(event, duration, **kwargs):
    if event == "/jax/core/compile/jaxpr_to_mlir_module_duration":
        _NEW_PROGRAMS[0] += 1


def pytest_runtest_teardown(item, nextitem):
    # Each compiled program holds hundreds of memory mappings on XLA's CPU backend (one code, data
    # and constants mapping per kernel: 134 kernels in a 10-step snakeboard rollout); a test worker
    # that compiles a few hundred programs would cross vm.max_map_count and crash inside XLA.
    # Measured in a full run (65530 allowed): untrimmed, the workers would reach 51k and 66k
    # mappings; no test added more than 4.6k; at 0.4 they trim once and twice. A trim makes the
    # tests after it compile again what they would have reused, but the threshold stays below the
    # library's own (0.5, checked in `simulate` every few new programs): at 0.6 the library's trim
    # fired inside a test, and test_step_is_traced_once_across_programs traced its step twice.
    # The mappings are counted (by reading /proc/self/maps: 35 ms at 30k mappings, measured) once 25
    # new programs have been lowered, not after every test: even at 1000 mappings a program, 25k
    # new mappings at most between two counts, inside the 39k between the trim and the limit.
    if _NEW_PROGRAMS[0] < 25:
        return
    _NEW_PROGRAMS[0] = 0
    import ldap_jax as lj  # imported by pytest_configure

    lj.trim_compilation_cache(0.4)
