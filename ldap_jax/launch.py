"""Run a script as several JAX processes on this machine, and the options by which a script joins
such a run.

JAX's multi-controller runtime runs the same program in every process; the processes find each
other through a coordinator that process 0 serves at ``HOST:PORT``, and a computation over a mesh
of every process's devices runs each device's part in its own process (on CPUs, collectives go
over TCP with gloo). On many machines, start one process per machine by hand, with ``mpirun`` or
with a cluster's job launcher; to try it on one machine::

    python -m ldap_jax.launch -n 2 -- python scripts/sweep.py --quick --out results

starts ``python scripts/sweep.py --quick --out results --coordinator 127.0.0.1:PORT
--num-processes 2 --process-id I --cpu-devices 1`` for I = 0, 1 (a free port, each process with
``--cpu-devices`` CPU devices; the command must not give its own), waits for all of them, and,
if one fails, says which, stops the others and exits with its status. Ctrl-C or ``SIGTERM`` to
the launcher stops them all.

A script joins a run with :func:`add_arguments` (the options ``--coordinator``,
``--num-processes``, ``--process-id``, ``--cluster``, ``--init-timeout``; the first three also
from the environment variables ``JAX_COORDINATOR_ADDRESS``, ``JAX_NUM_PROCESSES`` and
``JAX_PROCESS_ID``), :func:`check_arguments` (before JAX is imported) and :func:`start` (before
JAX computes anything).
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence

__all__ = ["add_arguments", "check_arguments", "start", "launch", "free_port", "main"]

#: Seconds a starting process waits for the others (``--init-timeout``).
DEFAULT_INIT_TIMEOUT = 120.0
_ENV = {
    "coordinator": "JAX_COORDINATOR_ADDRESS",
    "num_processes": "JAX_NUM_PROCESSES",
    "process_id": "JAX_PROCESS_ID",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of a run of several processes to ``parser`` (see the module's text)."""
    group = parser.add_argument_group(
        "several processes (JAX's multi-controller runtime; see python -m ldap_jax.launch --help)"
    )
    group.add_argument(
        "--coordinator",
        default=None,
        metavar="HOST:PORT",
        help=f"address of process 0's coordinator (default ${_ENV['coordinator']})",
    )
    group.add_argument(
        "--num-processes",
        default=None,
        metavar="P",
        help=f"number of processes of the run (default ${_ENV['num_processes']})",
    )
    group.add_argument(
        "--process-id",
        default=None,
        metavar="I",
        help=f"this process's index, 0..P-1 (default ${_ENV['process_id']})",
    )
    group.add_argument(
        "--cluster",
        default=None,
        metavar="METHOD",
        help="let JAX read the processes from a job launcher: auto, slurm, ompi, mpi4py, ...",
    )
    group.add_argument(
        "--init-timeout",
        type=float,
        default=DEFAULT_INIT_TIMEOUT,
        metavar="SECONDS",
        help=f"seconds for all processes to join (default {DEFAULT_INIT_TIMEOUT:g})",
    )


def check_arguments(args: argparse.Namespace, error: Callable[[str], object]) -> None:
    """Check the options of :func:`add_arguments` before JAX is imported, calling ``error`` (e.g.
    ``parser.error``) with a message naming the option on a bad one. Sets ``args.distributed``
    (several processes) and, when known, ``args.process_id`` as an int (else ``None``)."""
    for name, var in _ENV.items():
        flag = _flag(name)
        if getattr(args, name) is None and os.environ.get(var):
            setattr(args, name, os.environ[var])
            flag += f" (from ${var})"
        value = getattr(args, name)
        if value is None or name == "coordinator":
            continue
        try:
            setattr(args, name, int(value))
        except ValueError:
            error(f"argument {flag}: must be an integer, got {value!r}")
    given = [n for n in _ENV if getattr(args, n) is not None]
    if not (args.init_timeout > 0 and args.init_timeout < float("inf")):
        error(f"argument --init-timeout: must be a positive number of seconds, got {args.init_timeout}")
    if args.cluster is not None:
        if given:
            error(f"argument --cluster: the job launcher gives them; leave out {_flag(given[0])}")
        args.distributed = True
        return
    args.distributed = bool(given)
    if not given:
        return
    missing = [n for n in _ENV if getattr(args, n) is None]
    if missing:
        with_ = ", ".join(_flag(n) for n in given)
        error(f"argument {_flag(missing[0])}: required with {with_} (or set ${_ENV[missing[0]]})")
    host, _, port = args.coordinator.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        error(f"argument --coordinator: must be HOST:PORT with a port in 1..65535, got {args.coordinator!r}")
    if args.num_processes < 1:
        error(f"argument --num-processes: must be a positive integer, got {args.num_processes}")
    if not 0 <= args.process_id < args.num_processes:
        error(
            f"argument --process-id: must be in 0..{args.num_processes - 1} "
            f"(--num-processes {args.num_processes}), got {args.process_id}"
        )


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def start(args: argparse.Namespace, error: Callable[[str], object], settings: Mapping[str, object]) -> int:
    """Join the run described by ``args`` (checked by :func:`check_arguments`), or do nothing
    for a single process. ``settings`` (e.g. the other flags) must agree across processes;
    ``error`` is called with a message naming those that do not.

    Returns:
        This process's index (0 for a single process).
    """
    if not args.distributed:
        return 0
    from ._distributed import CoordinatorBusy, SettingsMismatch, initialize

    try:
        return initialize(
            args.coordinator,
            args.num_processes,
            args.process_id,
            cluster=args.cluster,
            timeout=args.init_timeout,
            settings={**settings, "--num-processes": args.num_processes},
        )
    except SettingsMismatch as err:
        error(f"argument {', '.join(err.names)}: {err}")
    except CoordinatorBusy as err:
        error(f"argument --coordinator: {err}")
    except ValueError as err:  # JAX's own check of what a job launcher gave it
        if args.cluster is None:
            raise
        error(f"argument --cluster: {err}")
    raise AssertionError("unreachable: 'error' returned")  # pragma: no cover


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` now (the system's choice; another program may take it later)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def launch(
    command: Sequence[str],
    n: int,
    *,
    cpu_devices: int = 1,
    host: str = "127.0.0.1",
    port: int | None = None,
    poll: float = 0.05,
    grace: float = 5.0,
) -> int:
    """Run ``command`` as ``n`` processes, each with the options of process ``i`` of the run
    appended; wait for all of them. If one fails, name it on stderr, stop the others (``SIGTERM``,
    then ``SIGKILL`` after ``grace`` seconds) and return its exit status (``128 + signal`` for a
    process killed by a signal); else return 0. ``KeyboardInterrupt`` or ``SIGTERM`` (received in
    the main thread) stops them all too, returning ``128 + SIGINT`` or ``128 + SIGTERM``. Defaults:
    one CPU device per process, ``host`` 127.0.0.1, a free port, a poll every 0.05 s, 5 s of grace.

    Raises:
        ValueError: ``n`` or ``cpu_devices`` below 1, or an empty command.
    """
    if n < 1 or cpu_devices < 1 or not command:
        raise ValueError(
            f"'n' and 'cpu_devices' must be positive, 'command' not empty: {n}, {cpu_devices}, {command}"
        )
    address = f"{host}:{free_port(host) if port is None else port}"
    procs = [
        subprocess.Popen(
            [
                *command,
                *("--coordinator", address, "--num-processes", str(n), "--process-id", str(i)),
                *("--cpu-devices", str(cpu_devices)),
            ]
        )
        for i in range(n)
    ]
    # a supervisor's SIGTERM stops the processes too, as Ctrl-C does (else they run on, orphaned)
    previous = _set_handlers({signal.SIGTERM: _terminate})
    try:
        while True:
            codes = [p.poll() for p in procs]
            failed = next((i for i, c in enumerate(codes) if c not in (None, 0)), None)
            if failed is not None:
                code = codes[failed]
                print(
                    f"ldap_jax.launch: process {failed} (pid {procs[failed].pid}) {_status(code)}; "
                    "stopping the others",
                    file=sys.stderr,
                    flush=True,
                )
                return 128 - code if code < 0 else code  # killed by a signal: 128 + its number
            if all(c == 0 for c in codes):
                return 0
            time.sleep(poll)
    except KeyboardInterrupt:
        return 128 + signal.SIGINT
    except _Terminated:
        return 128 + signal.SIGTERM
    finally:
        # stopping: a second Ctrl-C or SIGTERM must not cut it short (the processes would be left)
        stopping = _set_handlers(dict.fromkeys((signal.SIGINT, signal.SIGTERM), signal.SIG_IGN))
        _stop(procs, grace)
        _set_handlers({**stopping, **previous})  # SIGINT's and SIGTERM's handlers from before


class _Terminated(Exception):
    """The launcher received SIGTERM."""


def _terminate(signum, frame):
    raise _Terminated


def _set_handlers(handlers: dict) -> dict:
    """Install ``{signal: handler}`` (in the main thread only: elsewhere nothing changes) and
    return the handlers they replace."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {sig: signal.signal(sig, handler) for sig, handler in handlers.items()}


def _status(code: int) -> str:
    if code >= 0:
        return f"exited with status {code}"
    try:
        name = signal.Signals(-code).name
    except ValueError:
        name = f"signal {-code}"
    return f"was killed by {name}"


def _stop(procs: list[subprocess.Popen], grace: float) -> None:
    for p in procs:
        if p.poll() is None:
            p.terminate()
    deadline = time.monotonic() + grace
    for p in procs:
        try:
            p.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m ldap_jax.launch",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-n", "--num-processes", type=int, required=True, help="processes to start")
    parser.add_argument("--cpu-devices", type=int, default=1, help="CPU devices of each process (default 1)")
    parser.add_argument("--host", default="127.0.0.1", help="the coordinator's host (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=None, help="the coordinator's port (default: a free one)")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- then the command to run")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("argument command: give the command to run after --")
    for flag, value in (("-n/--num-processes", args.num_processes), ("--cpu-devices", args.cpu_devices)):
        if value < 1:
            parser.error(f"argument {flag}: must be a positive integer, got {value}")
    if args.port is not None and not 0 < args.port < 65536:
        parser.error(f"argument --port: must be in 1..65535, got {args.port}")
    given = next((a for a in command[1:] if a == "--cpu-devices" or a.startswith("--cpu-devices=")), None)
    if given is not None:
        parser.error(
            f"argument command: leave out {given!r}: the launcher gives each process its own "
            "(python -m ldap_jax.launch --cpu-devices K -n P -- ...)"
        )
    if shutil.which(command[0]) is None:
        parser.error(f"argument command: {command[0]!r} is not a program on PATH (nor an executable path)")
    return launch(command, args.num_processes, cpu_devices=args.cpu_devices, host=args.host, port=args.port)


if __name__ == "__main__":
    sys.exit(main())
