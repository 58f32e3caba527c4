"""Batched rollouts split over devices, and the study's reference solution."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .._sharding import device_mesh, shard_vmap
from .._simulate import simulate
from ..integrators import RK4, AbstractIntegrator
from ..systems import AbstractSystem

__all__ = [
    "device_mesh",
    "shard_batch",
    "rollout_nodes",
    "timed",
    "batch_rollout",
    "reference_batch",
    "reference_steps",
]


def shard_batch(tree, mesh: Mesh):
    """Pad the leading (batch) axis of every array leaf to a multiple of the mesh size (repeating
    the last member) and place it with ``NamedSharding(mesh, P("batch"))``.

    Returns:
        ``(sharded_tree, n)`` with ``n`` the original batch size.
    """
    leaves = jax.tree_util.tree_leaves(tree)
    n = leaves[0].shape[0]
    pad = (-n) % mesh.devices.size
    sharding = NamedSharding(mesh, PartitionSpec("batch"))

    def place(x):
        x = np.asarray(x)
        if pad:
            x = np.concatenate([x, np.repeat(x[-1:], pad, axis=0)])
        return jax.device_put(x, sharding)

    return jax.tree_util.tree_map(place, tree), n


def _gather(x) -> np.ndarray:
    if jax.process_count() > 1 and not x.is_fully_addressable:  # pragma: no cover (multi-host)
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(x)


def _nodes(system, integrator, t_final, n_steps: int, n_out: int, q0, qdot0, controls):
    """One maneuver's ``n_out + 1`` evenly spaced positions and its result code."""
    traj = simulate(
        system,
        q0,
        qdot0,
        controls,
        t_final=t_final,
        n_steps=n_steps,
        integrator=integrator,
        save=n_steps // n_out,
        diagnostics=False,
        check_constraints=False,
    )
    return traj.q, traj.result._value


def rollout_nodes(
    system: AbstractSystem,
    integrator: AbstractIntegrator,
    maneuvers,
    t_final: float,
    n_steps: int,
    *,
    n_out: int,
    mesh: Mesh,
    xla_defaults: bool = False,
):
    """:func:`ldap_jax.simulate` over a batch of maneuvers already placed on the devices of
    ``mesh`` (global arrays, e.g. from :func:`shard_batch` or
    :func:`~ldap_jax.study.global_maneuvers`), keeping ``n_out + 1`` evenly spaced positions.

    ``xla_defaults``: compile the program with XLA's default options, as a user's ``jax.jit``
    does, instead of :func:`ldap_jax.compiler_options` (default ``False``). The study times its
    points this way: the library's options halve the compile time but slow some methods' runs
    more than others' (200 snakeboard maneuvers, 1000 steps: RDP order 2 1.37x, order 6 1.52x,
    RK4 0.92x), which would bias the runtime ratios between methods.

    Returns:
        ``(q_out (B, n_out + 1, d), result codes (B,))``, global arrays split as the batch is.

    Raises:
        ValueError: ``n_steps`` not a multiple of ``n_out``.
    """
    if int(n_steps) % n_out:
        raise ValueError(f"'n_steps' ({n_steps}) must be a multiple of n_out ({n_out})")
    q0, qdot0, ctl = maneuvers
    t_final = jnp.asarray(t_final, q0.dtype)
    args = (system, integrator, t_final, int(n_steps), int(n_out), mesh, q0, qdot0, ctl)
    return (_sharded_nodes_xla_defaults if xla_defaults else _sharded_nodes)(*args)


def _sharded_nodes(system, integrator, t_final, n_steps, n_out, mesh, q0, qdot0, ctl):
    run = shard_vmap(_nodes, in_axes=(None,) * 5 + (0, 0, 0), mesh=mesh)
    return run(system, integrator, t_final, n_steps, n_out, q0, qdot0, ctl)


# the caller's jit of a user: the sharded program inside it is traced inline and compiles with
# XLA's defaults
_sharded_nodes_xla_defaults = eqx.filter_jit(_sharded_nodes)


def timed(call: Callable[[], Any], repeats: int) -> tuple[Any, float]:
    """The median wall time of ``repeats`` calls of ``call`` after one untimed (compiling) call,
    each waiting for its results. With several processes, a call's time is the longest any
    process took (a collective of one number per call and process).

    Returns:
        ``(the last call's results, seconds)``.
    """
    out = jax.block_until_ready(call())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(call())
        times.append(time.perf_counter() - start)
    times = np.asarray(times)
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        times = np.max(np.asarray(multihost_utils.process_allgather(times)), axis=0)
    return out, float(np.median(times))


def batch_rollout(
    system: AbstractSystem,
    integrator: AbstractIntegrator,
    maneuvers,
    t_final: float,
    n_steps: int,
    *,
    n_out: int,
    mesh: Mesh | None = None,
    repeats: int = 0,
) -> tuple[np.ndarray, np.ndarray, float]:
    """:func:`ldap_jax.simulate` over a batch of maneuvers ``(q0, qdot0, controls)``, keeping
    ``n_out + 1`` evenly spaced nodes (positions only, ``save=n_steps // n_out``), the batch split
    over the devices of ``mesh`` (default: all devices) by :func:`ldap_jax.shard_vmap`.

    Args:
        repeats: if positive, a first call (compiling) is not timed, then ``repeats`` calls are.

    Returns:
        ``(q_out (B, n_out + 1, d), result codes (B,), seconds)`` on the host (with several
        processes, every process gets the whole batch), with ``seconds`` the median wall time
        of the timed calls for the whole batch (``nan`` when ``repeats == 0``).

    Raises:
        ValueError: ``n_steps`` not a multiple of ``n_out``.
    """
    mesh = device_mesh() if mesh is None else mesh
    # placed on the devices before the timed calls, padded to a multiple of them
    placed, n = shard_batch(maneuvers, mesh)

    def call():
        return rollout_nodes(system, integrator, placed, t_final, n_steps, n_out=n_out, mesh=mesh)

    (q_out, code), seconds = timed(call, repeats) if repeats else (call(), float("nan"))
    return _gather(q_out)[:n], _gather(code)[:n], seconds


def reference_batch(
    system: AbstractSystem,
    maneuvers,
    t_final: float,
    *,
    n_out: int,
    step: float = 5e-3,
    mesh: Mesh | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """High-accuracy reference: RK4 on the continuous equations with a fine step (at most
    ``step``, default 5e-3 s, a multiple of ``n_out`` steps), sampled at the ``n_out + 1`` output
    nodes, the batch split over the devices of ``mesh`` (default: every device).

    A converged fine-step run instead of diffrax's adaptive Dopri8, which costs too much over
    10 minutes for 1000 maneuvers; :func:`~ldap_jax.study.run_study` estimates its error by
    halving the step.

    Returns:
        ``(q_ref (B, n_out + 1, d), result codes (B,))``.
    """
    n_ref = reference_steps(t_final, n_out, step)
    q, code, _ = batch_rollout(system, RK4(), maneuvers, t_final, n_ref, n_out=n_out, mesh=mesh)
    return q, code


def reference_steps(t_final: float, n_out: int, step: float) -> int:
    """The reference's number of RK4 steps: the fewest multiple of ``n_out`` with a step of at
    most ``step``."""
    return n_out * max(1, math.ceil(t_final / (step * n_out)))
