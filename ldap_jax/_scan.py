"""``lax.scan`` with the rematerialisation policies offered for long, differentiated rollouts."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

__all__ = ["checkpointed_scan", "check_checkpoint"]


def check_checkpoint(checkpoint) -> bool | str | int:
    """Validate the ``checkpoint`` option of :func:`ldap_jax.simulate`."""
    if checkpoint in (False, None):
        return False
    if checkpoint is True or checkpoint == "step":
        return "step"
    if checkpoint == "sqrt":
        return "sqrt"
    if isinstance(checkpoint, int) and not isinstance(checkpoint, bool) and checkpoint >= 1:
        return int(checkpoint)
    raise ValueError(
        f"'checkpoint' must be False, True/'step', 'sqrt' or a positive chunk length, got {checkpoint!r}"
    )


def checkpointed_scan(
    body, init, xs, *, length: int, checkpoint=False, unroll: int = 1, saved: str | None = None
):
    """``lax.scan(body, init, xs)`` with a memory policy for reverse mode.

    Args:
        checkpoint: ``False``: store every step's residuals (fastest, memory O(N) step internals);
            with ``saved``, store only the values the body tagged with
            ``jax.ad_checkpoint.checkpoint_name(x, saved)`` (and the carry), and recompute the rest
            in the backward pass (``jax.checkpoint`` with ``save_only_these_names``).
            ``"step"`` (or ``True``): ``jax.checkpoint`` on the body, memory O(N) carries.
            ``"sqrt"``: nested, the scan split into ~sqrt(N) chunks of ~sqrt(N) steps with each chunk
            checkpointed, memory O(sqrt N) carries (plus the outputs) for about one extra forward pass.
            An integer ``k``: the nested scheme with chunks of ``k`` steps.
    """
    policy = check_checkpoint(checkpoint)
    if policy is False and saved is not None:
        body = jax.checkpoint(body, policy=jax.checkpoint_policies.save_only_these_names(saved))
        return jax.lax.scan(body, init, xs, length=length, unroll=unroll)
    if policy is False:
        return jax.lax.scan(body, init, xs, length=length, unroll=unroll)
    if policy == "step":
        return jax.lax.scan(jax.checkpoint(body), init, xs, length=length, unroll=unroll)
    k = max(1, math.isqrt(length - 1) + 1) if policy == "sqrt" else min(policy, length)
    n_chunks = -(-length // k)
    pad = n_chunks * k - length

    def padded(x):
        if pad == 0:
            return x
        return jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)], axis=0)

    xs_p = jax.tree_util.tree_map(padded, xs)
    valid = jnp.arange(n_chunks * k) < length

    def masked_body(carry, inp):
        x, ok = inp
        new, out = body(carry, x)
        new = jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), new, carry)
        return new, out

    @jax.checkpoint
    def chunk(carry, inp):
        return jax.lax.scan(masked_body, carry, inp, unroll=unroll)

    reshape = lambda x: x.reshape((n_chunks, k) + x.shape[1:])  # noqa: E731
    carry, outs = jax.lax.scan(chunk, init, jax.tree_util.tree_map(reshape, (xs_p, valid)))
    outs = jax.tree_util.tree_map(lambda o: o.reshape((n_chunks * k,) + o.shape[2:])[:length], outs)
    return carry, outs
