"""Benchmarks of the integrators: throughput, compiled C, diffrax peers, work-precision (10 s and
10 min), orders, energy, gradient cost, memory, compile times, first calls in a new process.

    python scripts/bench.py --quick --out results     # part of `make demo`, a few minutes
    python scripts/bench.py --out results             # the full sizes (B = N = 1000, dense sweeps)

Writes ``OUT/bench.json``, ``OUT/bench.md``, ``OUT/work_precision.png`` (10 s and 10 min). Every
timing is the minimum of several repeats after compilation (wall clock; the process CPU time is
kept too), all ratios are measured in the same run. Optimal control is benchmarked by
``scripts/bench_control.py``.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import platform
import resource
import sys
import time
from collections.abc import Callable

import ldap_jax as lj

if "--one-core" in sys.argv:
    # the pinned process of ours_over_c (_one_core): on one core before JAX starts its threads,
    # with JAX's one host device, as a user's process has it (with one device per core forced,
    # the same one-device program ran 1.7x as long on the pinned core)
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
else:
    # One XLA host device per core, so the headline is also measured with the batch sharded
    # across cores (one program per core, as the study runs), next to the default single device.
    # Set before JAX starts; everything else here runs on the first device as usual.
    lj.use_cpu_cores()
if "--kept-memory" in sys.argv:
    # the process of default_call's rows with the allocator keeping freed memory (_kept_memory):
    # set before JAX starts its threads, as lj.keep_freed_memory asks
    lj.keep_freed_memory()

import jax

jax.config.update("jax_enable_x64", True)

import diffrax
import jax.numpy as jnp
import numpy as np

from ldap_jax import study

SYSTEMS = {"car": lj.Car(), "snakeboard": lj.Snakeboard()}
INTEGRATORS: dict[str, Callable[[], lj.integrators.AbstractIntegrator]] = {
    "RDP2": lambda: lj.RDP(),
    "RDP2 cayley": lambda: lj.RDP(retraction="cayley"),
    "RDP4": lambda: lj.RDP(order=4),
    "RDP6": lambda: lj.RDP(order=6),
    "RDP6 cayley": lambda: lj.RDP(order=6, retraction="cayley"),
    "RDP8": lambda: lj.RDP(order=8),
    "RK2": lj.RK2,
    "RK4": lj.RK4,
    "GNI": lj.GNI,
    "DLA": lj.DLA,
}


@dataclasses.dataclass(frozen=True)
class Config:
    """Sizes of a run (``--quick`` shrinks them)."""

    quick: bool = False
    repeats: int = 5
    #: paired rounds of the ratio sections (ours_over_c, default_call)
    rounds: int = 30
    batch: int = 1000
    steps: int = 1000
    throughput_batch: int = 1000
    grad_batch: int = 1000
    mem_steps: int = 10_000
    memory_batch: int = 1000
    memory_steps: int = 4000
    wp_maneuvers: int = 256
    wp_steps_10s: tuple[int, ...] = (10, 20, 40, 80, 160, 320, 640, 1280, 2560)
    wp_steps_600s: tuple[int, ...] = (250, 500, 1000, 2000, 4000, 8000)
    wp_tols: tuple[float, ...] = (1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10)
    order_steps: tuple[int, ...] = (8, 16, 32)
    energy_steps: int = 100_000

    @staticmethod
    def for_run(quick: bool, repeats: int | None, rounds: int | None = None) -> Config:
        if not quick:
            return Config(repeats=repeats or 5, rounds=rounds or 30)
        return Config(
            quick=True,
            repeats=repeats or 2,
            rounds=rounds or 5,
            throughput_batch=200,
            grad_batch=100,
            memory_batch=100,
            wp_maneuvers=32,
            wp_steps_10s=(10, 20, 40, 80, 160, 640),
            wp_steps_600s=(500, 2000, 8000),
            wp_tols=(1e-4, 1e-7, 1e-10),
            energy_steps=20_000,
        )


def maneuvers(system, n, seed=0, dtype=jnp.float64):
    q0, qdot0, ctl = study.sample_maneuvers(system, n, seed)
    return jax.tree_util.tree_map(lambda x: x.astype(dtype), (q0, qdot0, ctl))


def timeit(fn, *args, repeats=3):
    """Compile (first call), then ``repeats`` timed calls: wall/cpu statistics."""
    t = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t
    wall, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn(*args))
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return {
        "min": float(np.min(wall)),
        "median": float(np.median(wall)),
        "cpu_min": float(np.min(cpu)),
        "first_call": first,
    }


def paired_rounds(fns: dict[str, Callable[[], tuple[float, float]]], rounds: int) -> dict[str, np.ndarray]:
    """Time every ``fns[k]()`` (each returns its ``(wall, cpu)`` seconds) once per round, for
    ``rounds`` rounds, the order rotated from round to round (no call always runs first or after
    the same neighbour): ``{k: array (rounds, 2)}``. A change of load hits every call of a round
    alike, so the per-round ratios (:func:`paired_ratio`) are far steadier than ratios of minima
    taken apart."""
    keys = list(fns)
    out = {k: [] for k in keys}
    for r in range(rounds):
        for k in keys[r % len(keys) :] + keys[: r % len(keys)]:
            out[k].append(fns[k]())
    return {k: np.asarray(v, float) for k, v in out.items()}


def paired_ratio(times: np.ndarray, base: np.ndarray) -> dict[str, float]:
    """Ratios of two series from :func:`paired_rounds`: the median over rounds of the per-round
    ratio (wall and CPU; the figure reported), and the ratio of the minima (wall)."""
    return {
        "ratio": float(np.median(times[:, 0] / base[:, 0])),
        "ratio_cpu": float(np.median(times[:, 1] / base[:, 1])),
        "ratio_of_min": float(times[:, 0].min() / base[:, 0].min()),
    }


def _timed(fn, *args) -> Callable[[], tuple[float, float, float]]:
    """A call of ``fn(*args)`` for :func:`paired_rounds`: ``(wall, cpu, minor page faults)``. The
    faults are the first touches of memory the allocator mapped afresh for the call (glibc maps
    each block above 32 MB anew): a call that writes every node of a B = N = 1000 rollout pays
    for ~1e4 of them in system time, a cost apart from the arithmetic."""

    def run():
        f = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        t, c = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn(*args))
        wall, cpu = time.perf_counter() - t, time.process_time() - c
        return wall, cpu, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f

    return run


def rollout_fn(system, integrator, n_steps, t_final=10.0, *, save="final", diagnostics=False):
    def one(q0, qdot0, ctl):
        traj = lj.simulate(
            system,
            q0,
            qdot0,
            ctl,
            t_final=t_final,
            n_steps=n_steps,
            integrator=integrator,
            check_constraints=False,
            save=save,
            diagnostics=diagnostics,
        )
        return traj if diagnostics else traj.q

    return jax.jit(jax.vmap(one))


def _terminal_loss(system, q0, qdot0, ctl, n, checkpoint, diagnostics=False):
    """Sum over the batch of ``|(x_N, y_N)|^2``: the loss whose gradient is timed (``diagnostics``:
    the run's tests on, as ``simulate``'s default)."""

    def one(a, b, c):
        q = lj.simulate(
            system,
            a,
            b,
            c,
            t_final=10.0,
            n_steps=n,
            check_constraints=False,
            checkpoint=checkpoint,
            save="final",
            diagnostics=diagnostics,
        ).q
        return jnp.sum(q[-1, :2] ** 2)

    return jnp.sum(jax.vmap(one)(q0, qdot0, ctl))


# ------------------------------------------------------------------------------------ sections
def headline(cfg: Config, log) -> list[dict]:
    """Snakeboard, RDP (order 2), float64, B x N: positions only, the whole trajectory with its
    diagnostics, and a gradient of a terminal cost; on one device and sharded over every device."""
    system = SYSTEMS["snakeboard"]
    b, n = cfg.batch, cfg.steps
    data = maneuvers(system, b)
    layouts = [("1 device", data)]
    if jax.device_count() > 1:
        layouts.append(
            (f"sharded over {jax.device_count()} devices", study.shard_batch(data, study.device_mesh())[0])
        )
    rows = []
    for layout, (q0, qdot0, ctl) in layouts:
        row = dict(layout=layout, B=b, N=n)
        st = timeit(rollout_fn(system, lj.RDP(), n), q0, qdot0, ctl, repeats=cfg.repeats)
        row["steps_per_s_q"] = b * n / st["min"]
        st = timeit(
            rollout_fn(system, lj.RDP(), n, save="all", diagnostics=True), q0, qdot0, ctl, repeats=cfg.repeats
        )
        row["steps_per_s_traj"] = b * n / st["min"]
        fwd = jax.jit(lambda c, q0=q0, qdot0=qdot0: _terminal_loss(system, q0, qdot0, c, n, False))
        grad = jax.jit(jax.grad(lambda c, q0=q0, qdot0=qdot0: _terminal_loss(system, q0, qdot0, c, n, False)))
        st_f, st_g = timeit(fwd, ctl, repeats=cfg.repeats), timeit(grad, ctl, repeats=cfg.repeats)
        row.update(forward_s=st_f["min"], grad_s=st_g["min"], grad_ratio=st_g["min"] / st_f["min"])
        rows.append(row)
        log(
            f"  {layout}: {row['steps_per_s_q']:.3g} steps/s (positions), {row['steps_per_s_traj']:.3g} "
            f"(trajectory), gradient/forward {row['grad_ratio']:.2f}"
        )
    return rows


C_SOURCE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "c", "rdp_snakeboard.c")


def _c_library(log):
    """Compile ``scripts/c/rdp_snakeboard.c`` (``cc -O3 -march=native -fopenmp``, no
    ``-ffast-math``: it would change the arithmetic); ``None`` without a C compiler."""
    import ctypes
    import shutil
    import subprocess
    import tempfile

    cc = shutil.which(os.environ.get("CC", "cc")) or shutil.which("gcc")
    if cc is None:
        log("  no C compiler: skipped")
        return None
    lib_path = os.path.join(tempfile.mkdtemp(prefix="ldap_jax_bench_"), "librdp.so")
    flags = ["-O3", "-march=native", "-fopenmp", "-shared", "-fPIC"]
    subprocess.run([cc, *flags, C_SOURCE, "-o", lib_path, "-lm"], check=True)
    return ctypes.CDLL(lib_path)


def _c_setup(cfg: Config, log):
    """The compiled C library and ``call_args(q)`` for the snakeboard maneuvers of the headline
    (B x N, 10 s): the same initial momenta as ours. ``None`` without a C compiler."""
    import ctypes

    lib = _c_library(log)
    if lib is None:
        return None
    system = SYSTEMS["snakeboard"]
    b, n, t_final = cfg.batch, cfg.steps, 10.0
    h = t_final / n
    q0, qdot0, ctl = maneuvers(system, b)
    st = jax.vmap(lambda a, v: lj.RDP().init(system, jnp.asarray(h), a, v, None))(q0, qdot0)
    init = np.ascontiguousarray(
        np.stack(
            [q0[:, 2], q0[:, 0], q0[:, 1], q0[:, 3], q0[:, 4], st.pu[0], st.pu[1], st.mu[0], st.mu[1]], 1
        ),
        np.float64,
    )
    ctl_np = np.ascontiguousarray(np.stack([ctl.amplitude, ctl.frequency, ctl.phase], 1), np.float64)
    ptr, dbl = ctypes.POINTER(ctypes.c_double), ctypes.c_double

    def call_args(q):
        return (
            ctypes.c_int(b),
            ctypes.c_int(n),
            ctypes.c_int(ctl_np.shape[-1]),
            dbl(h),
            *(dbl(float(getattr(system, k))) for k in ("m", "l", "I", "J")),
            init.ctypes.data_as(ptr),
            ctl_np.ctypes.data_as(ptr),
            q.ctypes.data_as(ptr),
        )

    return lib, call_args, (q0, qdot0, ctl)


def compiled_c(cfg: Config, headline_rows, log) -> list[dict]:
    """The same snakeboard RDP rollout (alpha = 1/2, exp) in scalar C (``scripts/c``), compiled
    here at ``-O3 -march=native`` without fast-math: a loop over maneuvers with the steps inside,
    the model's constants hoisted, one sincos per angle, with glibc's ``sin``/``sincos`` and with
    the inlined polynomial kernels that ldap_jax uses. Every node is checked against
    ``lj.simulate`` (round-off); the positions-only variants (the final node, as ``save="final"``)
    are timed on one thread and on every core: ns per step (wall) and, on one thread, the
    thread's CPU time (less inflated when other processes share the cores)."""
    setup = _c_setup(cfg, log)
    if setup is None:
        return []
    lib, call_args, (q0, qdot0, ctl) = setup
    system = SYSTEMS["snakeboard"]
    b, n, t_final = cfg.batch, cfg.steps, 10.0
    ours = np.asarray(rollout_fn(system, lj.RDP(), n, t_final, save="all")(q0, qdot0, ctl))
    best_ours = max(r["steps_per_s_q"] for r in headline_rows) if headline_rows else None
    rows = []
    for sc, label in (("libm", "glibc sin/sincos"), ("poly", "inlined polynomial sincos")):
        q_all = np.zeros((b, n + 1, 5))
        lib.set_threads(1)
        getattr(lib, f"rollout_{sc}")(*call_args(q_all))
        diff = float(np.max(np.abs(q_all - ours)))
        f = getattr(lib, f"rollout_final_{sc}")
        q = np.zeros((b, 5))
        for threads in sorted({1, os.cpu_count() or 1}):
            lib.set_threads(threads)
            f(*call_args(q))
            wall, cpu = [], []
            for _ in range(cfg.repeats):
                t, c = time.perf_counter(), time.thread_time()
                f(*call_args(q))
                wall.append(time.perf_counter() - t)
                cpu.append(time.thread_time() - c)
            row = dict(
                variant=f"scalar, {label}",
                threads=threads,
                B=b,
                N=n,
                steps_per_s=b * n / min(wall),
                ns_per_step=min(wall) / (b * n) * 1e9,
                cpu_ns_per_step=min(cpu) / (b * n) * 1e9 if threads == 1 else None,
                max_abs_diff_vs_ours=diff,
            )
            row["ours_best_over_c"] = best_ours / row["steps_per_s"] if best_ours else None
            rows.append(row)
            log(
                f"  C {label}, {threads} thread(s): {row['ns_per_step']:.1f} ns/step"
                + (f" (thread CPU {row['cpu_ns_per_step']:.1f})" if threads == 1 else "")
                + f" (|q - ours| <= {diff:.1e})"
            )
    return rows


#: substeps per composed step (the compositions' base steps: C's cost of order p is this many of
#: its order-2 steps): the default schemes', 1, 5 and 11
SUBSTEPS = {order: len(lj.RDP(order=order).weights) for order in (2, 4, 6)}


def ours_over_c(cfg: Config, log, *, one_core: bool = False) -> list[dict]:
    """The positions-only rollout (snakeboard, ``save="final", diagnostics=False``, B x N) for
    RDP orders 2, 4 and 6, as a user writes it, ``jax.jit(jax.vmap(...))`` (XLA's default
    options), and with ``compiler_options=lj.compiler_options()``; on one device against the C
    rollout on one thread, and sharded over every device against C on every core. Ours and C run
    in alternating rounds (paired, so that a change of load hits both). C's time per composed step
    is ``SUBSTEPS[order]`` times its order-2 step (inlined polynomial sincos, the faster variant).
    Reported: wall and CPU time per step, medians over ``cfg.rounds`` rounds (CPU: the process's,
    JAX's threads included; C on one thread: the thread's), and the ratios ours/C: the median over
    the rounds of each round's ratio (:func:`paired_ratio`; also the ratio of the minima).

    Then one core against one core (:func:`_one_core`): the one-device program under the plain
    ``jax.jit`` and C in a process pinned to a single core. On one device XLA splits each kernel
    of the loop over its threads, one per core, and the process's CPU time exceeds its wall time;
    pinned, every thread shares one core (CPU time = wall time), as C's one thread has. With
    ``one_core`` (the pinned process itself) only that layout is measured."""
    setup = _c_setup(cfg, log)
    if setup is None:
        return []
    lib, call_args, data = setup
    c_fn = lib.rollout_final_poly
    q_c = np.zeros((cfg.batch, 5))
    system = SYSTEMS["snakeboard"]
    b, n = cfg.batch, cfg.steps
    layouts = [("1 device", data, 1)]
    if one_core:
        layouts = [("1 core (process pinned)", data, 1)]
    elif jax.device_count() > 1:
        layouts.append(
            (
                f"sharded over {jax.device_count()} devices",
                study.shard_batch(data, study.device_mesh())[0],
                os.cpu_count() or 1,
            )
        )
    opts = lj.compiler_options()

    def run_c(threads):
        def run():
            lib.set_threads(threads)
            t, c = time.perf_counter(), time.thread_time() if threads == 1 else time.process_time()
            c_fn(*call_args(q_c))
            cpu = (time.thread_time() if threads == 1 else time.process_time()) - c
            return time.perf_counter() - t, cpu

        return run

    rows = []
    for order in (2, 4, 6):
        integ = lj.RDP(order=order)

        def one(q0, qdot0, ctl, integ=integ):
            traj = lj.simulate(
                system,
                q0,
                qdot0,
                ctl,
                t_final=10.0,
                n_steps=n,
                integrator=integ,
                check_constraints=False,
                save="final",
                diagnostics=False,
            )
            return traj.q

        fns = {"plain jax.jit": jax.jit(jax.vmap(one))}
        if opts is not None and not one_core:
            fns["lj.compiler_options()"] = jax.jit(jax.vmap(one), compiler_options=opts)
        for layout, args, threads in layouts:
            for f in fns.values():
                jax.block_until_ready(f(*args))
            run_c(threads)()
            calls = {k: _timed(f, *args) for k, f in fns.items()}
            times = paired_rounds({**calls, "C": run_c(threads)}, cfg.rounds)
            # C's time per composed step: SUBSTEPS[order] of its order-2 steps
            times["C"] = times["C"] * SUBSTEPS[order]
            c_ns = [float(np.median(times["C"][:, i])) / (b * n) * 1e9 for i in (0, 1)]
            for k in fns:
                ns = [float(np.median(times[k][:, i])) / (b * n) * 1e9 for i in (0, 1)]
                r = paired_ratio(times[k], times["C"])
                row = dict(
                    order=order,
                    layout=layout,
                    compile=k,
                    B=b,
                    N=n,
                    rounds=cfg.rounds,
                    ns_per_step=ns[0],
                    cpu_ns_per_step=ns[1],
                    c_ns_per_step=c_ns[0],
                    c_cpu_ns_per_step=c_ns[1],
                    ours_over_c=r["ratio"],
                    ours_over_c_cpu=r["ratio_cpu"],
                    ours_over_c_of_min=r["ratio_of_min"],
                )
                rows.append(row)
                log(
                    f"  RDP{order} {layout}, {k}: {ns[0]:.1f} ns/step (CPU {ns[1]:.1f}), C {c_ns[0]:.1f} "
                    f"(CPU {c_ns[1]:.1f}): ours/C {row['ours_over_c']:.3f} "
                    f"(CPU {row['ours_over_c_cpu']:.3f}, of minima {row['ours_over_c_of_min']:.3f})"
                )
    if not one_core:
        rows += _one_core(cfg, log)
    return rows


def _one_core(cfg: Config, log) -> list[dict]:
    """:func:`ours_over_c` for one device in a new process that pins itself to one core
    (``os.sched_setaffinity`` before JAX starts, so JAX's threads and C's share that core; JAX
    with its one host device, not one per core), its rows read back; ``[]`` where a process
    cannot be pinned (no ``sched_setaffinity``)."""

    if not hasattr(os, "sched_setaffinity"):
        log("  one core: no os.sched_setaffinity here, skipped")
        return []
    core = min(os.sched_getaffinity(0))
    # without this process's one-device-per-core flag (lj.use_cpu_cores above): the pinned process
    # runs JAX with its one host device, as a user's has it (inheriting the flag, its one-device
    # program ran 2x as long on the pinned core)
    count = "--xla_force_host_platform_device_count"
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if not f.startswith(count)]
    env = dict(os.environ, XLA_FLAGS=" ".join(flags))
    log(f"  one core: a process pinned to core {core}")
    return _child_rows("--one-core", cfg, env)


def _child_rows(flag: str, cfg: Config, env: dict | None = None) -> list[dict]:
    """The rows of a section run in a new process of this script (``flag``: ``--one-core`` or
    ``--kept-memory``, each set up before JAX starts), with this run's rounds and size."""
    import subprocess
    import tempfile

    out = os.path.join(tempfile.mkdtemp(prefix="ldap_jax_bench_"), "rows.json")
    cmd = [sys.executable, os.path.abspath(__file__), flag, out, "--rounds", str(cfg.rounds)]
    cmd += ["--quick"] if cfg.quick else []
    subprocess.run(cmd, check=True, env=env)
    with open(out) as f:
        return json.load(f)


def default_call(cfg: Config, log, *, kept: bool = False) -> list[dict]:
    """The default call against the positions-only rollout, and a gradient against its forward
    (snakeboard, RDP order 2, B x N, one device, a plain ``jax.jit``), in alternating rounds of one
    process: ``lj.simulate`` with its defaults (every node, every diagnostic) returning the whole
    :class:`~ldap_jax.Trajectory`, the same call read as a user writes it (``.q[-1]``: XLA drops
    what is not read, the divergence and finiteness tests stay), ``save="final",
    diagnostics=False``; the sum of a terminal cost over the batch and its gradient with respect to
    the controls (``checkpoint=False``), also with JAX's own derivative of the step in place of its
    hand-written VJP (:func:`_autodiff_problem`; the order-2 rollout carries the sinusoids from node
    to node, differentiated by JAX, so the sampler's VJP has no part in these programs); the same
    terminal cost with the run's tests on (``simulate``'s default ``diagnostics=True``) and its
    gradient, against the terminal cost without them and against its own forward. Ratios:
    the median over ``cfg.rounds`` rounds of each round's ratio (:func:`paired_ratio`), of the wall
    times and of the process CPU times (less sensitive to other processes on a shared machine),
    and the ratio of the minima of the wall times; the minor page faults of a call (median). Then the
    terminal cost and its gradient again in a process that keeps freed memory
    (:func:`_kept_memory`; with ``kept``, that process's rows only)."""
    system = SYSTEMS["snakeboard"]
    b, n = cfg.batch, cfg.steps
    data = maneuvers(system, b)
    q0, qdot0, ctl = data

    def call(read, **kw):
        def one(q0, qdot0, ctl):
            traj = lj.simulate(system, q0, qdot0, ctl, t_final=10.0, n_steps=n, check_constraints=False, **kw)
            return read(traj)

        return jax.jit(jax.vmap(one)), data

    def loss(c):
        return _terminal_loss(system, q0, qdot0, c, n, False)

    def diag_loss(c):
        return _terminal_loss(system, q0, qdot0, c, n, False, diagnostics=True)

    ad_system, ad_ctl = _autodiff_problem(system, ctl)

    def ad_loss(c):
        return _terminal_loss(ad_system, q0, qdot0, c, n, False)

    if kept:
        fns = {
            f"terminal cost{KEPT}": (jax.jit(loss), (ctl,)),
            f"its gradient{KEPT}": (jax.jit(jax.grad(loss)), (ctl,)),
        }
    else:
        fns = {
            "positions only": call(lambda tr: tr.q, save="final", diagnostics=False),
            "default, Trajectory": call(lambda tr: tr),
            "default, .q[-1]": call(lambda tr: tr.q[-1]),
            "terminal cost": (jax.jit(loss), (ctl,)),
            "its gradient": (jax.jit(jax.grad(loss)), (ctl,)),
            "its gradient, JAX's derivatives": (jax.jit(jax.grad(ad_loss)), (ad_ctl,)),
            "terminal cost, diagnostics on": (jax.jit(diag_loss), (ctl,)),
            "its gradient, diagnostics on": (jax.jit(jax.grad(diag_loss)), (ctl,)),
        }
    for f, args in fns.values():
        jax.block_until_ready(f(*args))
    times = paired_rounds({k: _timed(f, *args) for k, (f, args) in fns.items()}, cfg.rounds)
    rows = []
    for k, t in times.items():
        if k.endswith(KEPT):  # their process's terminal cost (against itself: 1)
            base = f"terminal cost{KEPT}"
        elif k == "its gradient, diagnostics on":
            base = "terminal cost, diagnostics on"
        elif k.startswith("its gradient") or k == "terminal cost, diagnostics on":
            base = "terminal cost"
        else:
            base = "positions only"
        row = dict(
            call=k,
            B=b,
            N=n,
            rounds=cfg.rounds,
            ns_per_step=float(np.median(t[:, 0])) / (b * n) * 1e9,
            page_faults=float(np.median(t[:, 2])),
            over=base,
            **paired_ratio(t, times[base]),
        )
        rows.append(row)
        log(
            f"  {k}: {row['ns_per_step']:.1f} ns/step, {row['ratio']:.3f}x {base} "
            f"({row['ratio_cpu']:.3f}x in CPU time, {row['ratio_of_min']:.3f}x of minima), "
            f"{row['page_faults']:.0f} page faults per call"
        )
    if not kept:
        rows += _kept_memory(cfg, log)
    return rows


#: the suffix of default_call's rows measured with the allocator keeping freed memory
KEPT = ", freed memory kept"


def _kept_memory(cfg: Config, log) -> list[dict]:
    """:func:`default_call`'s terminal cost and its gradient in a new process that calls
    :func:`ldap_jax.keep_freed_memory` before JAX starts (a setting of the whole process, which
    cannot be undone for the other rows), its rows read back."""
    log("  a process that keeps freed memory (lj.keep_freed_memory())")
    return _child_rows("--kept-memory", cfg)


def _autodiff_problem(system, ctl):
    """The snakeboard and sinusoids without their hand-written VJPs (JAX differentiates the step
    and the sampler itself): the gradient's cost before them, in the same process."""

    class AutodiffSnakeboard(type(system)):
        def kernel_step_reverse(self, alpha, h, retraction, state, c0, c1):
            return self.kernel_step(alpha, h, retraction, state, c0, c1)

    class AutodiffSinusoids(type(ctl)):
        def sampler(self, h, fractions, *, reverse_only=False):
            return super().sampler(h, fractions)

    new_system = AutodiffSnakeboard(m=system.m, l=system.l, I=system.I, J=system.J)
    return new_system, AutodiffSinusoids(amplitude=ctl.amplitude, frequency=ctl.frequency, phase=ctl.phase)


def throughput(cfg: Config, log) -> list[dict]:
    """Forward throughput of every integrator on both models (positions only, batched)."""
    rows = []
    for model, system in SYSTEMS.items():
        data = maneuvers(system, cfg.throughput_batch)
        for name, make in INTEGRATORS.items():
            if cfg.quick and model == "car" and name not in ("RDP2", "RDP6", "RK4"):
                continue
            st = timeit(rollout_fn(system, make(), cfg.steps), *data, repeats=cfg.repeats)
            row = dict(
                model=model,
                integrator=name,
                B=cfg.throughput_batch,
                N=cfg.steps,
                steps_per_s=cfg.throughput_batch * cfg.steps / st["min"],
                compile_s=st["first_call"] - st["min"],
            )
            rows.append(row)
            log(f"  {model:10s} {name:12s} {row['steps_per_s']:.3g} steps/s")
    return rows


def _diffrax_fn(system, solver, t_final, *, n_steps=None, rtol=None, max_steps=200_000):
    def one(q0, qdot0, ctl):
        v0 = system.velocities_from_qdot(q0, qdot0)
        term = diffrax.ODETerm(lambda t, y, args: system.ode(y, ctl(t)))
        ctrl, dt0 = (
            (diffrax.ConstantStepSize(), t_final / n_steps)
            if n_steps
            else (diffrax.PIDController(rtol=rtol, atol=rtol), None)
        )
        sol = diffrax.diffeqsolve(
            term,
            solver,
            0.0,
            t_final,
            dt0,
            (q0, v0),
            saveat=diffrax.SaveAt(t1=True),
            stepsize_controller=ctrl,
            max_steps=max_steps,
            throw=False,
        )
        return sol.ys[0][-1], sol.stats["num_steps"]

    return jax.jit(jax.vmap(one))


def _reference_final(system, data, t_final):
    q0, qdot0, ctl = data
    return np.asarray(
        jax.vmap(
            lambda a, b, c: lj.reference(
                system, a, b, c, jnp.array([t_final]), rtol=1e-12, atol=1e-12, max_steps=2_000_000
            ).q[-1]
        )(q0, qdot0, ctl)
    )


def work_precision(cfg: Config, t_final: float, steps: tuple[int, ...], log) -> dict:
    """Work-precision of both models over ``t_final``: ``{model: _work_precision(...)}``."""
    return {model: _work_precision(cfg, model, t_final, steps, log) for model in ("snakeboard", "car")}


def _work_precision(cfg: Config, model: str, t_final: float, steps: tuple[int, ...], log) -> dict:
    """Mean final position error over a batch of random maneuvers against seconds per
    trajectory (batched), for the RDP orders, RK2, RK4 and (10 s) diffrax's adaptive Tsit5 and Dopri8."""
    system = SYSTEMS[model]
    data = maneuvers(system, cfg.wp_maneuvers, seed=1)
    ref = _reference_final(system, data, t_final)
    m = cfg.wp_maneuvers

    def err(qf):
        e = np.linalg.norm(np.asarray(qf)[:, :2] - ref[:, :2], axis=-1)
        return float(np.mean(e)) if np.all(np.isfinite(e)) else float("nan")

    curves = {}
    names = ("RDP2", "RDP4", "RDP6", "RDP6 cayley", "RDP8", "RK2", "RK4")
    for name in names:
        pts = []
        for n in steps:
            if t_final > 60 and name in ("RDP4", "RDP6", "RDP6 cayley", "RDP8") and n > steps[-1] // 2:
                continue  # high orders converge before the densest grids: keep the run short
            fn = rollout_fn(system, INTEGRATORS[name](), n, t_final)
            st = timeit(fn, *data, repeats=cfg.repeats)
            pts.append(dict(n_steps=n, error=err(fn(*data)[:, -1]), seconds_per_traj=st["min"] / m))
        curves[name] = pts
        log(
            f"  {model} {t_final:g} s {name}: " + ", ".join(f"N={p['n_steps']} {p['error']:.1e}" for p in pts)
        )
    if t_final <= 60:
        for name, solver in (("diffrax Tsit5", diffrax.Tsit5()), ("diffrax Dopri8", diffrax.Dopri8())):
            pts = []
            for tol in cfg.wp_tols:
                fn = _diffrax_fn(system, solver, t_final, rtol=tol)
                st = timeit(fn, *data, repeats=cfg.repeats)
                qf, nsteps = fn(*data)
                pts.append(
                    dict(
                        rtol=tol, steps=float(np.mean(nsteps)), error=err(qf), seconds_per_traj=st["min"] / m
                    )
                )
            curves[name] = pts
            log(
                f"  {model} {t_final:g} s {name}: "
                + ", ".join(f"tol={p['rtol']:.0e} {p['error']:.1e}" for p in pts)
            )
    levels = (1e-3, 1e-6, 1e-9) if t_final <= 60 else (1.0, 1e-1, 1e-2, 1e-3)
    cost = {name: {f"{lvl:.0e}": _cost_to_reach(pts, lvl) for lvl in levels} for name, pts in curves.items()}
    ratios = {}
    for name in ("RDP2", "RDP4", "RDP6", "RDP6 cayley", "RDP8", "diffrax Tsit5"):
        if name in cost:
            ratios[name] = {
                lvl: (
                    None
                    if cost[name][lvl] is None or cost["RK4"][lvl] is None
                    else cost[name][lvl] / cost["RK4"][lvl]
                )
                for lvl in cost[name]
            }
    out = dict(model=model, t_final=t_final, curves=curves, cost=cost, ratio_to_rk4=ratios)
    if t_final > 60:
        out["equal_cost"] = _equal_cost_comparison(curves)
    return out


def _cost_to_reach(pts, level):
    """Seconds per trajectory to reach ``level`` (log-log interpolation between the two runs that
    bracket it), None if not reached."""
    pts = [p for p in pts if np.isfinite(p["error"]) and p["error"] > 0]
    pts = sorted(pts, key=lambda p: p["seconds_per_traj"])
    for i, p in enumerate(pts):
        if p["error"] <= level:
            if i == 0:
                return float(p["seconds_per_traj"])
            a, b = pts[i - 1], p
            x = (np.log(level) - np.log(a["error"])) / (np.log(b["error"]) - np.log(a["error"]))
            return float(
                np.exp(
                    np.log(a["seconds_per_traj"])
                    + x * (np.log(b["seconds_per_traj"]) - np.log(a["seconds_per_traj"]))
                )
            )
    return None


def _equal_cost_comparison(curves) -> list[dict]:
    """At each RK4 point below 1 m: the error of each RDP order at the same cost (log-log interpolation)."""
    rows = []
    for p in curves["RK4"]:
        if not (np.isfinite(p["error"]) and p["error"] < 1.0):
            continue
        row = dict(n_steps_rk4=p["n_steps"], seconds=p["seconds_per_traj"], rk4_error=p["error"])
        for name in ("RDP2", "RDP4", "RDP6", "RDP8"):
            pts = sorted(
                (q for q in curves[name] if np.isfinite(q["error"])), key=lambda q: q["seconds_per_traj"]
            )
            t = np.log([q["seconds_per_traj"] for q in pts])
            e = np.log([q["error"] for q in pts])
            row[name] = (
                float(np.exp(np.interp(np.log(p["seconds_per_traj"]), t, e))) if len(pts) > 1 else None
            )
        rows.append(row)
    return rows


def orders(cfg: Config, log) -> list[dict]:
    """Fitted orders of RDP4 and RDP6 (both retractions) on random 2 s maneuvers of both models."""
    rows = []
    for model, system in SYSTEMS.items():
        data = maneuvers(system, 4, seed=5)
        ref = _reference_final(system, data, 2.0)
        for order in (4, 6):
            for retraction in ("exp", "cayley"):
                errs = []
                ns = cfg.order_steps if order == 6 else tuple(2 * n for n in cfg.order_steps)
                for n in ns:
                    q = rollout_fn(system, lj.RDP(order=order, retraction=retraction), n, 2.0)(*data)[:, -1]
                    errs.append(float(np.max(np.linalg.norm(np.asarray(q)[:, :3] - ref[:, :3], axis=-1))))
                p = float(np.polyfit(np.log([2.0 / n for n in ns]), np.log(errs), 1)[0])
                rows.append(
                    dict(
                        model=model, order=order, retraction=retraction, steps=list(ns), errors=errs, fitted=p
                    )
                )
                errs_s = [f"{e:.1e}" for e in errs]
                log(f"  {model} RDP{order} {retraction}: errors {errs_s}, order {p:.2f}")
    return rows


def energy(cfg: Config, log) -> list[dict]:
    """Largest |E - E0| over the first and the second half of long work-free runs, with node
    velocities from the carried momenta. Car: no wheel torque, sinusoidal steering (steering does no
    work), h = 0.3 s. Snakeboard: no rotor torque and the matched steering torque
    ``f_phi = -2 J b w^2 sin(w t + p)`` with ``phi = b sin(w t + p)``, whose work is ``J phidot^2``
    exactly, so ``E - J phidot^2`` is the conserved quantity reported; h = 0.05 s."""
    rows = []
    car, sb = SYSTEMS["car"], SYSTEMS["snakeboard"]
    q_car = jnp.array([0.0, 0.0, 0.1, 0.0, 0.0])
    b, w, p = 0.3, 1.0, 0.4
    q_sb = jnp.array([0.0, 0.0, 0.3, 0.0, b * np.sin(p)])
    cases = {
        "car": (
            car,
            q_car,
            car.qdot_from_velocities(q_car, jnp.array([3.0]), jnp.zeros(2)),
            lj.Sinusoids([[0.0], [0.6]], [[1.0], [1.5]], [[0.0], [0.0]]),
            0.3,
            lambda traj: traj.energy,
        ),
        "snakeboard": (
            sb,
            q_sb,
            sb.qdot_from_velocities(q_sb, jnp.array([1.0, b * w * np.cos(p), 0.4]), jnp.zeros(2)),
            lj.Sinusoids([[0.0], [-2 * float(sb.J) * b * w**2]], [[1.0], [w]], [[0.0], [p]]),
            0.05,
            lambda traj: traj.energy - sb.J * traj.qdot[:, 4] ** 2,
        ),
    }
    n = cfg.energy_steps
    for model, (system, q0, qdot0, ctl, h, conserved) in cases.items():
        for name in ("RDP2", "RDP4", "RDP6", "RK4"):
            traj = lj.simulate(
                system, q0, qdot0, ctl, t_final=n * h, n_steps=n, integrator=INTEGRATORS[name](), save=100
            )
            c = np.asarray(conserved(traj))
            e = np.abs(c - c[0])
            row = dict(
                model=model,
                integrator=name,
                h=h,
                steps=n,
                first_half=float(e[: e.size // 2].max()),
                second_half=float(e[e.size // 2 :].max()),
                failed=bool(traj.failed),
            )
            rows.append(row)
            log(f"  {model} {name}: max |dE| {row['first_half']:.2e} / {row['second_half']:.2e}")
    return rows


def gradients(cfg: Config, log) -> list[dict]:
    """Gradient / forward of a terminal cost, and the gradient's memory per checkpoint policy."""
    system = SYSTEMS["snakeboard"]
    b, n = cfg.grad_batch, cfg.steps
    q0, qdot0, ctl = maneuvers(system, b)
    fwd = jax.jit(lambda c: _terminal_loss(system, q0, qdot0, c, n, False))
    st_f = timeit(fwd, ctl, repeats=cfg.repeats)
    rows = []
    for ck in (False, "step", "sqrt"):
        g = jax.jit(jax.grad(lambda c, ck=ck: _terminal_loss(system, q0, qdot0, c, n, ck)))
        st_g = timeit(g, ctl, repeats=cfg.repeats)
        mem = {}
        c0 = jax.tree_util.tree_map(lambda x: x[0], ctl)
        for nn in (cfg.mem_steps // 10, cfg.mem_steps):

            def loss1(c, nn=nn, ck=ck):
                q = lj.simulate(
                    system,
                    q0[0],
                    qdot0[0],
                    c,
                    t_final=10.0,
                    n_steps=nn,
                    check_constraints=False,
                    checkpoint=ck,
                    save="final",
                    diagnostics=False,
                ).q
                return jnp.sum(q[-1, :2] ** 2)

            ma = jax.jit(jax.grad(loss1)).lower(c0).compile().memory_analysis()
            mem[nn] = int(ma.temp_size_in_bytes) if ma else None
        row = dict(
            checkpoint=ck,
            B=b,
            N=n,
            forward_s=st_f["min"],
            grad_s=st_g["min"],
            ratio=st_g["min"] / st_f["min"],
            temp_bytes=mem,
        )
        rows.append(row)
        log(f"  checkpoint={ck}: grad/forward {row['ratio']:.2f}, temp memory {mem}")
    return rows


def memory(cfg: Config, log) -> list[dict]:
    """Memory of a batched rollout by save policy (XLA's memory analysis of the compiled program)."""
    system = SYSTEMS["snakeboard"]
    b, n = cfg.memory_batch, cfg.memory_steps
    data = maneuvers(system, b)
    rows = []
    for save, diag in (("all", True), ("all", False), (n // 40, False), ("final", True), ("final", False)):
        fn = rollout_fn(system, lj.RDP(), n, save=save, diagnostics=diag)
        ma = fn.lower(*data).compile().memory_analysis()
        row = dict(
            save=str(save),
            diagnostics=diag,
            B=b,
            N=n,
            output_bytes=int(ma.output_size_in_bytes),
            temp_bytes=int(ma.temp_size_in_bytes),
        )
        rows.append(row)
        log(
            f"  save={save}, diagnostics={diag}: output {row['output_bytes'] / 1e6:.1f} MB, "
            f"temp {row['temp_bytes'] / 1e6:.1f} MB"
        )
    return rows


def compile_times(cfg: Config, log) -> list[dict]:
    """Compile time of a batched ``simulate`` (snakeboard, N = 1000, diagnostics on) with XLA's
    defaults and with ``lj.compiler_options()`` (the options the library's own entry points use),
    and the run time of each compiled program: what the shorter compilation costs at run time
    (RDP up to about 1.16x, RK4 none, on the machine of docs/results/bench.md)."""
    rows = []
    system = SYSTEMS["snakeboard"]
    data = maneuvers(system, 16)
    for name in ("RDP2", "RDP6", "RK4"):
        for label, options in (("XLA defaults", None), ("lj.compiler_options()", lj.compiler_options())):
            fn = jax.jit(
                jax.vmap(
                    lambda a, b, c, name=name: (
                        lj.simulate(
                            system,
                            a,
                            b,
                            c,
                            t_final=10.0,
                            n_steps=1000,
                            integrator=INTEGRATORS[name](),
                            check_constraints=False,
                        ).q
                    )
                ),
                compiler_options=options,
            )
            t = time.perf_counter()
            compiled = fn.lower(*data).compile()
            compile_s = time.perf_counter() - t
            run = timeit(compiled, *data, repeats=cfg.repeats)
            rows.append(dict(integrator=name, options=label, compile_s=compile_s, run_s=run["min"]))
            log(f"  {name}, {label}: compile {compile_s:.2f} s, run {run['min'] * 1e3:.1f} ms (16 x 1000)")
    return rows


# A new interpreter (no persistent compilation cache) times the first calls a user makes; each
# entry: wall seconds and the number of XLA programs compiled during the call.
_FIRST_CALLS = r"""
import json, sys, time
import jax
jax.config.update("jax_enable_x64", True)
from jax._src import monitoring
import ldap_jax as lj
from ldap_jax import control as lc

count = [0]
monitoring.register_event_duration_secs_listener(
    lambda event, duration, **kw: count.__setitem__(0, count[0] + event.endswith("backend_compile_duration"))
)
out = {}


def timed(name, fn):
    count[0] = 0
    t = time.perf_counter()
    value = jax.block_until_ready(fn())
    out[name] = [time.perf_counter() - t, count[0]]
    return value


car = lj.Car()
q0, qdot0, ctl = timed("car.sample_maneuver", lambda: car.sample_maneuver(jax.random.PRNGKey(0)))
traj = timed(
    "simulate (car, RDP, N = 100)", lambda: lj.simulate(car, q0, qdot0, ctl, t_final=10.0, n_steps=100)
)
timed("reference (the same nodes)", lambda: lj.reference(car, q0, qdot0, ctl, traj.t).q)
task = timed("lc.parallel_park(n_steps=40)", lambda: lc.parallel_park(n_steps=40))
sol = timed("lc.solve", lambda: lc.solve(task))
timed("lc.replay", lambda: lc.replay(task, sol.params)["q_ref"])
dyn = lj.discretize(car, lj.RDP(order=4), h=0.1)
u0, u1, u2 = jax.block_until_ready([ctl(0.0), ctl(0.1), ctl(0.2)])
x0 = timed("dyn.init (RDP order 4)", lambda: dyn.init(q0, qdot0, u0))
timed("dyn.step", lambda: dyn.step(x0, u0, u1))
timed("dyn.step, new values", lambda: dyn.step(x0, u1, u2, 1))
timed("jax.jacfwd(dyn.step)", lambda: jax.jacfwd(dyn.step)(x0, u0, u1))
print("FIRST_CALLS " + json.dumps(out))
"""


def first_calls(cfg: Config, log) -> list[dict]:
    """First calls in one new process (no persistent compilation cache; a first call happens once,
    so it is not repeated): wall time and the number of programs XLA compiled for each (work run op
    by op would compile one program per operation)."""
    import subprocess
    import sys

    env = {
        k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT"))
    }
    proc = subprocess.run(
        [sys.executable, "-c", _FIRST_CALLS], env=env, capture_output=True, text=True, timeout=1200
    )
    line = [x for x in proc.stdout.splitlines() if x.startswith("FIRST_CALLS ")]
    if proc.returncode != 0 or not line:
        raise RuntimeError(f"first-call child process failed:\n{proc.stderr[-3000:]}")
    rows = []
    for name, (seconds, programs) in json.loads(line[0][len("FIRST_CALLS ") :]).items():
        rows.append(dict(call=name, seconds=seconds, programs=programs))
        log(f"  {name}: {seconds:.2f} s, {programs} programs compiled")
    return rows


def general_step(cfg: Config, log) -> list[dict]:
    """Cost of RDP's general implicit step relative to the closed form (snakeboard, batched)."""
    sb = SYSTEMS["snakeboard"]
    b, n = (100, 200) if cfg.quick else (1000, 1000)
    data = maneuvers(sb, b)
    user = lj.System(
        2,
        lambda p, r, u, xi: lj.Snakeboard(**p).reduced_lagrangian(r, u, xi),
        lambda p, r: lj.Snakeboard(**p).connection(r),
        lambda p, r: lj.Snakeboard(**p).symmetry_basis(r),
        params=dict(m=sb.m, l=sb.l, I=sb.I, J=sb.J),
        singularity=lambda p, r: jnp.cos(r[1]),
    )
    cases = [
        ("closed-form kernel", sb, lj.RDP()),
        ("general Newton step (dtau_order=1)", sb, lj.RDP(solver="newton")),
        ("general Newton step, exact dexp^-1", sb, lj.RDP(dtau_order=None)),
        ("lj.System description", user, lj.RDP()),
    ]
    rows = []
    for label, system, integrator in cases:
        st = timeit(rollout_fn(system, integrator, n), *data, repeats=cfg.repeats)
        rows.append(dict(case=label, B=b, N=n, wall_min=st["min"]))
        log(f"  {label}: {st['min']:.3f} s")
    for r in rows:
        r["ratio_to_kernel"] = r["wall_min"] / rows[0]["wall_min"]
    return rows


# ------------------------------------------------------------------------------------ output
def _fmt(x, spec=".2e"):
    return "n/a" if x is None else format(x, spec)


def _section(title: str, intro: list[str], columns: tuple[str, ...], rows: list[tuple]) -> list[str]:
    """A markdown section: heading, optional intro lines, and a table of ``rows`` (cells as text)."""
    lines = ["", f"## {title}", ""] + (intro + [""] if intro else [])
    lines += ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    return lines + ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]


def write_markdown(path, res):
    L = [
        "# ldap_jax benchmarks",
        "",
        f"Machine: {res['machine']}. Timings: min of repeats after compilation (wall).",
        "",
    ]
    L += [
        "## Headline (snakeboard, RDP order 2, float64)",
        "",
        "| layout | B x N | steps/s (positions) | steps/s (trajectory + diagnostics) | gradient / forward |",
        "|---|---|---|---|---|",
    ]
    L += [
        f"| {r['layout']} | {r['B']} x {r['N']} | {r['steps_per_s_q']:.3g} | {r['steps_per_s_traj']:.3g} "
        f"| {r['grad_ratio']:.2f} |"
        for r in res.get("headline", [])
    ]
    if res.get("compiled_c"):
        L += [
            "",
            "## Against compiled C (same step, same maneuvers; positions only)",
            "",
            "C: `-O3 -march=native`, no fast-math. ns/step: wall (min of repeats); CPU: the thread's CPU "
            "time (one thread).",
            "",
            "| C variant | threads | ns/step | CPU ns/step | steps/s | max abs diff vs ours "
            "| ours (best) / C, throughput |",
            "|---|---|---|---|---|---|---|",
        ]
        L += [
            f"| {r['variant']} | {r['threads']} | {r['ns_per_step']:.1f} "
            f"| {_fmt(r['cpu_ns_per_step'], '.1f')} | {r['steps_per_s']:.3g} "
            f"| {r['max_abs_diff_vs_ours']:.1e} | {_fmt(r['ours_best_over_c'], '.2f')} |"
            for r in res["compiled_c"]
        ]
    if res.get("ours_over_c"):
        L += [
            "",
            "## Ours / C, positions only (time per composed step; C = substeps x its order-2 step)",
            "",
            "Ours and C in alternating rounds; times: medians over the rounds; ratios: median over the "
            "rounds of each round's ratio. CPU: the process's CPU time (C on one thread: the thread's).",
            "",
            "| order | layout | compiled with | ns/step | C ns/step | ours / C | CPU: ours / C |",
            "|---|---|---|---|---|---|---|",
        ]
        L += [
            f"| {r['order']} | {r['layout']} | {r['compile']} | {r['ns_per_step']:.1f} | "
            f"{r['c_ns_per_step']:.1f} | {r['ours_over_c']:.2f} | {r['ours_over_c_cpu']:.2f} |"
            for r in res["ours_over_c"]
        ]
    if res.get("default_call"):
        L += [
            "",
            "## The default call against positions only, a gradient against its forward "
            "(snakeboard, RDP order 2, one device, plain jit)",
            "",
            "Alternating rounds; ns/step: median over the rounds; ratios: median over the rounds of each "
            "round's ratio.",
            "",
            "| call | B x N | ns/step | against | ratio (wall) | ratio (CPU) | page faults per call |",
            "|---|---|---|---|---|---|---|",
        ]
        L += [
            f"| {r['call']} | {r['B']} x {r['N']} | {r['ns_per_step']:.1f} | {r['over']} | {r['ratio']:.2f} "
            f"| {r['ratio_cpu']:.2f} | {r['page_faults']:.0f} |"
            for r in res["default_call"]
        ]
    L += _section(
        "Forward throughput (positions only, batched)",
        [],
        ("model", "integrator", "B x N", "steps/s"),
        [
            (r["model"], r["integrator"], f"{r['B']} x {r['N']}", f"{r['steps_per_s']:.3g}")
            for r in res.get("throughput", [])
        ],
    )
    for wp in (w for key in ("wp_10s", "wp_600s") for w in res.get(key, {}).values()):
        levels = list(next(iter(wp["cost"].values())))
        L += [
            "",
            f"## Work-precision, {wp['model']}, {wp['t_final']:g} s (mean final position error, batched)",
            "",
            "Seconds per trajectory to reach each error level (n/a: not reached):",
            "",
            "| method | " + " | ".join(f"{lvl} m" for lvl in levels) + " |",
            "|---" * (len(levels) + 1) + "|",
        ]
        L += [
            f"| {name} | " + " | ".join(_fmt(c[lvl]) for lvl in levels) + " |"
            for name, c in wp["cost"].items()
        ]
        L += [
            "",
            "Cost relative to RK4:",
            "",
            "| method | " + " | ".join(f"{lvl} m" for lvl in levels) + " |",
            "|---" * (len(levels) + 1) + "|",
        ]
        L += [
            f"| {name} | " + " | ".join(_fmt(r[lvl], ".2f") for lvl in levels) + " |"
            for name, r in wp["ratio_to_rk4"].items()
        ]
        if "equal_cost" in wp:
            L += [
                "",
                "At RK4's cost (RK4 points below 1 m): error of each method at the same seconds "
                "per trajectory",
                "",
                "| RK4 N | seconds/traj | RK4 | RDP2 | RDP4 | RDP6 |",
                "|---|---|---|---|---|---|",
            ]
            L += [
                f"| {r['n_steps_rk4']} | {r['seconds']:.2e} | {r['rk4_error']:.2e} | {_fmt(r['RDP2'])} "
                f"| {_fmt(r['RDP4'])} | {_fmt(r['RDP6'])} |"
                for r in wp["equal_cost"]
            ]
    L += [
        "",
        "![work-precision](work_precision.png)",
        "",
        "## Orders (2 s random maneuvers, vs lj.reference)",
        "",
        "| model | order | retraction | errors | fitted order |",
        "|---|---|---|---|---|",
    ]
    L += [
        f"| {r['model']} | {r['order']} | {r['retraction']} | {', '.join(f'{e:.1e}' for e in r['errors'])} "
        f"| {r['fitted']:.2f} |"
        for r in res.get("orders", [])
    ]
    L += [
        "",
        "## Energy over long work-free runs (velocities from the momenta; snakeboard: E - J phidot^2)",
        "",
        "| model | integrator | h [s] | steps | max abs(dE), first half | second half |",
        "|---|---|---|---|---|---|",
    ]
    L += [
        f"| {r['model']} | {r['integrator']} | {r['h']} | {r['steps']} "
        f"| {r['first_half']:.2e} | {r['second_half']:.2e} |"
        for r in res.get("energy", [])
    ]
    L += [
        "",
        "## Gradient cost (snakeboard, terminal cost)",
        "",
        "| checkpoint | B x N | forward (s) | gradient (s) | ratio | temp memory N/10 -> N (bytes) |",
        "|---|---|---|---|---|---|",
    ]
    L += [
        f"| {r['checkpoint']} | {r['B']} x {r['N']} | {r['forward_s']:.3f} | {r['grad_s']:.3f} "
        f"| {r['ratio']:.2f} "
        f"| {' -> '.join(str(v) for v in r['temp_bytes'].values())} |"
        for r in res.get("gradients", [])
    ]
    L += [
        "",
        "## Memory by save policy (snakeboard, RDP)",
        "",
        "| save | diagnostics | B x N | output (MB) | temp (MB) |",
        "|---|---|---|---|---|",
    ]
    L += [
        f"| {r['save']} | {r['diagnostics']} | {r['B']} x {r['N']} "
        f"| {r['output_bytes'] / 1e6:.2f} | {r['temp_bytes'] / 1e6:.2f} |"
        for r in res.get("memory", [])
    ]
    L += [
        "",
        "## General implicit RDP step vs the closed-form kernel",
        "",
        "| case | B x N | wall (s) | ratio |",
        "|---|---|---|---|",
    ]
    L += [
        f"| {r['case']} | {r['B']} x {r['N']} | {r['wall_min']:.3f} | {r['ratio_to_kernel']:.1f} |"
        for r in res.get("general_step", [])
    ]
    L += _section(
        "Compile times",
        [
            "Batched `simulate` (snakeboard, 16 maneuvers x 1000 steps, diagnostics on), compiled with XLA's",
            "defaults and with `lj.compiler_options()`; run = fastest of the timed calls.",
        ],
        ("integrator", "options", "compile (s)", "run (ms)"),
        [
            (r["integrator"], r["options"], f"{r['compile_s']:.2f}", f"{r['run_s'] * 1e3:.1f}")
            for r in res.get("compile", [])
        ],
    )
    L += _section(
        "First calls in a new process",
        [
            "Each call timed once in a fresh interpreter (no persistent compilation cache), with the number",
            "of programs XLA compiled during it (the rollout or solver itself, plus anything run op by op).",
        ],
        ("call", "wall (s)", "programs compiled"),
        [(r["call"], f"{r['seconds']:.2f}", r["programs"]) for r in res.get("first_calls", [])],
    )
    missing = [s for s in SECTIONS if s not in res]
    if missing:
        L += ["", f"(Sections not run: {', '.join(missing)}.)"]
    with open(path, "w") as f:
        f.write("\n".join(L) + "\n")


def plot(path, res):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ldap_jax.plotting import plot_work_precision

    wps = [w for key in ("wp_10s", "wp_600s") for w in res.get(key, {}).values()]
    if not wps:
        return
    rows = 2 if len(wps) > 2 else 1
    cols = -(-len(wps) // rows)
    fig, axes = plt.subplots(rows, cols, figsize=(6.5 * cols, 4.8 * rows), squeeze=False)
    for ax, wp in zip(axes.ravel(), wps):
        curves = {
            name: [(p["seconds_per_traj"], p["error"]) for p in pts] for name, pts in wp["curves"].items()
        }
        plot_work_precision(
            curves,
            ax=ax,
            title=f"{wp['model']}, {wp['t_final']:g} s, {res['config']['wp_maneuvers']} maneuvers",
        )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


SECTIONS = (
    "headline",
    "compiled_c",
    "ours_over_c",
    "default_call",
    "throughput",
    "wp_10s",
    "wp_600s",
    "orders",
    "energy",
    "gradients",
    "memory",
    "general_step",
    "compile",
    "first_calls",
)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="small sizes (a few minutes)")
    p.add_argument("--out", default="results", help="output directory (default: results)")
    p.add_argument("--repeats", type=int, default=None, help="timed repeats (default: 5, quick 2)")
    p.add_argument(
        "--rounds", type=int, default=None, help="paired rounds of the ratio sections (default: 30, quick 5)"
    )
    p.add_argument("--only", default=None, help=f"comma-separated sections among {', '.join(SECTIONS)}")
    # the pinned process of ours_over_c (_one_core): writes its rows to the given file
    p.add_argument("--one-core", default=None, help=argparse.SUPPRESS)
    # the process of default_call that keeps freed memory (_kept_memory): writes its rows there
    p.add_argument("--kept-memory", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.repeats is not None and args.repeats < 1:
        p.error("--repeats must be a positive integer")
    if args.rounds is not None and args.rounds < 1:
        p.error("--rounds must be a positive integer")
    only = SECTIONS if args.only is None else tuple(s.strip() for s in args.only.split(","))
    bad = [s for s in only if s not in SECTIONS]
    if bad:
        p.error(f"--only: unknown sections {bad}; choose among {', '.join(SECTIONS)}")
    # a process of its own that a section started (_child_rows): its rows, written to the file given
    for path, section in (
        (args.one_core, functools.partial(ours_over_c, one_core=True)),
        (args.kept_memory, functools.partial(default_call, kept=True)),
    ):
        if path is not None:
            cfg = Config.for_run(args.quick, args.repeats, args.rounds)
            t0 = time.perf_counter()
            rows = section(cfg, lambda msg: print(f"[{time.perf_counter() - t0:7.1f}s] {msg}", flush=True))
            with open(path, "w") as f:
                json.dump(rows, f)
            return 0
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        p.error(f"--out {args.out} exists and is not a directory")
    os.makedirs(args.out, exist_ok=True)
    cfg = Config.for_run(args.quick, args.repeats, args.rounds)
    t0 = time.perf_counter()

    def log(msg):
        print(f"[{time.perf_counter() - t0:7.1f}s] {msg}", flush=True)

    res = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"jax {jax.__version__}, "
        f"{jax.devices()[0].platform}",
        "config": dataclasses.asdict(cfg),
    }
    runs = {
        "headline": lambda: headline(cfg, log),
        "compiled_c": lambda: compiled_c(cfg, res.get("headline", []), log),
        "ours_over_c": lambda: ours_over_c(cfg, log),
        "default_call": lambda: default_call(cfg, log),
        "throughput": lambda: throughput(cfg, log),
        "wp_10s": lambda: work_precision(cfg, 10.0, cfg.wp_steps_10s, log),
        "wp_600s": lambda: work_precision(cfg, 600.0, cfg.wp_steps_600s, log),
        "orders": lambda: orders(cfg, log),
        "energy": lambda: energy(cfg, log),
        "gradients": lambda: gradients(cfg, log),
        "memory": lambda: memory(cfg, log),
        "general_step": lambda: general_step(cfg, log),
        "compile": lambda: compile_times(cfg, log),
        "first_calls": lambda: first_calls(cfg, log),
    }
    for name in SECTIONS:
        if name in only:
            log(name)
            res[name] = runs[name]()
            lj.trim_compilation_cache()
    res["total_seconds"] = time.perf_counter() - t0
    with open(os.path.join(args.out, "bench.json"), "w") as f:
        json.dump(res, f, indent=1, default=str)
    write_markdown(os.path.join(args.out, "bench.md"), res)
    plot(os.path.join(args.out, "work_precision.png"), res)
    log(
        f"wrote {args.out}/bench.json, bench.md"
        + (", work_precision.png" if "wp_10s" in res or "wp_600s" in res else "")
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
