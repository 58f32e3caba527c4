"""The demo's first stage: the car and the snakeboard under RDP against the diffrax reference and
RK4, the orders 4 and 6, a long work-free run, and a snakeboard gait.

    python scripts/quickstart.py --quick --out results    # part of `make demo`
    python scripts/quickstart.py --out results            # a 10^5-step long run

Writes under ``--out``:

* ``quickstart_paths.png``: a random maneuver of each model; paths (vehicles small, start and
  end marked) and the position error against the reference over time, per integrator;
* ``quickstart_diagnostics.png``: per model, the energy error against the reference, the
  work-energy balance ``|E - E0 - W|`` and (snakeboard) the nonholonomic momentum;
* ``quickstart.md``: the numbers (errors, energy, fitted orders, the long run, the gait, times),
  and ``quickstart.json``: the final position errors and fitted orders (for the demo's summary);
* ``convergence.png``: the car's position error at 10 s against the step, RDP orders 2, 4, 6
  and RK4, against ``lj.reference``;
* ``energy_long_run.png``: the car steered without torque (no work is done, the energy is
  conserved) over 10^5 steps (``--quick``: 10^4), RDP orders 2, 4, 6 against RK4;
* ``snakeboard_gait_loop.png``, ``snakeboard_gait.gif``: a snakeboard gait (its loop in shape
  space, its momentum and path) and an animation of the RDP run with the reference.

Compilation dominates a quick run (seconds per program, milliseconds per run), so every run of
one integrator on one model shares one compiled program: the runs differ only in traced inputs
(initial state, controls, final time) and all take the same ``n_steps`` and saved nodes, each
reading the nodes it needs (node ``n`` of a run with step ``T / n`` is at time ``T``: that is
how the convergence runs share the long run's program). ``--jobs`` programs compile at once.
JAX's persistent compilation cache is on (``lj.enable_compilation_cache``; ``--no-cache``): a
second run loads the programs instead of compiling them.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time
from concurrent.futures import ThreadPoolExecutor

from _args import out_dir, positive_int


def parse_args(argv=None) -> argparse.Namespace:
    """The flags, checked before JAX is imported (a bad flag costs no import)."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="small sizes (a 10^4-step long run)")
    parser.add_argument("--out", type=out_dir, default="results", help="output folder")
    parser.add_argument("--seed", type=int, default=3, help="seed of the random maneuvers")
    parser.add_argument("--jobs", type=positive_int, default=2, help="programs compiled at once (default 2)")
    parser.add_argument("--no-cache", action="store_true", help="no persistent compilation cache")
    return parser.parse_args(argv)


if __name__ == "__main__":
    ARGS = parse_args()

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt

import ldap_jax as lj
from ldap_jax.plotting import (
    animate,
    fitted_order,
    plot_convergence,
    plot_diagnostics,
    plot_energy_error,
    plot_paths,
    plot_position_error,
    plot_shape_loop,
    style_for,
)

# the car carries the orders (convergence, long run); the snakeboard the gait
METHODS = {
    "car": {"RDP": lj.RDP(), "RDP-4": lj.RDP(order=4), "RDP-6": lj.RDP(order=6), "RK4": lj.RK4()},
    "snakeboard": {"RDP": lj.RDP(), "RK4": lj.RK4()},
}
REFERENCE = "reference (diffrax Dopri8)"
T_FINAL = 10.0  # s: the maneuvers, the gait and the convergence study
H_SHOW = 0.1  # s: the step of the quickstart figures and table
H_GAIT = 0.05  # s: the gait's step
H_LONG = 0.1  # s: the long run's step
FIT_FLOOR = 1e-10  # m: smaller errors are at the reference's accuracy (not fitted)


def pad_terms(ctl: lj.Sinusoids, n_terms: int) -> lj.Sinusoids:
    """The same controls with zero-amplitude terms appended up to ``n_terms`` (equal shapes let
    different runs share one compiled program)."""
    pad = n_terms - ctl.amplitude.shape[-1]
    z = np.zeros(ctl.amplitude.shape[:-1] + (pad,))
    cat = lambda a, fill: np.concatenate([np.asarray(a), z + fill], -1)  # noqa: E731
    return lj.Sinusoids(cat(ctl.amplitude, 0.0), cat(ctl.frequency, 1.0), cat(ctl.phase, 0.0))


def snakeboard_gait(sb: lj.Snakeboard) -> lj.Sinusoids:
    """Rotor torque ``-0.2 cos 2t`` (N m) and the steering torque ``f_phi = 2 J 0.3 4 cos 2t``
    giving ``phi = 0.3 (1 - cos 2t)`` from rest (its phase matched to ``phidot(0) = 0``, so phi
    stays in [0, 0.6] rad, far from the singularity ``cos phi = 0``)."""
    J = float(sb.J)
    return lj.Sinusoids(
        amplitude=[[0.2], [-2 * J * 0.3 * 4.0]], frequency=[[2.0], [2.0]], phase=[[-np.pi / 2], [-np.pi / 2]]
    )


def build(args) -> tuple[dict, tuple[int, ...]]:
    """Per model: the system, its runs ``(name, q0, qdot0, controls, h)``, the shared ``n_steps``
    and saved nodes."""
    conv = (25, 50, 100, 200, 400) if args.quick else (25, 50, 100, 200, 400, 800)
    n_long = 10_000 if args.quick else 100_000
    car, sb = lj.Car(), lj.Snakeboard()
    key = jax.random.PRNGKey(args.seed)
    # car: a random maneuver at every convergence step; the long work-free run at h and h/2
    q0, qdot0, ctl = jax.jit(lambda k: car.sample_maneuver(k))(key)  # one small program, not many ops
    steer = pad_terms(
        lj.Sinusoids([[0.0], [0.5]], [[1.0], [1.0]], [[0.0], [np.pi / 2]]), ctl.amplitude.shape[-1]
    )
    rho, psidot = float(car.rho), 5.0  # 0.5 m/s, straight ahead (sigma = 0)
    qc, qdc = np.zeros(5), np.array([rho * psidot, 0.0, 0.0, psidot, 0.0])
    car_runs = [(f"maneuver n={n}", q0, qdot0, ctl, T_FINAL / n) for n in conv]
    car_runs += [("long", qc, qdc, steer, H_LONG), ("long h/2", qc, qdc, steer, H_LONG / 2)]
    car_save = sorted(set(range(max(conv) + 1)) | set(range(0, n_long + 1, n_long // 1000)))
    # snakeboard: a random maneuver at H_SHOW, and the gait
    q0, qdot0, ctl = jax.jit(lambda k: sb.sample_maneuver(k))(key)
    gait = pad_terms(snakeboard_gait(sb), ctl.amplitude.shape[-1])
    n_sb = round(T_FINAL / H_GAIT)
    sb_runs = [("maneuver", q0, qdot0, ctl, H_SHOW), ("gait", np.zeros(5), np.zeros(5), gait, H_GAIT)]
    models = {
        "car": dict(system=car, runs=car_runs, n_steps=n_long, save=car_save),
        "snakeboard": dict(system=sb, runs=sb_runs, n_steps=n_sb, save="all"),
    }
    return models, conv


def run_group(job) -> tuple[tuple[str, str], list, float]:
    """Every run of one integrator (or of the reference) on one model. The first call compiles;
    the others reuse the program (same ``n_steps``, saved nodes and shapes)."""
    (name, label), system, integ, runs, n_steps, save, ts = job
    trajs = []
    start = time.perf_counter()
    for _, q0, qdot0, ctl, h in runs:
        # the initial states are on the constraints by construction: skip the eager check
        if integ is None:
            tr = lj.reference(system, q0, qdot0, ctl, ts, check_constraints=False)
        else:
            tr = lj.simulate(
                system,
                q0,
                qdot0,
                ctl,
                t_final=n_steps * h,
                n_steps=n_steps,
                integrator=integ,
                save=save,
                check_constraints=False,
            )
        trajs.append(jax.tree_util.tree_map(np.asarray, jax.block_until_ready(tr)))
    return (name, label), trajs, time.perf_counter() - start


def run_all(models: dict, jobs: int) -> tuple[dict, dict]:
    """All (model, integrator) groups and the references, ``jobs`` at a time (compilation
    releases the GIL: two cores compile two programs at once). Returns the runs and the wall
    time of each group (its compilation and runs)."""
    ts = jnp.linspace(0.0, T_FINAL, round(T_FINAL / H_GAIT) + 1)
    work = []
    for name, m in models.items():
        for label, integ in METHODS[name].items():
            work.append(((name, label), m["system"], integ, m["runs"], m["n_steps"], m["save"], None))
        ref_runs = [m["runs"][0]] + [r for r in m["runs"] if r[0] == "gait"]
        work.append(((name, REFERENCE), m["system"], None, ref_runs, None, None, ts))
    work.sort(key=lambda w: w[2] is None or isinstance(w[2], lj.RK4))  # the costliest first
    with ThreadPoolExecutor(max(1, jobs)) as ex:
        done = list(ex.map(run_group, work))
    return {key: trajs for key, trajs, _ in done}, {key: sec for key, _, sec in done}


def time_runs(models: dict) -> dict:
    """Wall time of one compiled run per model and integrator (median of 3), for the table."""
    out = {}
    for name, m in models.items():
        _, q0, qdot0, ctl, h = m["runs"][0]
        for label, integ in METHODS[name].items():
            secs = []
            for _ in range(3):
                start = time.perf_counter()
                tr = lj.simulate(
                    m["system"],
                    q0,
                    qdot0,
                    ctl,
                    t_final=m["n_steps"] * h,
                    n_steps=m["n_steps"],
                    integrator=integ,
                    save=m["save"],
                    check_constraints=False,
                )
                jax.block_until_ready(tr)
                secs.append(time.perf_counter() - start)
            out[(name, label)] = float(np.median(secs))
    return out


def take(runs: list, member: int, n_nodes: int | None = None):
    """Run ``member`` of a group, its first ``n_nodes`` saved nodes."""
    one = runs[member]
    if n_nodes is None:
        return one
    return jax.tree_util.tree_map(lambda x: x[:n_nodes] if x.ndim >= 1 else x, one)


def tenths(traj) -> tuple[float, float]:
    """Largest abs(E - E0 - W) over the first and the last tenth of a run (after t0)."""
    b = np.abs(np.asarray(traj.energy_balance))
    t = np.asarray(traj.t)
    first = b[(t > t[0]) & (t <= t[0] + 0.1 * (t[-1] - t[0]))]
    return float(np.nanmax(first)), float(np.nanmax(b[t >= 0.9 * t[-1]]))


def position_error(traj, ref) -> np.ndarray:
    """``|(x, y) - (x, y)_ref|`` (m) at the trajectory's nodes (a subset of the reference's)."""
    idx = np.searchsorted(np.asarray(ref.t), np.asarray(traj.t) - 1e-9)
    return np.linalg.norm(np.asarray(traj.q)[:, :2] - np.asarray(ref.q)[idx, :2], axis=1)


def save(fig, path: pathlib.Path, written: list) -> None:
    fig.savefig(path, dpi=100)
    plt.close(fig)
    written.append(path)


def main(args: argparse.Namespace) -> None:
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if not args.no_cache:
        lj.enable_compilation_cache()
    start = time.perf_counter()

    models, conv = build(args)
    results, group_seconds = run_all(models, args.jobs)
    run_seconds = time_runs(models)
    t_sim = time.perf_counter() - start
    written: list[pathlib.Path] = []

    # ---------------------------------------------------------------- the h = H_SHOW runs
    n_show = round(T_FINAL / H_SHOW)
    i_show = {"car": conv.index(n_show), "snakeboard": 0}
    refs = {name: take(results[(name, REFERENCE)], 0) for name in models}
    show = {
        name: {label: take(results[(name, label)], i_show[name], n_show + 1) for label in METHODS[name]}
        for name in models
    }
    car = models["car"]
    conv_err = {}
    for label in METHODS["car"]:
        errs = []
        for i, n in enumerate(conv):
            tr = take(results[("car", label)], i, n + 1)
            ok = int(tr.failure_index) >= n and np.all(np.isfinite(tr.q[-1]))
            errs.append(float(np.linalg.norm(tr.q[-1, :2] - refs["car"].q[-1, :2])) if ok else np.nan)
        conv_err[label] = (np.array([T_FINAL / n for n in conv]), np.array(errs))

    # ---------------------------------------------------------------- quickstart_paths.png
    fig, axes = plt.subplots(2, 2, figsize=(12.5, 10.0), height_ratios=[1.5, 1.0], layout="constrained")
    for j, (name, m) in enumerate(models.items()):
        paths = {REFERENCE: refs[name], **show[name]}
        loc = "lower right" if name == "car" else "upper left"
        plot_paths(axes[0, j], m["system"], paths, draw=REFERENCE, n_draw=5, legend="markers", legend_loc=loc)
        axes[0, j].set_title(f"{name}: random maneuver (seed {args.seed}), h = {H_SHOW:g} s", fontsize=11)
        plot_position_error(axes[1, j], refs[name], show[name], legend=False)
        axes[1, j].set_title(f"{name}: position error against the reference, h = {H_SHOW:g} s", fontsize=11)
    labels = [REFERENCE] + list(METHODS["car"])
    handles = [
        plt.Line2D([], [], **{"lw": 1.6, **style_for(lab, i)}, label=lab) for i, lab in enumerate(labels)
    ]
    fig.legend(handles=handles, loc="outside upper center", ncol=len(labels), fontsize=9, frameon=False)
    save(fig, out / "quickstart_paths.png", written)

    # ---------------------------------------------------------------- quickstart_diagnostics.png
    fig = plot_diagnostics(show, references={name: (m["system"], refs[name]) for name, m in models.items()})
    fig.suptitle(f"the random maneuvers of quickstart_paths.png, h = {H_SHOW:g} s", fontsize=11)
    save(fig, out / "quickstart_diagnostics.png", written)

    # ---------------------------------------------------------------- convergence.png
    fig, ax = plt.subplots(figsize=(7.5, 5.2), layout="constrained")
    plot_convergence(
        conv_err,
        ax=ax,
        floor=FIT_FLOOR,
        floor_label=f"below {FIT_FLOOR:g} m: not fitted (lj.reference: rtol = atol = 1e-11)",
        ylabel=f"position error at t = {T_FINAL:g} s [m]",
        title=f"car, random maneuver (seed {args.seed}): convergence against lj.reference",
    )
    save(fig, out / "convergence.png", written)

    # ---------------------------------------------------------------- energy_long_run.png
    names = [r[0] for r in car["runs"]]
    long = {label: take(results[("car", label)], names.index("long")) for label in METHODS["car"]}
    half = {label: take(results[("car", label)], names.index("long h/2")) for label in METHODS["car"]}
    spans = {label: (tenths(long[label]), tenths(half[label])[1]) for label in long}
    n_long = car["n_steps"]
    roundoff = [lab for lab, ((_, last), last_half) in spans.items() if 0.5 < last_half / last < 2.0]
    fig, ax = plt.subplots(figsize=(8.0, 5.0), layout="constrained")
    note = f"\n(no change at h/2 for {', '.join(roundoff)}: round-off)" if roundoff else ""
    plot_energy_error(
        long,
        ax=ax,
        logx=True,
        title=(
            r"car steered without torque ($f_\psi = 0$, $\dot\sigma = 0.5\cos t$): no work, E conserved"
            f"\n{n_long:,} steps of h = {H_LONG:g} s ({n_long * H_LONG:,.0f} s), "
            f"$E_0$ = {float(long['RDP'].energy[0]):.3g} J{note}"
        ),
    )
    save(fig, out / "energy_long_run.png", written)

    # ---------------------------------------------------------------- the gait
    sb = models["snakeboard"]["system"]
    n_gait = round(T_FINAL / H_GAIT)
    gait = take(results[("snakeboard", "RDP")], 1, n_gait + 1)
    gait_ref = take(results[("snakeboard", REFERENCE)], 1)
    fig = plot_shape_loop(
        gait,
        sb,
        title=(
            r"snakeboard gait from rest: $f_\psi = -0.2\cos 2t$ N m, "
            r"$f_\phi$ giving $\phi = 0.3(1 - \cos 2t)$ rad"
            f" (RDP, h = {H_GAIT:g} s)"
        ),
    )
    save(fig, out / "snakeboard_gait_loop.png", written)
    t_gif = time.perf_counter()
    path = out / "snakeboard_gait.gif"
    animate(
        {f"RDP, h = {H_GAIT:g} s": gait, REFERENCE: gait_ref},
        sb,
        path,
        fps=10,
        every=2,
        title="snakeboard gait from rest",
    )
    written.append(path)
    t_gif = time.perf_counter() - t_gif

    # ---------------------------------------------------------------- quickstart.md
    summary = {"h": H_SHOW, "t_final": T_FINAL, "final_position_error": {}, "fitted_order": {}}
    lines = [
        "# Quickstart: the car and the snakeboard under RDP, against the diffrax reference and RK4",
        "",
        f"Written by `scripts/quickstart.py{' --quick' if args.quick else ''}` (seed {args.seed}), with the "
        "default `lj.Car()` and `lj.Snakeboard()`: one random maneuver per model "
        f"(`system.sample_maneuver`), {T_FINAL:g} s at h = {H_SHOW:g} s (N = {n_show}), errors against "
        "`lj.reference` (diffrax Dopri8, rtol = atol = 1e-11). RDP orders 4 and 6 compose "
        f"{len(lj.RDP(order=4).weights)} and {len(lj.RDP(order=6).weights)} RDP substeps per step.",
        "",
        "| model | integrator | final position error [m] | max position error [m] | max abs(E - E_ref) [J] "
        "| max abs(E - E0 - W) [J] | fitted order |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, m in models.items():
        ref = refs[name]
        e_ref = np.asarray(jax.vmap(m["system"].energy)(ref.q, ref.qdot))
        for label in METHODS[name]:
            tr = show[name][label]
            err = position_error(tr, ref)
            idx = np.searchsorted(np.asarray(ref.t), np.asarray(tr.t) - 1e-9)
            d_e = np.nanmax(np.abs(np.asarray(tr.energy) - e_ref[idx]))
            summary["final_position_error"][f"{name} {label}"] = float(err[-1])
            p = "-"
            if name == "car":
                summary["fitted_order"][label] = order = fitted_order(*conv_err[label], floor=FIT_FLOOR)
                p = f"{order:.2f}"
            lines.append(
                f"| {name} | {label} | {err[-1]:.2e} | {np.nanmax(err):.2e} | {d_e:.2e} | "
                f"{np.nanmax(np.abs(tr.energy_balance)):.2e} | {p} |"
            )
    lines += [
        "",
        f"Fitted order (car): least squares of log(error at {T_FINAL:g} s) against log(h) over "
        f"h = {', '.join(f'{T_FINAL / n:g}' for n in conv)} s, errors below {FIT_FLOOR:g} m excluded "
        "(`convergence.png`). The work W is the trapezoidal rule on the nodes (second order): on "
        "these forced runs its quadrature error, not the integrator, sets abs(E - E0 - W) of the "
        "higher-order methods; abs(E - E_ref) shows their accuracy.",
        "",
        f"## Long run: the car steered without torque, {n_long:,} steps of h = {H_LONG:g} s",
        "",
        "No work is done (`f_psi = 0`; the steering is kinematic), so E is conserved. Largest "
        "abs(E - E0) [J] over the first and the last tenth of the run, and over the last tenth of "
        "the same number of steps at h/2 (a truncation error shrinks by 2^p at h/2; round-off, "
        "which grows with the number of steps, does not):",
        "",
        "| integrator | first tenth | last tenth | growth | last tenth at h/2 |",
        "|---|---|---|---|---|",
    ]
    for label, ((first, last), last_half) in spans.items():
        lines.append(f"| {label} | {first:.2e} | {last:.2e} | {last / first:.2g}x | {last_half:.2e} |")
    dist = float(np.hypot(*gait.q[-1, :2]))
    gait_err = float(np.linalg.norm(gait.q[-1, :2] - gait_ref.q[-1, :2]))
    lines += [
        "",
        f"## Snakeboard gait ({T_FINAL:g} s from rest, RDP at h = {H_GAIT:g} s)",
        "",
        f"The board travels {dist:.2f} m and turns by {np.degrees(float(gait.q[-1, 2])):.0f} deg; its "
        f"final position differs from the reference's by {gait_err:.1e} m; phi stays in "
        f"[{np.nanmin(gait.q[:, 4]):.2f}, {np.nanmax(gait.q[:, 4]):.2f}] rad "
        "(`snakeboard_gait_loop.png`, `snakeboard_gait.gif`).",
        "",
        "## Cost",
        "",
        "Wall times on this machine. Per model and integrator one program runs every run; "
        f"{args.jobs} program(s) compiled at once. 'group' is its compilation and all its runs; "
        "'one run' the median of 3 runs after compilation.",
        "",
        "| model | integrator | runs x steps | group [s] | one run [ms] | us per step |",
        "|---|---|---|---|---|---|",
    ]
    for name, m in models.items():
        k, n = len(m["runs"]), m["n_steps"]
        for label in METHODS[name]:
            run = run_seconds[(name, label)]
            lines.append(
                f"| {name} | {label} | {k} x {n} | {group_seconds[(name, label)]:.1f} | {1e3 * run:.1f} | "
                f"{1e6 * run / n:.2f} |"
            )
        lines.append(f"| {name} | {REFERENCE} | 2 | {group_seconds[(name, REFERENCE)]:.1f} | - | - |")
    total = time.perf_counter() - start
    lines += [
        "",
        f"Total {total:.0f} s: simulations {t_sim:.0f} s (mostly compilation), figures "
        f"{total - t_sim - t_gif:.0f} s, the GIF {t_gif:.0f} s.",
    ]
    path = out / "quickstart.md"
    path.write_text("\n".join(lines) + "\n")
    written.append(path)
    path = out / "quickstart.json"
    path.write_text(json.dumps(summary, indent=1) + "\n")
    written.append(path)
    print("\n".join(lines))
    print(f"\nwrote ({total:.0f} s):")
    for p in written:
        print(f"  {p}")


if __name__ == "__main__":
    main(ARGS)
