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
            ks.append(system.ode((yq, yv), c[i]))
        dq = sum(bi * k[0] for bi, k in zip(tab.b, ks) if bi != 0.0)
        dv = sum(bi * k[1] for bi, k in zip(tab.b, ks) if bi != 0.0)
        new = (q + h * dq, v + h * dv)
        zero = jnp.zeros((), q.dtype)
        at_end = system.singular(new[0], q)
        singular = at_end if singular is None else singular | at_end
        result = classify(finite(new), singular, jnp.ones((), bool))
        return new, StepInfo(result=result, residual=zero, iterations=jnp.zeros((), jnp.int32))


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
