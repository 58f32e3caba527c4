"""First-order optimisation of a penalty-form loss with optax: one jitted ``value_and_grad`` +
update per iteration, iterations in ``lax.scan`` chunks.

A run is split into chunks of ``chunk`` iterations; each chunk is one jitted ``lax.scan`` over the
step, and a Python loop over the chunks drives a tqdm progress bar and stops early once the
stopping test holds. :func:`multistart` vmaps the same loop over a batch of initial guesses. For
hard constraints and second-order convergence use :func:`~ldap_jax.control.solve` instead.
"""

from __future__ import annotations

import contextlib
import functools
import math
import warnings
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Bool, Float, PyTree

from .._compilation_cache import jit
from .._validation import check_positive_int

__all__ = ["OptimizeResult", "optimize", "multistart", "default_optimizer", "best_of"]


class OptimizeResult(eqx.Module):
    """Result of :func:`optimize` (batched along a leading axis for :func:`multistart`).

    Attributes:
        params: the best parameters seen (lowest finite loss).
        loss: their loss.
        losses: loss at every iteration run, before that iteration's update, (iterations,).
        aux: the loss function's auxiliary output at every iteration (stacked; e.g. the cost
            terms of :meth:`Task.loss`), or ``None``.
        iterations: number of iterations run (fewer than asked when the stopping test held).
        converged: the stopping test held (``tol``).
    """

    params: PyTree
    loss: Float[Array, "*batch"]
    losses: Float[Array, "*batch n"]
    aux: PyTree
    iterations: int = eqx.field(static=True)
    converged: Bool[Array, "*batch"]


@functools.cache
def default_optimizer() -> optax.GradientTransformationExtraArgs:
    """L-BFGS with a zoom line search (``optax.lbfgs``): a good default for these smooth,
    moderately sized problems. One cached instance, so compiled loops are reused across calls."""
    return optax.lbfgs()


def _split_loss(loss_fn):
    def value_aux(params):
        out = loss_fn(params)
        return out if isinstance(out, tuple) else (out, None)

    return value_aux


def _strong(tree):
    """The same values without weak types, so the first chunk and the later ones (whose carry has
    been through the scan) trace identically: one compilation."""
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x, x.dtype) if eqx.is_array(x) else x, tree)


def _make_chunk(loss_fn: Callable, optimizer, n: int, tol: Array):
    value_aux = _split_loss(loss_fn)
    value_fn = lambda p: value_aux(p)[0]  # noqa: E731

    def step(carry, _):
        params, opt_state, best, best_loss, prev_loss, done = carry
        (loss, aux), grads = jax.value_and_grad(value_aux, has_aux=True)(params)
        # optax's L-BFGS mixes int32 and int64 counters internally, which fails under
        # jax_numpy_dtype_promotion="strict" (our test configuration): its update is traced with
        # standard promotion; our own code (the loss) stays under the caller's setting.
        with jax.numpy_dtype_promotion("standard"):
            updates, new_state = optimizer.update(
                grads, opt_state, params, value=loss, grad=grads, value_fn=value_fn
            )
        better = jnp.isfinite(loss) & (loss < best_loss)
        best = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), params, best)
        best_loss = jnp.where(better, loss, best_loss)
        converged = jnp.abs(prev_loss - loss) <= tol.astype(loss.dtype) * jnp.maximum(1.0, jnp.abs(loss))
        new_params = optax.apply_updates(params, updates)
        keep = done | converged
        params = jax.tree_util.tree_map(lambda a, b: jnp.where(keep, a, b), params, new_params)
        opt_state = jax.tree_util.tree_map(lambda a, b: jnp.where(keep, a, b), opt_state, new_state)
        return (params, opt_state, best, best_loss, jnp.where(keep, prev_loss, loss), keep), (loss, aux, keep)

    def chunk(carry):
        return jax.lax.scan(step, carry, None, length=n)

    return chunk


@jit
def _run_chunk(loss_fn, optimizer, carry, n, tol):
    # filter_jit: arrays inside ``loss_fn`` (e.g. a Task's bound method) are traced arguments, the
    # rest (functions, ints) static, so a new task of the same structure reuses the compilation
    return _make_chunk(loss_fn, optimizer, n, tol)(carry)


@jit
def _run_finish(loss_fn, carry):
    return _finish(loss_fn, carry)


@jit
def _run_multistart(loss_fn, optimizer, params0, n, tol):
    chunk = _make_chunk(loss_fn, optimizer, n, tol)

    def one(p0):
        carry, (losses, aux, done) = chunk(_init_carry(optimizer, p0))
        best, best_loss = _finish(loss_fn, carry)
        return best, best_loss, losses, aux, done[-1]

    return jax.vmap(one)(params0)


def _init_carry(optimizer, params0):
    params0 = jax.tree_util.tree_map(jnp.asarray, params0)
    dtype = jax.tree_util.tree_leaves(params0)[0].dtype
    inf = jnp.asarray(jnp.inf, dtype)
    with jax.numpy_dtype_promotion("standard"):  # see _make_chunk
        opt_state = optimizer.init(params0)
    return _strong((params0, opt_state, params0, inf, inf, jnp.zeros((), bool)))


def _finish(loss_fn, carry):
    params, _, best, best_loss, _, _ = carry
    # the last update is evaluated once more so the returned point is the best of all iterates
    last = _split_loss(loss_fn)(params)[0]
    better = jnp.isfinite(last) & (last < best_loss)
    best = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), params, best)
    return best, jnp.where(better, last, best_loss)


#: the warning of a run whose loss never fell below its initial value
_NO_PROGRESS = (
    "the loss never fell below its value at the initial guess, so the result is the initial guess. "
    "Its gradient may vanish there: from zero controls (at rest) the linearised car and snakeboard have "
    "no authority over their position, and a gradient method cannot leave; start from a guess that "
    "moves the system (task.init()), or use lc.solve, which restarts from perturbed controls"
)


def _traced(tol: float) -> Array:
    # an array, not a float: a float is static under filter_jit, and each new tol compiled anew
    return jnp.asarray(tol, jnp.result_type(float))


#: JAX's errors when a loss is not a scalar or its aux is not a pytree of arrays
_LOSS_ERRORS = (
    "Gradient only defined for scalar-output",
    "two-element tuple",
    "is not a valid JAX type",
    "traced for scan returned a value of type",
)


@contextlib.contextmanager
def _loss_errors():
    """JAX's error from a loss of the wrong kind, re-raised naming ``loss_fn``."""
    try:
        yield
    except TypeError as err:
        if not any(k in str(err) for k in _LOSS_ERRORS):
            raise
        first = str(err).splitlines()[0]
        raise TypeError(
            "'loss_fn' must return a real scalar loss, or a pair (loss, aux) with aux a pytree of arrays; "
            f"JAX: {first}"
        ) from err


def _check_positive_int(name: str, x: Any) -> int:
    return check_positive_int(name, x)


def _check_problem(loss_fn: Any, params0: Any, tol: Any) -> float:
    """The common input checks of :func:`optimize` and :func:`multistart`."""
    if not callable(loss_fn):
        raise TypeError(f"'loss_fn' must be a function params -> loss (or (loss, aux)), got {type(loss_fn)}")
    leaves = jax.tree_util.tree_leaves(params0)
    if not leaves:
        raise ValueError(f"'params0' must hold at least one array of parameters, got {params0!r}")
    for x in leaves:
        if not (eqx.is_array_like(x) and jnp.issubdtype(jnp.result_type(x), jnp.floating)):
            raise TypeError(
                f"'params0' must be a pytree of floating arrays (the optimised parameters), got a leaf {x!r}"
            )
    if isinstance(tol, bool) or not isinstance(tol, (int, float)):
        raise TypeError(f"'tol' must be a non-negative number, got {tol!r}")
    if not (tol >= 0 and math.isfinite(tol)):
        raise ValueError(f"'tol' must be a non-negative finite number, got {tol!r}")
    return float(tol)


def _as_extra_args(optimizer) -> optax.GradientTransformationExtraArgs:
    if optimizer is None:
        return default_optimizer()
    if not isinstance(optimizer, optax.GradientTransformation):
        raise TypeError(f"'optimizer' must be an optax GradientTransformation, got {type(optimizer)}")
    # any optax transformation: extra keyword arguments (value, grad, value_fn) are passed through
    # to those that use them (line searches) and dropped for the others
    return optax.with_extra_args_support(optimizer)


def optimize(
    loss_fn: Callable[[PyTree], Array | tuple[Array, PyTree]],
    params0: PyTree,
    *,
    n_iterations: int,
    optimizer: optax.GradientTransformation | None = None,
    tol: float = 0.0,
    chunk: int = 10,
    progress: bool = False,
    description: str = "optimize",
) -> OptimizeResult:
    """Minimise ``loss_fn`` from ``params0`` with optax.

    Each iteration is ``value_and_grad`` then ``optimizer.update`` (given ``value``, ``grad`` and
    ``value_fn``, so line-search methods such as ``optax.lbfgs`` work; any other optax
    transformation is wrapped with ``optax.with_extra_args_support``) and ``apply_updates``;
    ``chunk`` iterations are rolled in one jitted ``lax.scan`` (one compilation for the whole
    run) and a Python loop over chunks shows a tqdm progress bar (``progress=True``) and stops
    once ``|J_k - J_{k-1}| <= tol max(1, |J_k|)``. The returned parameters are the best iterate
    (lowest finite loss), so a diverging last step cannot spoil the result.

    Args:
        loss_fn: ``params -> loss`` or ``params -> (loss, aux)``; pure, differentiable. ``aux``
            is kept for every iteration (e.g. the terms of :meth:`~ldap_jax.control.Task.loss`).
        params0: initial parameters (a pytree of float arrays).
        n_iterations: largest number of optimizer steps (>= 1).
        optimizer: an optax transformation (default :func:`default_optimizer`, L-BFGS).
        tol: relative change of the loss at or below which the run stops (``0``: only when the
            loss does not change at all, e.g. an optimizer that no longer moves).
        chunk: iterations per jitted scan (rounded down to divide ``n_iterations``).
        progress: show a tqdm progress bar.
        description: progress bar label.

    Returns:
        :class:`OptimizeResult`.

    Raises:
        ValueError: ``n_iterations < 1``, ``chunk < 1``, a negative or non-finite ``tol``, an
            empty ``params0``.
        TypeError: ``loss_fn`` is not callable; ``params0`` holds a non-floating leaf;
            ``optimizer`` is not an optax transformation; a non-integer ``n_iterations``/``chunk``.

    Warns:
        UserWarning: when the loss was never finite (the result is then the initial guess, with
            ``loss = inf``), or never fell below its initial value (e.g. a zero gradient at the
            initial guess: the result is then the initial guess, and ``converged`` may be True,
            since the stopping test only sees the loss stop changing).
    """
    _check_positive_int("n_iterations", n_iterations)
    _check_positive_int("chunk", chunk)
    tol = _check_problem(loss_fn, params0, tol)
    optimizer = _as_extra_args(optimizer)
    chunk = _divisor(n_iterations, chunk)
    carry = _init_carry(optimizer, params0)
    pieces, done = [], False
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n_iterations, desc=description)
    for _ in range(n_iterations // chunk):
        with _loss_errors():
            carry, (losses, aux, stopped) = _run_chunk(loss_fn, optimizer, carry, chunk, _traced(tol))
        pieces.append((losses, aux, stopped))
        if bar is not None:
            bar.update(chunk)
            bar.set_postfix(loss=f"{float(carry[3]):.3e}")
        if bool(stopped[-1]):
            done = True
            break
    if bar is not None:
        bar.close()
    best, best_loss = _run_finish(loss_fn, carry)
    losses = jnp.concatenate([p[0] for p in pieces])
    aux = jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs), *[p[1] for p in pieces])
    stopped = jnp.concatenate([p[2] for p in pieces])
    # iterations whose update was skipped after the stopping test held are not counted
    n_run = int(jnp.sum(~stopped)) + (1 if done else 0)
    losses, aux = losses[:n_run], jax.tree_util.tree_map(lambda x: x[:n_run], aux)
    if not bool(jnp.isfinite(best_loss)):
        warnings.warn("optimize: the loss was never finite; the result is the initial guess", stacklevel=2)
    elif bool(jnp.isfinite(losses[0])) and not bool(best_loss < losses[0]):
        warnings.warn(f"optimize: {_NO_PROGRESS}", stacklevel=2)
    return OptimizeResult(
        params=best, loss=best_loss, losses=losses, aux=aux, iterations=n_run, converged=jnp.asarray(done)
    )


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
    tol: float = 0.0,
) -> OptimizeResult:
    """:func:`optimize` from a batch of initial guesses at once (``jax.vmap`` over the leading
    axis of every leaf of ``params0``), one jitted ``lax.scan`` over all iterations.
    ``optimizer`` (default :func:`default_optimizer`, L-BFGS) and ``tol`` (default 0) as for
    :func:`optimize`.

    Returns:
        :class:`OptimizeResult` with a leading batch axis (``params``, ``loss`` (B,),
        ``losses`` (B, n_iterations)); pick the best with :func:`best_of`.

    Warns:
        UserWarning: as :func:`optimize`, with the number of starts concerned.
    """
    _check_positive_int("n_iterations", n_iterations)
    tol = _check_problem(loss_fn, params0, tol)
    starts = {np.shape(x)[0] if np.ndim(x) else None for x in jax.tree_util.tree_leaves(params0)}
    if None in starts or len(starts) != 1 or 0 in starts:
        raise ValueError(
            "'params0' must be a batch of starts: every leaf with the same leading size >= 1, got "
            f"leading sizes {sorted(starts, key=str)}"
        )
    optimizer = _as_extra_args(optimizer)
    with _loss_errors():
        best, best_loss, losses, aux, done = _run_multistart(
            loss_fn, optimizer, params0, n_iterations, _traced(tol)
        )
    never = ~jnp.isfinite(best_loss)
    if bool(jnp.any(never)):
        warnings.warn(
            f"multistart: the loss was never finite for {int(jnp.sum(never))} of {never.size} starts; their "
            "result is the initial guess (loss inf)",
            stacklevel=2,
        )
    stuck = jnp.isfinite(losses[:, 0]) & ~(best_loss < losses[:, 0])
    if bool(jnp.any(stuck)):
        n_stuck = int(jnp.sum(stuck))
        warnings.warn(f"multistart, {n_stuck} of {stuck.size} starts: {_NO_PROGRESS}", stacklevel=2)
    return OptimizeResult(
        params=best, loss=best_loss, losses=losses, aux=aux, iterations=n_iterations, converged=done
    )


def best_of(result: OptimizeResult) -> OptimizeResult:
    """The start with the lowest finite loss of a :func:`multistart` result."""
    loss = jnp.where(jnp.isfinite(result.loss), result.loss, jnp.inf)
    i = jnp.argmin(loss)
    pick = lambda x: x[i]  # noqa: E731
    return OptimizeResult(
        params=jax.tree_util.tree_map(pick, result.params),
        loss=result.loss[i],
        losses=result.losses[i],
        aux=jax.tree_util.tree_map(pick, result.aux),
        iterations=result.iterations,
        converged=result.converged[i],
    )
