"""The reduced d'Alembert-Pontryagin (RDP) integrator (paper Sec. 4.2, eqs. (17)-(25))."""

from __future__ import annotations

from typing import Literal, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from .._linalg import solve
from ..lie import compose, dtau_inv, retract
from ..systems._base import body_velocity, spatial_velocity
from ._base import AbstractAlphaIntegrator, StepInfo

__all__ = ["RDP", "RDPState"]


class RDPState(NamedTuple):
    """State of RDP at node ``k``.

    Attributes:
        q: configuration ``q_k = (x, y, theta, r)``.
        pu: incoming shape momentum ``d_u l_{k-1} + h alpha d_r l_{k-1}`` (n,).
        mu: incoming group momentum ``(dtau^-1_{-h xi_{k-1}})^* mu_{k-1}`` (3,).
        u: previous shape velocity ``u_{k-1}`` (n,).
        f: previous interpolated force ``f_{k-1+alpha}`` (n,).
        w: previous locked-velocity coordinates ``Omega_{k-1}`` in the basis ``e(r)`` (c,),
            the Newton warm start.
    """

    q: Array
    pu: Array
    mu: Array
    u: Array
    f: Array
    w: Array


def _omega_coords(e: Array, v: Array) -> Array:
    """Coordinates of ``v`` in the columns of ``e`` (least squares; empty when c = 0)."""
    if e.shape[1] == 0:
        return jnp.zeros((0,), v.dtype)
    return solve(e.T @ e, e.T @ v)


class RDP(AbstractAlphaIntegrator):
    r"""Reduced d'Alembert-Pontryagin integrator of Kobilarov, Marsden and Sukhatme.

    On a segment ``[t_k, t_{k+1}]`` with ``r_{k+a} = r_k + a h u_k`` and
    ``xi_k = Omega_k - A(r_{k+a}) u_k``, ``Omega_k in span e(r_{k+a})``, the unknowns
    ``(u_k, Omega_k)`` solve (corrected (21), (23); DESIGN.md section 4)::

        d_u l_k - d_u l_{k-1} - h (a d_r l_{k-1} + (1-a) d_r l_k)
            = A(r_k)^T (dtau^-1_{h xi_k}^* mu_k - dtau^-1_{-h xi_{k-1}}^* mu_{k-1}) + h F_k,
        < dtau^-1_{h xi_k}^* mu_k - dtau^-1_{-h xi_{k-1}}^* mu_{k-1}, e_b(r_k) > = 0,

    with ``l_k = l(r_{k+a}, u_k, xi_k)``, ``mu_k = d_xi l_k``,
    ``F_k = a f_{k-1+a} + (1-a) f_{k+a}``, ``f_{k+a} = (1-a) f_k + a f_{k+1}``; then
    ``g_{k+1} = g_k tau(h xi_k)``, ``r_{k+1} = r_k + h u_k``. Kinematic shape coordinates
    take ``u_k`` = the trapezoidal average of the prescribed velocity over the segment.

    Initialisation (discrete Legendre transform): the incoming momenta are the continuous ones,
    ``pu = d_u l(r_0, rdot_0, xi_0)``, ``mu = d_xi l(r_0, rdot_0, xi_0)``, and ``F_0 = (1-a) f_a``.
    This keeps order 2 at ``a = 1/2``.

    Solvers: the car and the snakeboard have explicit closed forms (paper Sec. 5.1, 5.2), used
    when ``dtau_order == 1`` (``dtau^-1 ~ I - ad/2``, which is what those closed forms are).
    Otherwise the equations are solved by Newton's method (Jacobians by ``jax.jacfwd``,
    warm-started from the previous step, at most ``newton_iterations``), differentiated by the
    implicit function theorem (``lax.custom_root``); non-convergence is reported per step.

    Properties: order 2 for ``alpha = 1/2`` (symmetric), 1 otherwise; exact discrete momentum
    equation (Prop. 1); constraints hold exactly at every step (``xi_k`` lies in the
    discrete constraint space by construction); no energy drift in practice.

    Args:
        alpha: quadrature point in [0, 1].
        retraction: ``"exp"`` or ``"cayley"``.
        dtau_order: ``1`` truncates ``dtau^-1`` to ``I - ad/2`` (the paper's explicit
            car/snakeboard schemes); ``None`` uses the exact ``dexp^-1`` (28) or ``dcay^-1`` (32);
            ``p >= 2`` truncates the series after ``ad^p``.
        solver: ``"auto"`` (closed form where the system has one, else Newton) or ``"newton"``.
        newton_iterations: Newton budget per step (iterations stop early once the residual
            meets ``eps**0.75`` relative to the step's momenta; a step that does not is reported).
    """

    alpha: float = 0.5
    retraction: Literal["exp", "cayley"] = eqx.field(default="exp", static=True)
    dtau_order: int | None = eqx.field(default=1, static=True)
    solver: Literal["auto", "newton"] = eqx.field(default="auto", static=True)
    newton_iterations: int = eqx.field(default=20, static=True)

    def __check_init__(self):
        if self.retraction not in ("exp", "cayley"):
            raise ValueError(f"RDP: 'retraction' must be 'exp' or 'cayley', got {self.retraction!r}")
        if self.dtau_order is not None and (not isinstance(self.dtau_order, int) or self.dtau_order < 1):
            raise ValueError(f"RDP: 'dtau_order' must be None or an integer >= 1, got {self.dtau_order!r}")
        if self.solver not in ("auto", "newton"):
            raise ValueError(f"RDP: 'solver' must be 'auto' or 'newton', got {self.solver!r}")
        if not isinstance(self.newton_iterations, int) or self.newton_iterations < 1:
            raise ValueError(
                f"RDP: 'newton_iterations' must be a positive integer, got {self.newton_iterations!r}"
            )

    @property
    def implicit(self) -> bool:  # type: ignore[override]
        return self.solver == "newton" or self.dtau_order != 1

    def _uses_closed_form(self, system) -> bool:
        return self.solver == "auto" and self.dtau_order == 1 and hasattr(system, "rdp_closed_form")

    def init(self, system, h, q0, qdot0, c0):
        r0, rdot0 = q0[3:], qdot0[3:]
        xi0 = body_velocity(q0, qdot0)
        du, dxi = jax.grad(system.reduced_lagrangian, argnums=(1, 2))(r0, rdot0, xi0)
        w0 = _omega_coords(system.symmetry_basis(r0), xi0 + system.connection(r0) @ rdot0)
        return RDPState(q=q0, pu=du, mu=dxi, u=rdot0, f=jnp.zeros_like(rdot0), w=w0)

    def _dtau(self, v):
        return dtau_inv(v, self.retraction, self.dtau_order)

    def _residual_parts(self, system, h, r, u, xi, b, mu_in):
        """Horizontal (23) and vertical (21) residuals at ``(u, xi)``."""
        a = jnp.asarray(self.alpha, r.dtype)
        r_a = r + a * h * u
        dl_dr, dl_du, mu = jax.grad(system.reduced_lagrangian, argnums=(0, 1, 2))(r_a, u, xi)
        jump = self._dtau(h * xi).T @ mu - mu_in
        hor = dl_du - h * (1 - a) * dl_dr - system.connection(r).T @ jump - b
        vert = system.symmetry_basis(r).T @ jump
        return hor, vert

    def _newton(self, system, h, r, u_kin, b, mu_in, u_guess, w_guess):
        """Solve (21), (23) for ``z = (u_dyn, Omega coordinates)`` by Newton's method.

        Differentiable by the implicit function theorem (``lax.custom_root``): reverse mode
        never sees the iteration, only one linear solve with the Jacobian at the root.
        Iterates until the residual meets the dtype's tolerance or the budget is spent.
        """
        a = jnp.asarray(self.alpha, r.dtype)
        dyn = jnp.asarray(system.dynamic_index, dtype=int)
        nd = len(system.dynamic_index)
        tol = jnp.finfo(r.dtype).eps ** 0.75 * (1.0 + jnp.linalg.norm(b) + jnp.linalg.norm(mu_in))

        def unpack(z):
            u = u_kin.at[dyn].set(z[:nd]) if nd else u_kin
            r_a = r + a * h * u
            xi = system.symmetry_basis(r_a) @ z[nd:] - system.connection(r_a) @ u
            return u, xi

        def residual(z):
            u, xi = unpack(z)
            hor, vert = self._residual_parts(system, h, r, u, xi, b, mu_in)
            return jnp.concatenate([hor[dyn], vert])

        def newton(f, z0):
            def cond(carry):
                z, k, res = carry
                return (k < self.newton_iterations) & (res > tol)

            def body(carry):
                z, k, _ = carry
                z = z - solve(jax.jacfwd(f)(z), f(z))
                return z, k + 1, jnp.linalg.norm(f(z))

            z, k, _ = jax.lax.while_loop(cond, body, (z0, jnp.zeros((), jnp.int32), jnp.linalg.norm(f(z0))))
            # one more (quadratically converging) iteration takes the residual to round-off
            z = z - solve(jax.jacfwd(f)(z), f(z))
            # the iteration count rides as a float: custom_root's JVP rejects integer aux data
            return z, (k + 1).astype(z.dtype)

        def tangent_solve(g, y):
            return solve(jax.jacfwd(g)(jnp.zeros_like(y)), y)

        z0 = jnp.concatenate([u_guess[dyn], w_guess])
        z, iterations = jax.lax.custom_root(residual, z0, newton, tangent_solve, has_aux=True)
        u, xi = unpack(z)
        return u, xi, z[nd:], jax.lax.stop_gradient(iterations).astype(jnp.int32)

    def step(self, system, h, state, c):
        a = jnp.asarray(self.alpha, state.q.dtype)
        q = state.q
        r = q[3:]
        f0, uk0 = system.inputs(c[0])
        f1, uk1 = system.inputs(c[1])
        f_a = (1 - a) * f0 + a * f1
        force = a * state.f + (1 - a) * f_a
        u_kin = 0.5 * (uk0 + uk1)
        b = state.pu + h * force
        if self._uses_closed_form(system):
            u, xi = system.rdp_closed_form(a, h, r, u_kin, b, state.mu)
            r_a = r + a * h * u
            w = _omega_coords(system.symmetry_basis(r_a), xi + system.connection(r_a) @ u)
            iterations = jnp.zeros((), jnp.int32)
        else:
            kin = jnp.asarray(system.kinematic_index, dtype=int)
            u_guess = state.u.at[kin].set(u_kin[kin]) if kin.size else state.u
            u, xi, w, iterations = self._newton(system, h, r, u_kin, b, state.mu, u_guess, state.w)
        hor, vert = self._residual_parts(system, h, r, u, xi, b, state.mu)
        dyn = jnp.asarray(system.dynamic_index, dtype=int)
        residual = jnp.linalg.norm(jnp.concatenate([hor[dyn], vert]))
        scale = 1.0 + jnp.linalg.norm(b) + jnp.linalg.norm(state.mu)
        converged = residual <= jnp.finfo(q.dtype).eps ** 0.75 * scale * 10

        # momenta carried to the next node
        r_a = r + a * h * u
        dl_dr, dl_du, mu = jax.grad(system.reduced_lagrangian, argnums=(0, 1, 2))(r_a, u, xi)
        pu_next = dl_du + h * a * dl_dr
        mu_next = self._dtau(-h * xi).T @ mu
        g = jnp.stack([q[2], q[0], q[1]])
        g_next = compose(g, retract(h * xi, self.retraction))
        q_next = jnp.concatenate([jnp.stack([g_next[1], g_next[2], g_next[0]]), r + h * u])

        # velocity estimate at node k: central shape velocity, group part from the node momentum
        kin = jnp.asarray(system.kinematic_index, dtype=int)
        rdot_k = 0.5 * (state.u + u)
        if kin.size:
            rdot_k = rdot_k.at[kin].set(uk0[kin])
        momentum_k = system.symmetry_basis(r).T @ state.mu
        xi_k = system.locked_velocity(r, rdot_k, momentum_k)
        qdot_k = jnp.concatenate([spatial_velocity(q, xi_k), rdot_k])

        new_state = RDPState(q=q_next, pu=pu_next, mu=mu_next, u=u, f=f_a, w=w)
        info = StepInfo(residual=residual, converged=converged, iterations=iterations)
        return new_state, (q, qdot_k), info
