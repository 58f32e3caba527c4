"""Trace an integrator's step once per signature, however many programs use it.

A rollout's cost before XLA sees it is mostly JAX tracing and transforming the step: the step is
traced into the scan body, then differentiated (JVP, partial evaluation, transposition), batched
and rematerialised. Without a boundary all of that is redone for every program: each step count
``n_steps`` is a new program, as is each save policy, checkpoint policy and batch size.
:func:`ldap_jax._rollout.rollout` calls :func:`init`, :func:`step`, :func:`observe` and
:func:`shape_mobility`; the discrete dynamics (:func:`ldap_jax.discretize`, which the control
solver's programs call five times per solve: values, Jacobians, the line search's trial) call
:func:`step` (``parallel_park``'s interior-point program: the same 20840 optimised instructions
and the same solution, bit for bit; its tracing and lowering 0.1-0.2 s shorter).

:func:`traced_once` puts the step behind an inner ``jax.jit`` whenever it is called under a trace.
JAX caches that inner program's jaxpr by its signature and caches its JVP, partial evaluation,
transposition and batching by jaxpr, so a second program with the same step reuses all of them;
XLA inlines the call, so the compiled code is the one it would have been. Values that are concrete
at the call (Python numbers, concrete arrays such as a model's parameters) stay concrete inside,
so code that branches on them (``alpha in {0, 1}``, parameter checks) behaves exactly as inline.
"""

from __future__ import annotations

import collections
import functools
from collections.abc import Callable
from typing import Any, TypeVar

import jax
import numpy as np

from ._numerics import plain_active

__all__ = ["traced_once", "init", "step", "observe", "shape_mobility"]

F = TypeVar("F", bound=Callable[..., Any])

#: Signatures kept per wrapped function (least recently used dropped first).
CACHE_SIZE = 256


def _constant_key(x: Any) -> Any:
    """A hashable stand-in for a leaf that is not traced: arrays by content, others by value
    (or by identity when unhashable, e.g. a user's callable that defines no hash)."""
    if isinstance(x, (jax.Array, np.ndarray, np.generic)):
        a = np.asarray(x)
        return ("array", a.dtype.str, a.shape, a.tobytes())
    try:
        hash(x)
    except TypeError:
        return ("object", id(x))
    return ("value", type(x), x)


def traced_once(fn: F) -> F:
    """``fn(*args)`` through a cached inner ``jax.jit`` when any leaf of ``args`` is a tracer.

    The cache key is the pytree structure of ``args``, which leaves are traced, the content of the
    others and whether the closed-form kernels trace as plain arithmetic
    (:func:`ldap_jax._numerics.plain`); traced leaves are the inner program's arguments, with
    their shapes and dtypes checked by ``jax.jit``'s own cache. Outside any trace (an eager call)
    ``fn`` runs as it is.
    """
    cache: collections.OrderedDict[Any, Callable[..., Any]] = collections.OrderedDict()

    @functools.wraps(fn)
    def wrapper(*args: Any) -> Any:
        leaves, treedef = jax.tree_util.tree_flatten(args)
        traced = tuple(isinstance(x, jax.core.Tracer) for x in leaves)
        if not any(traced):
            return fn(*args)
        try:
            key = (treedef, traced, tuple(None if t else _constant_key(x) for x, t in zip(leaves, traced)))
            key = (key, plain_active())
            call = cache.get(key)
        except TypeError:  # an unhashable static field in the structure: trace inline
            return fn(*args)
        if call is None:
            constants = [None if t else x for x, t in zip(leaves, traced)]

            def inner(*dynamic: Any) -> Any:
                it = iter(dynamic)
                full = [next(it) if t else c for t, c in zip(traced, constants)]
                return fn(*jax.tree_util.tree_unflatten(treedef, full))

            call = cache[key] = jax.jit(inner)
            if len(cache) > CACHE_SIZE:
                cache.popitem(last=False)
        else:
            cache.move_to_end(key)
        return call(*[x for x, t in zip(leaves, traced) if t])

    return wrapper  # type: ignore[return-value]


# ----------------------------------------------------------------------------- the integrator's calls
@traced_once
def step(integrator: Any, system: Any, h: Any, state: Any, c: Any) -> Any:
    """``integrator.step(system, h, state, c)``, traced once per signature."""
    return integrator.step(system, h, state, c)


@traced_once
def observe(integrator: Any, system: Any, state: Any, c: Any) -> Any:
    """``integrator.observe(system, state, c)``, traced once per signature."""
    return integrator.observe(system, state, c)


@traced_once
def init(integrator: Any, system: Any, h: Any, q0: Any, qdot0: Any, c: Any) -> Any:
    """``integrator.init(system, h, q0, qdot0, c)``, traced once per signature."""
    return integrator.init(system, h, q0, qdot0, c)


@traced_once
def shape_mobility(system: Any, r: Any) -> Any:
    """``system.shape_mobility(r)`` (the divergence test's scale), traced once per signature: its
    second derivatives of the Lagrangian took a third of a rollout's tracing."""
    return system.shape_mobility(r)
