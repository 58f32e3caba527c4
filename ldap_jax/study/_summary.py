"""One point of the study reduced to its row on the devices: only numbers come back.

The rollouts of a point (one model, duration, method and resolution) and the reference stay
where they were computed, as global arrays split over the devices of every process; the
functions here reduce them to the row's statistics inside one compiled program, so that a
study over many processes moves a few numbers per point to the host instead of its
trajectories (XLA gathers the per-member errors, 16 bytes a member, for the median).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._compilation_cache import jit

__all__ = ["point_statistics", "reference_statistics", "host_scalars"]


def _errors(q: Array, q_ref: Array) -> tuple[Array, Array]:
    """Euclidean ``(x, y)`` errors: final, and max over the output nodes (NaN if any is NaN)."""
    err = jnp.linalg.norm(q[..., :2] - q_ref[..., :2], axis=-1)
    return err[:, -1], jnp.max(err, axis=-1)


def _finite_stats(x: Array, keep: Array) -> tuple[Array, Array, Array]:
    """Mean, median and max of ``x`` over the finite entries where ``keep`` (NaN if none)."""
    x = jnp.where(keep & jnp.isfinite(x), x, jnp.nan)
    return jnp.nanmean(x), jnp.nanmedian(x), jnp.nanmax(x)


@jit
def point_statistics(
    q: Array, code: Array, q_ref: Array, ref_code: Array, n: int, blowup_factor: float
) -> dict[str, Array]:
    """The statistics of one point over the first ``n`` members (the rest is padding).

    A member fails if its result code is nonzero or it blows up: finite, but its largest
    position error exceeds ``blowup_factor * (1 + e)``, with ``e`` the reference path's largest
    distance from its start. Errors are taken over the members that neither fail nor have a
    failed reference.

    Args:
        q: the method's positions at the output nodes, (B, K, d).
        code: its result codes, (B,).
        q_ref: the reference's positions at the same nodes, (B, K, d).
        ref_code: the reference's result codes, (B,).
        n: the number of members, ``n <= B``.
        blowup_factor: see above.

    Returns:
        Scalars: ``failures``, ``nonfinite``, ``singular``, ``not_converged``, ``blowup``
        (counts), and ``final_error_{mean,median,max}``, ``max_error_{mean,median,max}``.
    """
    valid = jnp.arange(q.shape[0]) < n
    final, worst = _errors(q, q_ref)
    extent = jnp.max(jnp.linalg.norm(q_ref[..., :2] - q_ref[:, :1, :2], axis=-1), axis=-1)
    blowup = valid & (code == 0) & ~(worst <= blowup_factor * (1.0 + extent))
    ok = valid & (code == 0) & ~blowup & (ref_code == 0)
    out = {
        "failures": jnp.sum(valid & (code != 0)) + jnp.sum(blowup),
        "nonfinite": jnp.sum(valid & (code == 1)),
        "singular": jnp.sum(valid & (code == 2)),
        "not_converged": jnp.sum(valid & (code == 3)),
        "blowup": jnp.sum(blowup),
    }
    for name, x in (("final_error", final), ("max_error", worst)):
        out[f"{name}_mean"], out[f"{name}_median"], out[f"{name}_max"] = _finite_stats(x, ok)
    return out


@jit
def reference_statistics(q_ref: Array, ref_code: Array, q_check: Array, n: int, m: int) -> dict[str, Array]:
    """The reference's failures over its first ``n`` members, and its ``error``: the largest
    position error over time of its first ``m`` members against ``q_check`` (the same members
    with half the step), ignoring NaN members."""
    _, worst = _errors(q_ref[:m], q_check[:m])
    return {"error": jnp.nanmax(worst), "failures": jnp.sum(ref_code[:n] != 0)}


def host_scalars(tree) -> dict:
    """The scalars of ``tree`` as Python numbers (ints for integer arrays). Each process holds a
    copy of a reduction's result; one that does not (a sharded output) is gathered."""

    def value(x):
        if not x.is_fully_addressable:  # pragma: no cover - XLA replicates scalar reductions
            from jax.experimental import multihost_utils

            x = multihost_utils.process_allgather(x, tiled=True)
        x = np.asarray(x)
        return int(x) if x.dtype.kind in "iub" else float(x)

    return jax.tree_util.tree_map(value, tree)
