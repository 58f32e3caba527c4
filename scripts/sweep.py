"""The paper's Monte Carlo accuracy/runtime study (Figs. 4 and 5): RDP, GNI, DLA, RK2, RK4.

For each model, duration (10 s and 10 min), method and resolution N (total number of steps):
position error against a fine-step reference (final and max over time), runtime per trajectory
(batched, after compilation, median of repeats) and failure counts, over random sinusoidal
maneuvers. Writes ``OUT/sweep.csv`` (one row per model x duration x method x N),
``OUT/sweep_ratios.csv`` (runtime ratios at equal N and at equal accuracy) and one figure per
model and duration, ``OUT/sweep_<model>_<seconds>s.png``.

The batch axis is sharded over all JAX devices; on a CPU-only machine the script exposes one XLA
host device per core (``--cpu-devices``), so both cores of a 2-core machine work.

    python scripts/sweep.py --quick --out results          # about a minute or two
    python scripts/sweep.py --out results                  # the full study (1000 maneuvers)
"""

from __future__ import annotations

import argparse
import os
import sys
import time

# Failures are data in the study (result codes); an in-jit runtime check that fired would raise
# through a host callback, which can deadlock a computation sharded over several XLA host
# devices. Turn equinox's runtime checks into NaNs (reported as failures) for this script.
os.environ.setdefault("EQX_ON_ERROR", "nan")


def _duration(text: str) -> float:
    t = text.strip().lower()
    for suffix, scale in (("min", 60.0), ("m", 60.0), ("s", 1.0)):
        if t.endswith(suffix):
            return float(t[: -len(suffix)]) * scale
    return float(t)


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="small run: snakeboard, 32 maneuvers, 5 methods")
    p.add_argument("--out", default="results", help="output directory (default: results)")
    p.add_argument("--methods", default=None, help="comma-separated names (default: all; see --list)")
    p.add_argument("--resolutions", default=None, help="comma-separated N (default 250,500,1000,2000,4000)")
    p.add_argument("--runs", type=int, default=None, help="maneuvers per model (default 1000)")
    p.add_argument(
        "--duration", default=None, help="comma-separated durations, e.g. 10s,10min or 10,600 (default both)"
    )
    p.add_argument("--model", default=None, help="snakeboard, car or all (default all)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--repeats", type=int, default=None, help="timed repeats per point (default 3)")
    p.add_argument("--reference-step", type=float, default=None, help="RK4 reference step (default 5e-3)")
    p.add_argument("--cpu-devices", type=int, default=os.cpu_count() or 1, help="XLA host devices on CPU")
    p.add_argument("--list", action="store_true", help="list the method names and exit")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" not in flags and args.cpu_devices > 1:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={args.cpu_devices}".strip()

    import jax

    jax.config.update("jax_enable_x64", True)
    from tqdm import tqdm

    from ldap_jax import sweeps

    if args.list:
        print("\n".join(sweeps.METHODS))
        return 0
    if args.quick:
        defaults = dict(
            models=("snakeboard",),
            methods=("rdp", "gni", "dla", "rk2", "rk4"),
            resolutions=(250, 500, 1000, 2000),
            runs=32,
            repeats=3,
        )
    else:
        defaults = dict(
            models=("snakeboard", "car"),
            methods=tuple(sweeps.METHODS),
            resolutions=(250, 500, 1000, 2000, 4000),
            runs=1000,
            repeats=3,
        )
    try:
        if args.model is not None:
            defaults["models"] = tuple(sweeps.MODELS) if args.model == "all" else tuple(args.model.split(","))
        if args.methods is not None:
            defaults["methods"] = tuple(m.strip() for m in args.methods.split(","))
        if args.resolutions is not None:
            defaults["resolutions"] = tuple(int(n) for n in args.resolutions.split(","))
        if args.runs is not None:
            defaults["runs"] = args.runs
        if args.repeats is not None:
            defaults["repeats"] = args.repeats
        durations = (
            (10.0, 600.0) if args.duration is None else tuple(map(_duration, args.duration.split(",")))
        )
        config = sweeps.StudyConfig(
            durations=durations,
            seed=args.seed,
            reference_step=args.reference_step or 5e-3,
            **defaults,
        )
    except ValueError as err:
        print(f"sweep.py: {err}", file=sys.stderr)
        return 2

    print(
        f"devices: {len(jax.devices())} x {jax.devices()[0].platform}; models {config.models}; "
        f"durations {config.durations}; {len(config.methods)} methods; N {config.resolutions}; "
        f"{config.runs} maneuvers"
    )
    start = time.perf_counter()
    bar = lambda tasks: tqdm(tasks, desc="study", unit="point")  # noqa: E731
    rows = sweeps.run_study(config, progress=bar, log=tqdm.write)
    elapsed = time.perf_counter() - start

    os.makedirs(args.out, exist_ok=True)
    csv_path = os.path.join(args.out, "sweep.csv")
    sweeps.write_csv(rows, csv_path)
    ratios = sweeps.runtime_ratios(rows)
    if ratios:
        sweeps.write_csv(ratios, os.path.join(args.out, "sweep_ratios.csv"))
    figs = sweeps.plot_study(rows, args.out)

    print(f"\nstudy time {elapsed:.1f} s; wrote {csv_path} and {len(figs)} figure(s)")
    print(sweeps.format_table(rows))
    if ratios:
        print("\nruntime ratios (geometric means): equal N | equal accuracy (median final error)")
        for r in ratios:
            print(
                f"  {r['model']:<10} {r['duration']:>6g} s  {r['ratio']:<8} "
                f"{r['equal_n']:8.3g} | {r['equal_accuracy']:8.3g}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
