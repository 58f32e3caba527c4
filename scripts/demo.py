"""`make demo`: the library's main results at quick settings, one stage after the other.

    python scripts/demo.py                  # quick settings, a few minutes on 2 cores -> results/
    python scripts/demo.py --full           # the paper-size versions (hours: the full study)
    python scripts/demo.py --only study,control --out DIR
    python scripts/demo.py --list           # the stages and the commands they run

Each stage is one of the scripts in this folder, run in a process of its own (the benchmarks fix
the number of XLA devices when JAX starts), with its output in ``OUT/logs/<stage>.log``. The demo
prints one line per stage as it finishes, and at the end a table: what each stage wrote, where,
and its headline numbers (read back from the files it wrote).

Every stage runs with JAX's persistent compilation cache (``$LDAP_JAX_CACHE``, by default
``~/.cache/ldap_jax/xla``, as ``lj.enable_compilation_cache()``; ``--no-cache`` turns it off):
compilation is most of a quick run, and a second run loads the programs instead. The
benchmarks' "first call in a new process" rows run without it.

Each stage is made by one function (``gait_stage`` etc.): to change a stage, change its function;
to add one, write a function that returns a :class:`Stage` (with a function that reads its
headline from the files it writes) and add it to :data:`STAGES`.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import pathlib
import resource
import subprocess
import sys
import time
from collections.abc import Callable

from _args import out_dir

SCRIPTS = pathlib.Path(__file__).resolve().parent


@dataclasses.dataclass(frozen=True)
class Stage:
    """One step of the demo: a script with its quick and full arguments (``--out`` is added),
    the files it writes (relative to ``--out``; ``*`` globs) and a function ``out -> text`` that
    reads its headline numbers from them. A stage with ``in_quick=False`` runs with ``--full`` or
    when named in ``--only`` (then with its quick arguments), not in the default quick demo."""

    name: str
    what: str
    script: str
    quick: tuple[str, ...]
    full: tuple[str, ...]
    outputs: tuple[str, ...]
    headline: Callable[[pathlib.Path], str]
    in_quick: bool = True

    def command(self, full: bool, out: pathlib.Path) -> list[str]:
        args = self.full if full else self.quick
        return [sys.executable, str(SCRIPTS / self.script), *args, "--out", str(out)]


def _json(path: pathlib.Path) -> dict:
    return json.loads(path.read_text())


def _quickstart(out: pathlib.Path) -> str:
    r = _json(out / "quickstart.json")
    err = r["final_position_error"]
    car = ", ".join(f"{k} {err[f'car {k}']:.1e}" for k in ("RDP", "RDP-4", "RDP-6", "RK4"))
    orders = "/".join(f"{r['fitted_order'][k]:.1f}" for k in ("RDP", "RDP-4", "RDP-6"))
    return f"car at h = {r['h']:g} s, error at {r['t_final']:g} s [m]: {car}; fitted orders {orders}"


def _study(out: pathlib.Path) -> str:
    with open(out / "sweep.csv") as f:
        rows = list(csv.DictReader(f))
    short = [r for r in rows if float(r["duration"]) <= 10.0]
    long = [r for r in rows if float(r["duration"]) > 10.0]
    n = max(int(r["n_steps"]) for r in short)
    at_n = {r["method"]: r for r in short if int(r["n_steps"]) == n}
    parts = [
        f"10 s, N = {n}: " + ", ".join(f"{m} {float(r['final_error_median']):.1e} m" for m, r in at_n.items())
    ]
    if long:
        n0 = min(int(r["n_steps"]) for r in long)
        fails = {r["method"]: float(r["failure_rate"]) for r in long if int(r["n_steps"]) == n0}
        parts.append(f"10 min, N = {n0} failures: " + ", ".join(f"{m} {v:.0%}" for m, v in fails.items()))
    return "; ".join(parts)


def _optimize(stem: str) -> Callable[[pathlib.Path], str]:
    def headline(out: pathlib.Path) -> str:
        r = _json(out / f"optimize_{stem}.json")
        how = f"{r['iterations']} iterations" + (" (converged)" if r.get("converged") else "")
        return (
            f"{how} in {r['wall_s']:.1f} s; replayed on lj.reference: "
            f"{r['final_position_error']:.1e} m, {r['final_heading_error']:.1e} rad from the goal"
        )

    return headline


def _gait(stem: str) -> Callable[[pathlib.Path], str]:
    def headline(out: pathlib.Path) -> str:
        r = _json(out / f"optimize_{stem}.json")
        dx = r["model_displacement"][0]
        return (
            f"{dx:.6f} m per cycle, {r['iterations']} iterations in {r['wall_s']:.1f} s; on lj.reference "
            f"the state is back to within {max(r['return_error']):.1e} after each of "
            f"{len(r['return_error'])} cycles; {r['stability']}"
        )

    return headline


def _bench(out: pathlib.Path) -> str:
    r = _json(out / "bench.json")
    parts = []
    one = next((h for h in r.get("headline", []) if h["layout"] == "1 device"), None)
    if one:
        parts.append(f"snakeboard RDP {one['steps_per_s_q']:.2g} steps/s (B = N = {one['N']}, 1 device)")
    c1 = next((c for c in r.get("compiled_c", []) if c["threads"] == 1), None)
    if c1:
        parts.append(f"C, 1 thread {c1['steps_per_s']:.2g}")
    calls = {c["call"].split(" ")[0]: c["seconds"] for c in r.get("first_calls", [])}
    if calls:
        parts.append(
            "first calls: "
            + ", ".join(f"{k} {calls[k]:.1f} s" for k in ("simulate", "lc.solve") if k in calls)
        )
    return "; ".join(parts)


def _control(out: pathlib.Path) -> str:
    r = _json(out / "bench_control.json")
    parts = []
    for task, ours in r["ours"].items():
        text = f"{task}: lc.solve {ours['repeat_s']:.3f} s, {ours['position_error']:.0e} m"
        ipopt = r.get("casadi", {}).get(task)
        if ipopt:
            text += f" (IPOPT {ipopt['repeat_s']:.3f} s, {ipopt['position_error']:.0e} m)"
        parts.append(text)
    return "; ".join(parts)


def quickstart_stage() -> Stage:
    return Stage(
        "quickstart",
        "the car and the snakeboard: RDP orders 2, 4, 6 and RK4 against the reference",
        "quickstart.py",
        ("--quick",),
        (),
        ("quickstart_*.png", "convergence.png", "energy_long_run.png", "snakeboard_gait*", "quickstart.*"),
        _quickstart,
    )


def study_stage() -> Stage:
    return Stage(
        "study",
        "the paper's Monte Carlo study (snakeboard, 32 maneuvers, 10 s and 10 min)",
        "sweep.py",
        ("--quick", "--resolutions", "250,1000", "--repeats", "2"),
        (),
        ("sweep*.csv", "sweep_*.png"),
        _study,
    )


def parking_stage() -> Stage:
    return Stage(
        "parking",
        "optimal control: the car parks (lc.solve)",
        "optimize.py",
        ("--model", "car", "--task", "parallel_park", "--quick"),
        ("--model", "car", "--task", "parallel_park"),
        ("optimize_car_parallel_park.*", "parallel_park.gif"),
        _optimize("car_parallel_park"),
    )


def gait_stage() -> Stage:
    """The snakeboard's gait: swap this function's stage for another gait (its script, arguments,
    files and headline) without touching the others."""
    return Stage(
        "drive gait",
        "the snakeboard's drive gait as a hard-constrained limit cycle (lc.solve), replayed 3 cycles",
        "optimize.py",
        ("--model", "snakeboard", "--task", "drive_gait"),
        ("--model", "snakeboard", "--task", "drive_gait"),
        ("optimize_snakeboard_drive_gait.*", "drive_gait.gif"),
        _gait("snakeboard_drive_gait"),
    )


def bench_stage() -> Stage:
    # the first calls in new processes (section first_calls) run with --full: they compile
    # everything again without the cache (about a third of the stage)
    return Stage(
        "bench",
        "throughput against compiled C",
        "bench.py",
        ("--quick", "--only", "headline,compiled_c"),
        (),
        ("bench.json", "bench.md"),
        _bench,
    )


def control_bench_stage() -> Stage:
    # about as long as the rest of the quick demo together (two solver programs compiled, CasADi,
    # a batch, a sharded batch, sensitivities): with --full, or --only "control bench"
    return Stage(
        "control bench",
        "lc.solve against CasADi + IPOPT on parallel_park and u_turn",
        "bench_control.py",
        ("--quick",),
        ("--robustness", "0,1,2"),
        ("bench_control.json", "bench_control.md"),
        _control,
        in_quick=False,
    )


#: The stages, in order, one function each. The quick settings keep the default demo within about
#: five minutes on 2 cores (docs/development.md); --full runs each script at its own full size.
STAGES = (
    quickstart_stage(),
    study_stage(),
    parking_stage(),
    gait_stage(),
    bench_stage(),
    control_bench_stage(),
)


def cache_environment(enabled: bool) -> tuple[dict[str, str], str | None]:
    """The stages' environment: JAX's persistent compilation cache on (JAX reads these variables
    when it starts), in ``$LDAP_JAX_CACHE`` or ``lj.enable_compilation_cache``'s default folder."""
    env = dict(os.environ)
    if not enabled:
        return env, None
    path = os.environ.get("LDAP_JAX_CACHE") or os.path.join(
        os.path.expanduser("~"), ".cache", "ldap_jax", "xla"
    )
    os.makedirs(path, exist_ok=True)
    env.update(
        LDAP_JAX_CACHE=path,
        JAX_COMPILATION_CACHE_DIR=path,
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0.5",
        JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0",
    )
    return env, path


def produced(stage: Stage, out: pathlib.Path) -> str:
    """The stage's files under ``out``, by pattern (with a count where a pattern matched several)."""
    found = []
    for pattern in stage.outputs:
        hits = sorted(out.glob(pattern))
        if len(hits) == 1:
            found.append(hits[0].name)
        elif hits:
            found.append(f"{pattern} ({len(hits)})")
    return ", ".join(found) or "nothing"


def run_stage(stage: Stage, i: int, n: int, args, env: dict[str, str]) -> dict:
    """Run one stage (its output to ``OUT/logs/<name>.log``) and print its line."""
    out = pathlib.Path(args.out)
    log = out / "logs" / f"{stage.name.replace(' ', '_')}.log"
    print(f"[{i}/{n}] {stage.name:<14} {stage.what} ...", end="", flush=True)
    start, cpu = time.perf_counter(), _children_cpu()
    with open(log, "w") as f:
        command = stage.command(args.full, out)
        rc = subprocess.run(command, stdout=f, stderr=subprocess.STDOUT, env=env).returncode
    seconds, cpu = time.perf_counter() - start, _children_cpu() - cpu
    headline = ""
    if rc == 0:
        try:
            headline = stage.headline(out)
        except (OSError, KeyError, ValueError, TypeError, StopIteration) as err:
            headline = f"(no headline: {type(err).__name__} {err}; see {log})"
    status = "ok" if rc == 0 else f"FAILED (exit {rc}; see {log})"
    print(f" {seconds:4.0f} s (cpu {cpu:.0f} s)  {status}", flush=True)
    return dict(stage=stage, seconds=seconds, cpu=cpu, ok=rc == 0, headline=headline, log=log)


def _children_cpu() -> float:
    """CPU seconds (user + system) of the finished child processes: on a shared machine the wall
    time of a stage says more about the other processes than about it."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def summary(done: list[dict], out: pathlib.Path, total: float, cache: str | None) -> str:
    """The closing table (markdown): what each stage wrote and its headline numbers."""
    cpu = sum(d["cpu"] for d in done)
    lines = [
        f"# ldap_jax demo: {len(done)} stages in {total:.0f} s (cpu {cpu:.0f} s)",
        "",
        f"Everything is under `{out}/` (logs in `{out}/logs/`). Persistent compilation cache: "
        + (f"`{cache}`." if cache else "off."),
        "",
        "| stage | time | wrote | headline |",
        "|---|---|---|---|",
    ]
    for d in done:
        wrote = produced(d["stage"], out) if d["ok"] else f"failed: see `{d['log']}`"
        lines.append(f"| {d['stage'].name} | {d['seconds']:.0f} s | {wrote} | {d['headline']} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--full", action="store_true", help="the paper-size versions (hours)")
    p.add_argument("--out", type=out_dir, default="results", help="output folder (default: results)")
    p.add_argument("--only", default=None, help="comma-separated stage names (default: all; see --list)")
    p.add_argument("--no-cache", action="store_true", help="without JAX's persistent compilation cache")
    p.add_argument("--list", action="store_true", help="list the stages and their commands, and exit")
    args = p.parse_args(argv)
    names = [s.name for s in STAGES]
    if args.only is None:
        chosen = [s.name for s in STAGES if args.full or s.in_quick]
    else:
        chosen = [s.strip() for s in args.only.split(",")]
    unknown = [s for s in chosen if s not in names]
    if unknown:
        p.error(f"--only: unknown stages {unknown}; choose among {', '.join(names)}")
    stages = [s for s in STAGES if s.name in chosen]
    skipped = [s.name for s in STAGES if s.name not in chosen]
    out = pathlib.Path(args.out)
    if args.list:
        for s in stages:
            print(f"{s.name:<14} {' '.join(s.command(args.full, out)[1:])}")
        return 0
    (out / "logs").mkdir(parents=True, exist_ok=True)
    env, cache = cache_environment(not args.no_cache)
    print(f"ldap_jax demo ({'full' if args.full else 'quick'} settings) -> {out}/", flush=True)
    start = time.perf_counter()
    done = [run_stage(s, i + 1, len(stages), args, env) for i, s in enumerate(stages)]
    text = summary(done, out, time.perf_counter() - start, cache)
    if skipped:
        text += (
            f"\nNot run: {', '.join(skipped)} (`python scripts/demo.py --only "
            f"'{','.join(skipped)}'` at quick settings; `--full` runs every stage).\n"
        )
    (out / "demo.md").write_text(text)
    print("\n" + text)
    return 0 if all(d["ok"] for d in done) else 1


if __name__ == "__main__":
    raise SystemExit(main())
