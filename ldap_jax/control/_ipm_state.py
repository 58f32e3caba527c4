"""The interior-point method's state, options and result codes (see :mod:`._ipm`)."""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._riccati import QPSolution

__all__ = ["SOLVER_RESULTS", "IPMOptions", "IPMState", "Bounds", "Step", "pushed", "MAX_RESETS"]


class SOLVER_RESULTS(eqx.Enumeration):
    """Why :func:`~ldap_jax.control.solve` stopped."""

    successful = "successful: the KKT error met the tolerance"
    max_iterations = "the iteration budget ran out before the KKT error met the tolerance"
    line_search_failed = (
        "the line search found no acceptable step: the problem may be infeasible from this guess "
        "(e.g. a goal the controls cannot reach within the bounds), or too far from a solution for "
        "its linearisation; try another initial guess (a gait that already moves the system)"
    )
    nonfinite = "non-finite values in the iterates (an integrator failure along the trajectory?)"
    regularization_failed = "the Hessian could not be regularised to the right inertia"
    infeasible = (
        "the constraints could not be met: the iterates stopped at a point of locally least "
        "violation that violates them (e.g. a displacement per cycle too far for the bounds and period)"
    )
    invalid_input = (
        "invalid task values found in the run (a non-positive model parameter, empty bounds, a start "
        "not strictly inside the bounds, a goal that is not finite or lies outside them, a non-finite "
        "displacement per cycle); build the task from known values to get the error naming the argument"
    )
    stalled = (
        "the KKT error stalled above the tolerance at a point that meets the constraints: round-off "
        "leaves the line search no acceptable step (a tol below what the float type resolves on this "
        "problem; sol.kkt_error is within 100 tol, or below the default tol); the point is optimal to "
        "sol.kkt_error: solve again with a larger tol"
    )


class IPMOptions(NamedTuple):
    tol: float = 1e-8
    max_iterations: int = 1000
    mu0: float = 0.1
    kappa_eps: float = 10.0
    tau_min: float = 0.99
    bound_push: float = 1e-2
    max_backtracks: int = 30
    # 1e6 rather than 1e4: on the car's sideways gait (multipliers ~1e3) the stagewise test failed
    # at every iteration near the solution with 1e4, and the inertia correction slowed the
    # iteration to a crawl (1000 iterations, KKT error 3e-5); with 1e6, 70 iterations. The
    # point-to-point tasks took the same iterations (reach 79 against 71).
    rho_c: float = 1e6
    # the dynamics' curvature enters the Hessian once theta = |defects|_1 + |c_K|_1 <= this. 0.1
    # rather than 1e-2: on 288 problems (16 random goals around each goal task, seeds 0-2, from the
    # default guesses and from rest) all converge with either, in 22377 iterations against 27059;
    # at 1.0 the three goal tasks took more iterations.
    exact_hessian_tol: float = 0.1
    filter_size: int = 64
    hessian: str = "exact"
    verbose: bool = False


class IPMState(NamedTuple):
    p: Float[Array, " s"]  # initial parameters
    chi: Float[Array, "K n"]  # chi_1 .. chi_K
    v: Float[Array, "K1 m"]  # v_1 .. v_{K-1}
    y: Float[Array, "K n"]  # dynamics multipliers (y_0: of chi_1 = F_0(p))
    nu: Float[Array, " p"]
    zl: Float[Array, "K n"]  # bound multipliers (0 where the bound is infinite)
    zu: Float[Array, "K n"]
    mu: Float[Array, ""]
    theta_max: Float[Array, ""]
    filter: Float[Array, "F 2"]  # (theta, phi) pairs of the filter; +inf = empty slot
    delta_w: Float[Array, ""]
    iteration: Int[Array, ""]
    error: Float[Array, ""]
    violation: Float[Array, ""]  # largest constraint violation (max norm) at the iterate
    held: Bool[Array, ""]  # the last iteration updated only the multipliers (see ``_next_point``)
    resets: Int[Array, ""]  # restarts after failed line searches far from feasibility
    stopped: Bool[Array, ""]  # the iteration has ended (``result`` says why)
    result: SOLVER_RESULTS


class Bounds(NamedTuple):
    lo: Array  # (K, n), -inf: none
    hi: Array

    @property
    def has_lo(self) -> Array:
        return jnp.isfinite(self.lo)

    @property
    def has_hi(self) -> Array:
        return jnp.isfinite(self.hi)

    def slacks(self, chi: Array) -> tuple[Array, Array]:
        return jnp.where(self.has_lo, chi - self.lo, 1.0), jnp.where(self.has_hi, self.hi - chi, 1.0)

    def log_barrier(self, chi: Array) -> Array:
        sl, su = self.slacks(chi)
        return jnp.sum(jnp.where(self.has_lo, jnp.log(sl), 0.0)) + jnp.sum(
            jnp.where(self.has_hi, jnp.log(su), 0.0)
        )


def pushed(x: Array, lo: Array, hi: Array, push: float) -> Array:
    """``x`` moved inside the bounds by IPOPT's bound push: at least ``push max(1, |bound|)`` from
    each finite bound, and at most half of ``push`` times the width of a two-sided interval."""
    has_lo, has_hi = jnp.isfinite(lo), jnp.isfinite(hi)
    width = jnp.where(has_lo & has_hi, hi - lo, jnp.inf)
    lo_in = jnp.where(
        has_lo, lo + jnp.minimum(push * jnp.maximum(1.0, jnp.abs(lo)), 0.5 * push * width), -jnp.inf
    )
    hi_in = jnp.where(
        has_hi, hi - jnp.minimum(push * jnp.maximum(1.0, jnp.abs(hi)), 0.5 * push * width), jnp.inf
    )
    return jnp.minimum(jnp.maximum(x, lo_in), hi_in)


#: restarts after a failed line search far from feasibility before the method gives up
MAX_RESETS = 5


class Step(NamedTuple):
    """One Newton step of the barrier problem and what the line search needs of it."""

    mu: Array
    sol: QPSolution
    delta: Array
    reg_ok: Array
    g: Array  # gradient of the barrier objective w.r.t. chi
    dzl: Array
    dzu: Array
