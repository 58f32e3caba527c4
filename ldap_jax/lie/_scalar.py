"""SE(2) on scalar components, for the closed-form kernels (structure of arrays).

A kernel keeps every state component as its own scalar, so that ``jax.vmap`` over a batch turns
each into one contiguous vector XLA vectorises. The pose is :class:`Pose`
``(x, y, theta, cos theta, sin theta)``: rotations are composed, never re-evaluated from the
angle, and ``theta`` is kept unwrapped. The conventions are those of :mod:`ldap_jax.lie`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jaxtyping import Array

from .._numerics import materialise, saved, sincos
from ._se2 import exp_parts, small_angle

__all__ = [
    "Pose",
    "pose_from_xy_theta",
    "pose_retract",
    "pose_retract_exp",
    "dtau1_transpose",
    "body_to_qdot",
]


class Pose(NamedTuple):
    """An SE(2) element as scalars: position, unwrapped heading and its cosine and sine."""

    x: Array
    y: Array
    theta: Array
    cos: Array
    sin: Array


def pose_from_xy_theta(x: Array, y: Array, theta: Array) -> Pose:
    s, c = sincos(theta)
    return Pose(x, y, theta, c, s)


def pose_retract(g: Pose, v: tuple[Array, Array, Array], retraction: str) -> Pose:
    """``g tau(v)`` for ``v = (v1, v2, v3) = h xi`` and ``tau`` the exp or Cayley map (App. B)."""
    if retraction == "exp":
        return pose_retract_exp(g, v)[0]
    w, v2, v3 = v
    d = 4.0 + w**2
    cw, sw = (4.0 - w**2) / d, 4.0 * w / d
    dx, dy = (4.0 * v2 - 2.0 * w * v3) / d, (4.0 * v3 + 2.0 * w * v2) / d
    return _compose(g, dx, dy, 2.0 * jnp.arctan(w / 2.0), cw, sw)


def pose_retract_exp(g: Pose, v: tuple[Array, Array, Array]) -> tuple[Pose, tuple[Array, Array]]:
    """``g exp(v)`` (App. B), and ``(sin, cos)`` of the safe stand-in for ``w = v1`` that its
    translation used (a hand-written derivative of a step reads them)."""
    w, v2, v3 = v
    _, ws = small_angle(w)
    sw, cw = saved(*materialise(*sincos(ws)))
    # below the threshold the rotation comes from the series too: the safe stand-in's sine and
    # cosine must not leak into it
    ta, tb, cr, sr = exp_parts(w, sw, cw)
    dx, dy = ta * v2 - tb * v3, tb * v2 + ta * v3
    return _compose(g, dx, dy, w, cr, sr), (sw, cw)


def _compose(g: Pose, dx: Array, dy: Array, dth: Array, cw: Array, sw: Array) -> Pose:
    """``g`` composed with the pose ``(dx, dy, dth)`` whose rotation has cosine ``cw``, sine ``sw``."""
    c, s = g.cos, g.sin
    return Pose(g.x + c * dx - s * dy, g.y + s * dx + c * dy, g.theta + dth, c * cw - s * sw, s * cw + c * sw)


def dtau1_transpose(
    v: tuple[Array, Array, Array], mu: tuple[Array, Array, Array], sign: float
) -> tuple[Array, Array, Array]:
    """``(I - sign ad_v / 2)^T mu``: ``dtau^-1_{sign v}`` truncated to first order, transposed
    (the paper's explicit car and snakeboard steps use this truncation)."""
    v1, v2, v3 = v
    m1, m2, m3 = mu
    adt = (v3 * m2 - v2 * m3, v1 * m3, -v1 * m2)
    return tuple(m - 0.5 * sign * t for m, t in zip(mu, adt))


def body_to_qdot(g: Pose, u: Array, xi: Array) -> Array:
    """``qdot = (xdot, ydot, thetadot, u)`` from the body velocity ``xi = (omega, v_x, v_y)`` at ``g``."""
    c, s = g.cos, g.sin
    return jnp.concatenate([jnp.stack([c * xi[1] - s * xi[2], s * xi[1] + c * xi[2], xi[0]]), u])
