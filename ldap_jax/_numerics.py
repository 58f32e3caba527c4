"""Numerical building blocks of the closed-form kernels: a vectorisable ``sincos`` and the
tags that decide what reverse mode keeps from a forward pass."""

from __future__ import annotations

import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name
from jaxtyping import Array

__all__ = ["sincos", "SAVED", "saved", "materialise", "plain", "plain_active", "safe_norm", "safe_vnorm"]

import contextlib

#: While True (inside :func:`plain`), the kernels use XLA's own sin and cos and no barriers: the
#: plainest graph, which compiles much faster when it is differentiated twice (a solver's Hessians).
_PLAIN = [False]


@contextlib.contextmanager
def plain():
    """Trace the closed-form kernels as plain arithmetic (XLA's ``sin``/``cos``, no fusion barriers,
    no reverse-mode names): for programs that differentiate them to second order, where the
    compile time of the polynomial ``sincos`` and the barriers outweighs their run-time gain."""
    _PLAIN.append(True)
    try:
        yield
    finally:
        _PLAIN.pop()


def plain_active() -> bool:
    """True inside :func:`plain`."""
    return _PLAIN[-1]


# fdlibm __kernel_sin / __kernel_cos coefficients (|r| <= pi/4)
_S = (
    -1.66666666666666324348e-01,
    8.33333333332248946124e-03,
    -1.98412698298579493134e-04,
    2.75573137070700676789e-06,
    -2.50507602534068634195e-08,
    1.58969099521155010221e-10,
)
_C = (
    4.16666666666666019037e-02,
    -1.38888888888741095749e-03,
    2.48015872894767294178e-05,
    -2.75573143513906633035e-07,
    2.08757232129817482790e-09,
    -1.13596475577881948265e-11,
)
# pi/2 split so that n * part is exact: 33-bit parts (float64, |n| < 2^20), cephes parts (float32)
_PIO2 = {
    np.dtype(np.float64): (1.57079632673412561417e00, 6.07710050630396597660e-11, 2.02226624871116645580e-21),
    np.dtype(np.float32): (1.5703125, 4.837512969970703125e-4, 7.54978995489188216e-8),
}


# traced once per shape and dtype, its equations inlined into the caller's (the same program): the
# polynomial's ~40 NumPy-style operations were ~30% of tracing a rollout, every call
@functools.partial(jax.jit, static_argnames="whole", inline=True)
def _sincos_impl(x: Array, whole: bool) -> tuple[Array, Array]:
    dtype = np.dtype(x.dtype)
    if dtype not in _PIO2:  # float16 / bfloat16: no hand-written kernel, use XLA's
        return jnp.sin(x), jnp.cos(x)
    p1, p2, p3 = (jnp.asarray(p, dtype) for p in _PIO2[dtype])
    n = jnp.round(x * jnp.asarray(2.0 / np.pi, dtype))
    r = ((x - n * p1) - n * p2) - n * p3
    z = r * r
    ps = jnp.asarray(_S[5], dtype)
    for coef in _S[4::-1]:
        ps = ps * z + jnp.asarray(coef, dtype)
    pc = jnp.asarray(_C[5], dtype)
    for coef in _C[4::-1]:
        pc = pc * z + jnp.asarray(coef, dtype)
    # A division by a runtime 1 (x * 0 is not folded for floats) marks a value "expensive" for
    # XLA's fusion pass, which then computes it once instead of fusing it into every consumer.
    # Either the two polynomials are marked (``whole=False``: one polynomial per kernel, the cheap
    # quadrant selects fused into the consumers; without a mark XLA duplicated the polynomials into
    # every consumer fusion, about five times per step), or the final values (``whole=True``:
    # each of sin and cos one kernel with both polynomials and the selects, which nothing
    # downstream recomputes: the controls' sampler, whose consumers redid the argument reduction
    # for every quadrant select).
    one = x * 0 + 1
    s = r + r * z * ps
    c = (1.0 - 0.5 * z) + z * z * pc
    if not whole:
        s, c = s / one, c / one
    # the quadrant n mod 4, in floating point: exact for every integer-valued n (an int32 cast
    # wrapped at |x| > 3.4e9, turning the result by a quarter turn)
    q = n - 4.0 * jnp.floor(0.25 * n)
    swap = (q == 1.0) | (q == 3.0)
    sin = jnp.where(swap, c, s)
    cos = jnp.where(swap, s, c)
    sin = jnp.where(q >= 2.0, -sin, sin)
    cos = jnp.where((q == 1.0) | (q == 2.0), -cos, cos)
    if whole:
        sin, cos = sin / one, cos / one
    return sin, cos


def sincos(x: Array, *, whole: bool = False) -> tuple[Array, Array]:
    """``(sin x, cos x)``: :func:`sincos_poly` in rollouts, XLA's own inside :func:`plain`.
    ``whole``: where XLA's fusion pass cuts the kernel (see :func:`sincos_poly`)."""
    if _PLAIN[-1]:
        return jnp.sin(x), jnp.cos(x)
    return (sincos_whole if whole else sincos_poly)(x)


def _exact_jvp(f):
    @f.defjvp
    def _jvp(primals, tangents):
        (x,), (dx,) = primals, tangents
        s, c = f(x)
        return (s, c), (c * dx, -s * dx)

    return f


@_exact_jvp
@jax.custom_jvp
def sincos_poly(x: Array) -> tuple[Array, Array]:
    """``(sin x, cos x)`` sharing one argument reduction, branch-free so XLA vectorises it.

    Accurate to about one ulp for ``|x| < 1.6e6`` (float64) or ``|x| < 6e3`` (float32): the
    Cody-Waite split of ``pi/2`` is exact for those quotients; beyond, accuracy degrades (float64:
    2e-16 still at 1e10 and 1e12, the quadrant being taken in floating point; float32: 0.14 off at
    1e9 and not even bounded by 1 beyond, where a float32 argument's own ulp is 64 or more and its
    sine has no meaning).
    Derivatives are the exact ``(cos x, -sin x)`` (a custom JVP, not the polynomial's). XLA
    computes each polynomial once and fuses the quadrant selects into the consumers.
    """
    return _sincos_impl(x, whole=False)


@_exact_jvp
@jax.custom_jvp
def sincos_whole(x: Array) -> tuple[Array, Array]:
    """:func:`sincos_poly` with XLA's fusion cut after the quadrant selects: sin and cos each one
    kernel (both polynomials in each), their consumers read finished values. The same values."""
    return _sincos_impl(x, whole=True)


#: Name of the values reverse mode keeps from the forward pass of a rollout (the default
#: ``checkpoint=False``): a few values per step from which the backward pass rebuilds the rest
#: with the step's own expressions, and the failure mask. Which ones is each step's choice: the
#: car's step keeps its transcendental values; the snakeboard's symmetric step keeps only its
#: right-hand side ``b = pu + h f / 2`` (which reads the controls) and recomputes its sines from it
#: and the carry, because every stored ``(N, B)`` array costs first-touch page faults at each call.
#: Either is faster than storing the ~55 per-step intermediates autodiff would otherwise keep
#: (measured: gradient / forward 3.6 -> 2.9 for the snakeboard, B = N = 1000).
SAVED = "ldap_jax_saved"


def saved(*values: Array) -> tuple[Array, ...]:
    """Tag ``values`` as kept for reverse mode (see :data:`SAVED`)."""
    if _PLAIN[-1]:
        return values
    return tuple(checkpoint_name(v, SAVED) for v in values)


def materialise(*values: Array) -> tuple[Array, ...]:
    """Compute ``values`` once and keep them: without the barrier XLA's fusion pass duplicates
    transcendental values into every consumer fusion (measured: 5x the sin/cos work per step)."""
    if _PLAIN[-1]:
        return values
    return jax.lax.optimization_barrier(values)


def materialise_result(result: Any) -> Any:
    """A result code (an ``eqx.Enumeration`` item) that XLA computes once.

    The barrier of :func:`materialise` does not survive XLA's CPU pipeline; a division by a
    runtime 1 (an "expensive" operation, which the fusion pass does not duplicate) does. Without
    it, the code of a step (finite state? singular?) was fused into every consumer of the failure
    mask: each field of the next state recomputed the whole step (15 copies for the snakeboard's
    order-2 step, 2.9x the time of the same loop in C under a plain ``jax.jit``)."""
    if _PLAIN[-1]:
        return result
    code = result._value
    f = code.astype(jnp.float32)
    f = f / (jax.lax.stop_gradient(f) * 0 + 1)
    return eqx.tree_at(lambda r: r._value, result, f.astype(code.dtype))


def safe_norm(*xs: Array) -> Array:
    """``sqrt(x_1^2 + ... + x_n^2)`` of scalars, with derivative 0 (not NaN) where every ``x_i``
    vanishes: the residual diagnostics are norms of quantities that are exactly zero on a run at
    rest, and ``sqrt``'s infinite slope at 0 made their derivatives NaN there."""
    return _safe_sqrt(sum(x * x for x in xs))


def safe_vnorm(v: Array) -> Array:
    """The Euclidean norm of a vector, as :func:`safe_norm` (derivative 0 at ``v = 0``)."""
    return _safe_sqrt(jnp.sum(v * v))


def _safe_sqrt(s: Array) -> Array:
    """``sqrt(s)`` for ``s >= 0`` with derivative 0 at ``s = 0`` (the double ``where``)."""
    pos = s > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, s, 1.0)), 0.0)
