"""Result codes of rollouts and solves, and the one rule that combines them."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool

from ._typing import ArrayLike

__all__ = ["RESULTS", "first_failure"]


class RESULTS(eqx.Enumeration):
    """What happened to a trajectory (``Trajectory.result``) or a step (``StepInfo.result``).

    Compare with ``==`` (``traj.result == lj.RESULTS.successful``); ``RESULTS[traj.result]`` gives
    the message; ``int(traj.result._value)`` the integer code (0 success, as listed here). Each
    message says what happened, success included, and a failure's what to do about it.
    """

    successful = "successful: the run finished and every diagnostic is finite."
    nonfinite = (
        "non-finite values (NaN or inf) in the state or in a diagnostic (energy, work, momentum): "
        "the step is far too large for the motion, or an input (a control, a parameter) is so "
        "large that the values overflow. Reduce the step or check the inputs' magnitudes."
    )
    singular = (
        "singular configuration: the reduced description breaks down (the snakeboard at "
        "cos(phi) = 0, or where a System's `singularity` vanishes). Keep the steering away from it "
        "(e.g. a steering torque matched to phidot(0)), or reduce the step."
    )
    not_converged = (
        "the implicit solve (Newton) did not converge: the step is too large (the root may "
        "have vanished in a fold of the discrete equations). Reduce the step or raise the "
        "integrator's newton_iterations. For a System of your own, also check that its kinetic "
        "energy is positive definite in the velocities the forces drive (else the Newton matrix is "
        "singular at every step), and whether the run is approaching a singularity of its "
        "connection or symmetry basis: Newton can fail there before the `singularity` function "
        "vanishes, at every step size; a lift that stays regular along the motion avoids it."
    )
    diverged = (
        "diverged: the energy balance E - E0 - W grew past `divergence` times the energy scale "
        "(or the state left the finite range). The run is numerically unstable at this step: "
        "reduce the step, or raise `divergence` if the growth is physical. For lj.GNI: a step's "
        "velocity left the constraints (normalised violation above `max_violation`), the "
        "faithful variant's parasitic mode, which a smaller step does not remove; use "
        'GNI(variant="folded") or RDP.'
    )
    invalid_input = (
        "an input is invalid: t_final <= t0, a non-finite time or a step (t_final - t0) / n_steps "
        "that is 0 in the run's dtype (simulate), a non-positive or "
        "non-finite step h (discretize), non-finite, decreasing "
        "or early sample times ts (reference), a non-finite initial state, non-finite controls, "
        "qdot0 violating the constraints, a physical parameter out of range (e.g. a non-positive "
        "mass, or I >= m l^2 for the snakeboard), alpha outside [0, 1], or alpha != 1/2 for "
        "RDP(order=4 | 6 | 8). It was found on traced values (inside jit or vmap), where no "
        "ValueError can be raised: every node of this trajectory is NaN, and simulate (or "
        "reference, or discretize) called eagerly on this member raises the error naming the "
        "argument."
    )
    max_steps_reached = (
        "the adaptive solver reached max_steps before the final time (lj.reference): the "
        "problem is stiff or nearly singular, the interval ts is very long, or the tolerances are "
        "too tight for the budget. Raise max_steps, loosen rtol/atol or shorten ts."
    )


def first_failure(
    result: RESULTS, index: Array, step_result: RESULTS, k: ArrayLike
) -> tuple[RESULTS, Array, Bool[Array, ""]]:
    """The failure rule of every rollout loop: the first failure wins.

    Args:
        result: the result so far (``successful`` until something failed).
        index: the step index of the first failure so far (any value while successful).
        step_result: what the current step reported.
        k: the current step index.

    Returns:
        ``(result, index, keep)``: the updated result and failure index, and ``keep``, True when
        the step's new state may be kept (nothing has failed yet, including this step). A loop
        reports NaN for every node after a failure; it freezes its state when ``keep`` is False
        where a later step could not run on a failed state (or when it is differentiated).
    """
    ok_before = result == RESULTS.successful
    failed_now = ok_before & (step_result != RESULTS.successful)
    new_result = RESULTS.where(ok_before, step_result, result)
    new_index = jnp.where(failed_now, jnp.asarray(k, jnp.int32), index)
    return new_result, new_index, ~failed_now & ok_before
