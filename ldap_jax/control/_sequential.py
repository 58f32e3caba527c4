"""A ``jax.vmap``-ped batch run one member after another instead of in lockstep."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax

from .._compilation_cache import jit

__all__ = ["one_after_another"]


def one_after_another(fn: Callable) -> Callable:
    """``fn(task, params0, options)`` that runs a ``jax.vmap``-ped batch one member after another
    (``lax.map``, the rule of :func:`jax.custom_batching.sequential_vmap`) instead of in lockstep.

    A batched interior-point loop runs every member for as many iterations as the slowest one
    needs, and evaluates both sides of its branches (restarts, the Hessian's two forms) for all;
    one after another, a family costs the sum of its members' own solves (a family of 8 drive
    gaits over the torque bound: 75x one solve in lockstep). The arrays of the arguments are the
    mapped ones; the rest (the task's functions and static settings) is closed over. The map is
    one compiled program per problem structure (:func:`_map_members`), so that an eager
    ``jax.vmap`` (no ``jit`` around it) traces the solver once, not on every call."""

    def run(task, params0, options):
        dynamic, static = eqx.partition((task, params0, options), eqx.is_array)

        @jax.custom_batching.custom_vmap
        def member(dynamic):
            return fn(*eqx.combine(dynamic, static))

        @member.def_vmap
        def rule(axis_size, in_batched, dynamic):
            leaves, treedef = jax.tree_util.tree_flatten(dynamic)
            flags = tuple(jax.tree_util.tree_leaves(in_batched))
            mapped = [x for x, b in zip(leaves, flags) if b]
            common = [x for x, b in zip(leaves, flags) if not b]
            out = _map_members(run, mapped, common, flags, treedef, static)
            return out, jax.tree_util.tree_map(lambda _: True, out)

        return member(dynamic)

    return run


@jit
def _map_members(run: Callable, mapped: list, common: list, flags: tuple, treedef: Any, static: Any) -> Any:
    """The members of a batch one after another: ``lax.map`` over the ``mapped`` leaves, the
    ``common`` ones shared (``flags``: which leaves of ``treedef`` are mapped). Each member goes
    through ``run`` (the wrapped function) again, so that an outer ``vmap`` level maps its own axis
    the same way."""

    def one(members):
        it_m, it_c = iter(members), iter(common)
        leaves = [next(it_m) if b else next(it_c) for b in flags]
        return run(*eqx.combine(jax.tree_util.tree_unflatten(treedef, leaves), static))

    return jax.lax.map(one, mapped)
