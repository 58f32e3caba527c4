"""Reproducible random maneuvers for the study."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from jaxtyping import Array

from .._controls import AbstractControls, Sinusoids
from .._sharding import global_batch
from ..systems import AbstractSystem, Snakeboard

__all__ = ["sample_maneuvers", "global_maneuvers", "SAMPLE_BLOCK"]

#: Members sampled by one call of :func:`global_maneuvers`'s compiled sampling program.
SAMPLE_BLOCK = 64


def _zero_steer_rate(system: Snakeboard, q0: Array, qdot0: Array, ctl: Sinusoids):
    """Re-phase a snakeboard maneuver's steering so that ``phidot(0) = 0``.

    ``sample_maneuver`` steers with ``phi(t) = phi_c + b sin(w t + p)`` from the torque
    ``f_phi = -2 J b w^2 sin(w t + p)``. Any second-order scheme's discrete steering rate then
    carries a mean bias ``~ h^2 f_phi'(0) / J`` (from the first step's quadrature), a linear drift
    of phi proportional to ``b w^3 cos(p) h^2 t`` that on 10-minute runs at coarse steps drives
    phi into the singularity ``cos(phi) = 0``. With ``p = +-pi/2`` (``phidot(0) = 0``,
    ``f_phi'(0) = 0``) the leading bias vanishes; ``phi_c``, ``b``, ``w`` stay random.
    """
    b = -ctl.amplitude[1, 0] / (2 * system.J * ctl.frequency[1, 0] ** 2)
    phi_c = q0[4] - b * jnp.sin(ctl.phase[1, 0])
    p_new = jnp.where(jnp.cos(ctl.phase[1, 0]) >= 0, 0.5 * jnp.pi, -0.5 * jnp.pi).astype(q0.dtype)
    ctl = eqx.tree_at(lambda c: c.phase, ctl, ctl.phase.at[1, 0].set(p_new))
    q0_new = q0.at[4].set(phi_c + b * jnp.sin(p_new))
    v = system.velocities_from_qdot(q0, qdot0).at[1].set(jnp.zeros((), q0.dtype))
    return q0_new, system.qdot_from_velocities(q0_new, v, jnp.zeros(2, q0.dtype)), ctl


def sample_maneuvers(
    system: AbstractSystem, n: int, seed: int, *, zero_steer_rate: bool = True
) -> tuple[Array, Array, AbstractControls]:
    """A reproducible batch of ``n`` random maneuvers ``(q0, qdot0, controls)`` (leading axis n).

    Uses the model's ``sample_maneuver`` (random sinusoidal controls producing parallel
    parking, sharp turns and winding; initial states on the constraints). For the snakeboard
    with ``zero_steer_rate`` (default ``True``) the steering phase is set so that ``phidot(0) = 0`` (see
    :func:`_zero_steer_rate`): this keeps long coarse runs off the singularity ``cos(phi) = 0``.

    Raises:
        ValueError: ``n < 1``.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"'n' must be a positive integer, got {n!r}")
    return _sample(system, jax.random.split(jax.random.PRNGKey(seed), n), zero_steer_rate)


def global_maneuvers(
    system: AbstractSystem, n: int, seed: int, *, zero_steer_rate: bool = True, mesh: Mesh | None = None
) -> tuple[Array, Array, AbstractControls]:
    """The maneuvers of :func:`sample_maneuvers` as global arrays split over the devices of
    ``mesh`` (default: all devices of all processes), each process sampling only the members its
    devices hold (:func:`ldap_jax.global_batch`: padded to a multiple of the devices with copies
    of member ``n - 1``). Member ``i`` is the same as ``sample_maneuvers(system, n, seed)``'s,
    up to the round-off of a batch of another size. Members are sampled in blocks of a fixed size
    (:data:`SAMPLE_BLOCK`): one compiled program for every batch size and number of devices, and
    the same numbers whatever the number of processes. ``zero_steer_rate`` (default ``True``) as
    for :func:`sample_maneuvers`.

    Raises:
        ValueError: ``n < 1``.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"'n' must be a positive integer, got {n!r}")
    keys = np.asarray(jax.random.split(jax.random.PRNGKey(seed), n))  # 8 bytes a member

    def make(indices: np.ndarray):
        parts = []
        for start in range(0, len(indices), SAMPLE_BLOCK):
            idx = indices[start : start + SAMPLE_BLOCK]
            block = np.concatenate([idx, np.full(SAMPLE_BLOCK - len(idx), idx[-1])])
            man = _sample(system, keys[block], zero_steer_rate)
            parts.append(jax.tree_util.tree_map(lambda x, k=len(idx): np.asarray(x)[:k], man))
        return jax.tree_util.tree_map(lambda *xs: np.concatenate(xs), *parts)

    return global_batch(make, n, mesh=mesh)


@eqx.filter_jit
def _sample(system: AbstractSystem, keys: Array, zero_steer_rate: bool):
    man = jax.vmap(system.sample_maneuver)(keys)
    if zero_steer_rate and isinstance(system, Snakeboard):
        man = jax.vmap(lambda a, b, c: _zero_steer_rate(system, a, b, c))(*man)
    return man
