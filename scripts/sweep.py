"""The paper's Monte Carlo accuracy/runtime study (Figs. 4 and 5): RDP, GNI, DLA, RK2, RK4.

For each model, duration (10 s and 10 min), method and resolution N (total number of steps):
position error against a fine-step reference (final and max over time), runtime per trajectory
(batched, after compilation, median of repeats) and failure counts, over random sinusoidal
maneuvers. Writes ``OUT/sweep.csv`` (one row per model x duration x method x N),
``OUT/sweep_ratios.csv`` (runtime ratios at equal N and at equal accuracy) and one figure per
model and duration, ``OUT/sweep_<model>_<seconds>s.png``.

The batch axis is sharded over all JAX devices; on a CPU-only machine the script exposes one XLA
host device per core (``--cpu-devices``), so both cores of a 2-core machine work.

Each point's row is also kept in ``OUT/chunks/`` as soon as it is done: a sweep stopped and
started again with the same ``--out`` and settings computes only the points it lacks
(``--fresh`` computes them all again).

Over several processes (JAX's multi-controller runtime; on many machines, one process per
machine), the batch is split over the devices of every process, each process sampling and
running its own devices' maneuvers; only process 0 writes files and prints the tables. Every
process gets the same options plus ``--coordinator HOST:PORT --num-processes P --process-id I``
(or ``--cluster auto`` under Slurm or ``mpirun``); to try it on one machine,
``python -m ldap_jax.launch -n 2 -- python scripts/sweep.py ARGS`` starts the processes.

    python scripts/sweep.py --quick --out results          # about a minute or two
    python scripts/sweep.py --out results                  # the full study (1000 maneuvers)
    python -m ldap_jax.launch -n 2 -- python scripts/sweep.py --quick --out results
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # also when loaded by file path
from _args import positive_int  # noqa: E402

# Failures are data in the study (result codes); an in-jit runtime check that fired would raise
# through a host callback, which can deadlock a computation sharded over several XLA host
# devices. Turn equinox's runtime checks into NaNs (reported as failures) for this script.
os.environ.setdefault("EQX_ON_ERROR", "nan")


#: The names of ``ldap_jax.study.METHODS`` and ``MODELS``, spelled out so that the flags are checked
#: before JAX is imported (seconds); tests/test_faults.py checks that they match the library's.
METHOD_NAMES = (
    "rdp",
    "rdp4",
    "rdp6",
    "rdp8",
    "rdp_a0",
    "rdp_a1",
    "rdp_cayley",
    "rdp_a0_cayley",
    "rdp_a1_cayley",
    "gni",
    "gni_folded",
    "dla",
    "rk2",
    "rk4",
)
MODEL_NAMES = ("snakeboard", "car")


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}") from None
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text!r}")
    return value


def _duration(text: str) -> float:
    """``10``, ``10s``, ``10min`` or ``10m`` (minutes) -> seconds."""
    t = text.strip().lower()
    scale = 1.0
    for suffix, factor in (("min", 60.0), ("m", 60.0), ("s", 1.0)):
        if t.endswith(suffix):
            t, scale = t[: -len(suffix)], factor
            break
    try:
        value = float(t) * scale
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be durations like 10s, 10min or 600, got {text!r}") from None
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"durations must be positive and finite, got {text!r}")
    return value


def _list(item):
    """A comma-separated list of ``item``s (non-empty)."""

    def parse(text: str):
        parts = [p.strip() for p in text.split(",")]
        if not parts or any(not p for p in parts):
            raise argparse.ArgumentTypeError(
                f"must be a comma-separated list without empty entries, got {text!r}"
            )
        return tuple(item(p) for p in parts)

    return parse


def _name(choices):
    def parse(text: str) -> str:
        if text not in choices:
            raise argparse.ArgumentTypeError(f"unknown name {text!r}; choose from {', '.join(choices)}")
        return text

    return parse


def _models(text: str) -> tuple[str, ...]:
    return MODEL_NAMES if text.strip() == "all" else _list(_name(MODEL_NAMES))(text)


def parse_args(argv=None):
    """Parse and check every flag (exit status 2 and a message naming the flag on a bad one),
    before JAX is imported and before any computation."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="small run: snakeboard, 32 maneuvers, 5 methods")
    p.add_argument("--out", default="results", help="output directory (default: results)")
    p.add_argument(
        "--methods",
        type=_list(_name(METHOD_NAMES)),
        default=None,
        help="comma-separated names (default: all; see --list)",
    )
    p.add_argument(
        "--resolutions",
        type=_list(positive_int),
        default=None,
        help="comma-separated N (default 250,500,1000,2000,4000)",
    )
    p.add_argument("--runs", type=positive_int, default=None, help="maneuvers per model (default 1000)")
    p.add_argument(
        "--duration",
        type=_list(_duration),
        default=None,
        help="comma-separated durations, e.g. 10s,10min or 10,600 (default both)",
    )
    p.add_argument("--model", type=_models, default=None, help="snakeboard, car or all (default all)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--repeats", type=positive_int, default=None, help="timed repeats per point (default 3)")
    p.add_argument(
        "--reference-step", type=_positive_float, default=None, help="RK4 reference step (default 5e-3)"
    )
    p.add_argument(
        "--cpu-devices", type=positive_int, default=os.cpu_count() or 1, help="XLA host devices on CPU"
    )
    p.add_argument("--list", action="store_true", help="list the method names and exit")
    p.add_argument(
        "--fresh", action="store_true", help="compute every point again (default: resume from OUT/chunks)"
    )
    here = os.path.dirname(os.path.abspath(__file__))
    if here not in sys.path:
        sys.path.insert(0, here)  # for _launch.py: the process options, ldap_jax.launch's
    import _launch

    options = _launch.launch_options()
    options.add_arguments(p)
    args = p.parse_args(argv)
    options.check_arguments(args, p.error)
    args.error = p.error
    if not args.list and (args.process_id == 0 or not args.distributed):
        check_out(args)  # by the process that writes (unknown yet under --cluster: checked later)
    return args


def check_out(args) -> None:
    """Check (and create) the output folder before the study, not after it."""
    p_error = args.error
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        p_error(f"argument --out: {args.out!r} exists and is not a directory")
    try:
        os.makedirs(args.out, exist_ok=True)
    except OSError as err:
        p_error(f"argument --out: cannot create {args.out!r}: {err}")


#: The flags that choose what is computed: every process of a run must be given the same.
STUDY_FLAGS = ("quick", "methods", "resolutions", "runs", "duration", "model", "seed", "repeats", "fresh")


def study_config(args, sweeps):
    """The study's settings from the flags (``--quick`` and the defaults, then each flag)."""
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
    for key, value in (
        ("models", args.model),
        ("methods", args.methods),
        ("resolutions", args.resolutions),
        ("runs", args.runs),
        ("repeats", args.repeats),
    ):
        if value is not None:
            defaults[key] = value
    try:
        return sweeps.StudyConfig(
            durations=(10.0, 600.0) if args.duration is None else args.duration,
            seed=args.seed,
            reference_step=5e-3 if args.reference_step is None else args.reference_step,
            **defaults,
        )
    except (TypeError, ValueError) as err:
        args.error(f"the settings are inconsistent: {err}")


def report(rows, args, sweeps, elapsed: float) -> None:
    """Write the CSV files and figures under ``--out`` and print the tables."""
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


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.list:
        print("\n".join(METHOD_NAMES))
        return 0
    import ldap_jax as lj

    if args.cpu_devices > 1:
        lj.use_cpu_cores(args.cpu_devices)  # before JAX starts
    import jax

    from ldap_jax import launch

    jax.config.update("jax_enable_x64", True)
    # JAX's preemption service would take SIGTERM over (noting a preemption, running on): a
    # process of a run must stop when the launcher or a job scheduler stops it
    jax.config.update("jax_enable_preemption_service", False)
    # joins the other processes, if any (before JAX computes anything), checking that they were
    # given the same study flags
    settings = {f"--{k.replace('_', '-')}": getattr(args, k) for k in STUDY_FLAGS + ("reference_step",)}
    lead = launch.start(args, args.error, settings) == 0
    from tqdm import tqdm

    from ldap_jax import study as sweeps

    if lead and args.process_id is None:
        check_out(args)  # --cluster: this process is the one that writes
    config = study_config(args, sweeps)
    if lead:
        print(
            f"devices: {len(jax.devices())} x {jax.devices()[0].platform} in {jax.process_count()} "
            f"process(es); models {config.models}; durations {config.durations}; "
            f"{len(config.methods)} methods; N {config.resolutions}; {config.runs} maneuvers"
        )
    start = time.perf_counter()
    rows = sweeps.run_study(
        config,
        progress=(lambda tasks: tqdm(tasks, desc="study", unit="point")) if lead else None,
        log=tqdm.write if lead else None,
        chunks=os.path.join(args.out, "chunks"),
        resume=not args.fresh,
    )
    if lead:  # the other processes write nothing
        report(rows, args, sweeps, time.perf_counter() - start)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
