"""The discrete Lagrange-d'Alembert (DLA) integrator of Cortes and Martinez (2001), with forces.

Full-coordinate, implicit (DESIGN.md section 8, INTEGRATORS-NOTES.md section 3). Also holds the
full-view helpers shared with :mod:`._gni`: the constraint rows including the prescribed
velocities of kinematic shape coordinates, and the kinetic-metric projection onto them.
"""

from __future__ import annotations

import functools
from typing import Literal, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._linalg import solve
from ._base import AbstractAlphaIntegrator, StepInfo

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


def mass_matrix(system, q: Array, qdot: Array) -> Array:
    """``M(q) = d^2 L / d qdot^2`` by autodiff (singular in kinematic directions, e.g. the car's
    sigma, which carries no inertia)."""
    return jax.hessian(system.lagrangian, argnums=1)(q, qdot)


def project(system, q: Array, w: Array, u_kin: Array) -> Array:
    """Kinetic-metric projection of ``w`` onto ``{W(q) qdot = b}``:
    ``argmin 1/2 (x - w)^T M (x - w)`` subject to the constraints (one KKT solve).

    The KKT matrix ``[[M, W^T], [W, 0]]`` is nonsingular even where ``M`` is singular in the
    kinematic directions, because those are fixed by rows of ``W``.
    """
    rows, rhs = constraint_rows(system, q, u_kin)
    mass = mass_matrix(system, q, w)
    m = rows.shape[0]
    kkt = jnp.block([[mass, rows.T], [rows, jnp.zeros((m, m), q.dtype)]])
    sol = solve(kkt, jnp.concatenate([mass @ w, rhs]))
    return sol[: w.shape[0]]


def _newton(f, z0, *, budget: int, tol):
    """Newton's method on ``f(z) = 0`` from ``z0``: at most ``budget`` iterations, stopping once
    ``|f(z)| <= tol``; an iterate that turns non-finite is rejected (the loop then stalls and
    reports non-convergence). Returns ``(z, (|f(z)|, iterations))``."""

    def cond(carry):
        _, res, it = carry
        return (it < budget) & (jnp.linalg.norm(res) > tol)

    def body(carry):
        z, res, it = carry
        z_new = z - solve(jax.jacfwd(f)(z), res)
        ok = jnp.all(jnp.isfinite(z_new))
        z_new = jnp.where(ok, z_new, z)
        res_new = jnp.where(ok, f(z_new), res)
        # a rejected step cannot be retried: mark the budget as spent
        return z_new, res_new, jnp.where(ok, it + 1, budget)

    res0 = f(z0)
    z, res, it = jax.lax.while_loop(cond, body, (z0, res0, jnp.zeros((), jnp.int32)))
    # aux as floats: custom_root differentiates through its outputs (an int would need float0)
    return z, (jnp.linalg.norm(res), it.astype(z.dtype))


def _tangent_solve(g, y):
    """Linear solve with the (linear) map ``g``, for implicit differentiation of the root."""
    return solve(jax.jacfwd(g)(y), y)


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
    fail (the physical root merges with a spurious one: a fold; INTEGRATORS-NOTES.md 3.4).

    Args:
        alpha: quadrature point in [0, 1].
        newton_iterations: Newton budget per step (iterations actually used: ``StepInfo``).
        initial_guess: ``"euler"`` or ``"explicit"``.
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

    def init(self, system, h, q0, qdot0, c0):
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
        a = jnp.asarray(self.alpha, dtype)
        d = system.n_config
        f0, uk0 = system.inputs(c[0])
        f1, uk1 = system.inputs(c[1])
        force = full_force(system, (1 - a) * f0 + a * f1)  # F_{k+a}
        u_kin = 0.5 * (uk0 + uk1)
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
        scale = 1.0 + jnp.linalg.norm(p) + h * jnp.linalg.norm(force)
        tol = rtol * jax.lax.stop_gradient(scale)
        z, (res_norm, iterations) = jax.lax.custom_root(
            residual_fn,
            z0,
            functools.partial(_newton, budget=self.newton_iterations, tol=tol),
            _tangent_solve,
            has_aux=True,
        )
        converged = res_norm <= tol
        iterations = jax.lax.stop_gradient(iterations).astype(jnp.int32)
        res_norm = jax.lax.stop_gradient(res_norm)

        v = z[:d]
        q_a = q + a * h * v
        dl_dq, dl_dv = jax.grad(system.lagrangian, argnums=(0, 1))(q_a, v)
        p_next = dl_dv + h * a * (dl_dq + force)
        q_next = q + h * v
        qdot_k = project(system, q, 0.5 * (v_prev + v), uk0)
        info = StepInfo(residual=res_norm, converged=converged, iterations=iterations)
        return DLAState(q=q_next, p=p_next, v=v), (q, qdot_k), info
