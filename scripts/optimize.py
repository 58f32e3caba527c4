"""Gait and maneuver optimization with the library's integrators as the dynamics model.

    python scripts/optimize.py --model car --task parallel_park --quick
    python scripts/optimize.py --model snakeboard --task forward_gait --quick --compare-integrators

Tasks with per-step controls (``parallel_park``, ``u_turn``, ``reach``) are solved with hard
constraints by ``lc.solve`` (interior point, Riccati steps, exact Hessians; ``--solver solve``,
the default for them); the periodic gait task (``forward_gait``) and ``--solver optimize`` use
``lc.optimize`` (optax, L-BFGS by default) on the task's penalty form. The optimized controls are
replayed on the high-accuracy reference ``lj.reference``. Writes ``OUT/optimize_<model>_<task>.json``
(final_position_error [m], final_heading_error [rad] of the replay, the cost terms, iterations,
wall_s, ...), ``OUT/optimize_<model>_<task>.png`` (path, controls, convergence) and
``OUT/<task>.gif`` (an animation of the optimized maneuver on the reference).

``--family N`` solves a family of N tasks that differ in one array (see :func:`family_values`:
the goal, for now) by ``lc.solve`` in one batched program split over the devices of every
process (``lj.shard_vmap``), and writes ``OUT/optimize_<model>_<task>_family.json`` (each
member's array, convergence, iterations, cost, constraint violation). It runs over several
processes as ``scripts/sweep.py`` does (``--coordinator --num-processes --process-id``, or
``python -m ldap_jax.launch -n P -- python scripts/optimize.py ...``), each process building only
its own members; only process 0 writes.
"""

import argparse
import json
import math
import os
import pathlib
import sys
import time

import numpy as np
from _args import positive_int

# JAX, matplotlib and the library are imported by _load(), after the flags are parsed and checked:
# a bad flag fails at once (exit status 2, the flag named) instead of after seconds of imports.
jax = plt = lj = lc = None

# L-BFGS iterations of the penalty form (quick, full) per task
ITERATIONS = {
    "parallel_park": (60, 200),
    "u_turn": (150, 400),
    "forward_gait": (60, 200),
    "reach": (150, 400),
}
#: the tasks of each model (the keys of ``lc.TASKS``; tests/test_faults.py checks that they agree)
#: and the periodic gaits among them (SinusoidGait controls: ``lc.optimize`` only)
MODEL_TASKS = {
    "car": ("parallel_park", "u_turn", "sideways_gait"),
    "snakeboard": ("forward_gait", "reach", "drive_gait", "turn_gait"),
    "roller_racer": ("racer_gait",),
}
PERIODIC_TASKS = ("forward_gait",)
INTEGRATORS = {
    "rdp": lambda: lj.RDP(),
    "rdp4": lambda: lj.RDP(order=4),
    "rdp6": lambda: lj.RDP(order=6),
    "rk4": lambda: lj.RK4(),
}
GOAL_TOL = (0.02, math.radians(2.0))  # "reaches the goal": within 2 cm and 2 degrees


def _load():
    """Import JAX (float64), matplotlib (Agg) and the library."""
    global jax, plt, lj, lc
    import jax as jax_

    jax_.config.update("jax_enable_x64", True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt_

    import ldap_jax as lj_
    from ldap_jax import control as lc_

    jax, plt, lj, lc = jax_, plt_, lj_, lc_


def run(task, solver, n_iterations, *, starts, seed, progress=True, label=""):
    """Optimize one task; returns (params, record, losses)."""
    t = time.perf_counter()
    info, losses = {}, None
    if solver == "solve":
        sol = lc.solve(task) if n_iterations is None else lc.solve(task, max_iterations=n_iterations)
        params = sol.params
        info = {
            "solver": "lc.solve (interior point)",
            "iterations": int(sol.iterations),
            "converged": bool(sol.converged),
            "result": lc.SOLVER_RESULTS[sol.result],
            "objective": float(sol.cost),
            "model_constraint_violation": float(sol.max_violation),
        }
    elif starts > 1:
        keys = jax.random.split(jax.random.PRNGKey(seed), starts)
        batch = lc.multistart(task.loss, jax.vmap(task.init)(keys), n_iterations=n_iterations)
        res = lc.best_of(batch)
        params, losses = res.params, np.asarray(res.losses)
        info = {
            "solver": "lc.multistart (optax)",
            "starts": starts,
            "start_losses": np.asarray(batch.loss).tolist(),
            "iterations": n_iterations,
            "loss": float(res.loss),
        }
    else:
        res = lc.optimize(
            task.loss, task.init(), n_iterations=n_iterations, progress=progress, description=label
        )
        params, losses = res.params, np.asarray(res.losses)
        info = {
            "solver": "lc.optimize (optax L-BFGS, penalty form)",
            "iterations": res.iterations,
            "loss": float(res.loss),
            "initial_loss": float(losses[0]),
            "final_terms": {k: float(v[-1]) for k, v in res.aux.items()},
        }
    jax.block_until_ready(params)
    info["wall_s"] = time.perf_counter() - t
    return params, info, losses


def figure(task, params, rp, losses, path, title):
    from ldap_jax.plotting import plot_paths

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    paths = {
        "reference replay (diffrax)": rp["q_ref"],
        f"model ({type(task.integrator).__name__})": rp["q_model"],
    }
    plot_paths(axes[0], task.system, paths, draw="reference replay (diffrax)")
    if task.goal is not None:
        g = np.asarray(task.goal)
        axes[0].plot([g[0]], [g[1]], "r*", ms=12, label="goal")
    axes[0].set_title(title)
    t = rp["t"]
    c = np.asarray(jax.vmap(task.controls(params))(t))
    units = {"f_psi": "N m", "f_phi": "N m", "u_sigma": "1/s"}
    for i, name in enumerate(task.system.control_names):
        ax = axes[1] if i == 0 else axes[1].twinx()
        ax.plot(t, c[:, i], color=f"C{i}", label=f"{name} [{units.get(name, '')}]")
        ax.set_ylabel(f"{name} [{units.get(name, '')}]", color=f"C{i}")
    axes[1].set_xlabel("t [s]")
    axes[1].set_title("optimized controls")
    if losses is not None:
        finite = losses[np.isfinite(losses)]
        axes[2].semilogy(np.abs(losses)) if np.all(finite > 0) else axes[2].plot(losses)
        axes[2].set_ylabel("penalty-form loss")
        axes[2].set_xlabel("iteration")
    else:
        err = np.linalg.norm(np.asarray(rp["q_ref"])[:, :2] - np.asarray(rp["q_model"])[:, :2], axis=1)
        axes[2].semilogy(t, np.maximum(err, 1e-16))
        axes[2].set_xlabel("t [s]")
        axes[2].set_ylabel("|model - reference| position [m]")
    axes[2].set_title("convergence" if losses is not None else "model error along the replay")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def parse_args(argv=None):
    """Parse and check every flag (exit status 2 and a message naming the flag on a bad one),
    before JAX is imported and before any computation; ``--out`` (and ``--cache``) are created here."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument(
        "--model", choices=sorted(MODEL_TASKS), required=True, help="the system (roller_racer: with drag)"
    )
    parser.add_argument(
        "--task",
        choices=sorted({t for tasks in MODEL_TASKS.values() for t in tasks}),
        required=True,
        help="the task (must belong to --model)",
    )
    parser.add_argument(
        "--quick", action="store_true", help="small settings (penalty form: fewer iterations)"
    )
    parser.add_argument("--out", default="results", help="output folder")
    parser.add_argument(
        "--solver",
        choices=["auto", "solve", "optimize"],
        default="auto",
        help="lc.solve (hard constraints) or lc.optimize (penalty form); auto: solve when the "
        "task has per-step controls",
    )
    parser.add_argument(
        "--integrator", choices=sorted(INTEGRATORS), default="rdp4", help="the dynamics model"
    )
    parser.add_argument(
        "--starts", type=positive_int, default=1, help="lc.optimize: random initial guesses (multi-start)"
    )
    parser.add_argument(
        "--iterations",
        type=positive_int,
        default=None,
        help="iterations of lc.optimize (default: per task, see ITERATIONS) or the budget of lc.solve "
        "(default 200)",
    )
    parser.add_argument(
        "--n-steps", type=positive_int, default=None, help="rollout steps (default: the task's)"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the multi-start guesses")
    parser.add_argument("--cache", default=None, metavar="DIR", help="persistent compilation cache directory")
    parser.add_argument(
        "--compare-integrators",
        action="store_true",
        help="also optimize with the other integrators at the same step and replay each",
    )
    parser.add_argument(
        "--family", type=positive_int, default=None, metavar="N", help="solve a family of N tasks (lc.solve)"
    )
    parser.add_argument(
        "--cpu-devices",
        type=positive_int,
        default=None,
        help="XLA host devices on CPU (--family: all cores)",
    )
    here = os.path.dirname(os.path.abspath(__file__))
    if here not in sys.path:
        sys.path.insert(0, here)  # for _launch.py: the process options, ldap_jax.launch's
    import _launch

    options = _launch.launch_options()
    options.add_arguments(parser)
    args = parser.parse_args(argv)
    options.check_arguments(args, parser.error)
    if args.distributed and args.family is None:
        parser.error("argument --num-processes: several processes run only a --family")
    if args.task not in MODEL_TASKS[args.model]:
        parser.error(
            f"argument --task: {args.task} is not a task of --model {args.model}; its tasks: "
            f"{', '.join(MODEL_TASKS[args.model])}"
        )
    periodic = args.task in PERIODIC_TASKS
    args.solver = ("optimize" if periodic else "solve") if args.solver == "auto" else args.solver
    if args.solver == "solve" and periodic:
        parser.error(
            f"argument --solver: solve needs per-step controls; {args.task} is a periodic gait: "
            "use --solver optimize"
        )
    if args.family is not None and args.compare_integrators:
        parser.error("argument --compare-integrators: not with --family (one integrator's solves)")
    if args.family is not None and args.solver != "solve":
        parser.error(
            f"argument --family: a family is solved by lc.solve; {args.task} is solved by lc.optimize"
        )
    if args.solver == "solve" and args.starts > 1:
        parser.error(
            "argument --starts: multi-start applies to --solver optimize (lc.solve starts from one guess)"
        )
    args.error = parser.error
    # --cache by every process (each keeps its programs there); --out by process 0, which writes
    # it (under --cluster once JAX has told it its index)
    check_folders(args, out=args.process_id == 0 or not args.distributed)
    return args


def check_folders(args, *, out: bool = True, cache: bool = True) -> None:
    """Check (and create) ``--out`` and ``--cache`` (those asked for)."""
    for flag, path, wanted in (("--out", args.out, out), ("--cache", args.cache, cache)):
        if path is None or not wanted:
            continue
        if pathlib.Path(path).exists() and not pathlib.Path(path).is_dir():
            args.error(f"argument {flag}: {path!r} exists and is not a directory")
        try:
            pathlib.Path(path).mkdir(parents=True, exist_ok=True)
        except OSError as err:
            args.error(f"argument {flag}: cannot create {path!r}: {err}")


#: --family: the members' goals spread over this much (x [m], y [m], theta [rad]) around the task's
FAMILY_SPREAD = (0.2, 0.2, 0.2)


def family_values(task, indices, size: int):
    """The arrays of members ``indices`` of a family of ``size`` tasks around ``task``: here its
    goal, moved along a line through it (``(1 - 2 i / (size - 1)) * FAMILY_SPREAD``). Each process
    calls it for its own members only. Point this and :func:`family_member` at another family
    (a bound, the mass, a gait's speed) to solve that one instead."""
    s = np.linspace(1.0, -1.0, size)[indices] if size > 1 else np.zeros(len(indices))
    return np.asarray(task.goal)[None] + s[:, None] * np.asarray(FAMILY_SPREAD)[None]


def family_member(task, value):
    """The family's task with array ``value`` (traced: inside the batched program)."""
    return task.with_options(goal=value)


def solve_family(args) -> int:
    """``--family``: every member solved by ``lc.solve`` in one program over all devices of all
    processes, each process building its own members; process 0 writes the members' results."""
    from ldap_jax import launch

    if args.cpu_devices != 1:
        lj.use_cpu_cores(args.cpu_devices)  # before JAX starts (default: one device per core)
    jax.config.update("jax_enable_preemption_service", False)  # SIGTERM stops a process (sweep.py)
    keys = ("model", "task", "family", "integrator", "iterations", "n_steps", "quick")
    settings = {f"--{k.replace('_', '-')}": getattr(args, k) for k in keys}
    lead = launch.start(args, args.error, settings) == 0
    if lead and args.process_id is None:
        check_folders(args, cache=False)  # --cluster: this process is the one that writes --out
    kw = {} if args.n_steps is None else {"n_steps": args.n_steps}
    task = lc.TASKS[(args.model, args.task)](integrator=INTEGRATORS[args.integrator](), **kw)
    n_iter = 1000 if args.iterations is None else args.iterations
    values = lj.global_batch(lambda idx: family_values(task, idx, args.family), args.family)

    def member(task, value):
        return lc.solve(family_member(task, value), max_iterations=n_iter)

    t = time.perf_counter()
    sol = jax.block_until_ready(lj.shard_vmap(member, in_axes=(None, 0))(task, values))
    wall = time.perf_counter() - t
    from jax.experimental import multihost_utils

    fields = {"value": values, "converged": sol.converged, "iterations": sol.iterations, "cost": sol.cost}
    fields.update(max_violation=sol.max_violation, result=sol.result._value)
    gathered = {
        k: np.asarray(multihost_utils.process_allgather(v, tiled=True))[: args.family]
        for k, v in fields.items()
    }
    if not lead:
        return 0
    members = [{k: gathered[k][i].tolist() for k in gathered} for i in range(args.family)]
    record = {
        "model": args.model,
        "task": args.task,
        "family": args.family,
        "family_array": "goal (x, y, theta)",
        "processes": jax.process_count(),
        "devices": jax.device_count(),
        "wall_s": wall,
        "converged": int(np.sum(gathered["converged"])),
        "members": members,
    }
    path = pathlib.Path(args.out) / f"optimize_{args.model}_{args.task}_family.json"
    path.write_text(json.dumps(record, indent=1) + "\n")
    print(f"{record['converged']} of {args.family} members converged in {wall:.1f} s; wrote {path}")
    return 0


def main(argv=None) -> int:
    args = parse_args(argv)
    _load()
    if args.cache:
        lj.enable_compilation_cache(args.cache)
    if args.family is not None:
        return solve_family(args)
    out = pathlib.Path(args.out)
    kw = {} if args.n_steps is None else {"n_steps": args.n_steps}
    task = lc.TASKS[(args.model, args.task)](integrator=INTEGRATORS[args.integrator](), **kw)
    solver = args.solver
    if args.iterations is not None:
        n_iter = args.iterations
    else:
        n_iter = None if solver == "solve" else ITERATIONS[args.task][0 if args.quick else 1]
    params, info, losses = run(task, solver, n_iter, starts=args.starts, seed=args.seed, label=args.task)
    if task.periodic is not None:
        return gait_report(args, task, params, info, out)
    rp = lc.replay(task, params)
    record = {
        "model": args.model,
        "task": args.task,
        "integrator": args.integrator,
        "n_steps": task.n_steps,
        "t_final": float(task.t_final),
        **info,
    }
    record.update(
        {
            k: rp[k]
            for k in (
                "final_position_error",
                "final_heading_error",
                "model_position_error",
                "model_heading_error",
                "final_speed_ref",
                "max_bound_violation",
                "forward_displacement",
                "terms_reference",
            )
        }
    )
    record["error_reference"] = (
        "goal" if task.goal is not None else "model rollout (no goal: model error at t_N)"
    )
    if task.goal is not None:
        record["goal"] = np.asarray(task.goal).tolist()
        record["reached_goal_reference"] = bool(
            rp["final_position_error"] <= GOAL_TOL[0] and rp["final_heading_error"] <= GOAL_TOL[1]
        )
    if args.compare_integrators:
        cmp = {}
        for name, make in INTEGRATORS.items():
            t_i = task.with_options(integrator=make())
            p_i, info_i, _ = run(t_i, solver, n_iter, starts=1, seed=args.seed, label=name)
            rp_i = lc.replay(t_i, p_i)
            cmp[name] = {
                **{k: info_i[k] for k in ("wall_s", "iterations")},
                **{
                    k: rp_i[k]
                    for k in (
                        "final_position_error",
                        "final_heading_error",
                        "model_position_error",
                        "forward_displacement",
                    )
                },
            }
        record["integrator_comparison"] = cmp
    stem = f"optimize_{args.model}_{args.task}"
    (out / f"{stem}.json").write_text(json.dumps(record, indent=2, default=float) + "\n")
    title = (
        f"{args.model} {args.task} ({args.integrator}, N = {task.n_steps}, {record['solver'].split(' ')[0]})"
    )
    figure(task, params, rp, losses, out / f"{stem}.png", title)
    written = [out / f"{stem}.json", out / f"{stem}.png"]
    from ldap_jax.plotting import animate

    traj = lj.reference(task.system, task.q0, task.qdot0, task.controls(params), rp["t"])
    animate(
        traj.q,
        task.system,
        out / f"{args.task}.gif",
        t=rp["t"],
        goal=None if task.goal is None else np.asarray(task.goal),
        title=title,
    )
    written.append(out / f"{args.task}.gif")
    keys = ("final_position_error", "final_heading_error", "iterations", "wall_s")
    print(json.dumps({k: record[k] for k in keys}, indent=1))
    if "integrator_comparison" in record:
        print("integrator_comparison", json.dumps(record["integrator_comparison"], indent=1))
    print("wrote " + ", ".join(str(p) for p in written))
    return 0


def gait_report(args, task, params, info, out: pathlib.Path, cycles: int = 3) -> int:
    """A periodic gait's record, figure and animation: ``cycles`` periods replayed on the
    reference from the optimised start (:func:`lc.replay_gait`), the displacement and return
    error of each, the Floquet multipliers; the shape-space loop and the path."""
    from ldap_jax.plotting import animate

    rp = lc.replay_gait(task, params, cycles=cycles)
    record = {
        "model": args.model,
        "task": args.task,
        "integrator": args.integrator,
        "n_steps": task.n_steps,
        "period": float(task.t_final),
        **info,
        "displacement_per_cycle": rp["displacement"].tolist(),
        "model_displacement": rp["model_displacement"].tolist(),
        "return_error": rp["return_error"].tolist(),
        "displacement_error": rp["displacement_error"].tolist(),
        "floquet_multipliers": [[float(z.real), float(z.imag)] for z in rp["multipliers"]],
        "jordan_blocks": rp["jordan_blocks"],
        "stability": rp["stability"],
    }
    stem = f"optimize_{args.model}_{args.task}"
    (out / f"{stem}.json").write_text(json.dumps(record, indent=2, default=float) + "\n")
    q = np.asarray(rp["q_ref"])
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 4))
    ax0.plot(q[:, 0], q[:, 1])
    ax0.set(xlabel="x [m]", ylabel="y [m]", title=f"{args.task}: {cycles} cycles on the reference")
    names = task.system.shape_names
    keep = [i for i, n in enumerate(names) if n not in task.periodic.cyclic]
    t = np.asarray(rp["t"])
    for i in keep:
        ax1.plot(t, q[:, 3 + i], label=names[i])
    dx, dy, dth = rp["model_displacement"]
    ax1.set(xlabel="t [s]", ylabel="shape [rad or m]", title="shape over the cycles")
    ax1.text(
        0.02,
        0.02,
        f"per cycle: dx = {dx:.4g} m, dy = {dy:.2g} m, dtheta = {dth:.2g} rad",
        transform=ax1.transAxes,
        fontsize=8,
    )
    ax1.legend()
    fig.tight_layout()
    fig.savefig(out / f"{stem}.png", dpi=110)
    plt.close(fig)
    animate(q, task.system, out / f"{args.task}.gif", t=t, title=f"{args.model} {args.task}")
    keys = ("objective", "iterations", "wall_s", "stability")
    print(json.dumps({k: record[k] for k in keys if k in record}, indent=1))
    print("return error per cycle", np.array2string(rp["return_error"], precision=2))
    print(f"wrote {out / (stem + '.json')}, {out / (stem + '.png')}, {out / (args.task + '.gif')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
