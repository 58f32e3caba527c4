"""The integrator interface: pure ``init`` / ``step`` over a system description."""

from __future__ import annotations

import abc
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, Bool, Float

__all__ = ["AbstractIntegrator", "AbstractAlphaIntegrator", "StepInfo", "concrete_float"]


def concrete_float(x) -> float | None:
    """``float(x)`` for a concrete scalar (e.g. an integrator's ``alpha``), ``None`` for a tracer."""
    if isinstance(x, jax.core.Tracer):
        return None
    return float(np.asarray(x))


class StepInfo(NamedTuple):
    """What one step reports.

    Attributes:
        residual: norm of the step's residual after the solve (0 for explicit schemes
            with no implicit equation), or the discrete momentum residual (21) for RDP.
        converged: False when an implicit solve did not meet its tolerance.
        iterations: Newton iterations used (0 for explicit steps).
    """

    residual: Float[Array, ""]
    converged: Bool[Array, ""]
    iterations: Array


class AbstractIntegrator(eqx.Module):
    """A one-step scheme on a :class:`~ldap_jax.systems.AbstractSystem`.

    ``init(system, h, q0, qdot0, c0)`` builds the scheme's state from the continuous initial
    condition; ``step(system, h, state, c)`` returns ``(state_next, (q_k, qdot_k), info)``:
    the configuration and velocity estimate at the current node ``t_k`` and the state at
    ``t_{k+1}``. ``c`` holds the control channel values at ``t_k + c_j h`` for the fractions
    ``c_j`` in :attr:`control_nodes`, shape ``(len(control_nodes), n_channels)``.
    """

    @property
    @abc.abstractmethod
    def control_nodes(self) -> tuple[float, ...]: ...

    @property
    @abc.abstractmethod
    def order(self) -> int: ...

    implicit: ClassVar[bool] = False

    @abc.abstractmethod
    def init(self, system, h, q0, qdot0, c0) -> Any: ...

    @abc.abstractmethod
    def step(self, system, h, state, c) -> tuple[Any, tuple[Array, Array], StepInfo]: ...

    @abc.abstractmethod
    def configuration(self, state) -> Array:
        """The configuration ``q_k`` held by a state."""


class AbstractAlphaIntegrator(AbstractIntegrator):
    """A one-step scheme with a quadrature point ``alpha in [0, 1]`` (RDP, DLA, GNI).

    Controls are read at both ends of each step (``f_{k+alpha} = (1-alpha) f_k + alpha f_{k+1}``),
    the state carries the configuration as ``state.q``, and the order is 2 at ``alpha = 1/2``
    (symmetric) and 1 otherwise.
    """

    alpha: eqx.AbstractVar[float]

    def __check_init__(self):
        a = concrete_float(self.alpha)
        if a is not None and not 0.0 <= a <= 1.0:
            raise ValueError(f"{type(self).__name__}: 'alpha' must lie in [0, 1], got {self.alpha}")

    @property
    def control_nodes(self):
        return (0.0, 1.0)

    @property
    def order(self) -> int:
        return 2 if concrete_float(self.alpha) == 0.5 else 1

    def configuration(self, state):
        return state.q
