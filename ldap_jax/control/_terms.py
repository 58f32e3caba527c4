"""Objective terms for optimal control on SE(2).

A term is a small module with three parts, each zero unless it says otherwise::

    J = sum_{k=0}^{N} term.stage(system, node_k, c_k, h)            (at every node)
      + sum_{k=0}^{N-1} term.interval(system, c_k, c_{k+1}, h)      (on every step)
      + term.terminal(system, node_N, q_0)                          (at the last node)

where ``node_k`` is the :class:`Node` ``k`` (configuration ``q`` and velocity ``qdot``), ``c_k``
the physical control values at ``t_k`` (linear in between, as the integrators read them), ``h``
the step and ``q_0`` the initial configuration. A task's objective is a tuple of terms (summed,
each reported on its own), the way optax chains transformations; the same terms score a
trajectory of the optimizer's model, the interior-point solver's stages and a replay on the
high-accuracy reference. A term of your own is an ``eqx.Module`` overriding one method.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._compilation_cache import asarray
from .._typing import ArrayLike
from ..lie import SE2

__all__ = [
    "AbstractTerm",
    "Effort",
    "Displacement",
    "Forward",
    "Rotation",
    "Node",
    "evaluate_terms",
    "displacement",
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


def displacement(q: Float[ArrayLike, " d"], q0: Float[ArrayLike, " d"]) -> Float[Array, " 3"]:
    """The net displacement ``(dx, dy, dtheta)`` from ``q0`` to ``q``: the position change in the
    body frame of ``q0`` and the heading change (not wrapped: a gait that turns a full circle
    per cycle has ``dtheta = 2 pi``). For ``g_0`` the identity this is ``g_0^-1 g = (x, y, theta)``."""
    q, q0 = jnp.asarray(q), jnp.asarray(q0)
    c, s = jnp.cos(q0[2]), jnp.sin(q0[2])
    dx, dy = q[0] - q0[0], q[1] - q0[1]
    return jnp.stack([c * dx + s * dy, -s * dx + c * dy, q[2] - q0[2]])


def effort_cost(values: Float[ArrayLike, "K n"], h: ArrayLike, scale: Float[ArrayLike, " n"]) -> Array:
    """The exact integral of ``|c(t) / scale|^2`` over piecewise-linear controls with node values
    ``values``: ``sum_k h/3 (U_k^2 + U_k U_{k+1} + U_{k+1}^2)``, ``U = c / scale``."""
    u = jnp.asarray(values) / jnp.asarray(scale)[None, :]
    return jnp.sum(_interval_effort(u[:-1], u[1:], jnp.asarray(h)))


def _interval_effort(u0: Array, u1: Array, h: Array) -> Array:
    return h / 3 * jnp.sum(u0 * u0 + u0 * u1 + u1 * u1, axis=-1)


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
    """An objective term: ``stage`` at every node, ``interval`` on every step, ``terminal`` at
    the last node (each 0 unless overridden; see the module docstring)."""

    def stage(self, system: Any, obs: Any, c: Array, h: Array) -> Array:
        return jnp.zeros((), c.dtype)

    def interval(self, system: Any, c0: Array, c1: Array, h: Array) -> Array:
        return jnp.zeros((), c0.dtype)

    def terminal(self, system: Any, obs: Any, q0: Array) -> Array:
        return jnp.zeros((), q0.dtype)

    @property
    def reads_nodes(self) -> bool:
        """Whether the term reads the nodes' ``q`` or ``qdot`` at every node (``stage``): the
        solver then recovers each node's velocity; the control effort does not need it."""
        return type(self).stage is not AbstractTerm.stage


class Effort(AbstractTerm):
    """``weight * int_0^T |c(t) / scale|^2 dt`` for piecewise-linear controls, exactly:
    ``weight * sum_k h/3 (U_k^2 + U_k U_{k+1} + U_{k+1}^2)`` with ``U_k = c_k / scale``.

    Args:
        scale: per-channel scale (n_channels,), in the controls' units.
        weight: the term's weight (default 1).
    """

    scale: Float[Array, " n"] = eqx.field(converter=asarray)
    weight: Array = eqx.field(default=1.0, converter=asarray)

    def __check_init__(self):
        if jnp.ndim(self.scale) != 1:
            raise ValueError(f"Effort: 'scale' must be 1-d (n_channels,), got shape {jnp.shape(self.scale)}")
        check_known("Effort", "scale", self.scale, positive=True)
        check_known("Effort", "weight", self.weight, positive=False)

    def interval(self, system, c0, c1, h):
        return self.weight * _interval_effort(c0 / self.scale, c1 / self.scale, h)


class Displacement(AbstractTerm):
    """``-weight * <direction, (dx, dy)>``: rewards the displacement along ``direction``, a unit
    vector in the body frame of the initial pose (``(1, 0)``: forward, ``(0, 1)``: to the left),
    from ``q_0`` to ``q_N`` (m). For a gait, the displacement per cycle."""

    direction: Float[Array, " 2"] = eqx.field(default=(1.0, 0.0), converter=asarray)
    weight: Array = eqx.field(default=1.0, converter=asarray)

    def __check_init__(self):
        if jnp.shape(self.direction) != (2,):
            raise ValueError(f"Displacement: 'direction' must be (2,), got shape {jnp.shape(self.direction)}")
        check_known("Displacement", "direction", self.direction)
        check_known("Displacement", "weight", self.weight)
        if not any(isinstance(x, jax.core.Tracer) for x in (self.direction,)):
            norm = float(np.hypot(*np.asarray(self.direction, float)))
            if abs(norm - 1.0) > 1e-9:
                raise ValueError(
                    f"Displacement: 'direction' must be a unit vector, got {np.asarray(self.direction)} "
                    f"(norm {norm:.6g}); scale the reward with 'weight'"
                )

    def terminal(self, system, obs, q0):
        d = displacement(obs.q, q0)
        return -self.weight * (self.direction[0] * d[0] + self.direction[1] * d[1])


def Forward(weight: ArrayLike = 1.0) -> Displacement:  # noqa: N802 (a constructor, as the class it builds)
    """``-weight *`` the displacement along the initial heading at ``t_N`` (m): rewards progress
    (a :class:`Displacement` with ``direction = (1, 0)``)."""
    return Displacement(direction=(1.0, 0.0), weight=weight)


class Rotation(AbstractTerm):
    """``-weight * (theta_N - theta_0)``: rewards turning counter-clockwise (rad; a negative
    weight rewards clockwise turns). For a gait, the rotation per cycle."""

    weight: Array = eqx.field(default=1.0, converter=asarray)

    def __check_init__(self):
        check_known("Rotation", "weight", self.weight)

    def terminal(self, system, obs, q0):
        return -self.weight * (obs.q[2] - q0[2])


def check_known(owner: str, name: str, x: Any, *, positive: bool | None = None) -> None:
    """A known value must be finite; ``positive=True``: every entry > 0, ``False``: >= 0."""
    if any(isinstance(v, jax.core.Tracer) for v in jax.tree_util.tree_leaves(x)):
        return
    a = np.asarray(x, float)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{owner}: '{name}' must be finite, got {a}")
    if positive is True and not np.all(a > 0):
        raise ValueError(f"{owner}: '{name}' must be positive, got {a}")
    if positive is False and not np.all(a >= 0):
        raise ValueError(f"{owner}: '{name}' must be non-negative, got {a}")


def evaluate_terms(terms: dict, system, obs, c: Array, h: Array, q0: Array) -> dict:
    """Each term of ``terms`` (a name -> term dict) on a trajectory: ``obs`` with leading axis
    the nodes ``0..N``, ``c`` the control values at the nodes."""
    out = {}
    last = jax.tree_util.tree_map(lambda x: x[-1], obs)
    for name, term in terms.items():
        stages = jax.vmap(lambda o, cc, term=term: term.stage(system, o, cc, h))(obs, c)
        steps = jax.vmap(lambda c0, c1, term=term: term.interval(system, c0, c1, h))(c[:-1], c[1:])
        out[name] = jnp.sum(stages) + jnp.sum(steps) + term.terminal(system, last, q0)
    return out
