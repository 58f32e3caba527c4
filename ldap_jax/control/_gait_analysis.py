"""A gait's cycle map, its Floquet multipliers, and its replay over several cycles on the reference.

The *cycle map* ``P`` of a periodic task takes the start's reduced state ``z = (r, v)`` (the
non-cyclic shape coordinates and the minimal velocities; the group at the identity and the cyclic
coordinates at 0) to the reduced state one period later, through the task's own discrete
dynamics and its periodic controls. A gait is a fixed point, ``P(z*) = z*``. Its *monodromy*
``M = dP/dz (z*)`` (by automatic differentiation) decides what happens to a perturbed start: its
eigenvalues are the Floquet multipliers. All inside the unit circle: the gait is asymptotically
stable (an error dies out cycle by cycle). One outside: unstable. On the unit circle: neutrally
stable, and a Jordan block of size ``k`` at a multiplier 1 lets an error grow like ``n^(k-1)`` over
``n`` cycles. The snakeboard and the car have multipliers at 1 (nothing pulls a drifted rotor or
wheel speed back), so their gaits drift under any error and need feedback to be executed.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .. import lie
from .._compilation_cache import asarray, jit
from .._reference import reference
from .._results import RESULTS
from .._validation import is_concrete
from . import _export
from ._solve import checked_params
from ._task import Task

__all__ = ["cycle_map", "monodromy", "floquet", "replay_gait"]


def gait_params(task: Task, params, where: str):
    """One solution's ``params`` of the periodic ``task``, checked (:func:`checked_params`)."""
    if isinstance(task, Task) and task.periodic is None:
        raise ValueError(
            f"{where} needs a periodic task (lc.drive_gait(), lc.make_gait(...)), got {task.name!r}"
        )
    return checked_params(task, params, where)


def _keep(task: Task) -> np.ndarray:
    """Indices in ``q`` of the non-cyclic shape coordinates."""
    names = task.system.shape_names
    return np.asarray([3 + i for i, n in enumerate(names) if n not in task.periodic.cyclic], int)


def reduced_state(task: Task, q: Array, qdot: Array) -> Array:
    """The gait's reduced state ``(r, v)`` of a configuration and velocity."""
    return jnp.concatenate([q[_keep(task)], task.system.velocities_from_qdot(q, qdot)])


def _configuration(task: Task, z: Array) -> tuple[Array, Array]:
    """``(q, v)`` of a reduced state ``z = (r, v)``: the group and the cyclic coordinates at 0."""
    keep = _keep(task)
    q = jnp.zeros((task.system.n_config,), z.dtype).at[keep].set(z[: keep.size])
    return q, z[keep.size :]


def _start(task: Task, params, z: Array) -> tuple[Array, Array]:
    q, v = _configuration(task, z)
    c0 = task.controls(params)(jnp.zeros((), z.dtype))
    return q, task.system.qdot_from_velocities(q, v, c0)


def _one_cycle(task: Task, params, z: Array):
    """``(P(z), the group at the period's end, the rollout's result, whether it failed)``."""
    q0, qdot0 = _start(task, params, z)
    traj = task.rollout(params, start=(q0, qdot0), save="final")
    q, qdot = traj.q.reshape(-1, q0.shape[0])[-1], traj.qdot.reshape(-1, q0.shape[0])[-1]
    return reduced_state(task, q, qdot), q[:3], traj.result, traj.failed


def cycle_map(task: Task, params, z: Array) -> Array:
    """``P(z)``: the reduced state after one period of the task's discrete dynamics, from the
    start with reduced state ``z`` (group at the identity, cyclic coordinates at 0).

    ``z`` has the shape of :func:`monodromy`'s ``z*`` (the non-cyclic shape coordinates, then the
    minimal velocities). Where the period's rollout fails (the snakeboard's ``cos(phi) = 0``, a
    non-finite state), ``P(z)`` is NaN; called on known values, that is an error naming the
    rollout's result.

    Raises:
        TypeError, ValueError: a task that is not periodic, ``params`` that are not its
            :class:`GaitParams`, ``z`` of the wrong shape; on known values, a failed rollout.
    """
    params = gait_params(task, params, "cycle_map")
    n_z = _keep(task).size + task.system.n_velocities
    if jnp.shape(z) != (n_z,):
        raise ValueError(
            f"cycle_map: 'z' must have shape ({n_z},) (the non-cyclic shape coordinates and the "
            f"minimal velocities), got {jnp.shape(z)}"
        )
    z_next, result = _cycle_map(task, params, asarray(z, task.bounds.q_lower.dtype))
    if is_concrete((z_next, result)) and not np.all(np.isfinite(np.asarray(z_next))):
        raise ValueError(f"cycle_map: the period's rollout from 'z' failed: {RESULTS[result]}")
    return z_next


@eqx.filter_jit
def _cycle_map(task: Task, params, z: Array):
    z1, _, result, failed = _one_cycle(task, params, z)
    return jnp.where(failed, jnp.nan, z1), result


def _analysis_of(task: Task, params):
    q0, qdot0 = task.initial_state(params)
    z0 = reduced_state(task, q0, qdot0)
    z1, g1, _, _ = _one_cycle(task, params, z0)
    M = jax.jacfwd(lambda z: _one_cycle(task, params, z)[0])(z0)
    return z0, z1, g1, M, q0, qdot0


_analysis_traced = jit(_analysis_of)  # the library's compile options (XLA's: 1.8x the compile time)


def _analysis(task: Task, params):
    """``(z*, P(z*), the group's displacement over the cycle, M, q0, qdot0)``, through the program an earlier
    process exported when it can (as ``lc.solve``'s: no tracing in a new process)."""
    out = _export.call("gait_analysis", _analysis_of, (task, params), lambda: (0,) * 6)
    return _analysis_traced(task, params) if out is NotImplemented else out


@eqx.filter_jit
def _cycle_starts(task: Task, q: Array, qdot: Array) -> tuple[Array, Array]:
    """The reduced states at the cycles' starts and the group's displacement over each cycle
    (one program, not an eager operation each)."""
    z = jax.vmap(lambda a, b: reduced_state(task, a, b))(q, qdot)
    g = q[:, :3]
    return z, jax.vmap(lambda a, b: lie.compose(lie.inverse(a), b))(g[:-1], g[1:])


def monodromy(task: Task, params) -> tuple[Array, Array]:
    """``(z*, M)``: the gait's start reduced state and the Jacobian of the cycle map there.

    Raises:
        TypeError, ValueError: a task that is not periodic, ``params`` that are not its
            :class:`GaitParams` (a :class:`~ldap_jax.control.Solution` counts as its ``params``);
            on known values, a period whose rollout fails (e.g. the snakeboard at ``cos(phi) = 0``).
    """
    params = gait_params(task, params, "monodromy")
    z0, z1, _, M, _, _ = _analysis(task, params)
    _check_finite("monodromy", task, params, z1, M)
    return z0, M


def _check_finite(where: str, task: Task, params, z1, M) -> None:
    """On known values, a ``ValueError`` for a cycle whose rollout failed (its end state or its
    monodromy not finite) instead of NaNs returned or LAPACK's error on them."""
    if is_concrete((z1, M)) and not all(np.all(np.isfinite(np.asarray(x))) for x in (z1, M)):
        result = task.rollout(params).result
        raise ValueError(
            f"{where}: the period's rollout from the gait's start failed ({RESULTS[result]}), so the "
            "cycle map and its monodromy are not finite: this start is not a periodic orbit of the model"
        )


def floquet(M: np.ndarray, *, cluster: float = 1e-3, rank_tol: float = 1e-7) -> dict:
    """The Floquet multipliers of a monodromy matrix and the Jordan structure at 1.

    Eigenvalues within ``cluster`` of 1 are taken as one multiplier 1 (a Jordan block of size
    ``k`` perturbed by ``eps`` splits into eigenvalues ``eps^(1/k)`` apart, which is why the
    eigenvalues alone are unreliable there); the block sizes follow from the ranks of
    ``(M - I)^j`` (singular values above ``rank_tol`` times the largest).

    Returns a dict: ``multipliers`` (complex array), ``moduli``, ``at_one`` (how many),
    ``jordan_blocks`` (sizes of the blocks at 1, largest first), ``stability``
    (``"asymptotically stable"``, ``"neutrally stable"`` or ``"unstable"``) and ``growth``
    (the power of the cycle count by which an error grows: the largest block size minus 1).
    """
    M = np.asarray(M, float)
    if M.ndim != 2 or M.shape[0] != M.shape[1]:
        raise ValueError(f"floquet: 'M' must be a square matrix (a monodromy), got shape {M.shape}")
    if not np.all(np.isfinite(M)):
        raise ValueError("floquet: 'M' has non-finite entries (the cycle's rollout failed?)")
    n = M.shape[0]
    lam = np.linalg.eigvals(M)
    near = np.abs(lam - 1.0) < cluster
    a = int(np.sum(near))
    blocks: list[int] = []
    if a:
        ranks = [n]
        P = np.eye(n)
        for _ in range(a):
            P = P @ (M - np.eye(n))
            s = np.linalg.svd(P, compute_uv=False)
            ranks.append(int(np.sum(s > rank_tol * max(1.0, s[0]))))
        at_least = [ranks[j] - ranks[j + 1] for j in range(a)]  # blocks of size >= j + 1
        for j in range(a):
            exactly = at_least[j] - (at_least[j + 1] if j + 1 < a else 0)
            blocks += [j + 1] * max(exactly, 0)
        blocks.sort(reverse=True)
    moduli = np.abs(lam)
    others = moduli[~near]
    if np.any(others > 1 + cluster):
        stability = "unstable"
    elif a or np.any(np.abs(others - 1) <= cluster):
        stability = "neutrally stable"
    else:
        stability = "asymptotically stable"
    return {
        "multipliers": lam,
        "moduli": moduli,
        "at_one": a,
        "jordan_blocks": blocks,
        "stability": stability,
        "growth": (max(blocks) - 1) if blocks else 0,
    }


def replay_gait(
    task: Task, params, *, cycles: int = 3, rtol: float | None = None, atol: float | None = None
) -> dict:
    """Replay a gait for ``cycles`` periods on the high-accuracy reference (:func:`ldap_jax.reference`)
    from the optimised start, and analyse its cycle on the model.

    Args:
        task: a periodic task (``lc.drive_gait()``, ``lc.make_gait(...)``).
        params: its solution's parameters (``lc.solve(task).params``: :class:`GaitParams`; the
            :class:`~ldap_jax.control.Solution` itself is taken as its ``params``).
        cycles: periods to replay (a positive integer; default 3).
        rtol, atol: the reference's tolerances (default ``None``: 1e-11 in float64, 1e-6 in float32).

    Returns:
        A dict with ``displacement`` (cycles, 3): each cycle's net displacement
        ``g(kT)^-1 g((k+1)T)`` as ``(dx, dy, dtheta)`` in that cycle's start frame, on the
        reference; ``model_displacement`` (3,): the model's (every cycle of the periodic orbit
        moves the same); ``return_error`` (cycles,): the largest entry of
        ``|z_ref(kT) - z*|`` after each cycle (``z*``: the model orbit's reduced state at its
        start: shape in rad or m, velocities in their units); ``displacement_error`` (cycles,):
        ``|dg_ref - dg_model|`` per cycle (m and rad together); ``model_return_error``: the model's
        own ``|P(z*) - z*|``; ``monodromy``, and the :func:`floquet` analysis of it
        (``multipliers``, ``jordan_blocks``, ``stability``, ``growth``); ``q_ref`` and ``t`` of
        the replay; ``reference_result``.

    Raises:
        TypeError, ValueError: a task that is not periodic, ``params`` that are not its
            :class:`GaitParams`; ``cycles`` not a positive integer; a period whose rollout fails.
    """
    known = isinstance(cycles, jax.Array) and is_concrete(cycles)
    if known and cycles.ndim == 0 and cycles.dtype.kind in "iu":  # a concrete JAX integer
        cycles = int(cycles)
    if isinstance(cycles, bool) or not isinstance(cycles, (int, np.integer)) or cycles < 1:
        raise ValueError(f"'cycles' must be a positive integer, got {cycles!r}")
    cycles = int(cycles)
    params = gait_params(task, params, "replay_gait")
    z0, z1, g1, M, q0, qdot0 = _analysis(task, params)
    _check_finite("replay_gait", task, params, z1, M)
    z0, z1, g1, M = (np.asarray(x) for x in (z0, z1, g1, M))
    n = task.n_steps
    ts = np.linspace(0.0, cycles * float(task.t_final), cycles * n + 1)
    ref = reference(task.system, q0, qdot0, task.controls(params).over(cycles), ts, rtol=rtol, atol=atol)
    q = np.asarray(ref.q)
    idx = np.arange(cycles + 1) * n
    z_ref, dg = (np.array(x) for x in _cycle_starts(task, ref.q[idx], ref.qdot[idx]))
    dg[:, 2] = [math.remainder(x, 2 * math.pi) for x in dg[:, 2]]
    g1 = np.array(g1)
    g1[2] = math.remainder(float(g1[2]), 2 * math.pi)
    out = {
        "displacement": dg,
        "model_displacement": g1,
        "return_error": np.max(np.abs(z_ref[1:] - z0[None]), axis=1),
        "displacement_error": np.max(np.abs(dg - g1[None]), axis=1),
        "model_return_error": float(np.max(np.abs(z1 - z0))),
        "monodromy": M,
        "q_ref": q,
        "t": ts,
        "reference_result": ref.result,
    }
    out.update(floquet(M))
    return out
