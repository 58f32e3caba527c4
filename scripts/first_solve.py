"""Where the first ``lc.solve(lc.parallel_park())`` of a new process spends its time.

    python scripts/first_solve.py                 # cold, then warm, each in a new process
    python scripts/first_solve.py --runs 3        # three warm processes
    python scripts/first_solve.py --cache DIR --runs 0   # one process on the cache DIR
    python scripts/first_solve.py --no-export     # the compilation cache only (no exported programs)
    python scripts/first_solve.py --no-cache --runs 2   # three processes without a cache (as a
                                                        # user who never enables it)
    python scripts/first_solve.py --program       # the run program alone: XLA's time, its size
    python scripts/first_solve.py --program --quick   # ... compiled as the quick tier's program

Each measurement is a new Python process (``--child``) that imports the library, turns on the
persistent compilation cache in a directory of this script's own (a fresh temporary one, so the
first process is cold and the later ones warm; ``--cache DIR`` to keep it) and times:

* ``import``: ``import ldap_jax`` and ``ldap_jax.control``;
* ``first``: the first ``lc.solve(lc.parallel_park())`` (everything: the task's construction,
  tracing, lowering, XLA compilation or cache reads, the run), and of it the task's construction;
* ``second``: a second solve of the same task in the same process right after the first, and
  ``repeat`` the least of ten more once the library's background compilations are done
  (``background``: when, from the first solve's start; a cold process compiles the run program
  quickly for its first calls and the optimised one behind them); ``first_cpu``: the first
  solve's CPU time (every thread's: XLA compiles on several);
* per program: JAX's own monitoring events (``jax.monitoring``): Python tracing to a jaxpr,
  lowering to StableHLO, XLA compilation, persistent-cache reads, summed per program name.

``--program [--task NAME] [--hlo FILE]`` instead lowers a task's interior-point run program
(``parallel_park`` by default) in this process, compiles it with the library's XLA options and
prints the compilation's wall and CPU time, the optimised HLO's instruction, fusion and while-loop
counts (``--hlo`` writes its text) and the run's time (the least of 7 calls); ``--quick`` compiles
the program a new export's first calls run (the quick tier's options on top), ``--outputs FILE``
writes the run's outputs (to compare two compilations' answers).

With ``--no-cache`` the children never enable the cache (every process is cold; the exports are
kept in memory). With ``--no-export`` the child sets ``LDAP_JAX_EXPORT=0`` (``lc.solve`` then never uses an
exported program). Prints a table; ``--json FILE`` writes the numbers. The children inherit the
environment: with ``PYTHONDONTWRITEBYTECODE=1`` every module a warm solve imports first (jaxlib's
MLIR dialects, for lowering the exported programs) is compiled from source in each process (about
0.1 s, which a user's Python caches).
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import subprocess
import sys
import tempfile
import threading
import time

EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "compile",
    "/jax/compilation_cache/cache_retrieval_time_sec": "cache read",
}


def child(cache: str) -> dict:
    """One new process's measurement (printed as JSON on the last line of stdout)."""
    t0 = time.perf_counter()
    import jax

    jax.config.update("jax_enable_x64", True)
    import ldap_jax as lj
    from ldap_jax import control as lc

    t_import = time.perf_counter() - t0
    if cache:
        lj.enable_compilation_cache(cache)

    per_program: dict = collections.defaultdict(lambda: collections.defaultdict(float))

    def listener(event, duration, **kwargs):
        kind = EVENTS.get(event)
        if kind is not None:
            name = kwargs.get("fun_name") or "?"
            per_program[name][kind] += duration

    jax.monitoring.register_event_duration_secs_listener(listener)

    t1, c1 = time.perf_counter(), time.process_time()
    task = lc.parallel_park()
    t_task = time.perf_counter() - t1
    sol = lc.solve(task)
    jax.block_until_ready(sol)
    t_first, c_first = time.perf_counter() - t1, time.process_time() - c1
    first_programs = {k: dict(v) for k, v in per_program.items()}

    t2 = time.perf_counter()
    sol2 = lc.solve(lc.parallel_park())
    jax.block_until_ready(sol2)
    t_second = time.perf_counter() - t2
    # the library's compilations still running in the background (the run's optimised program)
    for thread in threading.enumerate():
        if thread.name.startswith("ldap_jax-"):
            thread.join()
    t_background = time.perf_counter() - t1
    repeats = []
    for _ in range(10):
        t3 = time.perf_counter()
        jax.block_until_ready(lc.solve(lc.parallel_park()))
        repeats.append(time.perf_counter() - t3)
    return {
        "import": t_import,
        "first": t_first,
        "task": t_task,
        "second": t_second,
        "repeat": min(repeats),
        "background": t_background,
        "first_cpu": c_first,
        "converged": bool(sol.converged),
        "iterations": int(sol.iterations),
        "cost": float(sol.cost),
        "programs": first_programs,
    }


def program(task_name: str, hlo: str | None, quick: bool = False, outputs: str | None = None) -> None:
    """The run program of ``lc.<task_name>()`` alone: compilation time, size, run time. With
    ``quick``: compiled with the quick tier's options on top (``_export.QUICK_OPTIONS``, the
    first calls' program of a new export); ``outputs``: an ``.npz`` file of the run's output leaves."""
    import re

    import equinox as eqx
    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    import ldap_jax as lj
    from ldap_jax import control as lc
    from ldap_jax.control import _export, _solve

    task = getattr(lc, task_name)()
    options, params0, _ = _solve._checked(task, None, 1e-8, 1000, "base", 0.1, None)
    t0 = time.perf_counter()
    lowered = eqx.filter_jit(_solve._run_one).lower(task, params0, options)
    t_lower = time.perf_counter() - t0
    c0, t0 = time.process_time(), time.perf_counter()
    xla_options = {**(lj.compiler_options() or {}), **(_export.QUICK_OPTIONS if quick else {})}
    compiled = lowered.compile(xla_options)
    t_compile, c_compile = time.perf_counter() - t0, time.process_time() - c0
    text = compiled.compiled.as_text()
    if hlo:
        with open(hlo, "w") as f:
            f.write(text)
    instructions = sum(1 for line in text.splitlines() if re.match(r"\s+(ROOT )?%?[\w.\-]+ = ", line))
    fusions = len(re.findall(r"^%?fused", text, re.M))
    runs = []
    for _ in range(7):
        t0 = time.perf_counter()
        st, out = compiled(task, params0, options)
        jax.block_until_ready(st)
        runs.append(time.perf_counter() - t0)
    if outputs:
        leaves = jax.tree_util.tree_leaves(eqx.filter((st, out), eqx.is_array))
        np.savez(outputs, *[np.asarray(x) for x in leaves])
    print(
        f"{task_name}{' (quick)' if quick else ''}: lowering {t_lower:.2f} s, "
        f"XLA compilation {t_compile:.2f} s (CPU {c_compile:.2f} s), "
        f"{instructions} instructions, {fusions} fusions, {text.count(' while(')} while loops; "
        f"run {1e3 * min(runs):.1f} ms ({int(st.iteration)} iterations, KKT error {float(st.error):.3e})"
    )


def run_child(cache: str, export: bool) -> dict:
    env = dict(os.environ)
    if not export:
        env["LDAP_JAX_EXPORT"] = "0"
    t0 = time.perf_counter()
    out = subprocess.run(
        [sys.executable, __file__, "--child", "--cache", cache],
        env=env,
        check=True,
        capture_output=True,
        text=True,
    )
    result = json.loads(out.stdout.strip().splitlines()[-1])
    result["process"] = time.perf_counter() - t0
    return result


def report(label: str, r: dict, top: int) -> None:
    print(
        f"{label}: process {r['process']:.2f} s, import {r['import']:.2f} s, first solve {r['first']:.2f} s "
        f"(CPU {r['first_cpu']:.2f} s), second {r['second']:.3f} s, background done at "
        f"{r.get('background', 0):.2f} s, repeats {r['repeat']:.3f} s "
        f"(converged {r['converged']}, {r['iterations']} iterations, "
        f"cost {r['cost']:.10g})"
    )
    totals = collections.Counter()
    rows = []
    for name, kinds in r["programs"].items():
        rows.append((sum(kinds.values()), name, kinds))
        totals.update(kinds)
    print("  sum over programs: " + ", ".join(f"{k} {v:.2f} s" for k, v in sorted(totals.items())))
    print(f"  {len(rows)} programs; the {top} largest:")
    for total, name, kinds in sorted(rows, reverse=True)[:top]:
        parts = ", ".join(f"{k} {v:.2f}" for k, v in sorted(kinds.items()))
        print(f"    {total:6.2f} s  {name[:60]:60s} {parts}")


def lc_tasks():
    """``ldap_jax.control`` (imported when a flag needs it)."""
    from ldap_jax import control

    return control


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--cache", default=None, help="compilation cache directory (default: a new temporary one)")
    p.add_argument("--runs", type=int, default=1, help="processes after the first one")
    p.add_argument("--no-export", action="store_true", help="do not use exported solver programs")
    p.add_argument("--no-cache", action="store_true", help="the children never enable the compilation cache")
    p.add_argument("--top", type=int, default=8, help="programs listed per process")
    p.add_argument("--json", default=None, help="write the measurements to this file")
    p.add_argument("--program", action="store_true", help="time and count the run program alone")
    p.add_argument("--task", default="parallel_park", help="the task of --program")
    p.add_argument("--hlo", default=None, help="with --program: write the optimised HLO here")
    p.add_argument("--quick", action="store_true", help="with --program: compile the quick tier's program")
    p.add_argument("--outputs", default=None, help="with --program: write the run's outputs (.npz) here")
    args = p.parse_args()
    if args.runs < 0:
        p.error(f"argument --runs: must be a non-negative integer, got {args.runs}")
    if args.top < 1:
        p.error(f"argument --top: must be a positive integer, got {args.top}")
    if not args.program:
        for flag in ("hlo", "quick", "outputs"):
            if getattr(args, flag) not in (None, False):
                p.error(f"argument --{flag}: only with --program")
    if args.no_cache and args.cache is not None:
        p.error("argument --cache: not with --no-cache")
    if args.cache is not None and os.path.exists(args.cache) and not os.path.isdir(args.cache):
        p.error(f"argument --cache: {args.cache!r} exists and is not a folder")
    for flag in ("json", "hlo", "outputs"):
        path = getattr(args, flag)
        if path is not None and not os.path.isdir(os.path.dirname(os.path.abspath(path))):
            p.error(f"argument --{flag}: the folder of {path!r} does not exist")
    if args.program and not callable(getattr(lc_tasks(), args.task, None)):
        p.error(f"argument --task: not a task of ldap_jax.control, got {args.task!r}")
    if args.program:
        program(args.task, args.hlo, args.quick, args.outputs)
        return
    if args.child:
        print(json.dumps(child(args.cache)))
        return
    with tempfile.TemporaryDirectory(prefix="ldap_jax_first_solve_") as tmp:
        cache = "" if args.no_cache else args.cache or tmp
        results = {}
        for i in range(args.runs + 1):
            cold = not cache or not os.path.isdir(cache) or not os.listdir(cache)
            label = f"no cache {i}" if not cache else "cold" if cold else f"warm {i}"
            results[label] = r = run_child(cache, not args.no_export)
            report(label, r, args.top)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
