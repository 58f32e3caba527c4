"""The main job at quick settings: both models under RDP vs the reference and RK4.

Writes ``results/quickstart_paths.png``, ``results/quickstart_diagnostics.png`` and
``results/quickstart.md``. Later stages (sweep, optimization, benchmark) are run by ``make demo``.
"""

import argparse
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import ldap_jax as lj  # noqa: E402
from ldap_jax.plotting import plot_diagnostics, plot_paths  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="small sizes")
    parser.add_argument("--out", default="results", help="output folder")
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    t_final = 10.0
    n_steps = 100 if args.quick else 200
    models = {
        "car": lj.Car(m=1.0, I=0.1, K=0.2, rho=0.1, l=0.5),
        "snakeboard": lj.Snakeboard(m=1.0, l=0.5, I=0.05, J=0.02),
    }
    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    rows = [
        "| model | integrator | N | h [s] | final position error [m] | max position error [m] | wall [ms] |",
        "|---|---|---|---|---|---|---|",
    ]
    diag = {}
    for ax, (name, system) in zip(axes, models.items()):
        q0, qdot0, ctl = system.sample_maneuver(jax.random.PRNGKey(args.seed))
        ts = jnp.linspace(0.0, t_final, n_steps + 1)
        ref = lj.reference(system, q0, qdot0, ctl, ts)
        paths = {"reference (diffrax Dopri8)": ref.q}
        for label, integrator in (("RDP", lj.RDP()), ("RK4", lj.RK4()), ("RK2", lj.RK2())):
            lj.simulate(system, q0, qdot0, ctl, t_final=t_final, n_steps=n_steps, integrator=integrator)
            t = time.perf_counter()
            traj = lj.simulate(
                system, q0, qdot0, ctl, t_final=t_final, n_steps=n_steps, integrator=integrator
            )
            traj.q.block_until_ready()
            wall = 1e3 * (time.perf_counter() - t)
            err = jnp.linalg.norm(traj.q[:, :2] - ref.q[:, :2], axis=1)
            rows.append(
                f"| {name} | {label} | {n_steps} | {t_final / n_steps:.3f} | {float(err[-1]):.2e} | "
                f"{float(err.max()):.2e} | {wall:.2f} |"
            )
            paths[f"{label}, h = {t_final / n_steps:.2f} s"] = traj.q
            if label == "RDP":
                diag[f"{name}"] = traj
        plot_paths(
            ax,
            system,
            paths,
            draw="reference (diffrax Dopri8)",
            styles={"reference (diffrax Dopri8)": {"color": "k", "lw": 2.5, "alpha": 0.4}},
        )
        ax.set_title(f"{name}: random maneuver, {t_final:g} s")
    fig.tight_layout()
    fig.savefig(out / "quickstart_paths.png", dpi=120)
    plt.close(fig)
    axes = plot_diagnostics(diag)
    axes[0].figure.tight_layout()
    axes[0].figure.savefig(out / "quickstart_diagnostics.png", dpi=120)
    (out / "quickstart.md").write_text("\n".join(rows) + "\n")
    print("\n".join(rows))
    print(
        f"wrote {out / 'quickstart_paths.png'}, {out / 'quickstart_diagnostics.png'}, {out / 'quickstart.md'}"
    )


if __name__ == "__main__":
    main()
