"""The discrete Lagrange-d'Alembert (DLA) integrator of Cortes and Martinez (2001), with forces.

Full-coordinate, implicit (``docs/integrators.md``, section 4). Also holds the
full-view helpers shared with :mod:`._gni`: the constraint rows including the prescribed
velocities of kinematic shape coordinates, and the kinetic-metric projection onto them.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._linalg import solve
from .._newton import newton
from .._numerics import safe_vnorm
from ..systems._base import body_velocity
from ._base import AbstractAlphaIntegrator, StepInfo, classify, finite, refuse_friction

__all__ = ["DLA", "DLAState"]


def constraint_rows(system, q: Array, u_kin: Array) -> tuple[Array, Array]:
    """All velocity constraints as ``W(q) qdot = b``: the one-forms ``omega(q) qdot = 0`` and,
    for each kinematic shape coordinate ``i``, the prescribed velocity ``qdot_{3+i} = u_kin_i``.

    Returns:
        ``(W, b)`` with shapes ``(m + n_kin, d)`` and ``(m + n_kin,)``.
    """
    d = system.n_config
    omega = system.constraint_forms(q)
    kin = np.asarray(system.kinematic_index, dtype=int)
    if kin.size == 0:
        return omega, jnp.zeros(omega.shape[0], q.dtype)
    e_kin = jnp.eye(d, dtype=q.dtype)[3 + kin]
    rows = jnp.concatenate([omega, e_kin], axis=0)
    rhs = jnp.concatenate([jnp.zeros(omega.shape[0], q.dtype), u_kin[kin]])
    return rows, rhs


def full_force(system, f: Array) -> Array:
    """Generalized force ``F = (0, 0, 0, f)`` on ``q = (x, y, theta, r)`` (kinematic entries 0)."""
    dyn = np.asarray(system.dynamic_index, dtype=int)
    force = jnp.zeros(system.n_config, f.dtype)
    return force.at[3 + dyn].set(f[dyn])


def step_inputs(system, alpha, c: Array) -> tuple[Array, Array, Array]:
    """The step's inputs from the controls at its ends ``c = (c_k, c_{k+1})``: ``alpha`` (as an
    array), the generalized force ``F_{k+alpha} = F((1 - alpha) f_k + alpha f_{k+1})`` and the
    prescribed kinematic rates at the midpoint, ``(u_k + u_{k+1}) / 2``."""
    a = jnp.asarray(alpha, c.dtype)
    f0, uk0 = system.inputs(c[0])
    f1, uk1 = system.inputs(c[1])
    return a, full_force(system, (1 - a) * f0 + a * f1), 0.5 * (uk0 + uk1)


def mass_matrix(system, q: Array, qdot: Array) -> Array:
    """``M(q) = d^2 L / d qdot^2`` by autodiff (singular in kinematic directions, e.g. the car's
    sigma, which carries no inertia)."""
    return jax.hessian(system.lagrangian, argnums=1)(q, qdot)


def legendre_inverse(system, q: Array, p: Array, u_kin: Array) -> Array:
    """The velocity on the constraints ``{W(q) qdot = b}`` whose momentum is ``p`` up to a
    constraint reaction: ``dL/dqdot(q, qdot) = p + W(q)^T lambda``, ``W(q) qdot = b``.

    How DLA and GNI report node velocities from their carried discrete momenta (the kinetic-metric
    projection removes the reaction the constraints absorb). One Newton step from rest: exact
    for ``L`` quadratic in the velocities.
    """
    rows, rhs = constraint_rows(system, q, u_kin)
    d, m = q.shape[0], rows.shape[0]

    def residual(z):
        v, lam = z[:d], z[d:]
        return jnp.concatenate(
            [jax.grad(system.lagrangian, argnums=1)(q, v) - rows.T @ lam - p, rows @ v - rhs]
        )

    z0 = jnp.zeros(d + m, q.dtype)
    return (z0 - solve(jax.jacfwd(residual)(z0), residual(z0)))[:d]


class DLAState(NamedTuple):
    """State of DLA at node ``k``.

    Attributes:
        q: configuration ``q_k``.
        p: incoming discrete momentum ``p_k = D_2 L_d(q_{k-1}, q_k) + f^+_{k-1}`` (d,).
        v: previous discrete velocity ``v_{k-1} = (q_k - q_{k-1}) / h`` (d,), the Euler-type
            initial guess and the left half of the node velocity estimate.
    """

    q: Array
    p: Array
    v: Array


class DLA(AbstractAlphaIntegrator):
    r"""Discrete Lagrange-d'Alembert integrator (Cortes and Martinez 2001), modified for forces.

    Discrete Lagrangian ``L_d(q_k, q_{k+1}) = h L(q_{k+a}, v_k)`` with
    ``v_k = (q_{k+1} - q_k) / h``, ``q_{k+a} = q_k + a h v_k``; discrete constraint
    ``omega(q_{k+a}) v_k = 0``; variations in the continuous distribution at ``q_k``; forcing
    ``f^-_k = h (1-a) F_{k+a}``, ``f^+_k = h a F_{k+a}`` (so that the impulse across node k is
    ``h (a F_{k-1+a} + (1-a) F_{k+a})`` as for RDP). Each step solves, for ``(v_k, lambda_k)``,

    .. code-block:: text

        p_k + D_1 L_d(q_k, q_{k+1}) + f^-_k - W(q_k)^T lambda_k = 0      (d rows)
        omega(q_{k+a}) v_k = 0,   v_k[kinematic] = u_kin                  (m + n_kin rows)

    with ``D_1 L_d = -dL/dv + h (1-a) dL/dq`` at ``(q_{k+a}, v_k)``, then
    ``p_{k+1} = D_2 L_d + f^+_k = dL/dv + h a dL/dq + h a F_{k+a}`` and ``q_{k+1} = q_k + h v_k``.
    Kinematic shape coordinates (the car's sigma) are constraint rows with right-hand side the
    trapezoidal average of the prescribed velocity.

    The solve is Newton's method (Jacobian by ``jax.jacfwd``) with a fixed iteration budget,
    stopping early once the residual meets the tolerance; gradients pass through it by implicit
    differentiation (``lax.custom_root``: one linear solve with the step's Jacobian). An iterate
    that turns non-finite is rejected, so a failed solve shows as ``converged = False`` (result
    code 3 in :func:`~ldap_jax.simulate`), never as a silently wrong number.
    Initial guess: ``"euler"`` (the paper's Euler-type guess ``v = v_{k-1}``, ``lambda = 0``) or
    ``"explicit"`` (the explicit ``a = 0`` step, one KKT solve at ``q_k``; ``O(h^2)`` from the
    root).

    Initialisation (discrete Legendre transform): ``p_0 = dL/dqdot(q_0, qdot_0)``,
    ``v_{-1} = qdot_0``, and the first step's impulse is ``h (1-a) F_a`` only. Node velocity
    estimate: ``(v_{k-1} + v_k) / 2`` projected onto the constraints at ``q_k``.

    Properties: implicit; order 2 at ``a = 1/2`` (symmetric, the default), 1 otherwise; the
    discrete constraint holds to the solver tolerance at every step. At large steps Newton can
    fail (the physical root merges with a spurious one: a fold; ``docs/integrators.md`` section 4).

    Args:
        alpha: quadrature point in [0, 1] (default 1/2).
        newton_iterations: Newton budget per step (default 12; iterations actually used: ``StepInfo``).
        initial_guess: ``"euler"`` (default) or ``"explicit"``.
        rtol: convergence tolerance on the residual norm, relative to
            ``1 + |p_k| + h |F|`` (default ``10 eps^0.75`` of the dtype).

    Example:
        >>> traj = lj.simulate(sb, q0, qdot0, ctl, t_final=10.0, n_steps=1000, integrator=lj.DLA())
        >>> bool(traj.converged.all())
        True
    """

    alpha: float = 0.5
    newton_iterations: int = eqx.field(default=12, static=True)
    initial_guess: Literal["euler", "explicit"] = eqx.field(default="euler", static=True)
    rtol: float | None = eqx.field(default=None, static=True)

    implicit = True

    def __check_init__(self):
        if not isinstance(self.newton_iterations, int) or self.newton_iterations < 1:
            raise ValueError(
                f"DLA: 'newton_iterations' must be a positive integer, got {self.newton_iterations!r}"
            )
        if self.initial_guess not in ("euler", "explicit"):
            raise ValueError(
                f"DLA: 'initial_guess' must be 'euler' or 'explicit', got {self.initial_guess!r}"
            )
        if self.rtol is not None and not self.rtol > 0:
            raise ValueError(f"DLA: 'rtol' must be positive, got {self.rtol!r}")

    def init(self, system, h, q0, qdot0, c):
        refuse_friction("DLA", system)
        p0 = jax.grad(system.lagrangian, argnums=1)(q0, qdot0)
        return DLAState(q=q0, p=p0, v=qdot0)

    def _residual(self, system, h, q, p, force, u_kin, z):
        a = jnp.asarray(self.alpha, q.dtype)
        d = system.n_config
        v, lam = z[:d], z[d:]
        q_a = q + a * h * v
        dl_dq, dl_dv = jax.grad(system.lagrangian, argnums=(0, 1))(q_a, v)
        rows, _ = constraint_rows(system, q, u_kin)
        r_mom = p - dl_dv + h * (1 - a) * (dl_dq + force) - rows.T @ lam
        rows_a, rhs = constraint_rows(system, q_a, u_kin)
        return jnp.concatenate([r_mom, rows_a @ v - rhs])

    def step(self, system, h, state, c):
        q, p, v_prev = state
        dtype = q.dtype
        d = system.n_config
        a, force, u_kin = step_inputs(system, self.alpha, c)
        rows, rhs = constraint_rows(system, q, u_kin)
        n_rows = rows.shape[0]

        if self.initial_guess == "explicit":
            # a = 0 step at q_k: [[M, -W^T], [W, 0]] (v, lambda) = (p + h F, b)
            mass = mass_matrix(system, q, v_prev)
            kkt = jnp.block([[mass, -rows.T], [rows, jnp.zeros((n_rows, n_rows), dtype)]])
            z0 = solve(kkt, jnp.concatenate([p + h * force, rhs]))
        else:
            kin = np.asarray(system.kinematic_index, dtype=int)
            v0 = v_prev.at[3 + kin].set(u_kin[kin]) if kin.size else v_prev
            z0 = jnp.concatenate([v0, jnp.zeros(n_rows, dtype)])

        residual_fn = lambda z: self._residual(system, h, q, p, force, u_kin, z)  # noqa: E731
        rtol = self.rtol if self.rtol is not None else 10 * float(jnp.finfo(dtype).eps) ** 0.75
        scale = 1.0 + safe_vnorm(p) + jnp.abs(h) * safe_vnorm(force)
        z, info = newton(residual_fn, z0, tol=rtol * scale, max_iterations=self.newton_iterations)

        v = z[:d]
        q_a = q + a * h * v
        dl_dq, dl_dv = jax.grad(system.lagrangian, argnums=(0, 1))(q_a, v)
        new = DLAState(q=q + h * v, p=dl_dv + h * a * (dl_dq + force), v=v)
        result = classify(finite(new), system.singular(new.q, q), info.converged)
        return new, StepInfo(result=result, residual=info.residual / scale, iterations=info.iterations)

    def observe(self, system, state, c):
        q, qdot = self.node(system, state, c)
        return system.observation(q, qdot[3:], body_velocity(q, qdot), c)

    def node(self, system, state, c):
        return state.q, legendre_inverse(system, state.q, state.p, system.inputs(c)[1])
