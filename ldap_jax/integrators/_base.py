"""The integrator interface: pure ``init`` / ``step`` / ``observe`` over a system description."""

from __future__ import annotations

import abc
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._results import RESULTS
from ..systems import AbstractSystem, Observation

__all__ = [
    "AbstractIntegrator",
    "AbstractAlphaIntegrator",
    "StepInfo",
    "classify",
    "concrete_float",
    "finite",
]


def concrete_float(x: Any) -> float | None:
    """``float(x)`` for a concrete scalar (e.g. an integrator's ``alpha``), ``None`` for a tracer."""
    if isinstance(x, jax.core.Tracer):
        return None
    return float(np.asarray(x))


class StepInfo(NamedTuple):
    """What one step reports.

    Attributes:
        result: :data:`~ldap_jax.RESULTS` item of the step (``successful``, ``nonfinite``,
            ``singular`` or ``not_converged``).
        residual: norm of the step's residual after the solve, relative to the scale of the
            step's momenta (0 for explicit schemes with no implicit equation; for RDP the
            horizontal (23) and discrete momentum (21) equations; for a composition the largest
            over its substeps).
        iterations: Newton iterations used (0 for explicit steps; summed over substeps).
    """

    result: RESULTS
    residual: Float[Array, ""]
    iterations: Int[Array, ""]


def finite(tree: Any) -> Bool[Array, ""]:
    """True when every floating leaf of ``tree`` is finite (one test on the sum of all entries: a
    NaN or an infinity anywhere makes the sum non-finite)."""
    leaves = [x for x in jax.tree_util.tree_leaves(tree) if jnp.issubdtype(jnp.result_type(x), jnp.inexact)]
    return jnp.isfinite(sum(jnp.sum(x) for x in leaves))


def classify(is_finite: Bool[Array, ""], singular: Bool[Array, ""], converged: Bool[Array, ""]) -> RESULTS:
    """A step's result: non-finite values first, then a singularity, then non-convergence."""
    return RESULTS.where(
        ~is_finite,
        RESULTS.nonfinite,
        RESULTS.where(
            singular, RESULTS.singular, RESULTS.where(converged, RESULTS.successful, RESULTS.not_converged)
        ),
    )


class AbstractIntegrator(eqx.Module):
    """A one-step scheme on a :class:`~ldap_jax.systems.AbstractSystem`.

    * ``init(system, h, q0, qdot0, c)`` builds the scheme's state from the continuous initial
      condition at ``t0``;
    * ``step(system, h, state, c)`` advances it by ``h`` (which may be negative) and returns
      ``(state_next, StepInfo)``;
    * ``observe(system, state, c_node)`` reports the node held by a state: configuration,
      velocity and diagnostics (:class:`~ldap_jax.systems.Observation`).

    ``c`` holds the control channel values at ``t_k + f_j h`` for the fractions ``f_j`` of
    :attr:`control_nodes`, shape ``(len(control_nodes), n_channels)``; ``c_node`` the values at
    ``t_k``. A state is a pytree; the step is pure and jit-able, so any loop (``lax.scan``, an
    optimizer's dynamics, a policy rollout) can drive it.
    """

    implicit: ClassVar[bool] = False

    @property
    @abc.abstractmethod
    def control_nodes(self) -> tuple[float, ...]:
        """Fractions of the step at which :meth:`step` reads the controls."""

    @property
    @abc.abstractmethod
    def order(self) -> int:
        """Order of global accuracy."""

    @abc.abstractmethod
    def init(self, system: AbstractSystem, h: Array, q0: Array, qdot0: Array, c: Array) -> Any:
        """The state at ``t0`` from a configuration and a velocity on the constraints."""

    @abc.abstractmethod
    def step(self, system: AbstractSystem, h: Array, state: Any, c: Array) -> tuple[Any, StepInfo]:
        """One step of size ``h``."""

    @abc.abstractmethod
    def observe(self, system: AbstractSystem, state: Any, c: Array) -> Observation:
        """The node held by ``state``: configuration, velocity, diagnostics."""

    def node(self, system: AbstractSystem, state: Any, c: Array) -> tuple[Array, Array]:
        """``(q, qdot)`` held by ``state``, without the diagnostics (default: from :meth:`observe`)."""
        obs = self.observe(system, state, c)
        return obs.q, obs.qdot


class AbstractAlphaIntegrator(AbstractIntegrator):
    """A one-step scheme with a quadrature point ``alpha in [0, 1]`` (RDP, DLA, GNI).

    Controls are read at both ends of each step (``f_{k+alpha} = (1-alpha) f_k + alpha f_{k+1}``),
    and the order is 2 at ``alpha = 1/2`` (symmetric) and 1 otherwise.
    """

    alpha: eqx.AbstractVar[Any]

    def __check_init__(self):
        a = concrete_float(self.alpha)
        if a is not None and not 0.0 <= a <= 1.0:
            raise ValueError(f"{type(self).__name__}: 'alpha' must lie in [0, 1], got {self.alpha}")

    @property
    def control_nodes(self) -> tuple[float, ...]:
        return (0.0, 1.0)

    @property
    def order(self) -> int:
        a = concrete_float(self.alpha)
        return 2 if a is None or a == 0.5 else 1


def refuse_friction(integrator: str, system) -> None:
    """A ``ValueError`` for an integrator that does not take a system's friction (a dissipation
    function): DLA and GNI discretise the Lagrangian's full view, without forces on the group."""
    if system.has_friction:
        raise ValueError(
            f"{integrator} does not take a system's friction ('dissipation'); use lj.RDP, lj.RK2 or lj.RK4"
        )
