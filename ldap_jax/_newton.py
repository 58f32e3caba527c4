"""Newton's method for the implicit steps (the general RDP step and DLA), differentiated by the
implicit function theorem.

One solver for the whole library, written here rather than taken from optimistix because every
system it solves is tiny (3 to 10 unknowns) and must stay free of LAPACK: the linear solves are
:func:`ldap_jax._linalg.solve`, an unrolled Gauss-Jordan sweep that vectorises across a vmapped
batch and cannot deadlock when a batch is sharded over host devices (optimistix's Newton solves
through lineax, i.e. LAPACK, on CPU).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._linalg import solve
from ._typing import ArrayLike

__all__ = ["NewtonInfo", "newton"]


class NewtonInfo(NamedTuple):
    """What :func:`newton` reports: the final residual norm, the iterations used, and whether
    the residual met the tolerance."""

    residual: Float[Array, ""]
    iterations: Int[Array, ""]
    converged: Bool[Array, ""]


def newton(
    residual: Callable[[Array], Array], z0: Array, *, tol: ArrayLike, max_iterations: int
) -> tuple[Array, NewtonInfo]:
    """Solve ``residual(z) = 0`` by Newton's method from ``z0``.

    Iterates ``z <- z - J(z)^-1 residual(z)`` (``J`` by ``jax.jacfwd``) while
    ``|residual(z)| > tol`` and fewer than ``max_iterations`` iterations were used, then takes one
    more (quadratically convergent) iteration if it lowers the residual, which brings a converged
    root to round-off. An iterate that turns non-finite is rejected and the iteration stops there,
    so a failed solve reports ``converged = False`` with the last finite iterate, never a NaN
    passed off as a root.

    Gradients: ``lax.custom_root``. Reverse and forward mode see one linear solve with the
    Jacobian at the root (implicit function theorem), never the iteration; ``residual`` may close
    over the values to differentiate with respect to.

    Args:
        residual: ``z -> r``, same shape as ``z`` (a square system).
        z0: initial guess.
        tol: tolerance on ``|residual(z)|`` (Euclidean norm).
        max_iterations: iteration budget (a Python int).

    Returns:
        ``(z, NewtonInfo)``.
    """
    tol = jax.lax.stop_gradient(jnp.asarray(tol, z0.dtype))

    def iterate(f, z_init):
        # One loop body (one trace of the residual and its Jacobian): Newton steps while the
        # residual is above tol and the budget lasts, then the polishing step, kept only if it
        # lowers the residual.
        def cond(carry):
            return ~carry[3]

        def body(carry):
            z, r, it, _ = carry
            polish = ~((it < max_iterations) & (jnp.linalg.norm(r) > tol))
            z_new = z - solve(jax.jacfwd(f)(z), r)
            ok = jnp.all(jnp.isfinite(z_new))
            z_new = jnp.where(ok, z_new, z)
            r_new = jnp.where(ok, f(z_new), r)
            keep = jnp.where(polish, jnp.linalg.norm(r_new) <= jnp.linalg.norm(r), True)
            z, r = jnp.where(keep, z_new, z), jnp.where(keep, r_new, r)
            # a rejected step cannot be retried
            it = jnp.where(polish, it, jnp.where(ok, it + 1, max_iterations))
            return z, r, it, polish

        init = (z_init, f(z_init), jnp.zeros((), jnp.int32), jnp.zeros((), bool))
        z, r, it, _ = jax.lax.while_loop(cond, body, init)
        # the aux data rides as floats: custom_root differentiates through its outputs
        return z, (jnp.linalg.norm(r), it.astype(z.dtype))

    def tangent_solve(g, y):
        return solve(jax.jacfwd(g)(jnp.zeros_like(y)), y)

    z, (res, it) = jax.lax.custom_root(residual, z0, iterate, tangent_solve, has_aux=True)
    res = jax.lax.stop_gradient(res)
    info = NewtonInfo(
        residual=res, iterations=jax.lax.stop_gradient(it).astype(jnp.int32), converged=res <= tol
    )
    return z, info
