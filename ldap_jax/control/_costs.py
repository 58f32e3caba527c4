"""Costs for optimal control on SE(2), as composable terms.

A term is a small module with a per-node part and a terminal part,

    J = sum_{k=0}^{N} term.stage(system, obs_k, c_k, h) + term.terminal(system, obs_N, q_0),

where ``obs_k`` is the :class:`Node` ``k`` (its configuration ``q`` and velocity ``qdot``), ``c_k``
the physical control values at ``t_k`` and ``h`` the step. A task's cost is a tuple of terms
(summed, each reported on its own), the way optax chains transformations; the same terms score a
trajectory of the optimizer's model, the interior-point solver's stage costs and a replay on the
high-accuracy reference.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._typing import ArrayLike
from ..lie import SE2

__all__ = [
    "AbstractTerm",
    "Effort",
    "Forward",
    "TerminalPose",
    "TerminalRest",
    "BoundPenalty",
    "evaluate_terms",
    "Node",
    "pose_error",
    "effort_cost",
    "bound_penalty",
    "wrap_angle",
]


def wrap_angle(theta: ArrayLike) -> Array:
    """``theta`` wrapped to ``(-pi, pi]`` (rad)."""
    theta = jnp.asarray(theta)
    return jnp.arctan2(jnp.sin(theta), jnp.cos(theta))


def pose_error(q: Float[ArrayLike, " d"], goal: Float[ArrayLike, " 3"]) -> Float[Array, " 3"]:
    """Pose error ``log(g_goal^-1 g)`` in ``(omega, v_x, v_y)`` (App. B) for ``q = (x, y, theta, ...)``.

    Expressed in the goal's body frame: the first entry is the heading error in ``(-pi, pi]``
    (rad), the last two are (to first order) the position error along and across the goal
    heading (m). It vanishes exactly at the goal and is smooth near it.

    Args:
        q: configuration ``(x, y, theta, r1, ...)`` (only the first three entries are read).
        goal: goal pose ``(x, y, theta)``.
    """
    q, goal = jnp.asarray(q), jnp.asarray(goal)
    return (SE2.from_xy_theta(*goal).inverse() @ SE2.from_xy_theta(q[0], q[1], q[2])).log()


def effort_cost(values: Float[ArrayLike, "K n"], h: ArrayLike, scale: Float[ArrayLike, " n"]) -> Array:
    """Running control effort ``sum_k h |c_k / scale|^2`` (rectangle rule on the samples)."""
    values = jnp.asarray(values)
    return h * jnp.sum((values / jnp.asarray(scale)[None, :]) ** 2)


def bound_penalty(x: ArrayLike, lower: ArrayLike, upper: ArrayLike) -> Array:
    """Quadratic exterior penalty ``sum (max(x - upper, 0)^2 + max(lower - x, 0)^2)``.

    Zero (with zero gradient) inside the bounds; infinite bounds switch an entry off.
    """
    x = jnp.asarray(x)
    return jnp.sum(jnp.maximum(x - upper, 0.0) ** 2 + jnp.maximum(lower - x, 0.0) ** 2)


class Node(NamedTuple):
    """What a term reads of a node: configuration ``q`` and velocity ``qdot``."""

    q: Array
    qdot: Array


class AbstractTerm(eqx.Module):
    """A cost term: ``stage`` at every node (default 0) plus ``terminal`` at the last (default 0)."""

    def stage(self, system: Any, obs: Any, c: Array, h: Array) -> Array:
        return jnp.zeros((), c.dtype)

    def terminal(self, system: Any, obs: Any, q0: Array) -> Array:
        return jnp.zeros((), q0.dtype)


class Effort(AbstractTerm):
    """``weight * h * |c_k / scale|^2`` at every node: the control effort (a rectangle rule)."""

    scale: Float[Array, " n"]
    weight: Array = eqx.field(default=1.0, converter=jnp.asarray)

    def stage(self, system, obs, c, h):
        return self.weight * h * jnp.sum((c / self.scale) ** 2)


class Forward(AbstractTerm):
    """``-weight *`` the displacement along the initial heading at ``t_N`` (m): rewards progress."""

    weight: Array = eqx.field(default=1.0, converter=jnp.asarray)

    def terminal(self, system, obs, q0):
        q = obs.q
        return -self.weight * ((q[0] - q0[0]) * jnp.cos(q0[2]) + (q[1] - q0[1]) * jnp.sin(q0[2]))


class TerminalPose(AbstractTerm):
    """``w_heading e_1^2 + w_position (e_2^2 + e_3^2)`` with ``e = log(g_goal^-1 g_N)``."""

    goal: Float[Array, " 3"]
    w_heading: Array = eqx.field(default=1.0, converter=jnp.asarray)
    w_position: Array = eqx.field(default=1.0, converter=jnp.asarray)

    def terminal(self, system, obs, q0):
        e = pose_error(obs.q, self.goal)
        return self.w_heading * e[0] ** 2 + self.w_position * (e[1] ** 2 + e[2] ** 2)


class TerminalRest(AbstractTerm):
    """``weight * |v_i|^2`` for the minimal velocities ``v = system.velocities_from_qdot(q, qdot)``
    at ``t_N`` with indices ``i`` in ``indices`` (the car's wheel rate ``(0,)``; the snakeboard's
    board speed ``s``, ``(2,)``)."""

    indices: tuple[int, ...] = eqx.field(static=True)
    weight: Array = eqx.field(default=1.0, converter=jnp.asarray)

    def residual(self, system, obs) -> Array:
        v = system.velocities_from_qdot(obs.q, obs.qdot)
        return v[jnp.asarray(self.indices, int)]

    def terminal(self, system, obs, q0):
        return self.weight * jnp.sum(self.residual(system, obs) ** 2)


class BoundPenalty(AbstractTerm):
    """``weight * h * (bound_penalty(q_k) + bound_penalty(c_k / scale))`` at every node."""

    q_lower: Float[Array, " d"]
    q_upper: Float[Array, " d"]
    c_lower: Float[Array, " n"]
    c_upper: Float[Array, " n"]
    scale: Float[Array, " n"]
    weight: Array = eqx.field(default=1.0, converter=jnp.asarray)

    def stage(self, system, obs, c, h):
        pen = bound_penalty(obs.q, self.q_lower, self.q_upper)
        pen = pen + bound_penalty(c / self.scale, self.c_lower / self.scale, self.c_upper / self.scale)
        return self.weight * h * pen


def evaluate_terms(terms: dict, system, obs, c: Array, h: Array, q0: Array) -> dict:
    """Each term of ``terms`` (a name -> term dict) on a trajectory: ``obs`` with leading axis
    the nodes ``0..N``, ``c`` the control values at the nodes."""
    out = {}
    last = jax.tree_util.tree_map(lambda x: x[-1], obs)
    for name, term in terms.items():
        stages = jax.vmap(lambda o, cc, term=term: term.stage(system, o, cc, h))(obs, c)
        out[name] = jnp.sum(stages) + term.terminal(system, last, q0)
    return out
