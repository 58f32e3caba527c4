"""Gait and maneuver optimization through differentiable RDP rollouts (issue 5).

    python scripts/optimize.py --model car --task parallel_park --quick
    python scripts/optimize.py --model snakeboard --task forward_gait --quick --compare-integrators

Optimizes the task's controls with optax (L-BFGS by default) through ``lj.simulate`` (RDP by
default), replays the optimized controls on the high-accuracy reference ``lj.reference`` and
writes ``OUT/optimize_<model>_<task>.json`` (final_position_error [m], final_heading_error [rad]
of the replay, loss, iterations, wall_s, ...) and ``OUT/optimize_<model>_<task>.png`` (path with
the vehicle drawn, controls over time, loss curve). Options: ``--starts N`` multi-start (vmap
over N random initial guesses, keep the best, count how many reach the goal);
``--checkpoint [step|sqrt]`` rematerialises the rollout in reverse mode; ``--memory`` reports the peak memory
of the gradient of a 10^4-step rollout with and without checkpointing; ``--compare-integrators``
optimizes with RDP and RK4 at the same step and replays both on the reference.
"""

import argparse
import json
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import ldap_jax as lj  # noqa: E402
from ldap_jax import control as lc  # noqa: E402
from ldap_jax.plotting import plot_paths  # noqa: E402

# iterations (quick, full) per task
ITERATIONS = {
    "parallel_park": (60, 200),
    "u_turn": (150, 400),
    "forward_gait": (60, 200),
    "reach": (150, 400),
}
INTEGRATORS = {"rdp": lj.RDP, "rk4": lj.RK4}
GOAL_TOL = (0.02, np.deg2rad(2.0))  # "reaches the goal": within 2 cm and 2 degrees


def _reached(task, q_n):
    if task.goal is None:
        return None
    goal = np.asarray(task.goal)
    pos = np.linalg.norm(np.asarray(q_n)[..., :2] - goal[:2], axis=-1)
    head = np.abs(np.asarray(lc.wrap_angle(np.asarray(q_n)[..., 2] - goal[2])))
    return (pos <= GOAL_TOL[0]) & (head <= GOAL_TOL[1])


def run(task, n_iterations, *, starts, seed, progress=True, label=""):
    """Optimize one task (single start from the deterministic guess, or multi-start)."""
    t = time.perf_counter()
    info = {}
    if starts > 1:
        keys = jax.random.split(jax.random.PRNGKey(seed), starts)
        p0 = jax.vmap(task.init)(keys)
        batch = lc.multistart(task.value, p0, n_iterations=n_iterations)
        q_n = jax.vmap(lambda p: task.rollout(p).q[-1])(batch.params)
        reached = _reached(task, q_n)
        losses = np.asarray(batch.loss)
        res = lc.best_of(batch)
        info = {
            "starts": starts,
            "start_losses": losses.tolist(),
            "starts_reaching_goal_model": None if reached is None else int(np.sum(reached)),
        }
        initial = float(np.min(np.asarray(batch.losses)[:, 0]))
    else:
        p0 = task.init()
        res = lc.optimize(task.value, p0, n_iterations=n_iterations, progress=progress, description=label)
        initial = float(np.asarray(res.losses)[0])
    jax.block_until_ready(res.params)
    wall = time.perf_counter() - t
    return res, initial, wall, info


def figure(task, res, rp, path, title, extra_paths=None):
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    paths = {
        "reference replay (diffrax)": rp["q_ref"],
        f"model ({type(task.integrator).__name__})": rp["q_model"],
    }
    paths.update(extra_paths or {})
    plot_paths(axes[0], task.system, paths, draw="reference replay (diffrax)", n_draw=8)
    if task.goal is not None:
        g = np.asarray(task.goal)
        axes[0].plot([g[0]], [g[1]], "r*", ms=12)
        axes[0].arrow(g[0], g[1], 0.15 * np.cos(g[2]), 0.15 * np.sin(g[2]), color="r", width=0.005)
    axes[0].set_title(title)
    ctl = task.controls(res.params)
    t = rp["t"]
    c = np.asarray(jax.vmap(ctl)(t))
    for i, name in enumerate(task.system.control_names):
        axes[1].plot(t, c[:, i], label=name)
    axes[1].set_xlabel("t [s]")
    axes[1].set_title("optimized controls")
    axes[1].legend(fontsize=8)
    losses = np.asarray(res.losses)
    if np.all(losses[np.isfinite(losses)] > 0):
        axes[2].semilogy(losses)
    else:
        axes[2].plot(losses)
    axes[2].set_xlabel("iteration")
    axes[2].set_title("loss")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--model", choices=["car", "snakeboard"], required=True)
    parser.add_argument("--task", choices=sorted(ITERATIONS), required=True)
    parser.add_argument("--quick", action="store_true", help="small settings (< 3 min)")
    parser.add_argument("--out", default="results", help="output folder")
    parser.add_argument("--integrator", choices=sorted(INTEGRATORS), default="rdp")
    parser.add_argument("--starts", type=int, default=1, help="multi-start: number of random initial guesses")
    parser.add_argument(
        "--checkpoint",
        nargs="?",
        const="step",
        default=False,
        choices=["step", "sqrt"],
        help="memory policy of the rollout in reverse mode: 'step' (jax.checkpoint on the scan body) or "
        "'sqrt' (nested, O(sqrt N) stored carries)",
    )
    parser.add_argument("--iterations", type=int, default=None)
    parser.add_argument("--n-steps", type=int, default=None, help="rollout steps (default: the task's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--memory", action="store_true", help="gradient memory of 10^4 steps, with/without checkpoint"
    )
    parser.add_argument(
        "--compare-integrators",
        action="store_true",
        help="optimize with RDP and RK4, replay both on the reference",
    )
    args = parser.parse_args()
    if (args.model, args.task) not in lc.TASKS:
        parser.error(f"--task {args.task} is not a task of --model {args.model}; tasks: {sorted(lc.TASKS)}")
    if args.starts < 1:
        parser.error("--starts must be >= 1")
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    n_iter = args.iterations or ITERATIONS[args.task][0 if args.quick else 1]

    kw = {} if args.n_steps is None else {"n_steps": args.n_steps}
    task = lc.TASKS[(args.model, args.task)](
        integrator=INTEGRATORS[args.integrator](), checkpoint=args.checkpoint, **kw
    )
    res, initial, wall, info = run(task, n_iter, starts=args.starts, seed=args.seed, label=args.task)
    rp = lc.replay(task, res.params)
    _, terms = lc.Task.loss(task, res.params)
    record = {
        "model": args.model,
        "task": args.task,
        "integrator": args.integrator,
        "n_steps": task.n_steps,
        "t_final": float(task.t_final),
        "final_position_error": rp["final_position_error"],
        "final_heading_error": rp["final_heading_error"],
        "error_reference": "goal" if task.goal is not None else "model rollout (no goal: model error at t_N)",
        "model_position_error": rp["model_position_error"],
        "model_heading_error": rp["model_heading_error"],
        "forward_displacement": rp["forward_displacement"],
        "final_speed_reference": rp["final_speed_ref"],
        "loss": float(res.loss),
        "initial_loss": initial,
        "loss_terms": {k: float(v) for k, v in terms.items()},
        "iterations": n_iter,
        "wall_s": wall,
        "checkpoint": args.checkpoint,
        **info,
    }
    if task.goal is not None:
        record["goal"] = np.asarray(task.goal).tolist()
        record["reached_goal_reference"] = bool(
            rp["final_position_error"] <= GOAL_TOL[0] and rp["final_heading_error"] <= GOAL_TOL[1]
        )
    extra = {}
    if args.compare_integrators:
        cmp = {}
        for name, cls in INTEGRATORS.items():
            t_i = task.with_options(integrator=cls())
            r_i, init_i, wall_i, _ = run(t_i, n_iter, starts=1, seed=args.seed, progress=True, label=name)
            rp_i = lc.replay(t_i, r_i.params)
            cmp[name] = {
                "loss": float(r_i.loss),
                # compilation is cached across the two runs of the same integrator, so wall_s
                # of the integrator of the main run excludes compilation: not a fair timing
                "wall_s": wall_i,
                "final_position_error": rp_i["final_position_error"],
                "final_heading_error": rp_i["final_heading_error"],
                "model_position_error": rp_i["model_position_error"],
                "model_heading_error": rp_i["model_heading_error"],
                "forward_displacement_model": float(np.asarray(rp_i["q_model"])[-1, 0] - float(task.q0[0])),
                "forward_displacement_reference": rp_i["forward_displacement"],
            }
            extra[f"{name.upper()}-optimized, replayed"] = rp_i["q_ref"]
        record["integrator_comparison"] = cmp
    if args.memory:
        mem = {}
        for ck in (False, "step", "sqrt"):
            t_m = task.with_options(n_steps=10_000, checkpoint=ck)
            mem[f"checkpoint_{ck}" if ck else "no_checkpoint"] = lc.gradient_memory(t_m, t_m.init())
        record["gradient_memory_10k_steps"] = mem
    stem = f"optimize_{args.model}_{args.task}"
    (out / f"{stem}.json").write_text(json.dumps(record, indent=2) + "\n")
    title = f"{args.model} {args.task} ({args.integrator.upper()}, N = {task.n_steps})"
    figure(task, res, rp, out / f"{stem}.png", title, extra)
    keys = ("final_position_error", "final_heading_error", "loss", "initial_loss", "iterations", "wall_s")
    print(json.dumps({k: record[k] for k in keys}, indent=1))
    for k in ("starts_reaching_goal_model", "integrator_comparison", "gradient_memory_10k_steps"):
        if k in record:
            print(k, json.dumps(record[k], indent=1))
    print(f"wrote {out / (stem + '.json')}, {out / (stem + '.png')}")


if __name__ == "__main__":
    main()
