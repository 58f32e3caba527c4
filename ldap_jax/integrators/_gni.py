"""The geometric nonholonomic integrator (GNI) of Ferraro, Iglesias and Martin de Diego (2008),
with forces. Full-coordinate, explicit (``docs/integrators.md``, section 5)."""

from __future__ import annotations

from typing import Literal, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._linalg import solve
from .._numerics import safe_vnorm
from .._results import RESULTS
from ..systems._base import body_velocity
from ._base import AbstractAlphaIntegrator, StepInfo, classify, finite, refuse_friction
from ._dla import constraint_rows, legendre_inverse, mass_matrix, step_inputs

__all__ = ["GNI", "GNIState"]


class GNIState(NamedTuple):
    """State of GNI at node ``k``.

    Attributes:
        q: configuration ``q_k``.
        v: previous discrete velocity ``v_{k-1} = (q_k - q_{k-1}) / h`` (d,).
        p: incoming momentum ``M v_{k-1} + h a F_{k-1+a}`` (d,): the previous step's share of
            the force folded in (as for RDP and DLA), and the node velocity's source.
    """

    q: Array
    v: Array
    p: Array


class GNI(AbstractAlphaIntegrator):
    r"""Geometric nonholonomic integrator (Ferraro, Iglesias, Martin de Diego 2008), with forces.

    With the discrete Legendre transforms ``p^-_k = D_2 L_d(q_{k-1}, q_k)``,
    ``p^+_k = -D_1 L_d(q_k, q_{k+1})`` and the kinetic-metric projectors ``P`` onto the
    constraint distribution ``D(q_k)`` and ``Q = I - P = M^-1 W^T (W M^-1 W^T)^-1 W``, the
    faithful GNI (variant "A" of the notes: the impulse enters the jump condition) is

    .. code-block:: text

        P^* (p^+_k - p^-_k - h F_k) = 0,     Q^* (p^+_k + p^-_k) = 0,
        F_k = a F_{k-1+a} + (1-a) F_{k+a},

    i.e. the momentum reflects elastically at the constraint; no discrete constraint is imposed,
    the constraints hold only on average, ``W(q_k) (v_k + v_{k-1}) = 2 b``. For Lagrangians
    ``1/2 qdot^T M qdot`` with constant ``M`` (the car and the snakeboard in these coordinates)
    this is explicit:

    .. code-block:: text

        v_k = (P - Q)(q_k) v_{k-1} + h P(q_k) M^-1 F_k,     q_{k+1} = q_k + h v_k.

    Written with KKT solves, so a mass matrix singular in kinematic directions (the car's sigma)
    is fine: ``M v_k - W^T lambda = M v_{k-1} + h F_k``, ``W v_k = 2 b - W v_{k-1}``. ``M`` is
    must not depend on ``q`` (true for the car and the snakeboard in these coordinates); ``init``
    raises (``eqx.error_if``) otherwise, e.g. for a Chaplygin sleigh with an offset contact
    point, whose consistent GNI would be implicit — use :class:`DLA` or :class:`RDP` there.

    **Warning** (``docs/integrators.md`` section 5, measured again here): the normal velocity
    ``n_k = omega(q_k) v_k`` obeys exactly ``n_{k+1} = -n_k - (omega(q_{k+1}) - omega(q_k)) v_k``,
    a period-2 (parasitic) mode of this two-step method whose amplitude evolves on a time scale
    set by speed x curvature of ``D``, independent of ``h``. On long forced runs it grows until
    the relative violation ``|omega(q_k) v_k| / |v_k|`` is O(1); :attr:`StepInfo.residual` logs
    that ratio each step.

    ``variant="folded"`` keeps the GNI momentum (jump) equation ``P^*(p^+ - p^- - h F) = 0`` but
    replaces the averaged-constraint condition by the constraint at the predicted point
    ``q_k + a h v``: ``omega(q_k + a h v~) v_k = 0``, with ``v~`` from one explicit predictor
    pass (two KKT solves per step, no Newton). The parasitic mode is gone and the constraint
    holds at the quadrature point up to ``O(h^3)``; this is the DLA equation set solved by a
    fixed two-pass explicit iteration instead of Newton.

    Initialisation: ``v_{-1} = qdot_0`` and the first step's impulse is ``h (1-a) F_a``. Node
    velocity estimate: ``(v_{k-1} + v_k) / 2`` projected onto the constraints at ``q_k`` (the
    faithful GNI's average already satisfies them).

    Properties: explicit; order 2 at ``a = 1/2`` (the force quadrature; ``L_d`` does not depend
    on ``a``), 1 otherwise; unforced, the kinetic energy is conserved exactly and, forced, an
    exact discrete work-energy balance holds (faithful variant).

    **Failure.** A step whose velocity leaves the constraints, ``|D omega(q_k) v_k| / |v_k| >
    max_violation`` with ``D`` scaling each constraint row to unit norm (default 0.5: the velocity
    30 degrees off the constraint distribution), ends the run as ``RESULTS.diverged``: the
    parasitic mode has taken over and the motion is no longer the system's. On a fast car (a
    wheel of radius 2 m at 3 rad/s) this happens within 4 s at every step size, with the heading
    36-42 rad off where the folded variant and RDP converge; healthy runs stay below 0.1.

    Args:
        alpha: force quadrature point in [0, 1] (default 1/2; also the constraint point of
            ``"folded"``).
        variant: ``"faithful"`` (default) or ``"folded"``.
        max_violation: the largest normalised constraint violation of a step's velocity before
            the run is reported ``diverged`` (default 0.5; ``None`` never, to watch the mode grow).

    Example:
        >>> traj = lj.simulate(sb, q0, qdot0, ctl, t_final=10.0, n_steps=1000, integrator=lj.GNI())
        >>> traj.step_residual.max()  # relative constraint violation |omega v| / |v|
    """

    alpha: float = 0.5
    variant: Literal["faithful", "folded"] = eqx.field(default="faithful", static=True)
    max_violation: float | None = eqx.field(default=0.5, static=True)

    def __check_init__(self):
        if self.variant not in ("faithful", "folded"):
            raise ValueError(f"GNI: 'variant' must be 'faithful' or 'folded', got {self.variant!r}")
        m = self.max_violation
        if m is not None and (isinstance(m, bool) or not isinstance(m, (int, float)) or not 0 < m < np.inf):
            raise ValueError(f"GNI: 'max_violation' must be a positive number or None, got {m!r}")

    def init(self, system, h, q0, qdot0, c):
        refuse_friction("GNI", system)
        # The explicit form needs a configuration-independent mass matrix (true for the car and
        # the snakeboard in these coordinates); with M(q) the dropped dL/dq terms make it
        # inconsistent, so refuse (inside jit) rather than return a wrong trajectory.
        mass = mass_matrix(system, q0, qdot0)
        dmass = jax.jacfwd(lambda qq: mass_matrix(system, qq, qdot0))(q0)
        tol = 1e3 * jnp.finfo(q0.dtype).eps * (1.0 + jnp.max(jnp.abs(mass)))
        q0 = eqx.error_if(
            q0,
            jnp.max(jnp.abs(dmass)) > tol,
            "GNI: the explicit GNI needs a mass matrix d^2L/dqdot^2 independent of q; this system's "
            "depends on q (use lj.DLA or lj.RDP)",
        )
        return GNIState(q=q0, v=qdot0, p=mass_matrix(system, q0, qdot0) @ qdot0)

    def step(self, system, h, state, c):
        q, v_prev, p = state
        dtype = q.dtype
        d = system.n_config
        a, force, u_kin = step_inputs(system, self.alpha, c)
        mass = mass_matrix(system, q, v_prev)
        rows, rhs = constraint_rows(system, q, u_kin)
        n_rows = rows.shape[0]
        zero = jnp.zeros((n_rows, n_rows), dtype)
        mom = p + h * (1 - a) * force  # M v_{k-1} + h F_k

        if self.variant == "faithful":
            # reflection: the constraint holds on average, W(q_k) (v_k + v_{k-1}) = 2 b
            rows_prev, rhs_prev = constraint_rows(system, q, _kin_velocity(system, v_prev, u_kin))
            target = rhs + rhs_prev - rows_prev @ v_prev
            kkt = jnp.block([[mass, -rows.T], [rows, zero]])
            v = solve(kkt, jnp.concatenate([mom, target]))[:d]
        else:

            def solve_at(v_guess):
                rows_a, rhs_a = constraint_rows(system, q + a * h * v_guess, u_kin)
                kkt = jnp.block([[mass, -rows.T], [rows_a, zero]])
                return solve(kkt, jnp.concatenate([mom, rhs_a]))[:d]

            v = solve_at(solve_at(v_prev))

        omega = system.constraint_forms(q)
        speed = safe_vnorm(v)
        tiny = jnp.finfo(dtype).tiny
        violation = safe_vnorm(omega @ v) / jnp.where(speed > tiny, speed, 1.0)
        new = GNIState(q=q + h * v, v=v, p=mass @ v + h * a * force)
        result = classify(finite(new), system.singular(new.q, q), jnp.ones((), bool))
        if self.max_violation is not None:
            # each constraint row scaled to unit norm: the sine-like angle of v off the distribution
            row_norm = jnp.sqrt(jnp.sum(omega**2, axis=1))
            unit = (omega @ v) / jnp.where(row_norm > tiny, row_norm, 1.0)
            off = safe_vnorm(unit) > self.max_violation * jnp.where(speed > tiny, speed, jnp.inf)
            result = RESULTS.where((result == RESULTS.successful) & off, RESULTS.diverged, result)
        return new, StepInfo(result=result, residual=violation, iterations=jnp.zeros((), jnp.int32))

    def observe(self, system, state, c):
        q, qdot = self.node(system, state, c)
        return system.observation(q, qdot[3:], body_velocity(q, qdot), c)

    def node(self, system, state, c):
        return state.q, legendre_inverse(system, state.q, state.p, system.inputs(c)[1])


def _kin_velocity(system, v: Array, u_kin: Array) -> Array:
    """The kinematic entries of ``v`` as a ``u_kin`` vector (the previous prescribed velocity)."""
    kin = np.asarray(system.kinematic_index, dtype=int)
    if kin.size == 0:
        return u_kin
    return u_kin.at[kin].set(v[3 + kin])
