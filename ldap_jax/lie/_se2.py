"""The special Euclidean group SE(2) (paper App. A, B).

Conventions follow the paper: a group element is
``g = [[cos th, -sin th, x], [sin th, cos th, y], [0, 0, 1]]`` and a Lie-algebra vector
``v = (v1, v2, v3) = (omega, v_x, v_y)`` is the body angular rate followed by the body-frame
linear velocity, with hat map (App. B)

    v^ = [[0, -v1, v2], [v1, 0, v3], [0, 0, 0]].

All maps are written for a single element; batch with :func:`jax.vmap`. Every function with a
removable singularity at ``v1 = 0`` uses a Taylor branch behind the double-``where`` trick, so
values *and* gradients are finite there.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

__all__ = [
    "SE2",
    "hat",
    "vee",
    "ad",
    "exp",
    "log",
    "cay",
    "cay_inv",
    "dexp_inv",
    "dcay_inv",
    "dtau_inv",
    "retract",
    "compose",
]


def _small(x: Array) -> tuple[Array, Array]:
    """Mask of ``|x|`` below a dtype-keyed threshold, and a safe stand-in for ``x``."""
    eps = jnp.finfo(jnp.result_type(x)).eps
    small = jnp.abs(x) < eps**0.25
    return small, jnp.where(small, jnp.ones_like(x), x)


def _sinc_terms(w: Array) -> tuple[Array, Array]:
    """``A(w) = sin(w)/w`` and ``B(w) = (1 - cos w)/w`` with Taylor branches at ``w = 0``."""
    small, ws = _small(w)
    a = jnp.where(small, 1.0 - w**2 / 6.0 + w**4 / 120.0, jnp.sin(ws) / ws)
    b = jnp.where(small, w / 2.0 - w**3 / 24.0 + w**5 / 720.0, (1.0 - jnp.cos(ws)) / ws)
    return a, b


def _half_cot_half(w: Array) -> Array:
    """``(w/2) cot(w/2)``, the even function appearing in ``log`` and ``dexp^-1``."""
    small, ws = _small(w)
    return jnp.where(
        small,
        1.0 - w**2 / 12.0 - w**4 / 720.0,
        (ws / 2.0) * jnp.cos(ws / 2.0) / jnp.sin(ws / 2.0),
    )


def hat(v: Float[ArrayLike, 3]) -> Float[Array, "3 3"]:
    """The hat map ``R^3 -> se(2)`` of App. B."""
    v = jnp.asarray(v)
    z = jnp.zeros_like(v[0])
    return jnp.array([[z, -v[0], v[1]], [v[0], z, v[2]], [z, z, z]])


def vee(xi_hat: Float[ArrayLike, "3 3"]) -> Float[Array, 3]:
    """Inverse of :func:`hat`: ``(v1, v2, v3) = (X[1, 0], X[0, 2], X[1, 2])``."""
    x = jnp.asarray(xi_hat)
    return jnp.stack([x[1, 0], x[0, 2], x[1, 2]])


def ad(v: Float[ArrayLike, 3]) -> Float[Array, "3 3"]:
    """Matrix of ``ad_v w = [v, w]`` (App. B): ``[[0, 0, 0], [v3, 0, -v1], [-v2, v1, 0]]``."""
    v = jnp.asarray(v)
    z = jnp.zeros_like(v[0])
    return jnp.array([[z, z, z], [v[2], z, -v[0]], [-v[1], v[0], z]])


def exp(v: Float[ArrayLike, 3]) -> Float[Array, 3]:
    """Exponential map, returned as group coordinates ``(theta, x, y)`` (App. B).

    ``exp(v^)`` rotates by ``v1`` and translates by
    ``((v2 sin v1 - v3 (1 - cos v1)) / v1, (v2 (1 - cos v1) + v3 sin v1) / v1)``.
    """
    v = jnp.asarray(v)
    a, b = _sinc_terms(v[0])
    return jnp.stack([v[0], a * v[1] - b * v[2], b * v[1] + a * v[2]])


def log(g: Float[ArrayLike, 3]) -> Float[Array, 3]:
    """Inverse of :func:`exp` for ``g = (theta, x, y)`` with ``theta`` taken in ``(-pi, pi]``.

    ``(v2, v3) = [[c, w/2], [-w/2, c]] (x, y)`` with ``w = theta`` and ``c = (w/2) cot(w/2)``.
    """
    g = jnp.asarray(g)
    w = jnp.arctan2(jnp.sin(g[0]), jnp.cos(g[0]))
    c = _half_cot_half(w)
    return jnp.stack([w, c * g[1] + 0.5 * w * g[2], -0.5 * w * g[1] + c * g[2]])


def cay(v: Float[ArrayLike, 3]) -> Float[Array, 3]:
    """Cayley map ``(I - v^/2)^-1 (I + v^/2)`` as group coordinates ``(theta, x, y)``.

    Corrected App. B: rotation block ``[[4 - v1^2, -4 v1], [4 v1, 4 - v1^2]] / (4 + v1^2)``,
    translation ``(4 v2 - 2 v1 v3, 4 v3 + 2 v1 v2) / (4 + v1^2)``; so ``theta = 2 atan(v1 / 2)``.
    """
    v = jnp.asarray(v)
    d = 4.0 + v[0] ** 2
    return jnp.stack(
        [
            2.0 * jnp.arctan(v[0] / 2.0),
            (4.0 * v[1] - 2.0 * v[0] * v[2]) / d,
            (4.0 * v[2] + 2.0 * v[0] * v[1]) / d,
        ]
    )


def cay_inv(g: Float[ArrayLike, 3]) -> Float[Array, 3]:
    """Inverse Cayley map: ``v1 = 2 tan(theta/2)``, ``(v2, v3) = (x + v1 y / 2, y - v1 x / 2)``."""
    g = jnp.asarray(g)
    w = 2.0 * jnp.tan(g[0] / 2.0)
    return jnp.stack([w, g[1] + 0.5 * w * g[2], g[2] - 0.5 * w * g[1]])


def dexp_inv(v: Float[ArrayLike, 3]) -> Float[Array, "3 3"]:
    """Exact right-trivialized inverse differential of ``exp`` (eq. (28), all terms).

    ``dexp^-1_v = sum_j B_j / j! ad_v^j`` (Bernoulli numbers). On SE(2), with
    ``c = (v1/2) cot(v1/2)``, ``beta = (1 - c) / v1``, ``J = [[0, -1], [1, 0]]`` and ``b = (v3, -v2)``:

        dexp^-1_v = [[1, 0], [(-I/2 + beta J) b, c I - (v1/2) J]],

    whose Taylor expansion is ``I - ad_v/2 + ad_v^2/12 + ...`` (the paper's (31) truncation).
    """
    v = jnp.asarray(v)
    w = v[0]
    c = _half_cot_half(w)
    small, ws = _small(w)
    beta = jnp.where(small, w / 12.0 + w**3 / 720.0, (1.0 - c) / ws)
    b1, b2 = v[2], -v[1]
    z = jnp.zeros_like(w)
    one = jnp.ones_like(w)
    return jnp.array(
        [
            [one, z, z],
            [-0.5 * b1 - beta * b2, c, 0.5 * w],
            [-0.5 * b2 + beta * b1, -0.5 * w, c],
        ]
    )


def dcay_inv(v: Float[ArrayLike, 3]) -> Float[Array, "3 3"]:
    """Right-trivialized inverse differential of the Cayley map, eq. (32) (exact).

    ``dcay^-1_v = I - ad_v / 2 + [v1 v, 0_{3x2}] / 4``, i.e. ``w -> (I - v^/2) w^ (I + v^/2)`` (29).
    """
    v = jnp.asarray(v)
    extra = jnp.zeros((3, 3), v.dtype).at[:, 0].set(0.25 * v[0] * v)
    return jnp.eye(3, dtype=v.dtype) - 0.5 * ad(v) + extra


def dtau_inv(v: Float[ArrayLike, 3], retraction: str, order: int | None = None) -> Array:
    """``dtau^-1_v`` for ``retraction in {"exp", "cayley"}``.

    Args:
        v: Lie-algebra vector, shape (3,).
        retraction: ``"exp"`` or ``"cayley"``.
        order: ``None`` for the exact map; an integer ``p`` truncates the series in ``ad_v``
            after the ``ad_v^p`` term: ``p = 1`` gives ``I - ad_v/2`` (what the paper's explicit
            car and snakeboard steps use), ``p = 2`` gives eq. (31) for exp and (32) for Cayley.
    """
    v = jnp.asarray(v)
    if order is None:
        return dexp_inv(v) if retraction == "exp" else dcay_inv(v)
    if order < 1:
        raise ValueError(f"order must be None or >= 1, got {order}")
    eye = jnp.eye(3, dtype=v.dtype)
    a = ad(v)
    out = eye - 0.5 * a
    if order >= 2:
        if retraction == "exp":
            # Bernoulli series: B_2/2! = 1/12, B_odd>1 = 0, B_4/4! = -1/720, B_6/6! = 1/30240, ...
            coeffs = {2: 1.0 / 12.0, 4: -1.0 / 720.0, 6: 1.0 / 30240.0, 8: -1.0 / 1209600.0}
            power = a
            for j in range(2, order + 1):
                power = power @ a
                out = out + coeffs.get(j, 0.0) * power
        else:
            out = dcay_inv(v)
    return out


def retract(v: Float[ArrayLike, 3], retraction: str) -> Float[Array, 3]:
    """``tau(v)`` as group coordinates, ``tau in {exp, cay}``."""
    return exp(v) if retraction == "exp" else cay(v)


def compose(g1: Array, g2: Array) -> Array:
    """``g1 g2`` in coordinates ``(theta, x, y)`` (angles add, no wrapping)."""
    c, s = jnp.cos(g1[0]), jnp.sin(g1[0])
    return jnp.stack([g1[0] + g2[0], g1[1] + c * g2[1] - s * g2[2], g1[2] + s * g2[1] + c * g2[2]])


class SE2(eqx.Module):
    """An element of SE(2), stored as ``(cos theta, sin theta, x, y)`` (as in jaxlie).

    The vocabulary follows jaxlie: :meth:`identity`, :meth:`exp`, :meth:`log`, ``@``,
    :meth:`inverse`, :meth:`adjoint`, :meth:`as_matrix`; plus :meth:`cay` and :meth:`cay_inv`.
    Tangent vectors use the paper's order ``(omega, v_x, v_y)``.

    Example:
        >>> g = SE2.exp(jnp.array([0.3, 1.0, 0.0]))
        >>> (g @ g.inverse()).log()   # ~ zeros
    """

    unit_complex_xy: Float[Array, 4]

    tangent_dim: ClassVar[int] = 3
    parameters_dim: ClassVar[int] = 4
    matrix_dim: ClassVar[int] = 3

    @staticmethod
    def from_xy_theta(x: ArrayLike, y: ArrayLike, theta: ArrayLike) -> SE2:
        x, y, theta = jnp.asarray(x), jnp.asarray(y), jnp.asarray(theta)
        return SE2(jnp.stack([jnp.cos(theta), jnp.sin(theta), x, y]))

    @staticmethod
    def identity(dtype=None) -> SE2:
        return SE2(jnp.array([1.0, 0.0, 0.0, 0.0], dtype=dtype))

    @staticmethod
    def from_matrix(matrix: ArrayLike) -> SE2:
        m = jnp.asarray(matrix)
        return SE2(jnp.stack([m[0, 0], m[1, 0], m[0, 2], m[1, 2]]))

    @property
    def theta(self) -> Array:
        return jnp.arctan2(self.unit_complex_xy[1], self.unit_complex_xy[0])

    @property
    def translation(self) -> Array:
        return self.unit_complex_xy[2:]

    def as_matrix(self) -> Float[Array, "3 3"]:
        c, s, x, y = self.unit_complex_xy
        z, o = jnp.zeros_like(c), jnp.ones_like(c)
        return jnp.array([[c, -s, x], [s, c, y], [z, z, o]])

    @staticmethod
    def exp(v: ArrayLike) -> SE2:
        th, x, y = exp(v)
        return SE2(jnp.stack([jnp.cos(th), jnp.sin(th), x, y]))

    @staticmethod
    def cay(v: ArrayLike) -> SE2:
        v = jnp.asarray(v)
        d = 4.0 + v[0] ** 2
        _, x, y = cay(v)
        return SE2(jnp.stack([(4.0 - v[0] ** 2) / d, 4.0 * v[0] / d, x, y]))

    def log(self) -> Array:
        return log(jnp.concatenate([self.theta[None], self.translation]))

    def cay_inv(self) -> Array:
        return cay_inv(jnp.concatenate([self.theta[None], self.translation]))

    def multiply(self, other: SE2) -> SE2:
        c1, s1, x1, y1 = self.unit_complex_xy
        c2, s2, x2, y2 = other.unit_complex_xy
        return SE2(
            jnp.stack([c1 * c2 - s1 * s2, s1 * c2 + c1 * s2, x1 + c1 * x2 - s1 * y2, y1 + s1 * x2 + c1 * y2])
        )

    def __matmul__(self, other: SE2) -> SE2:
        return self.multiply(other)

    def inverse(self) -> SE2:
        c, s, x, y = self.unit_complex_xy
        return SE2(jnp.stack([c, -s, -(c * x + s * y), s * x - c * y]))

    def adjoint(self) -> Float[Array, "3 3"]:
        """``Ad_g`` on ``(omega, v_x, v_y)``: ``[[1, 0, 0], [y, c, -s], [-x, s, c]]``."""
        c, s, x, y = self.unit_complex_xy
        z, o = jnp.zeros_like(c), jnp.ones_like(c)
        return jnp.array([[o, z, z], [y, c, -s], [-x, s, c]])

    def apply(self, p: ArrayLike) -> Array:
        """Act on a point of the plane."""
        c, s, x, y = self.unit_complex_xy
        p = jnp.asarray(p)
        return jnp.stack([x + c * p[0] - s * p[1], y + s * p[0] + c * p[1]])
