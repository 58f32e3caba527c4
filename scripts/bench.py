"""Benchmarks: throughput, diffrax peers, work-precision, gradient cost, memory, compile time.

Writes ``OUT/bench.json``, ``OUT/bench.md`` and ``OUT/work_precision.png``. Every timing is the
median/min/max of several repeats after compilation (wall clock; the process CPU time is
recorded too: on a shared machine it is the better estimate of the work). ``--quick`` runs in
under 3 minutes on 2 cores; the full run uses the sizes of the targets (B = 1000, N = 1000
everywhere, denser sweeps).

    python scripts/bench.py --quick --out results
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

# One XLA host device per core, so the headline is also measured with the batch sharded across
# cores (one program per core, as ``ldap_jax.sweeps`` runs the study), next to the default single
# device (whose loop fusions XLA splits over its intra-op thread pool, with a barrier per fusion).
# Set before jax is imported; everything else here runs on the first device as usual.
if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={os.cpu_count() or 1}"
    )

import jax

jax.config.update("jax_enable_x64", True)

import diffrax
import jax.numpy as jnp
import numpy as np

import ldap_jax as lj
from ldap_jax import sweeps

SYSTEMS = {
    "car": lj.Car(m=1.0, I=0.1, K=0.2, rho=0.1, l=0.5),
    "snakeboard": lj.Snakeboard(m=1.0, l=0.5, I=0.05, J=0.02),
}


def integrators():
    out = {
        "RDP(exp)": lj.RDP(alpha=0.5, retraction="exp"),
        "RDP(cayley)": lj.RDP(alpha=0.5, retraction="cayley"),
        "RK2": lj.RK2(),
        "RK4": lj.RK4(),
    }
    for name in ("DLA", "GNI"):  # added by other developers; picked up when present
        if hasattr(lj, name):
            out[name] = getattr(lj, name)()
    return out


def maneuvers(system, n, seed=0, dtype=jnp.float64):
    keys = jax.random.split(jax.random.PRNGKey(seed), n)
    q0, qdot0, ctl = jax.vmap(system.sample_maneuver)(keys)
    cast = lambda x: x.astype(dtype)  # noqa: E731
    return cast(q0), cast(qdot0), jax.tree_util.tree_map(cast, ctl)


def timeit(fn, *args, repeats=3):
    """Compile (first call), then ``repeats`` timed calls: dict of wall/cpu statistics."""
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
        "median": float(np.median(wall)),
        "min": float(np.min(wall)),
        "max": float(np.max(wall)),
        "cpu_min": float(np.min(cpu)),
        "first_call": first,
    }


def rollout_fn(system, integrator, n_steps, t_final=10.0, fast_path=True, what="q"):
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
            fast_path=fast_path,
        )
        return traj if what == "traj" else traj.q

    return jax.jit(jax.vmap(one))


# ------------------------------------------------------------------ diffrax peers
class _RK4(diffrax.AbstractERK):
    """Classical RK4 as a diffrax ERK (diffrax ships no plain RK4; no error estimate)."""

    tableau = diffrax.ButcherTableau(
        c=np.array([0.5, 0.5, 1.0]),
        b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
        b_error=np.zeros(4),
        a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])),
    )
    interpolation_cls = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

    def order(self, terms):
        return 4


def diffrax_fn(system, solver, t_final=10.0, n_steps=None, rtol=None, max_steps=100_000):
    def one(q0, qdot0, ctl):
        v0 = system.velocities_from_qdot(q0, qdot0)
        term = diffrax.ODETerm(lambda t, y, args: system.ode(y, ctl(t)))
        if n_steps is not None:
            ctrl, dt0 = diffrax.ConstantStepSize(), t_final / n_steps
        else:
            ctrl, dt0 = diffrax.PIDController(rtol=rtol, atol=rtol), None
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


# ------------------------------------------------------------------ sections
def throughput(args, log):
    rows = []
    b_sizes = [(args.batch, args.steps, "batched"), (1, args.steps, "single")]
    for model, system in SYSTEMS.items():
        for dtype in (jnp.float64, jnp.float32):
            for name, integ in integrators().items():
                for b, n, mode in b_sizes:
                    # quick: every integrator on the snakeboard in float64 batched; RDP elsewhere
                    headline = model == "snakeboard" and dtype == jnp.float64 and mode == "batched"
                    if args.quick and not (headline or name == "RDP(exp)"):
                        continue
                    data = maneuvers(system, b, dtype=dtype)
                    st = timeit(rollout_fn(system, integ, n, what="traj"), *data, repeats=args.repeats)
                    row = dict(model=model, integrator=name, dtype=jnp.dtype(dtype).name, mode=mode, B=b, N=n)
                    row.update(
                        st, steps_per_s=b * n / st["min"], steps_per_s_cpu=b * n / max(st["cpu_min"], 1e-9)
                    )
                    rows.append(row)
                    log(
                        f"  {model:10s} {row['dtype']:7s} {name:12s} {mode:7s} "
                        f"{row['steps_per_s']:.3g} steps/s"
                    )
    # the general path of RDP, for the speed-up of the fast path
    system = SYSTEMS["snakeboard"]
    data = maneuvers(system, args.batch)
    st = timeit(
        rollout_fn(system, lj.RDP(), args.steps, fast_path=False, what="traj"), *data, repeats=args.repeats
    )
    row = dict(model="snakeboard", integrator="RDP(exp) general path", dtype="float64", mode="batched")
    row.update(B=args.batch, N=args.steps, **st, steps_per_s=args.batch * args.steps / st["min"])
    row["steps_per_s_cpu"] = args.batch * args.steps / max(st["cpu_min"], 1e-9)
    rows.append(row)
    log(f"  snakeboard general-path RDP {row['steps_per_s']:.3g} steps/s")
    return rows


def headline(args, log):
    """The target configuration (snakeboard, RDP, float64, B x N = 1000 x 1000): forward
    throughput (positions only, and the whole trajectory with its diagnostics) and the cost of
    a gradient of a terminal cost, on one device and with the batch sharded over every device."""
    system = SYSTEMS["snakeboard"]
    b, n = args.batch, args.steps
    data = maneuvers(system, b)
    layouts = [("1 device", data)]
    if jax.device_count() > 1:
        layouts.append(
            (f"sharded over {jax.device_count()} devices", sweeps.shard_batch(data, sweeps.device_mesh())[0])
        )
    rows = []
    for layout, (q0, qdot0, ctl) in layouts:
        row = dict(layout=layout, B=b, N=n)
        for what in ("q", "traj"):
            st = timeit(rollout_fn(system, lj.RDP(), n, what=what), q0, qdot0, ctl, repeats=args.repeats)
            row[f"steps_per_s_{what}"] = b * n / st["min"]
        fwd = jax.jit(lambda c, q0=q0, qdot0=qdot0: _terminal_loss(system, q0, qdot0, c, n, False))
        grad = jax.jit(jax.grad(lambda c, q0=q0, qdot0=qdot0: _terminal_loss(system, q0, qdot0, c, n, False)))
        st_f = timeit(fwd, ctl, repeats=args.repeats)
        st_g = timeit(grad, ctl, repeats=args.repeats)
        row.update(forward_s=st_f["min"], grad_s=st_g["min"], grad_ratio=st_g["min"] / st_f["min"])
        rows.append(row)
        log(
            f"  {layout}: {row['steps_per_s_q']:.3g} steps/s (positions), {row['steps_per_s_traj']:.3g} "
            f"(trajectory), gradient/forward {row['grad_ratio']:.2f}"
        )
    return rows


C_SOURCE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "c", "rdp_snakeboard.c")


def compiled_c(args, headline_rows, log):
    """The same snakeboard RDP rollout (alpha = 1/2, exp, positions only) in C, compiled here with
    ``cc -O3 -march=native -ffast-math -fopenmp``: a scalar loop per trajectory and a loop
    vectorised across trajectories, on one thread and on every core (OpenMP). Same maneuvers
    and initial momenta as ours; the positions must agree with ``lj.simulate`` to round-off.
    Returns rows, or [] when no C compiler is found."""
    import ctypes
    import shutil
    import subprocess
    import tempfile

    cc = shutil.which(os.environ.get("CC", "cc")) or shutil.which("gcc")
    if cc is None:
        log("  no C compiler: skipped")
        return []
    lib_path = os.path.join(tempfile.mkdtemp(prefix="ldap_jax_bench_"), "librdp.so")
    flags = ["-O3", "-march=native", "-ffast-math", "-fopenmp", "-shared", "-fPIC"]
    subprocess.run([cc, *flags, C_SOURCE, "-o", lib_path, "-lm"], check=True)
    lib = ctypes.CDLL(lib_path)
    system = SYSTEMS["snakeboard"]
    b, n, t_final = args.batch, args.steps, 10.0
    h = t_final / n
    q0, qdot0, ctl = maneuvers(system, b)
    st = jax.vmap(lambda a, v: lj.RDP().init(system, jnp.asarray(h), a, v, None))(q0, qdot0)
    init = np.stack(
        [
            q0[:, 2],
            q0[:, 0],
            q0[:, 1],
            q0[:, 3],
            q0[:, 4],
            st.pu[:, 0],
            st.pu[:, 1],
            st.mu[:, 0],
            st.mu[:, 1],
        ],
        1,
    )
    init = np.ascontiguousarray(init, np.float64)
    ctl_np = np.ascontiguousarray(np.stack([ctl.amplitude, ctl.frequency, ctl.phase], 1), np.float64)
    q = np.zeros((b, n + 1, 5))
    ptr = ctypes.POINTER(ctypes.c_double)
    dbl = ctypes.c_double
    call_args = (
        ctypes.c_int(b),
        ctypes.c_int(n),
        ctypes.c_int(ctl_np.shape[-1]),
        dbl(h),
        *(dbl(float(getattr(system, k))) for k in ("m", "l", "I", "J")),
        init.ctypes.data_as(ptr),
        ctl_np.ctypes.data_as(ptr),
        q.ctypes.data_as(ptr),
    )
    ours = np.asarray(rollout_fn(system, lj.RDP(), n, t_final=t_final)(q0, qdot0, ctl))
    best_ours = max(r["steps_per_s_q"] for r in headline_rows) if headline_rows else None
    rows = []
    for fn, label in (
        ("rollout", "scalar loop per trajectory"),
        ("rollout_simd", "vectorised across trajectories"),
    ):
        for threads in sorted({1, os.cpu_count() or 1}):
            lib.set_threads(threads)
            f = getattr(lib, fn)
            f(*call_args)
            diff = float(np.max(np.abs(q - ours)))
            wall = []
            for _ in range(args.repeats):
                t = time.perf_counter()
                f(*call_args)
                wall.append(time.perf_counter() - t)
            row = dict(
                variant=label,
                threads=threads,
                B=b,
                N=n,
                wall_min=min(wall),
                steps_per_s=b * n / min(wall),
                max_abs_diff_vs_ours=diff,
            )
            row["ours_best_over_c"] = best_ours / row["steps_per_s"] if best_ours else None
            rows.append(row)
            log(
                f"  C {label}, {threads} thread(s): {row['steps_per_s']:.3g} steps/s "
                f"(|q - ours| <= {diff:.1e})"
            )
    return rows


def _terminal_loss(system, q0, qdot0, ctl, n, checkpoint):
    """Sum over the batch of ``|(x_N, y_N)|^2``: the loss whose gradient is timed."""

    def one(a, b, c):
        q = lj.simulate(
            system, a, b, c, t_final=10.0, n_steps=n, check_constraints=False, checkpoint=checkpoint
        ).q
        return jnp.sum(q[-1, :2] ** 2)

    return jnp.sum(jax.vmap(one)(q0, qdot0, ctl))


def peers(args, log):
    system = SYSTEMS["snakeboard"]
    b, n = args.batch, args.steps
    data = maneuvers(system, b)
    out = []
    ours = timeit(rollout_fn(system, lj.RDP(), n), *data, repeats=args.repeats)
    for name, fn in (
        ("diffrax Tsit5 (PID, rtol=atol=1e-6)", diffrax_fn(system, diffrax.Tsit5(), rtol=1e-6)),
        (f"diffrax RK4 (constant step, N={n})", diffrax_fn(system, _RK4(), n_steps=n)),
    ):
        st = timeit(fn, *data, repeats=args.repeats)
        steps = int(np.mean(np.asarray(fn(*data)[1])))
        out.append(
            dict(
                peer=name,
                B=b,
                wall_min=st["min"],
                steps=steps,
                rdp_wall_min=ours["min"],
                ratio_ours_over_peer=ours["min"] / st["min"],
            )
        )
        log(f"  {name}: {st['min']:.3f} s vs RDP {ours['min']:.3f} s")
    return out


def work_precision(args, log):
    system = SYSTEMS["snakeboard"]
    m = args.wp_maneuvers
    q0, qdot0, ctl = maneuvers(system, m, seed=1)
    t_final = 10.0
    ref = jax.vmap(lambda a, b, c: lj.reference(system, a, b, c, jnp.array([0.0, t_final])).q[-1])(
        q0, qdot0, ctl
    )
    curves = {}

    def err(qf):
        return float(np.mean(np.linalg.norm(np.asarray(qf)[..., :2] - np.asarray(ref)[:, :2], axis=-1)))

    for name, integ in integrators().items():
        pts = []
        for n in args.wp_steps:
            fn = rollout_fn(system, integ, n)
            st = timeit(lambda *a, fn=fn: fn(*a)[:, -1], q0, qdot0, ctl, repeats=args.repeats)
            pts.append(dict(n_steps=n, error=err(fn(q0, qdot0, ctl)[:, -1]), seconds_per_traj=st["min"] / m))
        curves[name] = pts
        log(f"  {name}: " + ", ".join(f"N={p['n_steps']} err={p['error']:.1e}" for p in pts))
    for name, solver in (("diffrax Tsit5", diffrax.Tsit5()), ("diffrax Dopri8", diffrax.Dopri8())):
        pts = []
        for tol in args.wp_tols:
            fn = diffrax_fn(system, solver, rtol=tol)
            st = timeit(fn, q0, qdot0, ctl, repeats=args.repeats)
            qf, steps = fn(q0, qdot0, ctl)
            pts.append(
                dict(rtol=tol, steps=float(np.mean(steps)), error=err(qf), seconds_per_traj=st["min"] / m)
            )
        curves[name] = pts
        log(f"  {name}: " + ", ".join(f"tol={p['rtol']:.0e} err={p['error']:.1e}" for p in pts))
    costs = {
        name: {f"{lvl:.0e}": _cost_to_reach(pts, lvl) for lvl in (1e-3, 1e-6)} for name, pts in curves.items()
    }
    return curves, costs


def _cost_to_reach(pts, level):
    """Seconds per trajectory to reach ``level`` (log-log interpolation), None if not reached."""
    e = np.array([p["error"] for p in pts])
    t = np.array([p["seconds_per_traj"] for p in pts])
    order = np.argsort(t)
    e, t = e[order], t[order]
    for i in range(len(e)):
        if e[i] <= level:
            if i == 0:
                return float(t[0])
            x = (np.log(level) - np.log(e[i - 1])) / (np.log(e[i]) - np.log(e[i - 1]))
            return float(np.exp(np.log(t[i - 1]) + x * (np.log(t[i]) - np.log(t[i - 1]))))
    return None


def gradients(args, log):
    system = SYSTEMS["snakeboard"]
    b, n = args.grad_batch, args.steps
    q0, qdot0, ctl = maneuvers(system, b)
    rows = []
    fwd = jax.jit(lambda c: jnp.sum(rollout_fn(system, lj.RDP(), n)(q0, qdot0, c)[:, -1, :2] ** 2))
    st_f = timeit(fwd, ctl, repeats=args.repeats)
    for ck in (False, "step", "sqrt"):
        g = jax.jit(jax.grad(lambda c, ck=ck: _terminal_loss(system, q0, qdot0, c, n, ck)))
        st_g = timeit(g, ctl, repeats=args.repeats)
        mem = {}
        for nn in (args.mem_steps // 10, args.mem_steps):

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
                ).q
                return jnp.sum(q[-1, :2] ** 2)

            c0 = jax.tree_util.tree_map(lambda x: x[0], ctl)
            t = time.perf_counter()
            compiled = jax.jit(jax.grad(loss1)).lower(c0).compile()
            ctime = time.perf_counter() - t
            ma = compiled.memory_analysis()
            mem[nn] = dict(temp_bytes=int(ma.temp_size_in_bytes) if ma else None, compile_s=ctime)
        row = dict(
            checkpoint=ck,
            B=b,
            N=n,
            forward_s=st_f["min"],
            grad_s=st_g["min"],
            ratio=st_g["min"] / st_f["min"],
            grad_compile_first_call_s=st_g["first_call"],
            memory=mem,
        )
        rows.append(row)
        log(f"  checkpoint={ck}: grad/forward = {row['ratio']:.2f}, temp memory {mem}")
    return rows


def compile_times(log):
    out = {}
    system = SYSTEMS["snakeboard"]
    q0, qdot0, ctl = maneuvers(system, 1)
    for name, integ in (("RDP(exp)", lj.RDP()), ("RK4", lj.RK4())):
        for n in (1000,):
            fn = jax.jit(
                lambda a, b, c, integ=integ, n=n: lj.simulate(
                    system, a, b, c, t_final=10.0, n_steps=n, integrator=integ, check_constraints=False
                )
            )
            args0 = (q0[0], qdot0[0], jax.tree_util.tree_map(lambda x: x[0], ctl))
            t = time.perf_counter()
            fn.lower(*args0).compile()
            out[f"simulate {name} N={n}"] = time.perf_counter() - t
    log("  " + ", ".join(f"{k}: {v:.2f} s" for k, v in out.items()))
    return out


# ------------------------------------------------------------------ output
def user_snakeboard(sb):
    """The snakeboard as a user's ``lj.System``: the model's reduced description (l, A(r), e(r))
    handed to the public description, so every step goes through the general autodiff path."""
    p = dict(m=sb.m, l=sb.l, I=sb.I, J=sb.J)

    def model(p):
        return lj.Snakeboard(**p)

    return lj.System(
        2,
        lambda p, r, u, xi: model(p).reduced_lagrangian(r, u, xi),
        lambda p, r: model(p).connection(r),
        lambda p, r: model(p).symmetry_basis(r),
        params=p,
        singularity=lambda p, r: jnp.cos(r[1]),
    )


def general_step(args, log):
    """Cost of RDP's general implicit step relative to the closed form (snakeboard, same N, batched)."""
    sb = SYSTEMS["snakeboard"]
    b, n = (100, 200) if args.quick else (1000, 1000)
    man = maneuvers(sb, b)
    cases = [
        ("closed form, fast path", sb, lj.RDP(), True),
        ("closed form, general rollout", sb, lj.RDP(), False),
        ("general Newton step (dtau_order=1)", sb, lj.RDP(solver="newton"), False),
        ("general Newton step, exact dexp^-1", sb, lj.RDP(dtau_order=None), False),
        ("lj.System description, Newton", user_snakeboard(sb), lj.RDP(), False),
    ]
    rows = []
    for label, system, integrator, fast in cases:
        t = timeit(rollout_fn(system, integrator, n, fast_path=fast), *man, repeats=args.repeats)
        rows.append({"case": label, "B": b, "N": n, "wall_min": t["min"], "cpu_min": t["cpu_min"]})
        log(f"  general step: {label}: {t['min']:.3f} s")
    base = rows[0]["wall_min"]
    for r in rows:
        r["ratio_to_fast_closed_form"] = r["wall_min"] / base
    return rows


def write_markdown(path, res):
    lines = [
        "# ldap_jax benchmarks",
        "",
        f"Machine: {res['machine']}",
        "",
        "Timings: min of repeats after compilation (wall); `cpu` = process CPU time.",
        "",
    ]
    lines += [
        "## Headline (snakeboard, RDP, float64, B x N = 1000 x 1000)",
        "",
        "| layout | steps/s (positions) | steps/s (trajectory + diagnostics) | forward (s) | gradient (s) "
        "| gradient / forward |",
        "|---|---|---|---|---|---|",
    ]
    for r in res.get("headline", []):
        lines.append(
            f"| {r['layout']} | {r['steps_per_s_q']:.3g} | {r['steps_per_s_traj']:.3g} "
            f"| {r['forward_s']:.3f} | {r['grad_s']:.3f} | {r['grad_ratio']:.2f} |"
        )
    if res.get("compiled_c"):
        lines += [
            "",
            "## Against compiled C (snakeboard, RDP, float64, positions only, B x N = 1000 x 1000)",
            "",
            "The same step in C (`scripts/c/rdp_snakeboard.c`, `cc -O3 -march=native -ffast-math -fopenmp`), "
            "same maneuvers; ratio = our best headline rate (positions) / C's.",
            "",
            "| C variant | threads | steps/s | max abs diff of q vs ours | ours / C |",
            "|---|---|---|---|---|",
        ]
        for r in res["compiled_c"]:
            ratio = "n/a" if r["ours_best_over_c"] is None else f"{r['ours_best_over_c']:.2f}"
            lines.append(
                f"| {r['variant']} | {r['threads']} | {r['steps_per_s']:.3g} "
                f"| {r['max_abs_diff_vs_ours']:.1e} | {ratio} |"
            )
    lines += [
        "",
        "## Forward throughput (steps/s)",
        "",
        "| model | dtype | integrator | mode | B x N | steps/s (wall) | steps/s (cpu) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in res["throughput"]:
        lines.append(
            f"| {r['model']} | {r['dtype']} | {r['integrator']} | {r['mode']} | {r['B']} x {r['N']} "
            f"| {r['steps_per_s']:.3g} | {r['steps_per_s_cpu']:.3g} |"
        )
    lines += [
        "",
        "## diffrax peers (snakeboard, float64)",
        "",
        "| peer | B | steps | peer wall (s) | RDP wall (s) | RDP / peer |",
        "|---|---|---|---|---|---|",
    ]
    for r in res["peers"]:
        lines.append(
            f"| {r['peer']} | {r['B']} | {r['steps']} | {r['wall_min']:.3f} | {r['rdp_wall_min']:.3f} "
            f"| {r['ratio_ours_over_peer']:.2f} |"
        )
    lines += [
        "",
        "## Work-precision (snakeboard, 10 s, mean position error)",
        "",
        "Seconds per trajectory to reach a mean position error at 10 s (None: not reached in the sweep).",
        "",
        "| method | 1e-3 m | 1e-6 m |",
        "|---|---|---|",
    ]
    fmt = lambda x: "n/a" if x is None else f"{x:.2e}"  # noqa: E731
    for name, c in res["work_precision_cost"].items():
        lines.append(f"| {name} | {fmt(c['1e-03'])} | {fmt(c['1e-06'])} |")
    lines += [
        "",
        "![work-precision](work_precision.png)",
        "",
        "## Gradient cost (snakeboard, float64, terminal cost)",
        "",
        "| checkpoint | B x N | forward (s) | gradient (s) | ratio | temp memory N/10 -> N (bytes) |",
        "|---|---|---|---|---|---|",
    ]
    for r in res["gradients"]:
        mem = " -> ".join(str(v["temp_bytes"]) for v in r["memory"].values())
        lines.append(
            f"| {r['checkpoint']} | {r['B']} x {r['N']} | {r['forward_s']:.3f} | {r['grad_s']:.3f} "
            f"| {r['ratio']:.2f} | {mem} |"
        )
    lines += [
        "",
        "## General implicit RDP step vs the closed form (snakeboard, float64)",
        "",
        "| case | B x N | wall (s) | ratio to the fast closed form |",
        "|---|---|---|---|",
    ]
    for r in res.get("general_step", []):
        lines.append(
            f"| {r['case']} | {r['B']} x {r['N']} | {r['wall_min']:.3f} "
            f"| {r['ratio_to_fast_closed_form']:.2f} |"
        )
    lines += ["", "## Compile times (s)", ""] + [f"- {k}: {v:.2f}" for k, v in res["compile"].items()]
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def plot(path, curves):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for name, pts in curves.items():
        ax.loglog([p["seconds_per_traj"] for p in pts], [p["error"] for p in pts], "o-", label=name)
    ax.set_xlabel("wall time per trajectory (s)")
    ax.set_ylabel("mean position error at 10 s (m)")
    ax.set_title("Snakeboard work-precision")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="small sizes, under 3 minutes")
    p.add_argument("--out", default="results", help="output directory")
    p.add_argument("--repeats", type=int, default=None)
    args = p.parse_args()
    q = args.quick
    args.repeats = args.repeats or (2 if q else 5)
    args.batch, args.steps = (1000, 1000)
    args.grad_batch = 100 if q else 1000
    args.mem_steps = 10_000
    args.wp_maneuvers = 64 if q else 256  # batched, as a sweep runs them (per-step overhead amortised)
    args.wp_steps = [50, 200, 800] if q else [25, 50, 100, 200, 400, 800, 1600, 3200]
    args.wp_tols = [1e-4, 1e-7] if q else [1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9]
    os.makedirs(args.out, exist_ok=True)
    t_start = time.perf_counter()

    def log(msg):
        print(f"[{time.perf_counter() - t_start:6.1f}s] {msg}", flush=True)

    res = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"jax {jax.__version__}, {jax.devices()[0].platform}",
        "quick": q,
    }
    if q:  # quick: throughput at a reduced batch except for the headline configuration
        args_tp = argparse.Namespace(**{**vars(args), "batch": 200, "steps": 500})
    else:
        args_tp = args
    log("headline (snakeboard RDP, B = N = 1000)")
    res["headline"] = headline(args, log)
    log("compiled C baseline (same step, same maneuvers)")
    res["compiled_c"] = compiled_c(args, res["headline"], log)
    log("compile times")
    res["compile"] = compile_times(log)
    log("forward throughput")
    res["throughput"] = throughput(args_tp, log)
    log("diffrax peers")
    res["peers"] = peers(args, log)
    log("gradients")
    res["gradients"] = gradients(args, log)
    log("general step vs closed form")
    res["general_step"] = general_step(args, log)
    log("work-precision")
    res["work_precision"], res["work_precision_cost"] = work_precision(args, log)
    res["total_seconds"] = time.perf_counter() - t_start
    with open(os.path.join(args.out, "bench.json"), "w") as f:
        json.dump(res, f, indent=1, default=str)
    write_markdown(os.path.join(args.out, "bench.md"), res)
    plot(os.path.join(args.out, "work_precision.png"), res["work_precision"])
    log(f"wrote {args.out}/bench.json, bench.md, work_precision.png")


if __name__ == "__main__":
    main()
