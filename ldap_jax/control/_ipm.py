"""A primal-dual interior-point method for discrete optimal control, jitted end to end.

The problem (built from a :class:`~ldap_jax.control.Task` by :mod:`._solve`), with the node
controls carried in an augmented state so that the dynamics ``x_{k+1} = f(x_k, u_k, u_{k+1})``
take the stage form of optimal control: ``chi_j = (x_{j-1}, u_{j-1})``, control ``v_j = u_j``::

    min   sum_{j=1}^{K} l(chi_j) + l_K(chi_K)
    s.t.  chi_{j+1} = F_j(chi_j, v_j)  (j = 0 .. K-1, chi_1 = (x_0, v_0)),   c(chi_K) = 0,
          lo <= chi_j <= hi  (j = 1 .. K),

``K = N + 1``. Multiple shooting: every ``chi_j`` and ``v_j`` is a variable and the dynamics are
equality constraints, so the dynamics and their derivatives are evaluated for all stages at once
(``vmap``), and only the Riccati recursion of :mod:`._riccati` is sequential.

One iteration follows Wachter and Biegler's IPOPT (Math. Program. 106, 2006), simplified:

* the Newton step of the barrier problem ``min f - mu sum log(slacks)``, solved by the Riccati
  recursion, with the Hessian of the Lagrangian: Gauss-Newton (the objective's and the barrier's
  curvature) while the constraint violation exceeds ``exact_hessian_tol``, then with the
  dynamics' curvature ``y^T F''`` (second derivatives by automatic differentiation, of
  ``OCPFunctions.curvature_dynamics`` where given: a cheaper step approximating ``F``), for fast
  local convergence; if its reduced Hessian is not positive definite, ``delta_w I`` is added and the
  solve repeated (inertia correction); up to two steps of iterative refinement (as IPOPT's) keep
  the residual of the solve below ``tol / 100``: near the solution the barrier makes the system
  ill-conditioned, and without them the KKT error stalled at 1e-9 to 2e-8 (the line search then
  fails), depending on how the code generation rounds;
* the fraction-to-the-boundary rule keeps the iterates strictly inside the bounds;
* a backtracking line search with IPOPT's filter (constraint violation ``theta``, barrier
  objective ``phi``) globalises;
* a line search that fails far from feasibility restarts the iteration from the current point
  pushed inside its bounds, with the multipliers reset; from the second restart on, the controls
  are also perturbed within their bounds and the states rolled out from them (at most
  ``MAX_RESETS`` restarts; a simple stand-in for IPOPT's feasibility restoration, see ``step``);
* ``mu`` decreases superlinearly (``mu <- min(0.2 mu, mu^1.5)``) once the barrier problem is solved
  to ``10 mu``; the method stops when the scaled KKT error is below ``tol``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._riccati import riccati_apply, riccati_factor

__all__ = ["SOLVER_RESULTS", "IPMOptions", "IPMState", "ipm_solve", "OCPFunctions"]


class SOLVER_RESULTS(eqx.Enumeration):
    """Why :func:`~ldap_jax.control.solve` stopped."""

    successful = ""
    max_iterations = "the iteration budget ran out before the KKT error met the tolerance"
    line_search_failed = (
        "the line search found no acceptable step: the problem may be infeasible from this guess "
        "(e.g. a goal the controls cannot reach within the bounds), or too far from a solution for "
        "its linearisation; try another initial guess (a gait that already moves the system)"
    )
    nonfinite = "non-finite values in the iterates (an integrator failure along the trajectory?)"
    regularization_failed = "the Hessian could not be regularised to the right inertia"


class OCPFunctions(NamedTuple):
    """The problem in stage form: callables of one stage (vmapped by the solver)."""

    dynamics: Callable[[Array, Array], Array]  # (chi, v) -> next chi, for stages j >= 1
    first: Callable[[Array], Array]  # v_0 -> chi_1 (affine)
    stage_cost: Callable[[Array], Array]  # chi -> scalar (stages 1..K)
    terminal_cost: Callable[[Array], Array]  # chi_K -> scalar (added to the stage cost of K)
    terminal: Callable[[Array], Array]  # chi_K -> (p,) equality residuals
    # (chi, v) -> next chi whose second derivatives stand in for the dynamics' in the Hessian of
    # the Lagrangian (default: ``dynamics`` itself)
    curvature_dynamics: Callable[[Array, Array], Array] | None = None
    # (v, key, size) -> controls v perturbed within their bounds by ``size`` (a fraction of their
    # half-width), for a restart from a point where the linearisation gives no direction (see
    # ``step``); None: restarts never perturb
    perturbation: Callable[[Array, Array, Array], Array] | None = None


class IPMOptions(NamedTuple):
    tol: float = 1e-8
    max_iterations: int = 1000
    mu0: float = 0.1
    kappa_eps: float = 10.0
    tau_min: float = 0.99
    bound_push: float = 1e-2
    max_backtracks: int = 30
    rho_c: float = 1e4
    # the dynamics' curvature enters the Hessian once theta = |defects|_1 + |c_K|_1 <= this. 0.1
    # rather than 1e-2: on 288 problems (16 random goals around each goal task, seeds 0-2, from the
    # default guesses and from rest) all converge with either, in 22377 iterations against 27059
    # (the slowest, a parallel_park goal, 63 against 749); the three tasks take 20 / 52 / 71
    # iterations against 21 / 55 / 86. At 1.0: 24 / 55 / 96.
    exact_hessian_tol: float = 0.1
    filter_size: int = 64
    hessian: str = "exact"
    verbose: bool = False


class IPMState(NamedTuple):
    chi: Float[Array, "K n"]  # chi_1 .. chi_K
    v: Float[Array, "K m"]  # v_0 .. v_{K-1}
    y: Float[Array, "K n"]  # dynamics multipliers
    nu: Float[Array, " p"]
    zl: Float[Array, "K n"]  # bound multipliers (0 where the bound is infinite)
    zu: Float[Array, "K n"]
    mu: Float[Array, ""]
    theta_max: Float[Array, ""]
    filter: Float[Array, "F 2"]  # (theta, phi) pairs of the filter; +inf = empty slot
    delta_w: Float[Array, ""]
    curvature: Float[Array, "K1 nm nm"]  # SR1 approximations of the dynamics' curvature y^T F''
    curvature_K: Float[Array, "n n"]  # ... and of the terminal constraints' nu^T c''
    previous: tuple[Array, Array, Array, Array]  # (chi, v, Z, CK) of the previous iterate
    iteration: Int[Array, ""]
    error: Float[Array, ""]
    violation: Float[Array, ""]  # largest constraint violation (max norm) at chi, v
    held: Bool[Array, ""]  # the last iteration updated only the multipliers (see ``step``)
    resets: Int[Array, ""]  # restarts after failed line searches far from feasibility (``step``)
    result: SOLVER_RESULTS


class _Derivatives(NamedTuple):
    defects: Array  # (K, n): F_j - chi_{j+1}
    Z: Array  # (K, n, n + m): [A_j, B_j] (stage 0: [0, B_0])
    W: Array  # (K, n + m, n + m): Hessian of the stage Lagrangian (stage 0: 0)
    g: Array  # (K, n): gradient of the objective w.r.t. chi_1..chi_K
    cK: Array  # (p,)
    CK: Array  # (p, n)
    QK: Array  # (n, n): Hessian of l_K + nu^T c (objective part of stage K included)


def _rollout(fns: OCPFunctions, v: Array) -> Array:
    """The states ``chi_1 .. chi_K`` of the controls ``v`` (no defects)."""

    def one(chi, vv):
        nxt = fns.dynamics(chi, vv)
        return nxt, nxt

    chi1 = fns.first(v[0])
    _, rest = jax.lax.scan(one, chi1, v[1:])
    return jnp.concatenate([chi1[None], rest])


def _constraints(fns: OCPFunctions, chi: Array, v: Array) -> tuple[Array, Array]:
    d0 = fns.first(v[0]) - chi[0]
    d = jax.vmap(fns.dynamics)(chi[:-1], v[1:]) - chi[1:]
    return jnp.concatenate([d0[None], d]), fns.terminal(chi[-1])


def _theta(defects: Array, cK: Array) -> Array:
    """The constraint violation of the filter, ``|defects|_1 + |c_K|_1``."""
    return jnp.sum(jnp.abs(defects)) + jnp.sum(jnp.abs(cK))


def _objective(fns: OCPFunctions, chi: Array) -> Array:
    return jnp.sum(jax.vmap(fns.stage_cost)(chi)) + fns.terminal_cost(chi[-1])


def _derivatives(fns: OCPFunctions, st: IPMState, exact_tol: Array, sr1: bool) -> _Derivatives:
    """The constraints and the derivatives of one iteration. The dynamics' curvature enters ``W``
    (and the terminal constraints' ``QK``) once the constraint violation ``theta = |defects|_1 +
    |c_K|_1``, from this same evaluation of the dynamics, is at most ``exact_tol``."""
    chi, v, y = st.chi, st.v, st.y
    K, n = chi.shape
    m = v.shape[1]
    dtype = chi.dtype

    def dyn_aux(c, vv):
        f = fns.dynamics(c, vv)
        return f, f

    (A, B), F = jax.vmap(jax.jacfwd(dyn_aux, argnums=(0, 1), has_aux=True))(chi[:-1], v[1:])
    B0 = jax.jacfwd(fns.first)(v[0])
    defects = jnp.concatenate([(fns.first(v[0]) - chi[0])[None], F - chi[1:]])
    Z = jnp.concatenate(
        [jnp.concatenate([jnp.zeros((1, n, n), dtype), B0[None]], axis=2), jnp.concatenate([A, B], axis=2)]
    )
    g = jax.vmap(jax.grad(fns.stage_cost))(chi)
    H_cost = jax.vmap(jax.hessian(fns.stage_cost))(chi[:-1])
    chiK = chi[-1]
    CK, cK = jax.jacfwd(lambda c: (fns.terminal(c),) * 2, has_aux=True)(chiK)
    exact = _theta(defects, cK) <= exact_tol

    curved = fns.dynamics if fns.curvature_dynamics is None else fns.curvature_dynamics

    def curvature(_):  # the dynamics' second derivatives, weighted by the multipliers
        def one(c, vv, yy):
            return jax.hessian(lambda w: yy @ curved(w[:n], w[n:]))(jnp.concatenate([c, vv]))

        return jax.vmap(one)(chi[:-1], v[1:], y[1:])

    if sr1:  # the curvature comes from the SR1 approximations (added by the caller)
        H_dyn = jnp.zeros((K - 1, n + m, n + m), dtype)
    else:
        H_dyn = jax.lax.cond(exact, curvature, lambda _: jnp.zeros((K - 1, n + m, n + m), dtype), None)
    W = H_dyn.at[:, :n, :n].add(H_cost)
    W = jnp.concatenate([jnp.zeros((1, n + m, n + m), dtype), W])

    def lagrangian_K(c, weight):
        return fns.stage_cost(c) + fns.terminal_cost(c) + weight * st.nu @ fns.terminal(c)

    if sr1:
        QK = jax.hessian(lagrangian_K)(chiK, jnp.zeros((), dtype))
    else:
        QK = jax.hessian(lagrangian_K)(chiK, exact.astype(dtype))
    g = g.at[-1].add(jax.grad(fns.terminal_cost)(chiK))
    return _Derivatives(defects=defects, Z=Z, W=W, g=g, cK=cK, CK=CK, QK=QK)


def _sr1(B: Array, s: Array, r_grad: Array) -> Array:
    """Symmetric rank-one update of ``B`` with step ``s`` and gradient change ``r_grad``
    (skipped when the denominator is tiny, as usual)."""
    r = r_grad - B @ s
    den = r @ s
    ok = jnp.abs(den) > 1e-8 * jnp.linalg.norm(r) * jnp.linalg.norm(s) + 1e-300
    return jnp.where(ok, B + jnp.outer(r, r) / jnp.where(ok, den, 1.0), B)


def _kkt_parts(st: IPMState, d: _Derivatives, lo: Array, hi: Array):
    """Dual infeasibility, constraint violation (max norms), slacks and scaling of the KKT error."""
    n = st.chi.shape[1]
    A = d.Z[:, :, :n]
    B = d.Z[:, :, n:]
    AT_y = jnp.einsum("jab,ja->jb", A[1:], st.y[1:])
    gc = d.g + jnp.concatenate([AT_y, jnp.zeros((1, n), d.g.dtype)]) - st.y
    gc = gc.at[-1].add(d.CK.T @ st.nu) - st.zl + st.zu
    gv = jnp.einsum("jab,ja->jb", B, st.y)
    dual = jnp.maximum(jnp.max(jnp.abs(gc)), jnp.max(jnp.abs(gv)))
    primal = jnp.maximum(jnp.max(jnp.abs(d.defects)), jnp.max(jnp.abs(d.cK), initial=0.0))
    sl = jnp.where(jnp.isfinite(lo), st.chi - lo, 0.0)
    su = jnp.where(jnp.isfinite(hi), hi - st.chi, 0.0)
    n_mult = st.y.size + st.nu.size + st.zl.size
    s_d = jnp.maximum(
        1.0, (jnp.sum(jnp.abs(st.y)) + jnp.sum(jnp.abs(st.nu)) + jnp.sum(st.zl + st.zu)) / (100.0 * n_mult)
    )
    s_c = jnp.maximum(1.0, jnp.sum(st.zl + st.zu) / (100.0 * st.zl.size))
    return dual / s_d, primal, sl, su, s_c


def _kkt_error(parts, st: IPMState, lo: Array, hi: Array, mu: Array) -> Array:
    """IPOPT's E_mu: the largest of the scaled dual infeasibility, the constraint violation and
    the scaled deviation from the barrier's complementarity ``s zeta = mu``."""
    dual, primal, sl, su, s_c = parts
    comp = jnp.maximum(
        jnp.max(jnp.abs(sl * st.zl - jnp.where(jnp.isfinite(lo), mu, 0.0))),
        jnp.max(jnp.abs(su * st.zu - jnp.where(jnp.isfinite(hi), mu, 0.0))),
    )
    return jnp.maximum(jnp.maximum(dual, primal), comp / s_c)


def _fraction_to_boundary(x, dx, lo, hi, tau):
    """Largest alpha in (0, 1] with ``x + alpha dx >= lo + (1 - tau)(x - lo)`` (and for ``hi``)."""
    al = jnp.where(jnp.isfinite(lo) & (dx < 0), -tau * (x - lo) / jnp.where(dx < 0, dx, -1.0), 1.0)
    au = jnp.where(jnp.isfinite(hi) & (dx > 0), tau * (hi - x) / jnp.where(dx > 0, dx, 1.0), 1.0)
    return jnp.minimum(1.0, jnp.minimum(jnp.min(al), jnp.min(au)))


def _multiplier_step(z, dz, tau):
    return jnp.minimum(1.0, jnp.min(jnp.where(dz < 0, -tau * z / jnp.where(dz < 0, dz, -1.0), 1.0)))


def _pushed(x: Array, lo: Array, hi: Array, push: float) -> Array:
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


def ipm_solve(fns: OCPFunctions, chi: Array, v: Array, lo: Array, hi: Array, options: IPMOptions) -> IPMState:
    """Run the interior-point method from the primal guess ``(chi, v)``; ``lo``/``hi`` (n,) bound
    every ``chi_j`` (infinite entries: no bound)."""
    dtype = chi.dtype
    K, n = chi.shape
    m = v.shape[1]
    p = jax.eval_shape(fns.terminal, chi[-1]).shape[0]
    lo = jnp.broadcast_to(lo, chi.shape)
    hi = jnp.broadcast_to(hi, chi.shape)
    has_lo, has_hi = jnp.isfinite(lo), jnp.isfinite(hi)

    def pushed(c):  # strictly inside the bounds (IPOPT's bound_push)
        return _pushed(c, lo, hi, options.bound_push)

    chi = pushed(chi)
    mu0 = jnp.asarray(options.mu0, dtype)
    zero = jnp.zeros((), dtype)

    def slacks(c):
        return jnp.where(has_lo, c - lo, 1.0), jnp.where(has_hi, hi - c, 1.0)

    sl0, su0 = slacks(chi)
    st = IPMState(
        chi=chi,
        v=v,
        y=jnp.zeros((K, n), dtype),
        nu=jnp.zeros((p,), dtype),
        zl=jnp.where(has_lo, mu0 / sl0, 0.0),
        zu=jnp.where(has_hi, mu0 / su0, 0.0),
        mu=mu0,
        theta_max=jnp.asarray(jnp.inf, dtype),
        filter=jnp.full((options.filter_size, 2), jnp.inf, dtype),
        delta_w=zero,
        curvature=jnp.zeros((K - 1, n + m, n + m), dtype),
        curvature_K=jnp.zeros((n, n), dtype),
        previous=(chi, v, jnp.zeros((K, n, n + m), dtype), jnp.zeros((p, n), dtype)),
        iteration=jnp.zeros((), jnp.int32),
        error=jnp.asarray(jnp.inf, dtype),
        violation=jnp.asarray(jnp.inf, dtype),
        held=jnp.zeros((), bool),
        resets=jnp.zeros((), jnp.int32),
        result=SOLVER_RESULTS.max_iterations,
    )
    tol = jnp.asarray(options.tol, dtype)
    eye_n, eye_m = jnp.eye(n, dtype=dtype), jnp.eye(m, dtype=dtype)

    def barrier_objective(c, mu):
        sl, su = slacks(c)
        return _objective(fns, c) - mu * (
            jnp.sum(jnp.where(has_lo, jnp.log(sl), 0.0)) + jnp.sum(jnp.where(has_hi, jnp.log(su), 0.0))
        )

    def theta_phi(c, vv, mu):
        defects, cK = _constraints(fns, c, vv)
        return _theta(defects, cK), barrier_objective(c, mu)

    def step(st: IPMState, d: _Derivatives, parts) -> IPMState:
        # barrier update (possibly several times) once the barrier problem is solved to kappa mu
        def mu_cond(mu_):
            return (_kkt_error(parts, st, lo, hi, mu_) <= options.kappa_eps * mu_) & (mu_ > tol / 10)

        mu = jax.lax.while_loop(
            mu_cond, lambda mu_: jnp.maximum(tol / 10, jnp.minimum(0.2 * mu_, mu_**1.5)), st.mu
        )
        sl, su = slacks(st.chi)
        sigma = jnp.where(has_lo, st.zl / sl, 0.0) + jnp.where(has_hi, st.zu / su, 0.0)
        g = d.g + jnp.where(has_lo, -mu / sl, 0.0) + jnp.where(has_hi, mu / su, 0.0)
        diag = jax.vmap(jnp.diag)(jnp.concatenate([jnp.zeros((1, n), dtype), sigma[:-1]]))
        W0 = d.W.at[:, :n, :n].add(diag)
        w = jnp.concatenate(
            [jnp.concatenate([jnp.zeros((1, n), dtype), g[:-1]]), jnp.zeros((K, m), dtype)], axis=1
        )
        # rho_c C^T C: free in the QP (C dx_K = -c holds exactly) but it curves the terminal
        # directions, so that the stagewise positive-definiteness test is the inertia test
        QK0 = d.QK + jnp.diag(sigma[-1]) + options.rho_c * d.CK.T @ d.CK
        eye = jnp.zeros((K, n + m, n + m), dtype).at[:, :n, :n].set(eye_n).at[:, n:, n:].set(eye_m)
        eye = eye.at[0, :n, :n].set(0.0)

        def factor_with(delta):
            return riccati_factor(W0 + delta * eye, d.Z, QK0 + delta * eye_n, d.CK, jnp.asarray(1e-10, dtype))

        def reg_cond(c):
            _, f, tries = c
            return (~f.positive | ~jnp.all(jnp.isfinite(f.CM_inv))) & (tries < 40)

        def reg_body(c):
            delta, _, tries = c
            delta = jnp.where(
                tries == 0, zero, jnp.where(delta == 0, jnp.maximum(1e-4, st.delta_w / 3), 8.0 * delta)
            )
            return delta, factor_with(delta), tries + 1

        shapes = jax.eval_shape(factor_with, zero)
        empty = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
        delta, fac, _ = jax.lax.while_loop(reg_cond, reg_body, (zero, empty, jnp.zeros((), jnp.int32)))
        # iterative refinement keeps the solve's residual, which enters the next iterate's KKT
        # error directly, two orders below the tolerance
        sol = riccati_apply(fac, w, d.defects, g[-1], d.cK, refine=2, atol=1e-2 * tol)
        reg_ok = fac.positive & jnp.all(jnp.isfinite(sol.dx))
        dchi, dv = sol.dx[1:], sol.dv
        # bound multipliers: zeta + dzeta = mu / s - Sigma ds
        dzl = jnp.where(has_lo, mu / sl - st.zl - st.zl / sl * dchi, 0.0)
        dzu = jnp.where(has_hi, mu / su - st.zu + st.zu / su * dchi, 0.0)
        tau = jnp.maximum(options.tau_min, 1.0 - mu)
        a_max = _fraction_to_boundary(st.chi, dchi, lo, hi, tau)
        a_z = jnp.minimum(_multiplier_step(st.zl, dzl, tau), _multiplier_step(st.zu, dzu, tau))
        # line search with IPOPT's filter acceptance test
        theta0 = _theta(d.defects, d.cK)
        phi0 = barrier_objective(st.chi, mu)
        slope = jnp.sum(g * dchi)
        theta_max = jnp.where(jnp.isfinite(st.theta_max), st.theta_max, 1e4 * jnp.maximum(1.0, theta0))
        theta_min = 1e-4 * jnp.maximum(1.0, theta_max / 1e4)
        filt = jnp.where(mu == st.mu, st.filter, jnp.inf)  # reset when mu changes

        # comparisons of phi allow its round-off (IPOPT's Compare_le, 10 eps |phi0|): near the
        # solution the decrease alpha * slope falls below it, and a strict test rejects every step
        slack = 10 * jnp.finfo(dtype).eps * jnp.abs(phi0)

        def trial(alpha):
            theta, phi = theta_phi(st.chi + alpha * dchi, st.v + alpha * dv, mu)
            switching = (slope < 0) & (alpha * (-slope) ** 2.3 > theta0**1.1)
            f_type = (theta0 <= theta_min) & switching
            armijo = phi <= phi0 + 1e-4 * alpha * slope + slack
            h_ok = (theta <= (1 - 1e-5) * theta0) | (phi <= phi0 - 1e-8 * theta0 + slack)
            in_filter = jnp.any((theta >= (1 - 1e-5) * filt[:, 0]) & (phi >= filt[:, 1] - 1e-8 * filt[:, 0]))
            ok = jnp.where(f_type, armijo, h_ok) & (theta <= theta_max) & ~in_filter
            return ok & jnp.isfinite(theta) & jnp.isfinite(phi), f_type

        def ls_cond(c):
            _, k, ok, _ = c
            return (~ok) & (k < options.max_backtracks)

        def ls_body(c):
            alpha, k, _, _ = c
            alpha = jnp.where(k == 0, alpha, 0.5 * alpha)
            ok, f_type = trial(alpha)
            return alpha, k + 1, ok, f_type

        false = jnp.zeros((), bool)
        alpha, _, ls_ok, f_type = jax.lax.while_loop(
            ls_cond, ls_body, (a_max, jnp.zeros((), jnp.int32), false, false)
        )
        alpha = jnp.where(ls_ok, alpha, 0.0)
        # At a feasible point near the solution the barrier objective and the violation change
        # by less than their round-off along the step (|alpha * slope| ~ 1e-13 here), so the
        # filter may reject every step while the KKT error, mostly dual, is still above tol. The
        # iteration then keeps the primal point and takes the multipliers of the Newton step
        # (their update is the part the filter cannot see); a second failure in a row stops.
        hold = ~ls_ok & (theta0 <= theta_min) & ~st.held
        a_dual = jnp.where(hold, 1.0, alpha)
        entry = jnp.stack([(1 - 1e-5) * theta0, phi0 - 1e-8 * theta0])
        filt = jnp.where(ls_ok & ~f_type, jnp.concatenate([entry[None], filt[:-1]]), filt)
        # A failed line search far from feasibility: in the U-turns we traced, an iterate jammed
        # against the lane and steering bounds near the end: the linearised dynamics ask for a
        # step through a bound, the fraction to the boundary cuts it to 1e-4..1e-7, and no trial
        # reduces the violation enough. IPOPT leaves such a point by its restoration phase; we
        # restart instead: the primal point is pushed inside the bounds as the initial guess is
        # (bound_push), the bound multipliers restart on the central path (mu / slack), the
        # equality multipliers at 0, the filter empty. On 16 random goals around each task and
        # three seeds this took lc.solve from 132 to 144 of 144 problems; it changes nothing on
        # problems that converge without it (it acts only where they would have stopped). (A
        # hold needs theta0 <= theta_min, so the two never meet.)
        reset = ~ls_ok & (theta0 > theta_min) & (st.resets < MAX_RESETS)

        # A restart after the first also perturbs the controls within their bounds and rolls the
        # states out from them. From rest the snakeboard's linearisation has no authority over its
        # position: the Newton step is exactly zero, and a restart from the same point fails the
        # same way (reach from zero controls: five restarts in six iterations, dx = dv = 0 each
        # time). IPOPT leaves such a point through its restoration phase; a perturbation gives
        # the linearisation a direction: uniform, 0.25 of the bounds' half-width at the second
        # restart, growing by 0.25 at each further one.
        def perturbed(_):
            key = jax.random.fold_in(jax.random.PRNGKey(0), st.resets)
            v_p = fns.perturbation(st.v, key, 0.25 * st.resets.astype(dtype))
            return pushed(_rollout(fns, v_p)), v_p

        def continued(_):
            return jnp.where(reset, pushed(st.chi), st.chi + alpha * dchi), st.v + alpha * dv

        if fns.perturbation is None:  # restarts never perturb
            new_chi, new_v = continued(None)
        else:
            new_chi, new_v = jax.lax.cond(reset & (st.resets >= 1), perturbed, continued, None)
        sl_n, su_n = slacks(new_chi)
        zl = jnp.where(reset, mu / sl_n, st.zl + a_z * dzl)
        zu = jnp.where(reset, mu / su_n, st.zu + a_z * dzu)
        # keep the bound multipliers within IPOPT's kappa_Sigma corridor around mu / slack
        zl = jnp.where(has_lo, jnp.clip(zl, mu / (1e10 * sl_n), 1e10 * mu / sl_n), 0.0)
        zu = jnp.where(has_hi, jnp.clip(zu, mu / (1e10 * su_n), 1e10 * mu / su_n), 0.0)
        new = st._replace(
            chi=new_chi,
            v=new_v,
            y=jnp.where(reset, 0.0, st.y + a_dual * (sol.y - st.y)),
            nu=jnp.where(reset, 0.0, st.nu + a_dual * (sol.nu - st.nu)),
            zl=zl,
            zu=zu,
            mu=mu,
            theta_max=theta_max,
            filter=jnp.where(reset, jnp.inf, filt),
            delta_w=delta,
            resets=st.resets + reset.astype(jnp.int32),
            iteration=st.iteration + 1,
            held=hold,
        )
        finite = jnp.all(jnp.isfinite(new.chi)) & jnp.all(jnp.isfinite(new.v)) & jnp.all(jnp.isfinite(new.y))
        result = SOLVER_RESULTS.where(
            ~finite,
            SOLVER_RESULTS.nonfinite,
            SOLVER_RESULTS.where(
                ~reg_ok,
                SOLVER_RESULTS.regularization_failed,
                SOLVER_RESULTS.where(
                    ~ls_ok & ~hold & ~reset, SOLVER_RESULTS.line_search_failed, SOLVER_RESULTS.max_iterations
                ),
            ),
        )
        if options.verbose:
            jax.debug.print(
                "it {i:3d} mu {mu:.1e} err {e:.2e} theta {t:.2e} delta {dl:.1e} "
                "alpha {a:.2e} amax {am:.2e} ls {ls}",
                i=st.iteration,
                mu=mu,
                e=st.error,
                t=theta0,
                dl=delta,
                a=alpha,
                am=a_max,
                ls=ls_ok,
            )
        new = jax.tree_util.tree_map(lambda a, b: jnp.where(finite, a, b), new, st)
        return new._replace(result=result)

    def cond(st: IPMState):
        return (st.result == SOLVER_RESULTS.max_iterations) & (st.iteration < options.max_iterations)

    sr1 = options.hessian == "sr1"

    def body(st: IPMState):
        d = _derivatives(fns, st, jnp.asarray(options.exact_hessian_tol, dtype), sr1)
        if sr1:
            exact = _theta(d.defects, d.cK) <= options.exact_hessian_tol
            # learn the constraints' curvature from the change of their Jacobians along the step
            chi_o, v_o, Z_o, C_o = st.previous
            w_new = jnp.concatenate([st.chi[:-1], st.v[1:]], axis=1)
            w_old = jnp.concatenate([chi_o[:-1], v_o[1:]], axis=1)
            dgrad = jnp.einsum("jab,ja->jb", d.Z[1:] - Z_o[1:], st.y[1:])
            first = st.iteration > 0
            curv = jnp.where(first, jax.vmap(_sr1)(st.curvature, w_new - w_old, dgrad), st.curvature)
            curv_K = jnp.where(
                first, _sr1(st.curvature_K, st.chi[-1] - chi_o[-1], (d.CK - C_o).T @ st.nu), st.curvature_K
            )
            st = st._replace(curvature=curv, curvature_K=curv_K, previous=(st.chi, st.v, d.Z, d.CK))
            d = d._replace(
                W=d.W.at[1:].add(jnp.where(exact, curv, 0.0)), QK=d.QK + jnp.where(exact, curv_K, 0.0)
            )
        parts = _kkt_parts(st, d, lo, hi)
        e0 = _kkt_error(parts, st, lo, hi, zero)
        done = e0 <= tol
        stepped = step(st, d, parts)
        st = jax.tree_util.tree_map(lambda a, b: jnp.where(done, a, b), st, stepped)
        st = st._replace(error=e0, violation=parts[1])
        return st._replace(result=SOLVER_RESULTS.where(done, SOLVER_RESULTS.successful, st.result))

    return jax.lax.while_loop(cond, body, st)
