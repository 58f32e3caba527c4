"""Time notebooks as ``tests/test_docs.py`` runs them: each notebook's code cells in an IPython
shell of a new process (imports included), with the persistent compilation cache in a given
folder, printing every cell's wall time and the total.

    python scripts/time_notebooks.py 03 05            # each cold (an empty cache) then warm
    python scripts/time_notebooks.py 03 --cache DIR   # one run with the cache DIR (kept)
    python scripts/time_notebooks.py 03 --events      # and per cell its longest JAX events

Cold: a fresh temporary cache folder; warm: a second new process with the folder the cold run
filled. The notebooks' ``lj.enable_compilation_cache()`` finds the folder through
``$LDAP_JAX_CACHE``. Matplotlib draws to files (``MPLBACKEND=Agg``); the notebooks' files (their
animations) are written into a temporary working folder.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parent.parent

RUNNER = """
import collections, json, sys, time
t0 = time.perf_counter()
from IPython.core.interactiveshell import InteractiveShell
shell = InteractiveShell.instance(colors="nocolor")
cells = json.loads(open(sys.argv[1]).read())
events = collections.Counter()
if sys.argv[2] == "1":
    import jax

    def listen(event, duration, **kwargs):
        if "compile" in event or "trace" in event or "mlir" in event or "retrieval" in event:
            events[(event.rsplit("/", 1)[-1], kwargs.get("fun_name"))] += duration

    jax.monitoring.register_event_duration_secs_listener(listen)
times = []
for i, source in enumerate(cells):
    t = time.perf_counter()
    result = shell.run_cell(source, silent=True)
    times.append(time.perf_counter() - t)
    if events:
        top = ", ".join(f"{v:.1f} {k[0]} {k[1]}" for k, v in events.most_common(6) if v >= 0.3)
        print(f"  cell {i}: {times[-1]:.1f} s: {top}", file=sys.stderr, flush=True)
        events.clear()
    if not result.success:
        print(json.dumps({"failed": i, "error": repr(result.error_in_exec or result.error_before_exec)}))
        sys.exit(1)
print(json.dumps({"cells": times, "total": time.perf_counter() - t0}))
"""


def notebook(prefix: str) -> pathlib.Path | None:
    """The one notebook whose name starts with ``prefix``, else ``None``."""
    found = sorted((ROOT / "notebooks").glob(f"{prefix}*.ipynb"))
    return found[0] if len(found) == 1 and prefix else None


def run(path: pathlib.Path, cache: str, events: bool = False) -> dict:
    cells = ["".join(c["source"]) for c in json.loads(path.read_text())["cells"] if c["cell_type"] == "code"]
    with tempfile.TemporaryDirectory() as work:
        spec = pathlib.Path(work) / "cells.json"
        spec.write_text(json.dumps(cells))
        env = dict(os.environ, MPLBACKEND="Agg", LDAP_JAX_CACHE=cache)
        env.pop("JAX_COMPILATION_CACHE_DIR", None)
        res = subprocess.run(
            [sys.executable, "-c", RUNNER, str(spec), "1" if events else "0"],
            cwd=work,
            env=env,
            stdout=subprocess.PIPE,
            stderr=None if events else subprocess.PIPE,
            text=True,
        )
    lines = [line for line in res.stdout.splitlines() if line.startswith("{")]
    if res.returncode or not lines:
        raise SystemExit(f"{path.name} failed: {res.stdout[-2000:]}\n{(res.stderr or '')[-3000:]}")
    return json.loads(lines[-1])


def show(name: str, label: str, out: dict) -> None:
    cells = " ".join(f"{t:.1f}" for t in out["cells"])
    load = os.getloadavg()[0]
    print(f"{name} {label}: {out['total']:.1f} s  [cells: {cells}]  load {load:.1f}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("notebooks", nargs="+", help="notebook number prefixes, e.g. 03")
    parser.add_argument("--cache", help="one run with this cache folder (kept) instead of cold + warm")
    parser.add_argument(
        "--events", action="store_true", help="per cell, its longest JAX tracing, lowering and compilations"
    )
    args = parser.parse_args()
    paths = [notebook(prefix) for prefix in args.notebooks]
    for prefix, path in zip(args.notebooks, paths):
        if path is None:
            parser.error(f"notebooks: no single notebook in notebooks/ starts with {prefix!r}")
    if args.cache and pathlib.Path(args.cache).exists() and not pathlib.Path(args.cache).is_dir():
        parser.error(f"--cache: {args.cache!r} exists and is not a folder")
    for path in paths:
        if args.cache:
            show(path.name, "run", run(path, args.cache, args.events))
            continue
        with tempfile.TemporaryDirectory() as cache:
            show(path.name, "cold", run(path, cache, args.events))
            show(path.name, "warm", run(path, cache, args.events))


if __name__ == "__main__":
    main()
