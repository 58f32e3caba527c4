"""Systems whose RDP step has a closed form, and the observation every integrator reports."""

from __future__ import annotations

import abc
from typing import Any

from jaxtyping import Array

from ._base import AbstractSystem, Observation

__all__ = ["AbstractClosedFormSystem", "Observation"]


class AbstractClosedFormSystem(AbstractSystem):
    """A system whose RDP step, with ``dtau^-1`` truncated to ``I - ad/2``, is explicit.

    The paper's car (Sec. 5.1) and snakeboard (Sec. 5.2) are such systems. A subclass declares
    its closed-form RDP step on a *kernel state* of its own choosing, a pytree of scalars
    (structure of arrays: a ``vmap`` over a batch turns every component into one contiguous
    vector XLA vectorises), written once in the model's file:

    * :meth:`kernel_init` builds the kernel state from a configuration and incoming momenta;
    * :meth:`kernel_step` is one RDP step (``alpha``, step ``h``, retraction) with the control
      values at both ends of the step;
    * :meth:`kernel_observe` reports the node: configuration, velocity from the carried momenta
      and the diagnostics;
    * :meth:`kernel_momenta` reads the configuration and incoming momenta back.

    :class:`~ldap_jax.RDP` runs the kernel whenever the system is an
    ``AbstractClosedFormSystem`` (and ``dtau_order == 1``, ``solver == "auto"``); it must agree
    with the general Newton step (``RDP(solver="newton")``) to round-off, which the tests check
    for every closed-form system. Adding one touches only its own file.

    The incoming momenta are the RDP state's: ``pu = d_u l_{k-1} + h alpha (d_r l_{k-1} +
    f_{k-1+alpha})`` (the force folded in) and ``mu = (dtau^-1_{-h xi_{k-1}})^* d_xi l_{k-1}``.
    """

    @abc.abstractmethod
    def kernel_init(self, q: Array, pu: Array, mu: Array) -> Any:
        """The kernel state at configuration ``q`` with incoming momenta ``pu`` (n,), ``mu`` (3,)."""

    @abc.abstractmethod
    def kernel_step(
        self, alpha: Any, h: Array, retraction: str, state: Any, c0: Array, c1: Array
    ) -> tuple[Any, Array, Array]:
        """One RDP step from ``state`` with control values ``c0`` at ``t_k`` and ``c1`` at
        ``t_k + h`` (``h`` may be negative).

        Returns:
            ``(state_next, residual, singular)``: the residual of the step's equations (21), (23)
            after the closed-form solve, relative to ``1 + |pu + h (1 - alpha) f| + |mu|``, and
            whether the step reached or crossed a singularity.
        """

    def kernel_step_reverse(
        self, alpha: Any, h: Array, retraction: str, state: Any, c0: Array, c1: Array
    ) -> tuple[Any, Array, Array]:
        """:meth:`kernel_step` for a program differentiated in reverse mode only (the rollout of
        :func:`~ldap_jax.simulate` outside forward mode). A kernel may give it a hand-written VJP
        (``jax.custom_vjp``: no forward mode), equal to the derivative of :meth:`kernel_step`;
        its residual, a diagnostic, then has no derivative. Default: :meth:`kernel_step`."""
        return self.kernel_step(alpha, h, retraction, state, c0, c1)

    @abc.abstractmethod
    def kernel_observe(self, state: Any, c: Array) -> Observation:
        """The node's :class:`Observation`, with controls ``c`` at the node's time."""

    def kernel_node(self, state: Any, c: Array) -> tuple[Array, Array]:
        """``(q, qdot)`` of the node without the diagnostics (default: from :meth:`kernel_observe`;
        a kernel may give a lighter path, which derivatives of a rollout then differentiate)."""
        obs = self.kernel_observe(state, c)
        return obs.q, obs.qdot

    @abc.abstractmethod
    def kernel_momenta(self, state: Any) -> tuple[Array, Array, Array]:
        """``(q, pu, mu)`` held by a kernel state."""
