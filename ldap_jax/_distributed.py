"""Starting JAX as one of several processes: ``jax.distributed.initialize`` with a deadline, and a
check that every process was started with the same settings.

JAX's multi-controller runtime runs the same program in every process; process 0 also hosts the
coordinator that the others reach at its address. Two ways of starting it wrongly would
otherwise hang or mislead:

* a process that never connects (a wrong ``--num-processes`` on process 0, a wrong address, a
  process not started, two processes with the same id): JAX waits for it and then aborts the
  process from C++ without a Python error. :func:`initialize` gives the whole start-up (connect,
  then exchange devices) ``timeout`` seconds and ends the process with a message naming the
  coordinator's address and the settings to check.
* processes started with different settings (another ``--num-processes`` on a process other
  than 0, which JAX does not check, or another sweep): they would compute different things in
  lockstep. :func:`initialize` compares a digest of each named setting across processes and
  raises :class:`SettingsMismatch` naming the settings that differ, in every process.
"""

from __future__ import annotations

import collections
import hashlib
import os
import socket
import sys
import threading
from collections.abc import Mapping

import numpy as np

__all__ = ["CoordinatorBusy", "SettingsMismatch", "initialize", "EXIT_TIMEOUT"]

#: Exit status of a process whose start-up missed its deadline.
EXIT_TIMEOUT = 3


class SettingsMismatch(ValueError):
    """Processes of one run were started with different settings.

    Attributes:
        names: the settings that differ between processes.
    """

    def __init__(self, message: str, names: tuple[str, ...]):
        super().__init__(message)
        self.names = names


class CoordinatorBusy(ValueError):
    """Process 0 cannot serve the coordinator: its port is taken on this machine."""


def initialize(
    coordinator: str | None,
    num_processes: int | None,
    process_id: int | None,
    *,
    cluster: str | None = None,
    timeout: float = 60.0,
    settings: Mapping[str, object] | None = None,
) -> int:
    """Join a run of several JAX processes: ``jax.distributed.initialize``, then start JAX's
    backend (each process learns every process's devices), then compare ``settings``.

    Call it before anything else uses JAX (and after :func:`ldap_jax.use_cpu_cores`, whose
    count is per process). Give either all three of ``coordinator``, ``num_processes`` and
    ``process_id``, or ``cluster`` to let JAX read them from a job launcher (``"auto"``, or one
    of JAX's ``cluster_detection_method`` names: ``"slurm"``, ``"ompi"``, ``"mpi4py"``...).

    Args:
        coordinator: ``HOST:PORT`` of process 0, where it serves the coordinator.
        num_processes: the number of processes of the run.
        process_id: this process's index in ``0 .. num_processes - 1``.
        cluster: see above.
        timeout: seconds for the whole start-up; past them the process prints why and exits
            with status :data:`EXIT_TIMEOUT` (JAX would abort it without a message).
        settings: named values that must agree across processes (e.g. command-line flags).

    Returns:
        This process's index (``jax.process_index()``).

    Raises:
        ValueError: missing or inconsistent arguments (named).
        CoordinatorBusy: (process 0) the coordinator's port is in use on this machine.
        SettingsMismatch: some ``settings`` differ between processes (named), or the processes
            hold different numbers of devices (named ``--cpu-devices``).
    """
    import jax

    explicit = (coordinator, num_processes, process_id)
    if cluster is None and None in explicit:
        raise ValueError(
            "give 'coordinator', 'num_processes' and 'process_id' together, or 'cluster', got "
            f"{coordinator!r}, {num_processes!r}, {process_id!r}"
        )
    if num_processes is not None and not 0 <= (process_id or 0) < num_processes:
        raise ValueError(f"'process_id' must be in 0..{num_processes - 1}, got {process_id}")
    if process_id == 0 and coordinator is not None:
        _check_port_free(coordinator)
    # JAX reads the job launcher's settings unless detection is off; "auto": every method
    detection = {None: "deactivate", "auto": None}.get(cluster, cluster)
    where = coordinator or "the address given by the job launcher"
    with _Deadline(timeout, _late_message(where, num_processes, process_id, timeout)):
        jax.distributed.initialize(
            coordinator,
            num_processes,
            process_id,
            cluster_detection_method=detection,
            initialization_timeout=int(timeout) + 30,  # ours expires first, with a message
        )
        jax.devices()  # the processes exchange their devices here
        _same_device_counts()
        if settings:
            _agree(dict(settings))
    return jax.process_index()


def _check_port_free(coordinator: str) -> None:
    """Raise :class:`CoordinatorBusy` if the coordinator's port is taken on this machine (JAX's
    coordinator would crash the process, or fail with "Failed to start RPC server")."""
    port = int(coordinator.rpartition(":")[2])
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # a closed port's TIME_WAIT is free
        try:
            s.bind(("", port))
        except OSError as err:
            raise CoordinatorBusy(
                f"process 0 serves the coordinator at {coordinator}, but port {port} is in use on this "
                f"machine ({err.strerror}): choose another port (another run may still hold it)"
            ) from None


def _same_device_counts() -> None:
    """Raise :class:`SettingsMismatch` (``--cpu-devices``) in every process if the processes hold
    different numbers of devices: every process sees every device, so no exchange is needed."""
    import jax

    counts = collections.Counter(d.process_index for d in jax.devices())
    if len(set(counts.values())) > 1:
        each = ", ".join(f"process {p}: {c}" for p, c in sorted(counts.items()))
        raise SettingsMismatch(
            f"the processes hold different numbers of devices ({each}); start every process with the "
            "same number (on CPUs: the same --cpu-devices)",
            ("--cpu-devices",),
        )


def _late_message(where: str, n: int | None, i: int | None, timeout: float) -> str:
    this = "" if i is None else f" (this is process {i}, --process-id)"
    count = "all processes" if n is None else f"all {n} processes (--num-processes)"
    return (
        f"ldap_jax: {count} did not join within {timeout:g} s (--init-timeout) through the "
        f"coordinator at {where} (--coordinator){this}. Start every process with the same "
        "--coordinator and --num-processes and its own --process-id in 0..num_processes - 1, "
        "and check that the coordinator's host and port are reachable from every machine."
    )


class _Deadline:
    """Ends the process (status :data:`EXIT_TIMEOUT`) with ``message`` if the ``with`` block
    lasts longer than ``seconds``. A thread does it: the calls being waited on are JAX's C++
    waits, which a Python exception cannot interrupt (they release the GIL, so the thread runs)."""

    def __init__(self, seconds: float, message: str):
        self._timer = threading.Timer(seconds, self._expire, args=(message,))
        self._timer.daemon = True

    @staticmethod
    def _expire(message: str) -> None:  # pragma: no cover - runs in the process it ends
        sys.stdout.flush()
        print(message, file=sys.stderr, flush=True)
        os._exit(EXIT_TIMEOUT)

    def __enter__(self):
        self._timer.start()
        return self

    def __exit__(self, *exc):
        self._timer.cancel()
        return False


def _digest(text: str) -> int:
    """31 bits of a hash of ``text``: exact in int32, JAX's integers unless x64 is on."""
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:4], "little") >> 1


def _agree(settings: dict[str, object]) -> None:
    """Raise :class:`SettingsMismatch` in every process if some settings differ between them."""
    import jax
    from jax.experimental import multihost_utils

    names = sorted(settings)
    # one number per setting, and one for the names
    mine = np.array([_digest(repr(names))] + [_digest(repr(settings[k])) for k in names], np.int32)
    everyone = np.asarray(multihost_utils.process_allgather(mine))  # (processes, settings + 1)
    if np.all(everyone == mine):
        return
    if np.any(everyone[:, 0] != mine[0]):
        raise SettingsMismatch("the processes were started with different sets of options", ("",))
    here, details, differ = jax.process_index(), [], []
    for j, k in enumerate(names):
        others = np.flatnonzero(everyone[:, j + 1] != mine[j + 1])
        if others.size:
            differ.append(k)
            where = ", ".join(str(p) for p in others)
            details.append(f"{k} is {settings[k]!r} in this process ({here}), another in process(es) {where}")
    raise SettingsMismatch(
        f"the processes of this run were started with different settings: {'; '.join(details)}. "
        "Start every process with the same options (only --process-id differs).",
        tuple(differ),
    )
