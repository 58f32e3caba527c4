"""The special Euclidean group SE(2) (paper App. A, B).

**One convention, used everywhere in ldap_jax:**

* a group element (a *pose*) has coordinates ``g = (x, y, theta)``, the same order as the first
  three entries of a configuration ``q = (x, y, theta, r_1, ..., r_n)``; its matrix is
  ``[[cos th, -sin th, x], [sin th, cos th, y], [0, 0, 1]]``;
* a Lie-algebra vector is ``v = (v1, v2, v3) = (omega, v_x, v_y)``: the body angular rate
  followed by the body-frame linear velocity (the paper's order, in which the connection
  ``A(r)`` and the symmetry basis ``e(r)`` of every model are written), with hat map (App. B)
  ``v^ = [[0, -v1, v2], [v1, 0, v3], [0, 0, 0]]``;
* :class:`SE2` stores ``(cos theta, sin theta, x, y)``, exactly jaxlie's ``unit_complex_xy``;
  :meth:`SE2.from_jaxlie` / :meth:`SE2.to_jaxlie` convert, and :func:`tangent_to_jaxlie` /
  :func:`tangent_from_jaxlie` reorder tangent vectors to and from jaxlie's ``(v_x, v_y, omega)``.

All maps are written for a single element; batch with :func:`jax.vmap`. Every function with a
removable singularity at ``v1 = 0`` uses a Taylor branch behind the double-``where`` trick, so
values *and* gradients are finite there.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._typing import ArrayLike

__all__ = [
    "SE2",
    "hat",
    "vee",
    "ad",
    "exp",
    "log",
    "cay",
    "cay_inv",
    "compose",
    "inverse",
    "retract",
    "dexp_inv",
    "dcay_inv",
    "dtau_inv",
    "exp_translation",
    "exp_series",
    "exp_parts",
    "exp_series_derivative",
    "tangent_to_jaxlie",
    "tangent_from_jaxlie",
]


def _floats(x: ArrayLike) -> Array:
    """``x`` as an array, integer and boolean values converted to the default float dtype."""
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.inexact) else x.astype(jnp.result_type(float))


def _element(x: ArrayLike, caller: str, name: str, shape: tuple[int, ...] = (3,)) -> Array:
    """:func:`_floats` of one element of shape ``shape`` (these maps act on one element: a batch
    goes through :func:`jax.vmap`)."""
    x = _floats(x)
    if x.shape != shape:
        raise ValueError(
            f"lie.{caller}: {name!r} must have shape {shape} (one element; batch with jax.vmap), "
            f"got {x.shape}"
        )
    return x


def _retraction(caller: str, retraction: str) -> str:
    if retraction not in ("exp", "cayley"):
        raise ValueError(f"lie.{caller}: 'retraction' must be 'exp' or 'cayley', got {retraction!r}")
    return retraction


def small_angle(w: Array) -> tuple[Array, Array]:
    """Mask of ``|w|`` below a dtype-keyed threshold (``eps^(1/16)``: 0.105 in float64, 0.37 in
    float32), and a safe stand-in for ``w``.

    Below it the ratios of the exponential map and of ``dexp^-1`` are taken from their Taylor
    series (:func:`exp_series`, :func:`_half_cot_half`), exact to round-off there. Above it the
    direct formulas ``(1 - cos w) / w`` and ``(1 - (w/2) cot(w/2)) / w`` lose about ``eps / w^2``
    of their relative accuracy to cancellation, and their k-th derivatives ``eps / w^(k+2)``: the
    threshold keeps second derivatives (Hessians of rollouts, Newton's Jacobians) to about 1e-10
    relative in float64, where ``eps^(1/4)`` (1.2e-4) left them with no correct digit.
    """
    eps = jnp.finfo(jnp.result_type(w)).eps
    small = jnp.abs(w) < eps**0.0625
    return small, jnp.where(small, jnp.ones_like(w), w)


def _horner(x: Array, coefficients: tuple[float, ...]) -> Array:
    """``sum_k c_k x^k`` by Horner's scheme: one multiply-add per coefficient (the coefficients as
    constants, not divisions, which the compiler keeps as divisions and which cost the rollout's
    composed step 8-12%)."""
    out = coefficients[-1]
    for c in coefficients[-2::-1]:
        out = out * x + c
    return out


#: Taylor coefficients in ``w^2``: ``sin(w)/w`` ((-1)^k / (2k+1)!), ``(1 - cos w)/w`` divided by
#: ``w`` ((-1)^k / (2k+2)!), and their derivatives divided by ``w`` and by 1
_SINC = tuple((-1) ** k / math.factorial(2 * k + 1) for k in range(5))
_COSC = tuple((-1) ** k / math.factorial(2 * k + 2) for k in range(5))
_DSINC = tuple((-1) ** (k + 1) * (2 * k + 2) / math.factorial(2 * k + 3) for k in range(5))
_DCOSC = tuple((-1) ** k * (2 * k + 1) / math.factorial(2 * k + 2) for k in range(6))


def exp_series(w: Array) -> tuple[Array, Array]:
    """Taylor series of ``sin(w) / w`` and ``(1 - cos w) / w`` through ``w^8`` and ``w^9``
    (Horner's scheme in ``w^2``): exact to round-off below :func:`small_angle`'s threshold. Then
    ``sin w = w sin(w)/w`` and ``cos w = 1 - w (1 - cos w)/w``."""
    w2 = w * w
    return _horner(w2, _SINC), w * _horner(w2, _COSC)


def exp_series_derivative(w: Array) -> tuple[Array, Array]:
    """Derivatives of :func:`exp_series` with respect to ``w`` (series through ``w^9`` and
    ``w^10``), for a hand-written VJP."""
    w2 = w * w
    return w * _horner(w2, _DSINC), _horner(w2, _DCOSC)


def exp_parts(w: Array, sin_w: Array, cos_w: Array) -> tuple[Array, Array, Array, Array]:
    """``(sin(w)/w, (1 - cos w)/w, cos w, sin w)`` of the exponential map, from the caller's
    ``sin w`` and ``cos w`` of the safe stand-in (:func:`small_angle`) above the threshold and from
    :func:`exp_series` below it (where the stand-in's values must not leak into the rotation)."""
    small, ws = small_angle(w)
    sinc, cosc = exp_series(w)
    a = jnp.where(small, sinc, sin_w / ws)
    b = jnp.where(small, cosc, (1.0 - cos_w) / ws)
    return a, b, jnp.where(small, 1.0 - w * cosc, cos_w), jnp.where(small, w * sinc, sin_w)


def exp_translation(w: Array, v2: Array, v3: Array, sin_w: Array, cos_w: Array) -> tuple[Array, Array]:
    """Translation part of ``exp(v)``, ``((v2 sin w - v3 (1 - cos w)) / w, (v2 (1 - cos w) + v3 sin w) / w)``.

    Takes ``sin w`` and ``cos w`` (of :func:`small_angle`'s safe stand-in) from the caller, so a
    kernel can share them with its rotation; below :func:`small_angle`'s threshold the ratios ``sin(w)/w`` and
    ``(1 - cos w)/w`` come from their Taylor series (:func:`exp_series`).
    """
    a, b, _, _ = exp_parts(w, sin_w, cos_w)
    return a * v2 - b * v3, b * v2 + a * v3


def _cot_series(w2: Array) -> Array:
    """``P(w^2)`` with ``(w/2) cot(w/2) = 1 - (w^2 / 12) P`` (Bernoulli numbers, through ``w^8``
    in ``P``): ``1 + w^2/60 + w^4/2520 + w^6/100800 + w^8/3991680``."""
    return _horner(w2, (1.0, 1.0 / 60.0, 1.0 / 2520.0, 1.0 / 100800.0, 1.0 / 3991680.0))


def _half_cot_half(w: Array) -> Array:
    """``(w/2) cot(w/2)``, the even function appearing in ``log`` and ``dexp^-1`` (series through
    ``w^10`` below :func:`small_angle`'s threshold)."""
    small, ws = small_angle(w)
    w2 = w * w
    series = 1.0 - w2 / 12.0 * _cot_series(w2)
    return jnp.where(small, series, (ws / 2.0) * jnp.cos(ws / 2.0) / jnp.sin(ws / 2.0))


def hat(v: Float[ArrayLike, " 3"]) -> Float[Array, "3 3"]:
    """The hat map ``R^3 -> se(2)`` of App. B."""
    v = _element(v, "hat", "v")
    z = jnp.zeros_like(v[0])
    return jnp.array([[z, -v[0], v[1]], [v[0], z, v[2]], [z, z, z]])


def vee(xi_hat: Float[ArrayLike, "3 3"]) -> Float[Array, " 3"]:
    """Inverse of :func:`hat`: ``(v1, v2, v3) = (X[1, 0], X[0, 2], X[1, 2])``."""
    x = _element(xi_hat, "vee", "xi_hat", (3, 3))
    return jnp.stack([x[1, 0], x[0, 2], x[1, 2]])


def ad(v: Float[ArrayLike, " 3"]) -> Float[Array, "3 3"]:
    """Matrix of ``ad_v w = [v, w]`` (App. B): ``[[0, 0, 0], [v3, 0, -v1], [-v2, v1, 0]]``."""
    v = _element(v, "ad", "v")
    z = jnp.zeros_like(v[0])
    return jnp.array([[z, z, z], [v[2], z, -v[0]], [-v[1], v[0], z]])


def exp(v: Float[ArrayLike, " 3"]) -> Float[Array, " 3"]:
    """Exponential map ``exp(v^)`` as a pose ``(x, y, theta)`` (App. B).

    Rotates by ``v1`` and translates by
    ``((v2 sin v1 - v3 (1 - cos v1)) / v1, (v2 (1 - cos v1) + v3 sin v1) / v1)``.
    """
    v = _element(v, "exp", "v")
    _, ws = small_angle(v[0])
    x, y = exp_translation(v[0], v[1], v[2], jnp.sin(ws), jnp.cos(ws))
    return jnp.stack([x, y, v[0]])


def log(g: Float[ArrayLike, " 3"]) -> Float[Array, " 3"]:
    """Inverse of :func:`exp` for a pose ``g = (x, y, theta)``, with ``theta`` taken in ``(-pi, pi]``.

    ``(v2, v3) = [[c, w/2], [-w/2, c]] (x, y)`` with ``w = theta`` and ``c = (w/2) cot(w/2)``.
    """
    g = _element(g, "log", "g")
    w = jnp.arctan2(jnp.sin(g[2]), jnp.cos(g[2]))
    c = _half_cot_half(w)
    return jnp.stack([w, c * g[0] + 0.5 * w * g[1], -0.5 * w * g[0] + c * g[1]])


def cay(v: Float[ArrayLike, " 3"]) -> Float[Array, " 3"]:
    """Cayley map ``(I - v^/2)^-1 (I + v^/2)`` as a pose ``(x, y, theta)``.

    Corrected App. B: rotation block ``[[4 - v1^2, -4 v1], [4 v1, 4 - v1^2]] / (4 + v1^2)``,
    translation ``(4 v2 - 2 v1 v3, 4 v3 + 2 v1 v2) / (4 + v1^2)``, so ``theta = 2 atan(v1 / 2)``.
    """
    v = _element(v, "cay", "v")
    d = 4.0 + v[0] ** 2
    return jnp.stack(
        [
            (4.0 * v[1] - 2.0 * v[0] * v[2]) / d,
            (4.0 * v[2] + 2.0 * v[0] * v[1]) / d,
            2.0 * jnp.arctan(v[0] / 2.0),
        ]
    )


def cay_inv(g: Float[ArrayLike, " 3"]) -> Float[Array, " 3"]:
    """Inverse Cayley map: ``v1 = 2 tan(theta/2)``, ``(v2, v3) = (x + v1 y / 2, y - v1 x / 2)``."""
    g = _element(g, "cay_inv", "g")
    w = 2.0 * jnp.tan(g[2] / 2.0)
    return jnp.stack([w, g[0] + 0.5 * w * g[1], g[1] - 0.5 * w * g[0]])


def compose(g1: Float[ArrayLike, " 3"], g2: Float[ArrayLike, " 3"]) -> Float[Array, " 3"]:
    """``g1 g2`` for poses ``(x, y, theta)`` (angles add, no wrapping)."""
    g1, g2 = _element(g1, "compose", "g1"), _element(g2, "compose", "g2")
    c, s = jnp.cos(g1[2]), jnp.sin(g1[2])
    return jnp.stack([g1[0] + c * g2[0] - s * g2[1], g1[1] + s * g2[0] + c * g2[1], g1[2] + g2[2]])


def inverse(g: Float[ArrayLike, " 3"]) -> Float[Array, " 3"]:
    """``g^-1`` for a pose ``(x, y, theta)``."""
    g = _element(g, "inverse", "g")
    c, s = jnp.cos(g[2]), jnp.sin(g[2])
    return jnp.stack([-(c * g[0] + s * g[1]), s * g[0] - c * g[1], -g[2]])


def retract(v: Float[ArrayLike, " 3"], retraction: str) -> Float[Array, " 3"]:
    """``tau(v)`` as a pose, ``tau in {exp, cay}`` (``retraction`` is ``"exp"`` or ``"cayley"``)."""
    return exp(v) if _retraction("retract", retraction) == "exp" else cay(v)


def dexp_inv(v: Float[ArrayLike, " 3"]) -> Float[Array, "3 3"]:
    """Exact right-trivialized inverse differential of ``exp`` (eq. (28), all terms).

    ``dexp^-1_v = sum_j B_j / j! ad_v^j`` (Bernoulli numbers). On SE(2), with
    ``c = (v1/2) cot(v1/2)``, ``beta = (1 - c) / v1``, ``J = [[0, -1], [1, 0]]`` and ``b = (v3, -v2)``::

        dexp^-1_v = [[1, 0], [(-I/2 + beta J) b, c I - (v1/2) J]],

    whose Taylor expansion is ``I - ad_v/2 + ad_v^2/12 + ...`` (the paper's (31) truncation).
    """
    v = _element(v, "dexp_inv", "v")
    w = v[0]
    c = _half_cot_half(w)
    small, ws = small_angle(w)
    beta = jnp.where(small, w / 12.0 * _cot_series(w * w), (1.0 - c) / ws)
    b1, b2 = v[2], -v[1]
    z, one = jnp.zeros_like(w), jnp.ones_like(w)
    return jnp.array([[one, z, z], [-0.5 * b1 - beta * b2, c, 0.5 * w], [-0.5 * b2 + beta * b1, -0.5 * w, c]])


def dcay_inv(v: Float[ArrayLike, " 3"]) -> Float[Array, "3 3"]:
    """Right-trivialized inverse differential of the Cayley map, eq. (32) (exact).

    ``dcay^-1_v = I - ad_v / 2 + [v1 v, 0_{3x2}] / 4``, i.e. ``w -> (I - v^/2) w^ (I + v^/2)`` (29).
    """
    v = _element(v, "dcay_inv", "v")
    extra = jnp.zeros((3, 3), v.dtype).at[:, 0].set(0.25 * v[0] * v)
    return jnp.eye(3, dtype=v.dtype) - 0.5 * ad(v) + extra


#: Bernoulli coefficients ``B_j / j!`` of the ``dexp^-1`` series (the odd ones beyond j = 1 vanish).
_BERNOULLI = {2: 1.0 / 12.0, 4: -1.0 / 720.0, 6: 1.0 / 30240.0, 8: -1.0 / 1209600.0}


def dtau_inv(v: Float[ArrayLike, " 3"], retraction: str, order: int | None = None) -> Float[Array, "3 3"]:
    """``dtau^-1_v`` for ``retraction in {"exp", "cayley"}``.

    Args:
        v: Lie-algebra vector, shape (3,).
        retraction: ``"exp"`` or ``"cayley"``.
        order: ``None`` for the exact map; an integer ``p`` truncates the series in ``ad_v``
            after the ``ad_v^p`` term: ``p = 1`` gives ``I - ad_v/2`` (what the paper's explicit
            car and snakeboard steps use), ``p = 2`` gives eq. (31) for exp and (32) for Cayley.

    Raises:
        ValueError: if ``order`` is not ``None`` or a positive integer.
    """
    v = _element(v, "dtau_inv", "v")
    _retraction("dtau_inv", retraction)
    if order is None:
        return dexp_inv(v) if retraction == "exp" else dcay_inv(v)
    if isinstance(order, bool) or not isinstance(order, int) or order < 1:
        raise ValueError(f"lie.dtau_inv: 'order' must be None or an integer >= 1, got {order!r}")
    a = ad(v)
    out = jnp.eye(3, dtype=v.dtype) - 0.5 * a
    if order >= 2:
        if retraction == "exp":
            power = a
            for j in range(2, order + 1):
                power = power @ a
                out = out + _BERNOULLI.get(j, 0.0) * power
        else:
            out = dcay_inv(v)
    return out


def tangent_to_jaxlie(v: Float[ArrayLike, " 3"]) -> Float[Array, " 3"]:
    """``(omega, v_x, v_y)`` (ours, the paper's) -> ``(v_x, v_y, omega)`` (jaxlie's)."""
    v = _element(v, "tangent_to_jaxlie", "v")
    return jnp.stack([v[1], v[2], v[0]])


def tangent_from_jaxlie(t: Float[ArrayLike, " 3"]) -> Float[Array, " 3"]:
    """``(v_x, v_y, omega)`` (jaxlie's) -> ``(omega, v_x, v_y)`` (ours, the paper's)."""
    t = _element(t, "tangent_from_jaxlie", "t")
    return jnp.stack([t[2], t[0], t[1]])


class SE2(eqx.Module):
    """An element of SE(2), stored as ``(cos theta, sin theta, x, y)`` (jaxlie's layout).

    The vocabulary follows jaxlie: :meth:`identity`, :meth:`exp`, :meth:`log`, ``@``,
    :meth:`inverse`, :meth:`adjoint`, :meth:`as_matrix`; plus :meth:`cay` and :meth:`cay_inv`.
    Tangent vectors use the paper's order ``(omega, v_x, v_y)``; :meth:`from_jaxlie` and
    :meth:`to_jaxlie` convert elements (the storage is the same), :func:`tangent_to_jaxlie` the
    tangent order.

    Example:
        >>> g = SE2.exp(jnp.array([0.3, 1.0, 0.0]))
        >>> (g @ g.inverse()).log()   # ~ zeros
    """

    unit_complex_xy: Float[Array, " 4"]

    tangent_dim: ClassVar[int] = 3
    parameters_dim: ClassVar[int] = 4
    matrix_dim: ClassVar[int] = 3

    @staticmethod
    def from_xy_theta(x: ArrayLike, y: ArrayLike, theta: ArrayLike) -> SE2:
        """From a pose ``(x, y, theta)``."""
        x, y, theta = _floats(x), _floats(y), _floats(theta)
        return SE2(jnp.stack([jnp.cos(theta), jnp.sin(theta), x, y]))

    def as_xy_theta(self) -> Float[Array, " 3"]:
        """The pose ``(x, y, theta)`` with ``theta`` in ``(-pi, pi]``."""
        return jnp.concatenate([self.translation, self.theta[None]])

    @staticmethod
    def identity(dtype: Any = None) -> SE2:
        return SE2(jnp.array([1.0, 0.0, 0.0, 0.0], dtype=dtype))

    @staticmethod
    def from_matrix(matrix: ArrayLike) -> SE2:
        m = jnp.asarray(matrix)
        return SE2(jnp.stack([m[0, 0], m[1, 0], m[0, 2], m[1, 2]]))

    @staticmethod
    def from_jaxlie(g: Any) -> SE2:
        """From a ``jaxlie.SE2`` (same storage, ``unit_complex_xy``)."""
        return SE2(jnp.asarray(g.unit_complex_xy))

    def to_jaxlie(self) -> Any:
        """As a ``jaxlie.SE2`` (requires jaxlie)."""
        import jaxlie

        return jaxlie.SE2(self.unit_complex_xy)

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
        """``exp(v^)`` for ``v = (omega, v_x, v_y)``."""
        return SE2.from_xy_theta(*exp(v))

    @staticmethod
    def cay(v: ArrayLike) -> SE2:
        """``cay(v^)``, with the rotation in rational form (no trigonometric function)."""
        v = _element(v, "SE2.cay", "v")
        d = 4.0 + v[0] ** 2
        x, y, _ = cay(v)
        return SE2(jnp.stack([(4.0 - v[0] ** 2) / d, 4.0 * v[0] / d, x, y]))

    def log(self) -> Float[Array, " 3"]:
        return log(self.as_xy_theta())

    def cay_inv(self) -> Float[Array, " 3"]:
        return cay_inv(self.as_xy_theta())

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

    def apply(self, p: ArrayLike) -> Float[Array, " 2"]:
        """Act on a point of the plane."""
        c, s, x, y = self.unit_complex_xy
        p = jnp.asarray(p)
        return jnp.stack([x + c * p[0] - s * p[1], y + s * p[0] + c * p[1]])
