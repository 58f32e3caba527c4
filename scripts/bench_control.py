"""Optimal control against CasADi + IPOPT: the three goal tasks, solved both ways in one run.

    python scripts/bench_control.py --out results            # all three tasks, 64-problem batch
    python scripts/bench_control.py --quick --out results    # parallel_park and u_turn, smaller batch

For each task (``parallel_park``, ``u_turn``, ``reach``; see ``scripts/casadi_baseline.py`` for the
common formulation: node controls interpolated linearly, effort objective, terminal pose and rest
as equalities, bounds at the nodes):

* CasADi 3 + IPOPT (direct multiple shooting with RK4, default options), when CasADi is installed
  (``pip install .[bench]``): build + first solve, repeat solve, iterations, terminal errors of
  its controls replayed on an independent DOP853 solution;
* ``lc.solve`` (interior point with Riccati steps on the discrete dynamics of ``lj.RDP(order=4)``
  by default): first call (compilation included, cold), repeat, iterations, terminal errors of
  its controls replayed on ``lj.reference``, bound violations at the nodes on the reference;
* a batch of problems (goals perturbed around the task's) in one ``jax.vmap``-ed call, against
  one solve;
* the derivative of the optimal effort with respect to the goal by the implicit function theorem
  against central differences of re-solves;
* ``lc.solve`` also from rest (zero controls, IPOPT's starting point on u_turn and reach);
* optionally (``--robustness 0,1,2``) robustness away from the three goals: for each seed, 16
  random goals around each task's (uniform offsets up to ``GOAL_OFFSETS``), solved from the
  default guess and from rest in one vmapped call per task and guess: how many converge, how
  many needed a restart;
* optionally (``--cache``) the first call in a new process with JAX's persistent compilation
  cache warm (``lj.enable_compilation_cache``).

Writes ``OUT/bench_control.json`` and ``OUT/bench_control.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import os
import pathlib
import subprocess
import sys
import tempfile
import time

from _args import positive_int

# JAX, NumPy, the library and the CasADi baseline are imported by _load(), after the flags are
# parsed and checked: a bad flag fails at once (exit status 2, the flag named).
jax = jnp = np = lj = lc = cb = None

TASK_NAMES = ("parallel_park", "u_turn", "reach")
#: largest offsets (x [m], y [m], heading [rad]) of the random goals of ``--robustness``
GOAL_OFFSETS = {"parallel_park": (0.5, 0.3, 0.4), "u_turn": (0.3, 0.1, 0.3), "reach": (1.0, 0.7, 0.8)}
TASK_FACTORIES: dict = {}  # name -> lc.parallel_park, ... (filled by _load)
INTEGRATORS = {
    "rdp2": lambda: lj.RDP(),
    "rdp4": lambda: lj.RDP(order=4),
    "rdp6": lambda: lj.RDP(order=6),
    "rk4": lambda: lj.RK4(),
}


def _load():
    """Import JAX (float64), NumPy, the library and the CasADi baseline script."""
    global jax, jnp, np, lj, lc, cb
    import ldap_jax as lj_

    # One XLA host device per core, so that the batch is also measured split over the cores
    # (lj.shard_vmap); everything else runs on the first device as usual. Set before JAX starts.
    lj_.use_cpu_cores()
    import jax as jax_

    jax_.config.update("jax_enable_x64", True)
    import jax.numpy as jnp_
    import numpy as np_

    from ldap_jax import control as lc_

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import casadi_baseline as cb_

    jax, jnp, np, lj, lc, cb = jax_, jnp_, np_, lj_, lc_, cb_
    TASK_FACTORIES.update({name: getattr(lc_, name) for name in TASK_NAMES})


def _seeds(text: str) -> tuple[int, ...]:
    try:
        seeds = tuple(int(t) for t in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be comma-separated integers, got {text!r}") from None
    if any(x < 0 for x in seeds):
        raise argparse.ArgumentTypeError(f"seeds must be non-negative, got {text!r}")
    return seeds


@dataclasses.dataclass(frozen=True)
class Config:
    """Settings of a run (``--quick`` shrinks them)."""

    tasks: tuple[str, ...] = ("parallel_park", "u_turn", "reach")
    integrator: str = "rdp4"
    repeats: int = 3
    batch: int = 64
    batch_task: str = "parallel_park"
    tol: float = 1e-8
    cache: bool = False
    robustness: tuple[int, ...] = ()
    goals: int = 16
    out: str = "results"


def _time(fn, repeats):
    t = time.perf_counter()
    first = jax.block_until_ready(fn())
    t_first = time.perf_counter() - t
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return first, t_first, float(np.median(times))


def ours(task_name: str, cfg: Config, log, *, from_rest: bool = False) -> dict:
    """``lc.solve`` on one task from its default guess, or from rest (zero controls: IPOPT's
    starting point here). From rest the program is the one the default guess compiled, so its
    first call is not a first call and is not reported."""
    task = TASK_FACTORIES[task_name](integrator=INTEGRATORS[cfg.integrator]())
    p0 = jnp.zeros((task.n_steps + 1, task.system.n_controls)) if from_rest else task.init()
    sol, first, repeat = _time(lambda: lc.solve(task, p0, tol=cfg.tol), cfg.repeats)
    rp = lc.replay(task, sol.params)
    row = dict(
        task=task_name,
        integrator=cfg.integrator,
        guess="rest" if from_rest else "default",
        first_call_s=float("nan") if from_rest else first,
        repeat_s=repeat,
        iterations=int(sol.iterations),
        converged=bool(sol.converged),
        result=lc.SOLVER_RESULTS[sol.result],
        objective=float(sol.cost),
        model_violation=float(sol.max_violation),
        position_error=rp["final_position_error"],
        heading_error=rp["final_heading_error"],
        terminal_speed=rp["final_speed_ref"],
        bound_violation=rp["max_bound_violation"],
        model_error=rp["model_position_error"],
    )
    log(
        f"  ours {task_name}{' from rest' if from_rest else f': first {first:.2f} s'}, "
        f"repeat {repeat:.3f} s, {row['iterations']} it, "
        f"position error {row['position_error']:.1e} m, heading {row['heading_error']:.1e} rad"
    )
    return row


def casadi(task_name: str, cfg: Config, log) -> dict | None:
    try:
        import casadi  # noqa: F401
    except ImportError:
        log("  CasADi is not installed (pip install .[bench]): skipped")
        return None
    r = cb.run_task(task_name, repeats=cfg.repeats)
    row = dict(
        task=task_name,
        first_call_s=r["first_call"],
        repeat_s=r["repeat_time"],
        iterations=int(r["iterations"]),
        converged=bool(r["success"]),
        result=r["return_status"],
        objective=float(r["objective"]),
        position_error=float(r["position_error"]),
        heading_error=float(r["heading_error"]),
        terminal_speed=float(r["terminal_speed"]),
        bound_violation=float(r["max_violation"]),
        guess=r.get("guess"),
    )
    log(
        f"  CasADi {task_name}: first {row['first_call_s']:.2f} s, repeat {row['repeat_s']:.3f} s, "
        f"{row['iterations']} it, position error {row['position_error']:.1e} m"
    )
    return row


def batched(cfg: Config, log) -> dict:
    task = TASK_FACTORIES[cfg.batch_task](integrator=INTEGRATORS[cfg.integrator]())
    key = jax.random.PRNGKey(0)
    goals = task.goal[None] + 0.05 * jax.random.normal(key, (cfg.batch, 3)) * jnp.array([1.0, 0.2, 0.2])
    p0 = task.init()

    def one(g):
        return lc.solve(task.with_options(goal=g), p0, tol=cfg.tol)

    sols, first, repeat = _time(lambda: jax.vmap(one)(goals), max(1, cfg.repeats - 1))
    _, _, single = _time(lambda: lc.solve(task, p0, tol=cfg.tol), cfg.repeats)
    row = dict(
        task=cfg.batch_task,
        batch=cfg.batch,
        first_call_s=first,
        batch_s=repeat,
        single_s=single,
        ratio=repeat / single,
        converged=int(np.sum(np.asarray(sols.converged))),
        max_iterations=int(np.max(np.asarray(sols.iterations))),
        devices=jax.device_count(),
    )
    log(
        f"  batch of {cfg.batch}: {repeat:.2f} s vs one {single:.3f} s (x{row['ratio']:.1f}), "
        f"{row['converged']}/{cfg.batch} converged"
    )
    if jax.device_count() > 1:  # the same batch split over the devices (cores), one call
        split = lj.shard_vmap(one)
        sols_s, _, repeat_s = _time(lambda: split(goals), max(1, cfg.repeats - 1))
        row.update(
            sharded_s=repeat_s,
            sharded_ratio=repeat_s / single,
            sharded_converged=int(np.sum(np.asarray(sols_s.converged))),
            sharded_max_difference=float(np.max(np.abs(np.asarray(sols_s.params) - np.asarray(sols.params)))),
        )
        log(
            f"  split over {jax.device_count()} devices (lj.shard_vmap): {repeat_s:.2f} s "
            f"(x{row['sharded_ratio']:.1f} one), {row['sharded_converged']}/{cfg.batch} converged"
        )
    return row


def robustness(cfg: Config, log) -> list[dict]:
    """For each seed, task and guess: ``cfg.goals`` random goals around the task's (NumPy's
    generator, uniform offsets up to ``GOAL_OFFSETS``), one vmapped ``lc.solve`` from the default
    guess and one from rest (zero controls)."""
    rows = []
    for seed, name, guess in itertools.product(cfg.robustness, cfg.tasks, ("default", "rest")):
        task = TASK_FACTORIES[name](integrator=INTEGRATORS[cfg.integrator]())
        rng = np.random.default_rng(seed)
        offsets = rng.uniform(-1.0, 1.0, (cfg.goals, 3)) * np.asarray(GOAL_OFFSETS[name])
        goals = jnp.asarray(np.asarray(task.goal) + offsets)
        p0 = task.init() if guess == "default" else jnp.zeros((task.n_steps + 1, task.system.n_controls))
        t = time.perf_counter()
        sols = jax.block_until_ready(
            jax.vmap(lambda g, task=task, p0=p0: lc.solve(task.with_options(goal=g), p0, tol=cfg.tol))(goals)
        )
        converged = np.asarray(sols.converged)
        row = dict(
            seed=seed,
            task=name,
            guess=guess,
            goals=cfg.goals,
            converged=int(np.sum(converged)),
            restarted=int(np.sum(np.asarray(sols.resets) > 0)),
            max_iterations=int(np.max(np.asarray(sols.iterations))),
            max_violation_converged=float(np.max(np.asarray(sols.max_violation)[converged], initial=0.0)),
            seconds=time.perf_counter() - t,
        )
        log(
            f"  seed {seed} {name} from {guess}: {row['converged']}/{cfg.goals} converged, "
            f"{row['restarted']} restarted, up to {row['max_iterations']} iterations ({row['seconds']:.1f} s)"
        )
        rows.append(row)
    return rows


def sensitivity(cfg: Config, log) -> dict:
    task = TASK_FACTORIES["parallel_park"](integrator=INTEGRATORS[cfg.integrator]())
    p0 = task.init()

    def cost(goal):
        return lc.solve(task.with_options(goal=goal), p0, tol=1e-10).cost

    g0 = task.goal
    ift = np.asarray(jax.grad(cost)(g0))
    eps = 1e-4
    fd = np.array(
        [
            (float(cost(g0 + jnp.zeros(3).at[i].set(eps))) - float(cost(g0 - jnp.zeros(3).at[i].set(eps))))
            / (2 * eps)
            for i in range(3)
        ]
    )
    rel = float(np.max(np.abs(ift - fd) / np.maximum(np.abs(fd), 1e-12)))
    log(f"  d effort / d goal: IFT {ift}, central differences {fd} (max rel. difference {rel:.1e})")
    return dict(ift=ift.tolist(), finite_differences=fd.tolist(), max_relative_difference=rel)


_WARM = """
import time, jax
jax.config.update("jax_enable_x64", True)
import ldap_jax as lj
from ldap_jax import control as lc
lj.enable_compilation_cache({path!r}, min_compile_seconds=0.0)
t = time.perf_counter()
task = lc.{task}(integrator=lj.RDP(order=4))
jax.block_until_ready(lc.solve(task).params)
print(time.perf_counter() - t)
"""


def warm_first_call(task_name: str, log) -> dict:
    """First call in a new process with the persistent cache: run once to fill it, once to use it."""
    path = tempfile.mkdtemp(prefix="ldap_jax_cache_")
    code = _WARM.format(path=path, task=task_name)
    times = []
    for _ in range(2):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
        times.append(float(out.stdout.strip().splitlines()[-1]))
    log(f"  persistent cache, {task_name}: cold process {times[0]:.1f} s, warm process {times[1]:.2f} s")
    return dict(task=task_name, cold_process_s=times[0], warm_process_s=times[1])


GAIT_OBJECTIVES = {
    "drive_gait": "m/cycle",
    "turn_gait": "rad/cycle",
    "sideways_gait": "effort",
    "racer_gait": "m/cycle",
}


def _best_start_repeat(task, repeats: int) -> tuple[int, float]:
    """For a task whose default guess is a batch of starts: the index of the start that converges
    to the least cost (each solved alone) and the repeat time of a solve from it alone, the time
    to compare with IPOPT's repeat from its best start."""
    guesses = task.init()
    n = jax.tree_util.tree_leaves(guesses)[0].shape[0]
    costs = []
    for i in range(n):
        s = lc.solve(task, jax.tree_util.tree_map(lambda x, i=i: x[i], guesses))
        costs.append(float(s.cost) if bool(s.converged) else np.inf)
    best = int(np.argmin(costs))
    guess = jax.tree_util.tree_map(lambda x: x[best], guesses)
    _, _, repeat = _time(lambda: lc.solve(task, guess), repeats)
    return best, repeat


def gait(name: str, cfg: Config, log, cycles: int = 10) -> dict:
    """One built-in gait: ``lc.solve`` from its default guess (first and repeat times), replayed
    ``cycles`` periods on the reference (return error, displacement error per cycle), the Floquet
    multipliers; and CasADi + IPOPT on the same formulation (best of its starts)."""
    task = getattr(lc, name)()
    sol, first, repeat = _time(lambda: lc.solve(task), cfg.repeats)
    best, best_repeat = _best_start_repeat(task, cfg.repeats) if int(sol.starts) > 1 else (0, repeat)
    rp = lc.replay_gait(task, sol.params, cycles=cycles)
    value = -float(sol.cost) if name != "sideways_gait" else float(sol.cost)
    row = dict(
        gait=name,
        objective=value,
        unit=GAIT_OBJECTIVES[name],
        converged=bool(sol.converged),
        iterations=int(sol.iterations),
        starts=int(sol.starts),
        violation=float(sol.max_violation),
        first_call_s=first,
        repeat_s=repeat,
        best_start=best,
        best_start_repeat_s=best_repeat,
        return_error=[float(x) for x in rp["return_error"]],
        displacement_error=[float(x) for x in rp["displacement_error"]],
        displacement=[float(x) for x in rp["model_displacement"]],
        multipliers=[abs(complex(z)) for z in rp["multipliers"]],
        jordan_blocks=rp["jordan_blocks"],
        stability=rp["stability"],
    )
    log(
        f"  ours {name}: {value:.7g} {row['unit']}, {row['iterations']} it, first {first:.1f} s, repeat "
        f"{repeat:.3f} s, return error after {cycles} cycles {row['return_error'][-1]:.1e}"
    )
    if name == "racer_gait":  # no CasADi model of the racer with friction
        return {"ours": row}
    try:
        import casadi  # noqa: F401  (casadi_gaits imports it only when a gait is built)
        import casadi_gaits as cg
    except ImportError:
        log("  CasADi is not installed (pip install .[bench]): skipped")
        return {"ours": row}
    r = cg.run_gait(name.replace("_gait", ""), repeats=cfg.repeats)
    ipopt = dict(
        objective=float(r["objective"]),
        iterations=int(r["iterations"]),
        converged=bool(r["success"]),
        best_start=int(r["best_start"]),
        n_starts=int(r["n_starts"]),
        first_call_s=float(r["best_first_call"]),
        all_starts_s=float(r["all_starts"]),
        repeat_s=float(r["repeat_time"]),
    )
    log(
        f"  IPOPT {name}: {ipopt['objective']:.7g}, best of {ipopt['n_starts']}, "
        f"repeat {ipopt['repeat_s']:.3f} s"
    )
    return {"ours": row, "ipopt": ipopt}


def family(cfg: Config, log, n: int = 32) -> dict:
    """A family of ``n`` drive gaits over the torque bound (0.05 to 0.15 N m), one ``jax.vmap`` of
    ``lc.solve`` (its members one after another) warm-started from the default gait's controls
    scaled to each bound; its time against one default solve (from the default guess) and one
    warm solve; the trade-off figure (``OUT/gait_family.png``)."""
    import equinox as eqx

    from ldap_jax.plotting import plot_gait_family

    task = lc.drive_gait()
    base = lc.solve(task)
    bounds = jnp.linspace(0.05, 0.15, n)
    ones = jnp.ones_like(task.bounds.u_upper)

    b0 = float(task.bounds.u_upper[0])

    def member(b):
        t = eqx.tree_at(lambda t: (t.bounds.u_lower, t.bounds.u_upper), task, (-b * ones, b * ones))
        # warm start: the default gait's controls scaled to the member's bound (bang-bang gaits)
        sol = lc.solve(t, eqx.tree_at(lambda p: p.controls, base.params, base.params.controls * (b / b0)))
        values = t.parameterization.values(sol.params.controls)
        effort = lc.effort_cost(values, t.h, t.parameterization.scale)
        return sol, effort

    run = jax.jit(jax.vmap(member))
    _, first, repeat = _time(lambda: run(bounds), cfg.repeats)
    sols, effort = run(bounds)

    def next_member(params, b):
        # continuation: each member starts from its neighbour's solution
        t = eqx.tree_at(lambda t: (t.bounds.u_lower, t.bounds.u_upper), task, (-b * ones, b * ones))
        sol = lc.solve(t, params)
        return sol.params, (sol.converged, sol.iterations, sol.cost)

    start = eqx.tree_at(lambda p: p.controls, base.params, base.params.controls * (bounds[0] / b0))
    chain = jax.jit(lambda: jax.lax.scan(next_member, start, bounds)[1])
    _, _, chain_repeat = _time(chain, cfg.repeats)
    chain_ok, chain_it, chain_cost = (np.asarray(x) for x in chain())
    _, _, single = _time(lambda: lc.solve(task, base.params), cfg.repeats)
    _, _, default = _time(lambda: lc.solve(task), cfg.repeats)
    conv = np.asarray(sols.converged)
    dist = -np.asarray(sols.cost)
    fig = plot_gait_family(
        np.asarray(bounds),
        dist,
        np.asarray(effort),
        converged=conv,
        title=f"{n} drive gaits of the snakeboard over the torque bound (one vmapped lc.solve)",
    )
    fig.savefig(pathlib.Path(cfg.out) / "gait_family.png", dpi=110)
    row = dict(
        members=n,
        converged=int(conv.sum()),
        first_call_s=first,
        repeat_s=repeat,
        single_repeat_s=single,
        default_repeat_s=default,
        ratio=repeat / single,
        ratio_default=repeat / default,
        iterations=np.asarray(sols.iterations).tolist(),
        continuation_repeat_s=chain_repeat,
        continuation_ratio_default=chain_repeat / default,
        continuation_converged=int(chain_ok.sum()),
        continuation_iterations=chain_it.tolist(),
        continuation_max_cost_difference=float(np.max(np.abs(chain_cost - np.asarray(sols.cost)))),
        default_iterations=int(base.iterations),
        displacement=dist.tolist(),
        bounds=np.asarray(bounds).tolist(),
    )
    log(
        f"  family of {n}: {row['converged']} converged, {sum(row['iterations'])} iterations, repeat "
        f"{repeat:.2f} s = {row['ratio_default']:.1f}x one default solve ({default:.3f} s, "
        f"{row['default_iterations']} iterations), {row['ratio']:.1f}x one warm solve ({single:.3f} s); "
        f"by continuation (lax.scan, each from its neighbour) {chain_repeat:.2f} s = "
        f"{row['continuation_ratio_default']:.1f}x, {int(chain_it.sum())} iterations, "
        f"{row['continuation_converged']} converged, "
        f"optima equal to {row['continuation_max_cost_difference']:.1e}"
    )
    return row


def gait_markdown(gaits: dict) -> list[str]:
    lines = [
        "",
        "## Periodic gaits (hard-constrained limit cycles, N = 100)",
        "",
        "IPOPT: RK4 multiple shooting on the same grid, bounds and exact effort, best of its starts.",
        "",
        "| gait | ours | IPOPT | ours it | IPOPT it | ours first / repeat / repeat from the best start [s] "
        "| IPOPT first (best start) / all starts / repeat [s] | return error, cycle 1 / last "
        "| Floquet: Jordan blocks at 1 |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, g in gaits.items():
        o, i = g["ours"], g.get("ipopt")
        ip = (
            (
                f"{i['objective']:.7g}",
                str(i["iterations"]),
                f"{i['first_call_s']:.2f} / {i['all_starts_s']:.1f} / {i['repeat_s']:.3f}",
            )
            if i
            else ("-",) * 3
        )
        lines.append(
            f"| {name} | {o['objective']:.7g} {o['unit']} | {ip[0]} | {o['iterations']} | {ip[1]} | "
            f"{o['first_call_s']:.1f} / {o['repeat_s']:.3f} / {o['best_start_repeat_s']:.3f} | {ip[2]} | "
            f"{o['return_error'][0]:.1e} / "
            f"{o['return_error'][-1]:.1e} | {o['jordan_blocks']} ({o['stability']}) |"
        )
    return lines


def markdown(res: dict) -> str:
    lines = [
        "# Optimal control: ldap_jax `lc.solve` vs CasADi + IPOPT",
        "",
        f"Machine: {res['machine']}. Integrator of `lc.solve`: {res['config']['integrator']}; CasADi: RK4 "
        "multiple shooting, default IPOPT options. Terminal errors: each method's controls replayed on an "
        "independent high-accuracy solution (ours: `lj.reference`; CasADi: SciPy DOP853).",
        "",
        "| task | method | first call [s] | repeat [s] | iterations | position error [m] "
        "| heading error [rad] "
        "| terminal speed | bound violation | objective |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in res["config"]["tasks"]:
        for label, row in (
            ("CasADi + IPOPT", res["casadi"].get(name)),
            ("lc.solve", res["ours"].get(name)),
            ("lc.solve from rest", res.get("ours_rest", {}).get(name)),
        ):
            if row is None:
                continue
            first = "-" if math.isnan(row["first_call_s"]) else f"{row['first_call_s']:.2f}"
            lines.append(
                f"| {name} | {label} | {first} | {row['repeat_s']:.3f} "
                f"| {row['iterations']} "
                f"| {row['position_error']:.1e} | {row['heading_error']:.1e} | {row['terminal_speed']:.1e} "
                f"| {row['bound_violation']:.1e} | {row['objective']:.6g} |"
            )
    ratios = []
    for name in res["config"]["tasks"]:
        o, c = res["ours"].get(name), res["casadi"].get(name)
        r = res.get("ours_rest", {}).get(name)
        if o and c:
            from_rest = f"{r['repeat_s'] / c['repeat_s']:.2f}" if r else "-"
            ratios.append(
                f"| {name} | {o['repeat_s'] / c['repeat_s']:.2f} | {from_rest} "
                f"| {o['first_call_s'] / c['first_call_s']:.1f} |"
            )
    guesses = [f"{n} {c['guess']}" for n, c in res["casadi"].items() if c and c.get("guess")]
    if guesses:
        lines += [
            "",
            "CasADi's initial guesses: "
            + ", ".join(guesses)
            + " (`scripts/casadi_baseline.py`: from rest IPOPT reports Infeasible_Problem_Detected on "
            "parallel_park). `lc.solve from rest`: zero controls, the program of the default guess.",
        ]
    if ratios:
        lines += [
            "",
            "| task | repeat: ours / CasADi | repeat: ours from rest / CasADi | first call: ours / CasADi |",
            "|---|---|---|---|",
            *ratios,
        ]
    b = res.get("batch")
    if b:
        lines += [
            "",
            f"Batch: {b['batch']} `{b['task']}` problems (perturbed goals) in one vmapped call: "
            f"{b['batch_s']:.2f} s vs {b['single_s']:.3f} s for one ({b['ratio']:.1f}x); "
            f"{b['converged']}/{b['batch']} converged."
            + (
                f" Split over {b['devices']} devices (one per core, `lj.shard_vmap`): {b['sharded_s']:.2f} s "
                f"({b['sharded_ratio']:.1f}x one); {b['sharded_converged']}/{b['batch']} converged; "
                f"controls within {b['sharded_max_difference']:.1e} of the one-device batch's."
                if "sharded_s" in b
                else ""
            ),
        ]
    s = res.get("sensitivity")
    if s:
        lines += [
            "",
            f"Sensitivity of the optimal effort to the goal (implicit function theorem vs central "
            f"differences of re-solves): max relative difference {s['max_relative_difference']:.1e}.",
        ]
    rob = res.get("robustness")
    if rob:
        lines += [
            "",
            "Robustness: random goals around each task's (uniform offsets up to "
            + "; ".join(f"{k} {v}" for k, v in GOAL_OFFSETS.items() if any(r["task"] == k for r in rob))
            + "), from the default guess and from rest (zero controls), one vmapped call per task, "
            "guess and seed.",
            "",
            "| seed | task | guess | converged | restarted | most iterations "
            "| largest violation (converged) |",
            "|---|---|---|---|---|---|---|",
            *(
                f"| {r['seed']} | {r['task']} | {r['guess']} | {r['converged']}/{r['goals']} | "
                f"{r['restarted']} | {r['max_iterations']} | {r['max_violation_converged']:.1e} |"
                for r in rob
            ),
        ]
    for w in res.get("warm", []):
        lines += [
            "",
            f"Persistent compilation cache ({w['task']}): first call in a new process "
            f"{w['cold_process_s']:.1f} s cold, {w['warm_process_s']:.2f} s warm.",
        ]
    return "\n".join(lines) + "\n"


def parse_args(argv=None):
    """Parse and check every flag (exit status 2 and a message naming the flag on a bad one),
    before JAX is imported and before any computation; ``--out`` is created here."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--quick", action="store_true", help="parallel_park and u_turn, a batch of 16 (default: all, 64)"
    )
    p.add_argument("--out", default="results", help="output directory (default: results)")
    p.add_argument(
        "--integrator", choices=sorted(INTEGRATORS), default="rdp4", help="lc.solve's model (default: rdp4)"
    )
    p.add_argument(
        "--repeats", type=positive_int, default=3, help="timed repeats after the first call (default: 3)"
    )
    p.add_argument(
        "--cache", action="store_true", help="also time the first call with a warm persistent cache"
    )
    p.add_argument(
        "--robustness",
        type=_seeds,
        default=(),
        help="comma-separated seeds: also solve 16 random goals around each task per seed (e.g. 0,1,2)",
    )
    p.add_argument(
        "--gaits",
        type=lambda t: tuple(x for x in t.split(",") if x),
        default=None,
        help="comma-separated built-in gaits to solve and compare with IPOPT (default: drive_gait with "
        "--quick, else drive_gait,sideways_gait,turn_gait,racer_gait; the racer has no IPOPT "
        "counterpart; '' for none)",
    )
    args = p.parse_args(argv)
    if args.gaits is None:
        args.gaits = ("drive_gait",) if args.quick else tuple(GAIT_OBJECTIVES)
    bad = [g for g in args.gaits if g not in GAIT_OBJECTIVES]
    if bad:
        p.error(f"argument --gaits: unknown gait(s) {bad}; choose from {sorted(GAIT_OBJECTIVES)}")
    out = pathlib.Path(args.out)
    if out.exists() and not out.is_dir():
        p.error(f"argument --out: {args.out!r} exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        p.error(f"argument --out: cannot create {args.out!r}: {err}")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    _load()
    out = pathlib.Path(args.out)
    cfg = Config(
        tasks=("parallel_park", "u_turn") if args.quick else Config.tasks,
        integrator=args.integrator,
        repeats=args.repeats,
        batch=16 if args.quick else 64,
        cache=args.cache,
        robustness=args.robustness,
        out=str(out),
    )
    t0 = time.perf_counter()

    def log(msg):
        print(f"[{time.perf_counter() - t0:6.1f}s] {msg}", flush=True)

    res = {
        "machine": f"{os.cpu_count()} cores, jax {jax.__version__}, {jax.devices()[0].platform}",
        "config": dataclasses.asdict(cfg),
        "ours": {},
        "casadi": {},
    }
    for name in cfg.tasks:
        log(name)
        row = casadi(name, cfg, log)
        if row:
            res["casadi"][name] = row
        res["ours"][name] = ours(name, cfg, log)
        res.setdefault("ours_rest", {})[name] = ours(name, cfg, log, from_rest=True)
    log("batch")
    res["batch"] = batched(cfg, log)
    log("sensitivity")
    res["sensitivity"] = sensitivity(cfg, log)
    if cfg.robustness:
        log("robustness")
        res["robustness"] = robustness(cfg, log)
    if cfg.cache:
        res["warm"] = [warm_first_call(name, log) for name in cfg.tasks[:1]]
    if args.gaits:
        res["gaits"] = {}
        for name in args.gaits:
            log(name)
            res["gaits"][name] = gait(name, cfg, log)
        if "drive_gait" in args.gaits:
            log("gait family")
            res["gait_family"] = family(cfg, log, n=8 if args.quick else 32)
    res["total_s"] = time.perf_counter() - t0
    (out / "bench_control.json").write_text(json.dumps(res, indent=1, default=str) + "\n")
    md = markdown(res) + ("\n".join(gait_markdown(res["gaits"])) + "\n" if "gaits" in res else "")
    if "gait_family" in res:
        f = res["gait_family"]
        md += (
            f"\nGait family: {f['members']} drive gaits over the torque bound in one vmapped solve, "
            f"{f['converged']} converged, {f['repeat_s']:.2f} s = {f['ratio_default']:.1f}x one default "
            f"solve, {f['ratio']:.1f}x one warm solve "
            f"(figure: gait_family.png).\n"
        )
    (out / "bench_control.md").write_text(md)
    print(md)
    log(f"wrote {out / 'bench_control.json'} and {out / 'bench_control.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
