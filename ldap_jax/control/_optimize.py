"""The optimizer loop: one jitted ``value_and_grad`` -> optax update, iterations in ``lax.scan``.

A run is split into chunks of ``chunk`` iterations; each chunk is one jitted ``lax.scan`` over
the step, and a Python loop over the chunks drives a tqdm progress bar. :func:`multistart`
vmaps the same chunk over a batch of initial guesses.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from jaxtyping import Array, Float, PyTree

__all__ = ["OptimizeResult", "optimize", "multistart", "default_optimizer"]


class OptimizeResult(eqx.Module):
    """Result of :func:`optimize` (batched along a leading axis for :func:`multistart`).

    Attributes:
        params: the best parameters seen (lowest finite loss).
        loss: their loss.
        losses: loss at every iteration, before that iteration's update, (n_iterations,).
        iterations: number of iterations run.
    """

    params: PyTree
    loss: Float[Array, ""]
    losses: Float[Array, " n"]
    iterations: int = eqx.field(static=True)


@functools.cache
def default_optimizer() -> optax.GradientTransformationExtraArgs:
    """L-BFGS with a zoom line search (``optax.lbfgs``): a good default for these smooth,
    moderately sized problems. One cached instance, so compiled loops are reused across calls."""
    return optax.lbfgs()


def _scalar_loss(loss_fn):
    def value(params):
        out = loss_fn(params)
        return out[0] if isinstance(out, tuple) else out

    return value


def _make_chunk(loss_fn: Callable, optimizer, n: int):
    """``n`` optimizer steps in a ``lax.scan``; the carry tracks the best parameters."""
    value_fn = _scalar_loss(loss_fn)

    def step(carry, _):
        params, opt_state, best, best_loss = carry
        loss, grads = jax.value_and_grad(value_fn)(params)
        # optax's L-BFGS mixes int32 and int64 counters internally, which fails under
        # jax_numpy_dtype_promotion="strict" (our test configuration): its update is traced with
        # standard promotion; our own code (the loss) stays under the caller's setting.
        with jax.numpy_dtype_promotion("standard"):
            updates, opt_state = optimizer.update(
                grads, opt_state, params, value=loss, grad=grads, value_fn=value_fn
            )
        better = jnp.isfinite(loss) & (loss < best_loss)
        best = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), params, best)
        best_loss = jnp.where(better, loss, best_loss)
        params = optax.apply_updates(params, updates)
        return (params, opt_state, best, best_loss), loss

    def chunk(carry):
        return jax.lax.scan(step, carry, None, length=n)

    return chunk


@eqx.filter_jit
def _run_chunk(loss_fn, optimizer, carry, n):
    # filter_jit: arrays inside ``loss_fn`` (e.g. a Task's bound method) are traced arguments, the
    # rest (functions, ints) static, so a new task of the same structure reuses the compilation
    return _make_chunk(loss_fn, optimizer, n)(carry)


@eqx.filter_jit
def _run_finish(loss_fn, carry, losses):
    return _finish(loss_fn, carry, losses)


@eqx.filter_jit
def _run_multistart(loss_fn, optimizer, params0, n):
    chunk = _make_chunk(loss_fn, optimizer, n)

    def one(p0):
        carry, losses = chunk(_init_carry(loss_fn, optimizer, p0))
        return _finish(loss_fn, carry, losses)

    return jax.vmap(one)(params0)


def _init_carry(loss_fn, optimizer, params0):
    inf = jnp.asarray(jnp.inf, jax.tree_util.tree_leaves(params0)[0].dtype)
    with jax.numpy_dtype_promotion("standard"):  # see _make_chunk
        opt_state = optimizer.init(params0)
    return (params0, opt_state, params0, inf)


def _finish(loss_fn, carry, losses):
    params, _, best, best_loss = carry
    # the last update is evaluated once more so the returned point is the best of all iterates
    last = _scalar_loss(loss_fn)(params)
    better = jnp.isfinite(last) & (last < best_loss)
    best = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), params, best)
    best_loss = jnp.where(better, last, best_loss)
    return best, best_loss, losses


def optimize(
    loss_fn: Callable[[PyTree], Array | tuple[Array, PyTree]],
    params0: PyTree,
    *,
    n_iterations: int,
    optimizer: optax.GradientTransformation | None = None,
    chunk: int = 10,
    progress: bool = False,
    description: str = "optimize",
) -> OptimizeResult:
    """Minimise ``loss_fn`` from ``params0`` with optax.

    Each iteration is ``value_and_grad`` then ``optimizer.update`` (given ``value``, ``grad`` and
    ``value_fn``, so line-search methods such as ``optax.lbfgs`` work) and ``apply_updates``;
    ``chunk`` iterations are rolled in one jitted ``lax.scan`` and a Python loop over chunks
    shows a tqdm progress bar (``progress=True``). The returned parameters are the best iterate
    (lowest finite loss), so a diverging last step cannot spoil the result.

    Args:
        loss_fn: ``params -> loss`` or ``params -> (loss, aux)``; pure, differentiable.
        params0: initial parameters (a pytree of float arrays).
        n_iterations: number of optimizer steps (>= 1).
        optimizer: an optax transformation (default :func:`default_optimizer`, L-BFGS).
        chunk: iterations per jitted scan (rounded down to divide ``n_iterations``).
        progress: show a tqdm progress bar.
        description: progress bar label.

    Returns:
        :class:`OptimizeResult`.

    Raises:
        ValueError: ``n_iterations < 1`` or ``chunk < 1``.
    """
    if isinstance(n_iterations, bool) or not isinstance(n_iterations, int) or n_iterations < 1:
        raise ValueError(f"'n_iterations' must be a positive integer, got {n_iterations!r}")
    if isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1:
        raise ValueError(f"'chunk' must be a positive integer, got {chunk!r}")
    optimizer = optimizer or default_optimizer()
    chunk = _divisor(n_iterations, chunk)
    carry = _init_carry(loss_fn, optimizer, params0)
    pieces = []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n_iterations, desc=description)
    for _ in range(n_iterations // chunk):
        carry, losses = _run_chunk(loss_fn, optimizer, carry, chunk)
        pieces.append(losses)
        if bar is not None:
            bar.update(chunk)
            bar.set_postfix(loss=f"{float(carry[3]):.3e}")
    if bar is not None:
        bar.close()
    best, best_loss, losses = _run_finish(loss_fn, carry, jnp.concatenate(pieces))
    return OptimizeResult(params=best, loss=best_loss, losses=losses, iterations=n_iterations)


def _divisor(n: int, chunk: int) -> int:
    chunk = min(chunk, n)
    while n % chunk:
        chunk -= 1
    return chunk


def multistart(
    loss_fn: Callable[[PyTree], Array | tuple[Array, PyTree]],
    params0: PyTree,
    *,
    n_iterations: int,
    optimizer: optax.GradientTransformation | None = None,
) -> OptimizeResult:
    """:func:`optimize` from a batch of initial guesses at once (``jax.vmap`` over the leading
    axis of every leaf of ``params0``), one jitted ``lax.scan`` over all iterations.

    Returns:
        :class:`OptimizeResult` with a leading batch axis (``params``, ``loss`` (B,),
        ``losses`` (B, n_iterations)); pick the best with :func:`best_of`.
    """
    if isinstance(n_iterations, bool) or not isinstance(n_iterations, int) or n_iterations < 1:
        raise ValueError(f"'n_iterations' must be a positive integer, got {n_iterations!r}")
    optimizer = optimizer or default_optimizer()
    best, best_loss, losses = _run_multistart(loss_fn, optimizer, params0, n_iterations)
    return OptimizeResult(params=best, loss=best_loss, losses=losses, iterations=n_iterations)


def best_of(result: OptimizeResult) -> OptimizeResult:
    """The start with the lowest finite loss of a :func:`multistart` result."""
    loss = jnp.where(jnp.isfinite(result.loss), result.loss, jnp.inf)
    i = jnp.argmin(loss)
    return OptimizeResult(
        params=jax.tree_util.tree_map(lambda x: x[i], result.params),
        loss=result.loss[i],
        losses=result.losses[i],
        iterations=result.iterations,
    )
