"""``lc.solve``'s exported programs (``ldap_jax/control/_export.py``): a program exported by one
call and read back from disk gives the solution of the traced program; a structure other than
the exported one is never served it."""

import json
import os
import subprocess
import sys
import threading

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import compiled_programs

import ldap_jax as lj
from ldap_jax import control as lc
from ldap_jax.control import _export, _solve

# every test here solves tests/test_control.py's small parallel_park (N = 40, RDP order 2): on the
# worker of its tests, they reuse its compiled programs (the traced run and finish, the derivatives)
pytestmark = pytest.mark.xdist_group("parallel_park_40")


@pytest.fixture
def exports(tmp_path, monkeypatch):
    """Exports on, in an empty folder of their own, with nothing loaded in this process."""
    monkeypatch.setenv("LDAP_JAX_EXPORT", "1")
    # exports are stored with the persistent cache on; tests/conftest.py turns it on for the suite
    assert jax.config.jax_compilation_cache_dir, "the suite runs with the persistent cache on"
    monkeypatch.setattr(_export, "export_dir", lambda: tmp_path)
    monkeypatch.setattr(_export, "_loaded", {})
    return tmp_path


def _traced(task, params0=None, **kwargs):
    """The solve without exports (the traced program)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("LDAP_JAX_EXPORT", "0")
        return lc.solve(task, params0, **kwargs)


def _key(task, params0=None, **kwargs):
    options, params0, _ = _solve._checked(task, params0, 1e-8, 1000, "base", 0.1, None)
    signature = _export._signature("solve", (_solve._solver_view(task), params0, options))
    return None if signature is None else signature[0]


def _assert_same(a: lc.Solution, b: lc.Solution):
    assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
    assert lc.SOLVER_RESULTS[a.result] == lc.SOLVER_RESULTS[b.result]
    assert int(a.iterations) == int(b.iterations)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-12, atol=1e-12)


def test_reloaded_export_gives_the_traced_solution(exports):
    """parallel_park (N = 40, RDP order 2): the first call exports the program to disk, and serves
    another goal and mass with the traced program's solution for them; a process that has loaded
    nothing (the in-process table cleared) reads it back without tracing the solver, and both give
    the traced program's solution (every leaf to 1e-12, the same iterations)."""
    task = lc.parallel_park(integrator=lj.RDP(), n_steps=40)
    reference = _traced(task)
    first = lc.solve(task)
    # an executable is written by the thread that compiled it, after the program is handed over
    # (through a temporary file beside it): listed mid-write, the folder held that temporary file
    _join_background_compilations()
    files = sorted(p.suffix for p in exports.iterdir())
    # the run's and the finish's exports, and the executable of each that this process compiled
    # (none of those JAX's cache already held: which, depends on the tests run before)
    exported = [f for f in files if f != ".executable"]
    assert exported == [".jaxexport", ".jaxexport", ".json", ".json"], files
    assert files.count(".executable") <= 2, files
    # the export serves another goal and mass with their own solution (see
    # test_values_are_arguments_and_structures_are_keys: the same key)
    moved = task.with_options(goal=jnp.array([0.1, 0.55, 0.05]), system=lj.Car(m=1.3))
    _assert_same(lc.solve(moved), _traced(moved))
    assert len(list(exports.glob("*.jaxexport"))) == 2
    _export._loaded.clear()
    with compiled_programs("trace") as traced:
        again = lc.solve(task)
    assert not {"export_run", "export_finish", "_run_one", "_finish"} & set(traced), traced
    assert bool(reference.converged)
    _assert_same(first, reference)
    _assert_same(again, reference)


def _join_background_compilations():
    for thread in threading.enumerate():
        if thread.name.startswith("ldap_jax-"):
            thread.join()


def test_a_new_export_runs_its_quick_program_first_then_the_optimised_one(exports, monkeypatch):
    """The process that exports the run compiles it twice, in a thread of its own: first with
    ``QUICK_OPTIONS`` (the first call runs that program), then with the library's options (the
    calls after it is ready run that one, and its executable is the one stored). Both give the
    traced program's solution to 1e-12. Only a process's first such program: the next new export
    compiles once. An XLA that rejects the newer of the quick options (``QUICK_NEWER``) compiles
    the quick program without them; one that rejects the quick options compiles the run once,
    with the library's options, and solves the same. Without a cache directory (nothing stored)
    the optimised compilation starts with the run's second call, not after its first."""
    quick_options, quick_newer = _export.QUICK_OPTIONS, _export.QUICK_NEWER
    calls = []
    original = _export._compile_lowered
    executables = {}

    def recording(lowered, options):
        calls.append(dict(options or {}))
        # what this test counts is the library's requests; a module it compiled before with the
        # same options (each part below exports the same run and finish again) is that executable
        key = (lowered.as_text(), repr(sorted((options or {}).items())))
        if key not in executables:
            executables[key] = original(lowered, options)
        return executables[key]

    monkeypatch.setattr(_export, "_compile_lowered", recording)
    monkeypatch.setattr(_export, "_quick_spent", [False])  # as in a new process
    monkeypatch.setenv("LDAP_JAX_QUICK_FIRST", "1")  # off in the rest of the suite (conftest)
    task = lc.parallel_park(integrator=lj.RDP(), n_steps=40)
    reference = _traced(task)
    first = lc.solve(task)
    _join_background_compilations()
    second = lc.solve(task)
    quick = [c for c in calls if c.items() >= _export.QUICK_OPTIONS.items()]
    assert len(quick) == 1, calls  # the run's quick program (the finish compiles once)
    assert len(calls) == 3, calls  # and the run's and the finish's with the library's options
    for sol in (first, second):
        _assert_same(sol, reference)
    _export._loaded.clear()  # a second new structure in the process compiles once
    for path in exports.iterdir():
        path.unlink()
    calls.clear()
    lc.solve(task)
    _join_background_compilations()
    assert len(calls) == 2 and not any(c.items() >= _export.QUICK_OPTIONS.items() for c in calls), calls

    older = dict(_export.QUICK_OPTIONS)
    for name in _export.QUICK_NEWER:
        older.pop(name, None)
    _export._loaded.clear()
    monkeypatch.setattr(_export, "_quick_spent", [False])
    monkeypatch.setattr(_export, "QUICK_OPTIONS", {**_export.QUICK_OPTIONS, "xla_no_such_option": 1})
    monkeypatch.setattr(_export, "QUICK_NEWER", (*_export.QUICK_NEWER, "xla_no_such_option"))
    for path in exports.iterdir():
        path.unlink()
    calls.clear()
    fourth = lc.solve(task)
    _join_background_compilations()
    # rejected with the unknown option, then compiled without the newer ones; the run's and the
    # finish's programs with the library's options
    assert len(calls) == 4 and "xla_no_such_option" in calls[0], calls
    assert sum(c.items() >= older.items() and "xla_no_such_option" not in c for c in calls) == 1, calls
    _assert_same(fourth, reference)

    _export._loaded.clear()
    monkeypatch.setattr(_export, "_quick_spent", [False])
    monkeypatch.setattr(_export, "QUICK_OPTIONS", {"xla_no_such_option": 1})
    for path in exports.iterdir():
        path.unlink()
    calls.clear()
    third = lc.solve(task)
    _join_background_compilations()
    assert len(calls) == 3 and sum("xla_no_such_option" in c for c in calls) == 1, calls
    _assert_same(third, reference)

    _export._loaded.clear()
    monkeypatch.setattr(_export, "_quick_spent", [False])
    monkeypatch.setattr(_export, "QUICK_OPTIONS", quick_options)
    monkeypatch.setattr(_export, "QUICK_NEWER", quick_newer)
    monkeypatch.setattr(_export, "export_dir", lambda: None)
    for path in exports.iterdir():
        path.unlink()
    calls.clear()
    solutions = [lc.solve(task)]
    _join_background_compilations()
    # the run's quick program and the finish's: nothing compiles after the answer
    assert len(calls) == 2 and sum(c.items() >= quick_options.items() for c in calls) == 1, calls
    solutions.append(lc.solve(task))  # runs the quick program and starts the optimised one
    _join_background_compilations()
    assert len(calls) == 3 and not calls[2].items() >= quick_options.items(), calls
    solutions.append(lc.solve(task))  # the optimised program
    assert len(calls) == 3, calls
    for sol in solutions:
        _assert_same(sol, reference)
    assert not list(exports.iterdir())


def test_a_batch_of_starts_is_served_from_its_export(exports):
    """A batch of guesses (the multi-start path: every start's run in one program, the best one
    finished) is exported too: read back without tracing the batch's run or the finish, it gives
    the traced program's solution, which is the best start's own solve."""
    task = lc.parallel_park(integrator=lj.RDP(), n_steps=40)
    guess = task.init()
    starts = jax.tree_util.tree_map(lambda x: np.stack([np.asarray(x), 0.5 * np.asarray(x)]), guess)
    reference = _traced(task, starts)
    first = lc.solve(task, starts)
    assert len(list(exports.glob("*.jaxexport"))) == 2  # the batch's run and the finish
    _export._loaded.clear()
    with compiled_programs("trace") as traced:
        again = lc.solve(task, starts)
    programs = {"export_run_batch", "export_finish", "_run_batch", "_run_one", "_finish"}
    assert not programs & set(traced), traced
    assert bool(reference.converged) and reference.starts == 2
    for sol in (first, again):
        _assert_same(sol, reference)
        assert sol.starts == 2 and sol.starts_converged == reference.starts_converged


def test_values_are_arguments_and_structures_are_keys(exports):
    """A new goal, mass or tolerance is an argument of the same export (same key; that the export
    serves the traced program's solution for those values is checked on the export of
    test_reloaded_export_gives_the_traced_solution); a new number of steps, integrator order,
    retraction or Hessian option is another key; a structure holding a function or a class of the
    user's is not exported."""
    task = lc.parallel_park(integrator=lj.RDP(), n_steps=40)
    key = _key(task)
    moved = task.with_options(goal=jnp.array([0.1, 0.55, 0.05]), system=lj.Car(m=1.3))
    assert _key(moved) == key
    assert _key(task, tol=1e-10) == key
    assert _key(task.with_options(n_steps=41)) not in (None, key)
    assert _key(task.with_options(integrator=lj.RDP(order=4))) not in (None, key)
    assert _key(task.with_options(integrator=lj.RDP(retraction="cayley"))) not in (None, key)
    options, params0, _ = _solve._checked(task, None, 1e-8, 1000, "exact", 0.1, None)
    exact = _export._signature("solve", (_solve._solver_view(task), params0, options))[0]
    assert exact != key
    assert _export._signature("solve", (task, lambda x: x)) is None

    class MyCar(lj.Car):  # code outside the key: never exported
        pass

    assert _export._signature("solve", (task.with_options(system=MyCar()),)) is None


def test_exported_sensitivities_in_forward_and_reverse_mode(exports):
    """Under a top-level grad or jvp the finish runs as its exported program and its exported
    Jacobian with respect to the task's arrays (one program whichever of them are traced): the
    derivatives of the cost and of the optimal controls equal the traced IFT derivatives (to
    1e-10), in reverse and in forward mode; under jacfwd (vmap of jvp) the derivative is traced,
    with the same values.

    d(optimal effort)/d(goal, mass) after a solve that exported its programs (both tests in one:
    they compiled the same exports): under grad the interior-point run is the exported program,
    neither traced nor lowered again (its inputs are cut from differentiation, and are passed to
    it as NumPy arrays: the solution's own params as the guess and the mass made an array under
    grad lowered it a second time before), the IFT step is traced, and the gradient is the one
    without exports (to 1e-10); as in a new process, the finish and its Jacobian are read back."""
    task = lc.parallel_park(integrator=lj.RDP(), n_steps=40)
    sol = lc.solve(task)

    def optimum(goal, m):
        out = lc.solve(task.with_options(goal=goal, system=lj.Car(m=m)), sol.params, tol=1e-10)
        return out.cost, out.params[10]

    g0, m0, dg = task.goal, jnp.asarray(1.0), jnp.asarray([0.3, -0.2, 0.1])
    runs = {
        "grad": lambda: jax.grad(lambda g, m: optimum(g, m)[0], argnums=(0, 1))(g0, m0),
        "jvp": lambda: jax.jvp(lambda g: optimum(g, m0), (g0,), (dg,))[1],
        "jacfwd": lambda: jax.jacfwd(lambda g: optimum(g, m0)[1])(g0),
    }
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("LDAP_JAX_EXPORT", "0")
        want = {name: run() for name, run in runs.items()}
    for name, run in runs.items():
        with compiled_programs("trace") as traced, compiled_programs() as compiled:
            got = run()
        assert ("export_finish_jacobian" in traced) == (name == "grad"), (name, traced)
        if name == "grad":
            assert "_run_one" not in traced and "export_run" not in traced, traced
            assert "jit(exported_run)" not in compiled, compiled
        for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want[name])):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-12)
    # the grad traced the goal and the mass, the jvp the goal only: one Jacobian program
    assert len(list(exports.glob("*.jaxexport"))) == 3

    def effort(goal, m):  # as notebook 03: from the solution, at a tighter tolerance
        return lc.solve(task.with_options(goal=goal, system=lj.Car(m=m)), sol, tol=1e-10).cost

    with compiled_programs("trace") as traced, compiled_programs() as compiled:
        grad = jax.grad(effort, argnums=(0, 1))(task.goal, 1.0)  # the mass a Python number
    assert "_run_one" not in traced and "export_run" not in traced, traced
    assert "jit(exported_run)" not in compiled, compiled
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("LDAP_JAX_EXPORT", "0")
        want = jax.grad(effort, argnums=(0, 1))(task.goal, 1.0)
    for a, b in zip(grad, want):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-12)
    # as a new process: the finish and its Jacobian are read back, nothing of the solver traced
    _export._loaded.clear()
    with compiled_programs("trace") as traced:
        again = jax.grad(effort, argnums=(0, 1))(task.goal, 1.0)
    assert not {"_run_one", "_finish", "export_finish", "export_finish_jacobian"} & set(traced), traced
    for a, b in zip(again, want):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-12)


def test_exports_off_inside_traces_in_memory_without_a_cache(exports, monkeypatch):
    """Under a user's jit the solver is traced as written (no export is read or written); without
    a cache directory a solve runs an export kept in memory (nothing written, the traced
    program's solution); with LDAP_JAX_EXPORT=0, call declines."""
    task = lc.parallel_park(integrator=lj.RDP(), n_steps=40)
    reference = _traced(task)
    cost = jax.jit(lambda g: lc.solve(task.with_options(goal=g)).cost)(task.goal)
    assert not list(exports.iterdir())
    np.testing.assert_allclose(float(cost), float(reference.cost), rtol=1e-12)
    with monkeypatch.context() as mp:
        mp.setattr(_export, "export_dir", lambda: None)
        assert _export.enabled() and _export._paths("any") is None and _export._executable_path("any") is None
        assert _export._serves("run") and not _export._serves("gait_tracker")
        _assert_same(lc.solve(task), reference)
        # served by in-memory exports of the run and the finish
        assert len([r for r in _export._loaded.values() if r is not None]) == 2
    assert not list(exports.iterdir())
    monkeypatch.setenv("LDAP_JAX_EXPORT", "0")
    assert not _export.enabled()
    assert _export.call("solve", None, (task,), lambda: None) is NotImplemented


#: a new process: solves the small parallel_park, then runs a program with a LAPACK call (a custom
#: call) through an export, then computes the key of the roller racer's gait (an lj.System of
#: library functions) as this module does; what it traced and lowered is recorded before the two
#: last steps, which lower their own programs
NEW_PROCESS = """
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
import ldap_jax as lj
from ldap_jax import control as lc
from ldap_jax.control import _export
lj.enable_compilation_cache(sys.argv[1])
traced, lowered = [], []
def listen(event, duration, **kwargs):
    if event == "/jax/core/compile/jaxpr_trace_duration":
        traced.append(kwargs.get("fun_name"))
    if event == "/jax/core/compile/jaxpr_to_mlir_module_duration":
        lowered.append(kwargs.get("fun_name"))
jax.monitoring.register_event_duration_secs_listener(listen)
sol = lc.solve(lc.parallel_park(integrator=lj.RDP(), n_steps=40))
out = {"params": np.asarray(sol.params).tolist(), "iterations": int(sol.iterations),
       "traced": list(traced), "lowered": list(lowered), "scipy": "scipy.linalg" in sys.modules}
a = np.array([[4.0, 1.0, 0.0], [1.0, 3.0, 1.0], [0.0, 1.0, 2.0]])
x = _export.call("lapack_probe", lambda a, b: (jnp.linalg.solve(a, b),), (a, np.ones(3)), lambda: (0,))
out["lapack_x"] = np.asarray(x[0]).tolist()
out["lapack_key"] = _export._signature("lapack_probe", (a, np.ones(3)))[0]
sys.path.insert(0, sys.argv[2])
from test_export import _key
out["racer_key"] = _key(lc.racer_gait())
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def new_processes(tmp_path_factory):
    """Three new processes (:data:`NEW_PROCESS`) one after another on one fresh cache folder: the
    first exports and compiles the programs, the second finds them, and the third runs after
    the executables the first stored were damaged. Their outputs, the executables stored after
    the first, and the names of the export folder's files after each."""
    import pathlib

    env = dict(os.environ, LDAP_JAX_EXPORT="1")
    cache = tmp_path_factory.mktemp("new_processes") / "cache"
    tests = str(pathlib.Path(__file__).parent)
    runs, files = [], []

    def run():
        cmd = [sys.executable, "-c", NEW_PROCESS, str(cache), tests]
        res = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)
        assert res.returncode == 0, res.stderr[-3000:]
        runs.append(json.loads(res.stdout.strip().splitlines()[-1]))
        files.append(sorted(p.name for p in (cache / _export.SUBDIR).iterdir()))

    run()
    stored = sorted((cache / _export.SUBDIR).glob("*.executable"))
    run()
    for path in stored:
        path.write_bytes(b"damaged")
    run()
    return runs, stored, files


def test_a_new_process_solves_from_the_export(new_processes):
    """Two new processes on one cache folder: the second traces neither the run nor the finish,
    imports no SciPy (JAX's LAPACK set-up is skipped for programs without LAPACK calls), and both
    give this process's traced solution to 1e-12."""
    runs, _, _ = new_processes
    second = runs[1]
    names = {"export_run", "export_finish", "_run_one", "_finish"}
    assert not names & set(second["traced"]), second["traced"]
    assert not second["scipy"]
    want = _traced(lc.parallel_park(integrator=lj.RDP(), n_steps=40))
    for run in runs[:2]:
        assert run["iterations"] == int(want.iterations)
        np.testing.assert_allclose(np.asarray(run["params"]), np.asarray(want.params), rtol=1e-12, atol=1e-12)


def test_a_new_process_loads_the_executable_the_first_one_compiled(new_processes):
    """On a fresh cache folder the process that compiles the exported programs stores their
    executables next to the exports; a second process loads them without lowering anything, and
    a third, whose executables are damaged, lowers and compiles through JAX's cache as before;
    all three give the traced solution to 1e-12."""
    runs, stored, _ = new_processes
    assert len(stored) == 2, stored  # the run's and the finish's
    assert runs[1]["lowered"] == [] and runs[1]["traced"] == []
    assert {"jit(exported_run)", "jit(exported_finish)"} <= set(runs[2]["lowered"])
    want = _traced(lc.parallel_park(integrator=lj.RDP(), n_steps=40))
    for r in runs:
        assert r["iterations"] == int(want.iterations)
        np.testing.assert_allclose(np.asarray(r["params"]), np.asarray(want.params), rtol=1e-12, atol=1e-12)


def test_executables_are_kept_per_host_cpu(monkeypatch):
    """An executable is machine code for the CPU that compiled it: a machine with other
    instruction-set extensions (another node of a cluster sharing the cache folder) looks for a
    file of its own and never loads a foreign one."""
    here = _export._executable_path("some_key")
    assert here is not None and here.name.startswith("some_key.")
    assert _export._executable_path("some_key") == here  # the same machine: the same file
    monkeypatch.setattr(_export, "_host_cpu", lambda: "x86_64 fpu sse2 avx512f")
    there = _export._executable_path("some_key")
    monkeypatch.setattr(_export, "_host_cpu", lambda: "x86_64 fpu sse2")
    assert len({here, there, _export._executable_path("some_key")}) == 3


def test_a_program_with_custom_calls_is_never_loaded_as_an_executable(new_processes):
    """A program calling LAPACK (a custom call, whose kernels JAX registers while lowering) is
    exported but its executable is not stored: a second process lowers it as before (a loaded
    one crashed at its first call) and both solve the system (the new processes above, after
    their solve)."""
    runs, _, files = new_processes
    a = np.array([[4.0, 1.0, 0.0], [1.0, 3.0, 1.0], [0.0, 1.0, 2.0]])
    for r, names in zip(runs[:2], files[:2]):
        np.testing.assert_allclose(a @ np.asarray(r["lapack_x"]), np.ones(3), rtol=0, atol=1e-14)
        key = r["lapack_key"]
        assert key == runs[0]["lapack_key"] and f"{key}.jaxexport" in names, (key, names)
        assert not [n for n in names if n.startswith(key) and n.endswith(".executable")], names


def test_library_functions_are_keyed_by_name_user_functions_never(new_processes):
    """A system of the library's own functions (``lj.roller_racer``: nested functions, one
    calling another through its closure) is exported under a key that a new process computes
    alike (its code is in the library's source hash; the new processes above); its parameter
    values are arguments, and the racer without friction is another key. A system holding a
    user-written function, or a library function whose closure holds an array, is never
    exported."""
    runs, _, _ = new_processes
    key = _key(lc.racer_gait())
    assert key is not None
    assert _key(lc.racer_gait(lj.roller_racer(drag=0.5, m1=2.0))) == key
    assert [r["racer_key"] for r in runs] == [key] * len(runs)
    racer, frictionless = lj.roller_racer(drag=0.3), lj.roller_racer()
    assert _export._signature("run", (frictionless,))[0] != _export._signature("run", (racer,))[0]

    def swap(fn):
        return eqx.tree_at(lambda s: s.lagrangian_fn, racer, fn)

    def lagrangian(*args):  # a user's function: its code is not in the key
        return racer.lagrangian_fn(*args)

    assert _export._signature("run", (swap(lagrangian),)) is None
    for held in (np.ones(3), lagrangian):  # held by a library function's closure

        def library(*args, held=held):
            return held

        library.__module__ = "ldap_jax.systems"
        assert _export._static_text(library) is None
        assert _export._signature("run", (swap(library),)) is None


def _served_from_export(exports, call, traced_names):
    """``call()`` without exports, then with them (exporting one program), then again with nothing
    loaded in this process: that last one traces none of ``traced_names``. The three results."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("LDAP_JAX_EXPORT", "0")
        want = call()
    first = call()
    assert len(list(exports.glob("*.jaxexport"))) == 1
    _export._loaded.clear()
    with compiled_programs("trace") as traced:
        again = call()
    assert not set(traced_names) & set(traced), traced
    return want, first, again


def test_gait_analysis_is_served_from_its_export(exports):
    """The cycle map's analysis behind ``lc.monodromy`` and ``lc.replay_gait`` (one period and
    its Jacobian) goes through an exported program like the solver's: read back without tracing,
    it gives the traced program's values."""
    from ldap_jax.control import _gait_analysis

    task = lc.drive_gait(n_steps=8)
    params = task.init()
    want, first, again = _served_from_export(
        exports, lambda: _gait_analysis._analysis(task, params), ("export_gait_analysis", "_analysis_of")
    )
    for got in (first, again):
        for x, y in zip(got, want):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-12, atol=1e-12)


def test_gait_tracker_is_served_from_its_export(exports):
    """``lc.gait_tracker``'s program (the linearised cycle and the periodic Riccati sweeps) goes
    through an exported program: read back without tracing, the same gains to 1e-12; a weight is
    an argument of the same program."""
    task = lc.drive_gait(n_steps=8)
    params = task.init()
    want, first, again = _served_from_export(
        exports, lambda: lc.gait_tracker(task, params), ("export_gait_tracker", "_tracker_of")
    )
    for got in (first, again):
        np.testing.assert_allclose(np.asarray(got.gains), np.asarray(want.gains), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(got.z_ref), np.asarray(want.z_ref), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(got.z_rate), np.asarray(want.z_rate), rtol=1e-12, atol=1e-12)
    with compiled_programs("trace") as traced:
        heavier = lc.gait_tracker(task, params, q_weight=2.0)
    assert not {"export_gait_tracker", "_tracker_of"} & set(traced), traced
    assert not np.allclose(np.asarray(heavier.gains), np.asarray(want.gains))
