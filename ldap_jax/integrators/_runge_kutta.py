"""Explicit Runge-Kutta schemes on the continuous equations, one stepper over Butcher tables."""

from __future__ import annotations

from typing import ClassVar, NamedTuple

import jax.numpy as jnp
import numpy as np

from ..systems._base import body_velocity
from ._base import AbstractIntegrator, StepInfo, classify, finite

__all__ = ["ButcherTableau", "AbstractRungeKutta", "RK2", "RK4"]


class ButcherTableau(NamedTuple):
    """``a`` (s x s, strictly lower triangular), weights ``b`` (s,), nodes ``c`` (s,)."""

    a: tuple[tuple[float, ...], ...]
    b: tuple[float, ...]
    c: tuple[float, ...]


class AbstractRungeKutta(AbstractIntegrator):
    """Explicit RK on the minimal equations ``y = (q, v)``, ``ydot = system.ode(y, controls(t))``.

    The state stays on the constraint distribution by construction (``qdot`` is rebuilt from
    the independent velocities ``v``), but the scheme knows nothing of the geometry.

    The steps read the controls' values at the stage times only. Where a kinematic coordinate's
    prescribed acceleration enters the dynamics (an :class:`~ldap_jax.System` whose prescribed
    coordinate has inertia coupled to the others), it comes from the derivative of the polynomial
    through the step's distinct stage values (RK4: the quadratic through ``t``, ``t + h/2``,
    ``t + h``), ``O(h^2)`` off for RK4 and ``O(h)`` for RK2. On a sleigh steered by a prescribed rate
    with an inert front wheel, RK4 kept order 4 (3.95-4.0 against the reference) and RK2 fell to
    order 1. RDP and DLA do not need it; :func:`ldap_jax.reference` uses the exact one.
    """

    tableau: ClassVar[ButcherTableau]

    @property
    def control_nodes(self) -> tuple[float, ...]:
        return self.tableau.c

    def init(self, system, h, q0, qdot0, c):
        return (q0, system.velocities_from_qdot(q0, qdot0))

    def observe(self, system, state, c):
        q, v = state
        qdot = system.qdot_from_velocities(q, v, system.inputs(c)[1])
        return system.observation(q, qdot[3:], body_velocity(q, qdot), c)

    def node(self, system, state, c):
        q, v = state
        return q, system.qdot_from_velocities(q, v, system.inputs(c)[1])

    def step(self, system, h, state, c):
        q, v = state
        tab = self.tableau
        c_dot = _stage_derivatives(tab.c, h, c) if len(system.kinematic_index) else None
        ks = []
        # the singularity at the step's end and at every stage the equations are evaluated at: a
        # stage past it (e.g. cos(phi) < 0 between two steps' ends with cos(phi) > 0) is a failure
        singular = None
        for i in range(len(tab.b)):
            yq, yv = q, v
            for j, aij in enumerate(tab.a[i][:i]):
                if aij != 0.0:
                    yq = yq + (h * aij) * ks[j][0]
                    yv = yv + (h * aij) * ks[j][1]
            if i > 0:
                at_stage = system.singular(yq, q)
                singular = at_stage if singular is None else singular | at_stage
            ks.append(system.ode((yq, yv), c[i], None if c_dot is None else c_dot[i]))
        dq = sum(bi * k[0] for bi, k in zip(tab.b, ks) if bi != 0.0)
        dv = sum(bi * k[1] for bi, k in zip(tab.b, ks) if bi != 0.0)
        new = (q + h * dq, v + h * dv)
        zero = jnp.zeros((), q.dtype)
        at_end = system.singular(new[0], q)
        singular = at_end if singular is None else singular | at_end
        result = classify(finite(new), singular, jnp.ones((), bool))
        return new, StepInfo(result=result, residual=zero, iterations=jnp.zeros((), jnp.int32))


def _stage_derivatives(nodes: tuple[float, ...], h, c):
    """The controls' time derivative at each stage, from the derivative of the Lagrange polynomial
    through the values at the step's distinct nodes (``c`` (stages, channels), values at
    ``t + nodes[i] h``)."""
    distinct = sorted(set(nodes))
    first = [nodes.index(x) for x in distinct]  # the stage holding each distinct node's value
    if len(distinct) < 2:
        return jnp.zeros_like(c)
    x = np.asarray(distinct, float)
    rows = []
    for xi in nodes:  # d/dx of the Lagrange basis polynomials at xi (exact weights, host side)
        w = []
        for j in range(len(x)):
            others = [k for k in range(len(x)) if k != j]
            total = 0.0
            for m in others:
                term = 1.0 / (x[j] - x[m])
                for k in others:
                    if k != m:
                        term *= (xi - x[k]) / (x[j] - x[k])
                total += term
            w.append(total)
        rows.append(w)
    weights = np.asarray(rows)  # (stages, distinct)
    values = c[np.asarray(first)]  # (distinct, channels)
    return jnp.asarray(weights, c.dtype) @ values / h


class RK2(AbstractRungeKutta):
    """Explicit midpoint rule, order 2: ``y_{k+1} = y_k + h F(t_k + h/2, y_k + h F(t_k, y_k) / 2)``."""

    tableau: ClassVar[ButcherTableau] = ButcherTableau(a=((), (0.5,)), b=(0.0, 1.0), c=(0.0, 0.5))

    @property
    def order(self) -> int:
        return 2


class RK4(AbstractRungeKutta):
    """The classical fourth-order Runge-Kutta method (four stages, nodes 0, 1/2, 1/2, 1)."""

    tableau: ClassVar[ButcherTableau] = ButcherTableau(
        a=((), (0.5,), (0.0, 0.5), (0.0, 0.0, 1.0)),
        b=(1 / 6, 1 / 3, 1 / 3, 1 / 6),
        c=(0.0, 0.5, 0.5, 1.0),
    )

    @property
    def order(self) -> int:
        return 4


def _check(tab: ButcherTableau) -> None:  # consistency of the tables, at import
    assert np.isclose(sum(tab.b), 1.0)
    for i, row in enumerate(tab.a):
        assert np.isclose(sum(row), tab.c[i])


_check(RK2.tableau)
_check(RK4.tableau)
