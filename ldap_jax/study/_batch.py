"""Batched rollouts split over devices, and the study's reference solution."""

from __future__ import annotations

import math
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .._sharding import device_mesh, shard_vmap
from .._simulate import simulate
from ..integrators import RK4, AbstractIntegrator
from ..systems import AbstractSystem

__all__ = ["device_mesh", "shard_batch", "batch_rollout", "reference_batch"]


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
        ``(q_out (B, n_out + 1, d), result codes (B,), seconds)`` with ``seconds`` the median
        wall time of the timed calls for the whole batch (``nan`` when ``repeats == 0``).

    Raises:
        ValueError: ``n_steps`` not a multiple of ``n_out``.
    """
    if int(n_steps) % n_out:
        raise ValueError(f"'n_steps' ({n_steps}) must be a multiple of n_out ({n_out})")
    mesh = device_mesh() if mesh is None else mesh
    # placed on the devices before the timed calls, padded to a multiple of them
    (q0, qdot0, ctl), n = shard_batch(maneuvers, mesh)
    run = shard_vmap(_nodes, in_axes=(None,) * 5 + (0, 0, 0), mesh=mesh)
    t_final = jnp.asarray(t_final, q0.dtype)
    args = (system, integrator, t_final, int(n_steps), int(n_out), q0, qdot0, ctl)
    if repeats:
        jax.block_until_ready(run(*args))
    times = []
    q_out = code = None
    for _ in range(max(repeats, 1)):
        start = time.perf_counter()
        q_out, code = jax.block_until_ready(run(*args))
        times.append(time.perf_counter() - start)
    seconds = float(np.median(times)) if repeats else float("nan")
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
    ``step``, a multiple of ``n_out`` steps), sampled at the ``n_out + 1`` output nodes.

    A converged fine-step run instead of diffrax's adaptive Dopri8, which costs too much over
    10 minutes for 1000 maneuvers; :func:`~ldap_jax.study.run_study` estimates its error by
    halving the step.

    Returns:
        ``(q_ref (B, n_out + 1, d), result codes (B,))``.
    """
    n_ref = n_out * max(1, math.ceil(t_final / (step * n_out)))
    q, code, _ = batch_rollout(system, RK4(), maneuvers, t_final, n_ref, n_out=n_out, mesh=mesh)
    return q, code
