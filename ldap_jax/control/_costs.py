"""Costs for optimal control on SE(2): terminal pose error, effort, bound penalties."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ..lie import SE2

__all__ = ["pose_error", "terminal_pose_cost", "effort_cost", "bound_penalty", "wrap_angle"]


def wrap_angle(theta: ArrayLike) -> Array:
    """``theta`` wrapped to ``(-pi, pi]``."""
    theta = jnp.asarray(theta)
    return jnp.arctan2(jnp.sin(theta), jnp.cos(theta))


def _pose(q: Float[ArrayLike, " d"]) -> SE2:
    q = jnp.asarray(q)
    return SE2.from_xy_theta(q[0], q[1], q[2])


def pose_error(q: Float[ArrayLike, " d"], goal: Float[ArrayLike, 3]) -> Float[Array, 3]:
    """Pose error ``log(g_goal^-1 g)`` in ``(omega, v_x, v_y)`` (App. B) for ``q = (x, y, theta, ...)``.

    The error is expressed in the goal's body frame: its first entry is the heading error in
    ``(-pi, pi]``, the last two are (to first order) the position error along and across the goal
    heading. It vanishes exactly at the goal and is smooth near it (the ``log`` of
    :mod:`ldap_jax.lie` has a Taylor branch at zero rotation).

    Args:
        q: configuration ``(x, y, theta, r1, r2)`` (only the first three entries are read).
        goal: goal pose ``(x, y, theta)``.

    Returns:
        ``log(g_goal^-1 g)``, shape (3,).
    """
    goal = jnp.asarray(goal)
    return (_pose(goal).inverse() @ _pose(q)).log()


def terminal_pose_cost(
    q: Float[ArrayLike, " d"], goal: Float[ArrayLike, 3], *, w_heading: ArrayLike, w_position: ArrayLike
) -> Array:
    """``w_heading e_1^2 + w_position (e_2^2 + e_3^2)`` with ``e = log(g_goal^-1 g_N)``."""
    e = pose_error(q, goal)
    return w_heading * e[0] ** 2 + w_position * (e[1] ** 2 + e[2] ** 2)


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
