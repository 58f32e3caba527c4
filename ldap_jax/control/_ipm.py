"""A primal-dual interior-point method for discrete optimal control, jitted end to end.

It solves the stage form of :mod:`._kkt` (initial parameters ``p``, states ``chi_1 .. chi_K``,
controls ``v_1 .. v_{K-1}``, dynamics and terminal equalities, bounds on the states). One
iteration follows Wachter and Biegler's IPOPT (Math. Program. 106, 2006), simplified:

* the Newton step of the barrier problem ``min f - mu sum log(slacks)``, solved by the Riccati
  recursion of :mod:`._riccati`, with the Hessian of the Lagrangian: Gauss-Newton (the objective's
  and the barrier's curvature) while the constraint violation exceeds ``exact_hessian_tol``, then
  with the dynamics' curvature ``y^T F''`` (second derivatives by automatic differentiation, of
  ``OCPFunctions.curvature_dynamics`` where given: a cheaper step approximating ``F``), for fast
  local convergence; if its reduced Hessian is not positive definite, ``delta_w I`` is added and
  the solve repeated (inertia correction); up to two steps of iterative refinement (as IPOPT's)
  keep the residual of the solve below ``tol / 100``: near the solution the barrier makes the
  system ill-conditioned, and without them the KKT error stalled at 1e-9 to 2e-8 (the line search
  then fails), depending on how the code generation rounds;
* the fraction-to-the-boundary rule keeps the iterates strictly inside the bounds;
* a backtracking line search with IPOPT's filter (constraint violation ``theta``, barrier
  objective ``phi``) globalises;
* a line search that fails far from feasibility restarts the iteration from the current point
  pushed inside its bounds, with the multipliers reset; from the second restart on, the controls
  are also perturbed within their bounds and the states rolled out from them (at most
  ``MAX_RESETS`` restarts; a simple stand-in for IPOPT's feasibility restoration, see
  :func:`_next_point`);
* ``mu`` decreases superlinearly (``mu <- min(0.2 mu, mu^1.5)``) once the barrier problem is solved
  to ``10 mu``; the method stops when the scaled KKT error is below ``tol``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array

from ._ipm_state import MAX_RESETS, SOLVER_RESULTS, IPMOptions, IPMState, pushed
from ._ipm_state import Bounds as _Bounds
from ._ipm_state import Step as _Step
from ._kkt import (
    Derivatives,
    OCPFunctions,
    constraints,
    derivatives,
    dual_residuals,
    objective,
    rollout,
    theta,
)
from ._riccati import QPMatrices, QPVector, riccati_apply, riccati_factor

__all__ = ["SOLVER_RESULTS", "IPMOptions", "IPMState", "ipm_solve", "pushed", "MAX_RESETS"]


def _kkt_parts(st: IPMState, d: Derivatives, b: _Bounds):
    """Dual infeasibility (scaled), constraint violation (max norms), slacks and the
    complementarity scaling of IPOPT's KKT error."""
    gp, gc, gv = dual_residuals(d, st.y, st.nu, st.zl, st.zu)
    dual = jnp.maximum(
        jnp.max(jnp.abs(gc)),
        jnp.maximum(jnp.max(jnp.abs(gv), initial=0.0), jnp.max(jnp.abs(gp), initial=0.0)),
    )
    primal = jnp.maximum(jnp.max(jnp.abs(d.defects)), jnp.max(jnp.abs(d.cK), initial=0.0))
    sl = jnp.where(b.has_lo, st.chi - b.lo, 0.0)
    su = jnp.where(b.has_hi, b.hi - st.chi, 0.0)
    n_mult = st.y.size + st.nu.size + st.zl.size
    s_d = jnp.maximum(
        1.0, (jnp.sum(jnp.abs(st.y)) + jnp.sum(jnp.abs(st.nu)) + jnp.sum(st.zl + st.zu)) / (100.0 * n_mult)
    )
    s_c = jnp.maximum(1.0, jnp.sum(st.zl + st.zu) / (100.0 * st.zl.size))
    return dual / s_d, primal, sl, su, s_c


def _kkt_error(parts, st: IPMState, b: _Bounds, mu: Array) -> Array:
    """IPOPT's E_mu: the largest of the scaled dual infeasibility, the constraint violation and
    the scaled deviation from the barrier's complementarity ``s zeta = mu``."""
    dual, primal, sl, su, s_c = parts
    comp = jnp.maximum(
        jnp.max(jnp.abs(sl * st.zl - jnp.where(b.has_lo, mu, 0.0))),
        jnp.max(jnp.abs(su * st.zu - jnp.where(b.has_hi, mu, 0.0))),
    )
    return jnp.maximum(jnp.maximum(dual, primal), comp / s_c)


def _fraction_to_boundary(x, dx, lo, hi, tau):
    """Largest alpha in (0, 1] with ``x + alpha dx >= lo + (1 - tau)(x - lo)`` (and for ``hi``)."""
    al = jnp.where(jnp.isfinite(lo) & (dx < 0), -tau * (x - lo) / jnp.where(dx < 0, dx, -1.0), 1.0)
    au = jnp.where(jnp.isfinite(hi) & (dx > 0), tau * (hi - x) / jnp.where(dx > 0, dx, 1.0), 1.0)
    return jnp.minimum(1.0, jnp.minimum(jnp.min(al), jnp.min(au)))


def _multiplier_step(z, dz, tau):
    return jnp.minimum(1.0, jnp.min(jnp.where(dz < 0, -tau * z / jnp.where(dz < 0, dz, -1.0), 1.0)))


def _barrier_parameter(st: IPMState, parts, b: _Bounds, options: IPMOptions, tol: Array) -> Array:
    """``mu``, decreased (possibly several times) once the barrier problem is solved to
    ``kappa_eps mu``."""

    def cond(mu):
        return (_kkt_error(parts, st, b, mu) <= options.kappa_eps * mu) & (mu > tol / 10)

    return jax.lax.while_loop(cond, lambda mu: jnp.maximum(tol / 10, jnp.minimum(0.2 * mu, mu**1.5)), st.mu)


def _newton_step(
    st: IPMState, d: Derivatives, b: _Bounds, mu: Array, options: IPMOptions, tol: Array
) -> _Step:
    """The regularised Newton step: the QP of :mod:`._riccati` with the barrier's curvature
    ``Sigma = zeta / slack``, factored with the smallest ``delta_w I`` that gives the right inertia."""
    K, n = st.chi.shape
    m = st.v.shape[1]
    s = st.p.shape[0]
    dtype = st.chi.dtype
    zero = jnp.zeros((), dtype)
    sl, su = b.slacks(st.chi)
    sigma = jnp.where(b.has_lo, st.zl / sl, 0.0) + jnp.where(b.has_hi, st.zu / su, 0.0)
    g = d.g + jnp.where(b.has_lo, -mu / sl, 0.0) + jnp.where(b.has_hi, mu / su, 0.0)
    W0 = d.W.at[:, :n, :n].add(jax.vmap(jnp.diag)(sigma[:-1]))
    # rho_c C^T C: free in the QP (C dx_K = -c holds exactly) but it curves the terminal
    # directions, so that the stagewise positive-definiteness test is the inertia test
    QK0 = d.QK + jnp.diag(sigma[-1]) + options.rho_c * d.CK.T @ d.CK
    rhs = QPVector(
        wp=jnp.zeros((s,), dtype),
        e0=d.defects[0],
        w=jnp.concatenate([g[:-1], d.gv], axis=1),
        e=d.defects[1:],
        qK=g[-1],
        c=d.cK,
    )

    def factor_with(delta):
        mat = QPMatrices(
            Wp=d.Wp + delta * jnp.eye(s, dtype=dtype),
            G=d.G,
            W=W0 + delta * jnp.eye(n + m, dtype=dtype)[None],
            Z=d.Z,
            QK=QK0 + delta * jnp.eye(n, dtype=dtype),
            C=d.CK,
        )
        return riccati_factor(mat, jnp.asarray(1e-10, dtype))

    def reg_cond(c):
        _, f, tries = c
        return (~f.positive | ~jnp.all(jnp.isfinite(f.CM_inv))) & (tries < 40)

    def reg_body(c):
        delta, _, tries = c
        delta = jnp.where(
            tries == 0, zero, jnp.where(delta == 0, jnp.maximum(1e-4, st.delta_w / 3), 8.0 * delta)
        )
        return delta, factor_with(delta), tries + 1

    empty = jax.tree_util.tree_map(lambda x: jnp.zeros(x.shape, x.dtype), jax.eval_shape(factor_with, zero))
    delta, fac, _ = jax.lax.while_loop(reg_cond, reg_body, (zero, empty, jnp.zeros((), jnp.int32)))
    # iterative refinement keeps the solve's residual, which enters the next iterate's KKT
    # error directly, two orders below the tolerance
    sol = riccati_apply(fac, rhs, refine=2, atol=1e-2 * tol)
    reg_ok = fac.positive & jnp.all(jnp.isfinite(sol.dx))
    # bound multipliers: zeta + dzeta = mu / s - Sigma ds
    dzl = jnp.where(b.has_lo, mu / sl - st.zl - st.zl / sl * sol.dx, 0.0)
    dzu = jnp.where(b.has_hi, mu / su - st.zu + st.zu / su * sol.dx, 0.0)
    del K
    return _Step(mu=mu, sol=sol, delta=delta, reg_ok=reg_ok, g=g, dzl=dzl, dzu=dzu)


def _barrier_objective(fns: OCPFunctions, b: _Bounds, chi: Array, v: Array, mu: Array) -> Array:
    return objective(fns, chi, v) - mu * b.log_barrier(chi)


def _line_search(fns, st: IPMState, d: Derivatives, b: _Bounds, step: _Step, options: IPMOptions):
    """Backtracking from the fraction to the boundary with IPOPT's filter acceptance test.
    Returns ``(alpha, accepted, f_type, theta0, phi0, filter, theta_max)``."""
    dtype = st.chi.dtype
    mu, sol = step.mu, step.sol
    tau = jnp.maximum(options.tau_min, 1.0 - mu)
    a_max = _fraction_to_boundary(st.chi, sol.dx, b.lo, b.hi, tau)
    theta0 = theta(d.defects, d.cK)
    phi0 = d.f - mu * b.log_barrier(st.chi)  # the barrier objective at the current point
    slope = jnp.sum(step.g * sol.dx) + jnp.sum(d.gv * sol.dv)
    theta_max = jnp.where(jnp.isfinite(st.theta_max), st.theta_max, 1e4 * jnp.maximum(1.0, theta0))
    theta_min = 1e-4 * jnp.maximum(1.0, theta_max / 1e4)
    filt = jnp.where(mu == st.mu, st.filter, jnp.inf)  # reset when mu changes
    # comparisons of phi allow its round-off (IPOPT's Compare_le, 10 eps |phi0|): near the
    # solution the decrease alpha * slope falls below it, and a strict test rejects every step
    slack = 10 * jnp.finfo(dtype).eps * jnp.abs(phi0)

    def trial(alpha):
        p, chi, v = st.p + alpha * sol.dp, st.chi + alpha * sol.dx, st.v + alpha * sol.dv
        th = theta(*constraints(fns, p, chi, v))
        phi = _barrier_objective(fns, b, chi, v, mu)
        switching = (slope < 0) & (alpha * (-slope) ** 2.3 > theta0**1.1)
        f_type = (theta0 <= theta_min) & switching
        armijo = phi <= phi0 + 1e-4 * alpha * slope + slack
        h_ok = (th <= (1 - 1e-5) * theta0) | (phi <= phi0 - 1e-8 * theta0 + slack)
        in_filter = jnp.any((th >= (1 - 1e-5) * filt[:, 0]) & (phi >= filt[:, 1] - 1e-8 * filt[:, 0]))
        ok = jnp.where(f_type, armijo, h_ok) & (th <= theta_max) & ~in_filter
        return ok & jnp.isfinite(th) & jnp.isfinite(phi), f_type

    def ls_cond(c):
        _, k, ok, _ = c
        return (~ok) & (k < options.max_backtracks)

    def ls_body(c):
        alpha, k, _, _ = c
        alpha = jnp.where(k == 0, alpha, 0.5 * alpha)
        ok, f_type = trial(alpha)
        return alpha, k + 1, ok, f_type

    false = jnp.zeros((), bool)
    alpha, _, ok, f_type = jax.lax.while_loop(
        ls_cond, ls_body, (a_max, jnp.zeros((), jnp.int32), false, false)
    )
    entry = jnp.stack([(1 - 1e-5) * theta0, phi0 - 1e-8 * theta0])
    filt = jnp.where(ok & ~f_type, jnp.concatenate([entry[None], filt[:-1]]), filt)
    return jnp.where(ok, alpha, 0.0), ok, theta0 <= theta_min, filt, theta_max


def _next_point(fns, st: IPMState, b: _Bounds, step: _Step, alpha, ok, feasible, options: IPMOptions):
    """The next primal point and the multipliers' step length.

    At a feasible point near the solution the barrier objective and the violation change by less
    than their round-off along the step, so the filter may reject every step while the KKT error,
    mostly dual, is still above tol. The iteration then keeps the primal point and takes the
    multipliers of the Newton step (*hold*; a second failure in a row stops).

    A line search that fails far from feasibility (an iterate jammed against bounds, the
    linearised dynamics asking for a step through one) restarts instead (*reset*): the primal point
    is pushed inside the bounds as the initial guess is, the bound multipliers restart on the
    central path, the equality multipliers at 0, the filter empty. From the second restart on the
    controls are also perturbed within their bounds and the states rolled out from them: from rest
    the snakeboard's linearisation has no authority over its position and the Newton step is
    exactly zero, so a restart from the same point fails the same way (uniform noise, 0.25 of the
    bounds' half-width at the second restart, growing by 0.25 at each further one). IPOPT leaves
    such points through its feasibility restoration phase; this is a simple stand-in.
    """
    dtype = st.chi.dtype
    sol = step.sol
    hold = ~ok & feasible & ~st.held
    reset = ~ok & ~feasible & (st.resets < MAX_RESETS)

    def push(c):
        return pushed(c, b.lo, b.hi, options.bound_push)

    def perturbed(_):
        key = jax.random.fold_in(jax.random.PRNGKey(0), st.resets)
        p, v = fns.perturbation(st.p, st.v, key, 0.25 * st.resets.astype(dtype))
        return p, push(rollout(fns, p, v)), v

    def continued(_):
        chi = jnp.where(reset, push(st.chi), st.chi + alpha * sol.dx)
        return st.p + alpha * sol.dp, chi, st.v + alpha * sol.dv

    if fns.perturbation is None:  # restarts never perturb
        p, chi, v = continued(None)
    else:
        p, chi, v = jax.lax.cond(reset & (st.resets >= 1), perturbed, continued, None)
    return p, chi, v, hold, reset


def _iterate(
    fns, st: IPMState, d: Derivatives, parts, b: _Bounds, options: IPMOptions, tol: Array
) -> IPMState:
    """One interior-point iteration from ``st`` with its derivatives ``d``."""
    mu = _barrier_parameter(st, parts, b, options, tol)
    step = _newton_step(st, d, b, mu, options, tol)
    alpha, ok, feasible, filt, theta_max = _line_search(fns, st, d, b, step, options)
    p, chi, v, hold, reset = _next_point(fns, st, b, step, alpha, ok, feasible, options)
    tau = jnp.maximum(options.tau_min, 1.0 - mu)
    a_z = jnp.minimum(_multiplier_step(st.zl, step.dzl, tau), _multiplier_step(st.zu, step.dzu, tau))
    a_dual = jnp.where(hold, 1.0, alpha)
    sl, su = b.slacks(chi)
    zl = jnp.where(reset, mu / sl, st.zl + a_z * step.dzl)
    zu = jnp.where(reset, mu / su, st.zu + a_z * step.dzu)
    # keep the bound multipliers within IPOPT's kappa_Sigma corridor around mu / slack
    zl = jnp.where(b.has_lo, jnp.clip(zl, mu / (1e10 * sl), 1e10 * mu / sl), 0.0)
    zu = jnp.where(b.has_hi, jnp.clip(zu, mu / (1e10 * su), 1e10 * mu / su), 0.0)
    new = st._replace(
        p=p,
        chi=chi,
        v=v,
        y=jnp.where(reset, 0.0, st.y + a_dual * (step.sol.y - st.y)),
        nu=jnp.where(reset, 0.0, st.nu + a_dual * (step.sol.nu - st.nu)),
        zl=zl,
        zu=zu,
        mu=mu,
        theta_max=theta_max,
        filter=jnp.where(reset, jnp.inf, filt),
        delta_w=step.delta,
        resets=st.resets + reset.astype(jnp.int32),
        iteration=st.iteration + 1,
        held=hold,
    )
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in (new.p, new.chi, new.v, new.y)]))
    result = SOLVER_RESULTS.where(
        ~finite,
        SOLVER_RESULTS.nonfinite,
        SOLVER_RESULTS.where(
            ~step.reg_ok,
            SOLVER_RESULTS.regularization_failed,
            SOLVER_RESULTS.where(~ok & ~hold & ~reset, _failure(st, feasible), SOLVER_RESULTS.max_iterations),
        ),
    )
    if options.verbose:
        jax.debug.print(
            "it {i:3d} mu {mu:.1e} err {e:.2e} theta {t:.2e} delta {dl:.1e} alpha {a:.2e} ls {ls} "
            "|y| {ym:.1e} |nu| {nm:.1e} f {f:.4e} reg {ro}",
            ym=jnp.max(jnp.abs(st.y)),
            nm=jnp.max(jnp.abs(st.nu), initial=0.0),
            f=objective(fns, st.chi, st.v),
            ro=step.reg_ok,
            i=st.iteration,
            mu=mu,
            e=st.error,
            t=theta(d.defects, d.cK),
            dl=step.delta,
            a=alpha,
            ls=ok,
        )
    new = jax.tree_util.tree_map(lambda a, c: jnp.where(finite, a, c), new, st)
    return new._replace(result=result)


def _failure(st: IPMState, feasible: Array) -> SOLVER_RESULTS:
    """A line search that failed for good: far from feasibility after every restart the
    constraints could not be met (infeasible); near it, no acceptable step."""
    return SOLVER_RESULTS.where(
        ~feasible & (st.resets >= MAX_RESETS), SOLVER_RESULTS.infeasible, SOLVER_RESULTS.line_search_failed
    )


def initial_state(
    fns: OCPFunctions, p: Array, chi: Array, v: Array, b: _Bounds, options: IPMOptions
) -> IPMState:
    K, n = chi.shape
    dtype = chi.dtype
    chi = pushed(chi, b.lo, b.hi, options.bound_push)
    n_c = jax.eval_shape(fns.terminal, chi[-1]).shape[0]
    mu0 = jnp.asarray(options.mu0, dtype)
    sl, su = b.slacks(chi)
    return IPMState(
        p=p,
        chi=chi,
        v=v,
        y=jnp.zeros((K, n), dtype),
        nu=jnp.zeros((n_c,), dtype),
        zl=jnp.where(b.has_lo, mu0 / sl, 0.0),
        zu=jnp.where(b.has_hi, mu0 / su, 0.0),
        mu=mu0,
        theta_max=jnp.asarray(jnp.inf, dtype),
        filter=jnp.full((options.filter_size, 2), jnp.inf, dtype),
        delta_w=jnp.zeros((), dtype),
        iteration=jnp.zeros((), jnp.int32),
        error=jnp.asarray(jnp.inf, dtype),
        violation=jnp.asarray(jnp.inf, dtype),
        held=jnp.zeros((), bool),
        resets=jnp.zeros((), jnp.int32),
        result=SOLVER_RESULTS.max_iterations,
        stopped=jnp.zeros((), bool),
    )


def ipm_solve(
    fns: OCPFunctions, p: Array, chi: Array, v: Array, lo: Array, hi: Array, options: IPMOptions
) -> IPMState:
    """Run the interior-point method from the primal guess ``(p, chi, v)``; ``lo``/``hi`` (n,)
    bound every ``chi_j`` (infinite entries: no bound)."""
    dtype = chi.dtype
    b = _Bounds(jnp.broadcast_to(lo, chi.shape), jnp.broadcast_to(hi, chi.shape))
    st = initial_state(fns, p, chi, v, b, options)
    tol = jnp.asarray(options.tol, dtype)
    zero = jnp.zeros((), dtype)

    def cond(st: IPMState):
        return ~st.stopped

    def body(st: IPMState):
        # every pass evaluates the current point; the loop stops after the pass that finds it
        # optimal, or after the pass that follows a failed step or the last iteration: the
        # returned point's KKT error and violation are always its own
        d = derivatives(fns, st.p, st.chi, st.v, st.y, st.nu, jnp.asarray(options.exact_hessian_tol, dtype))
        parts = _kkt_parts(st, d, b)
        e0 = _kkt_error(parts, st, b, zero)
        ended = (st.result != SOLVER_RESULTS.max_iterations) | (st.iteration >= options.max_iterations)
        done = ~ended & (e0 <= tol)
        stop = ended | done
        stepped = _iterate(fns, st, d, parts, b, options, tol)
        # no acceptable step at a point within round-off of optimal (the KKT error within 100 tol,
        # or below the default tol: 1e-8 in float64, 1e-5 in float32): stalled, not a search failure
        near = jnp.maximum(100 * tol, 1e-5 if tol.dtype == jnp.float32 else 1e-8)
        stalled = (stepped.result == SOLVER_RESULTS.line_search_failed) & (e0 <= near) & (parts[1] <= near)
        result = SOLVER_RESULTS.where(stalled, SOLVER_RESULTS.stalled, stepped.result)
        stepped = stepped._replace(result=result)
        st = jax.tree_util.tree_map(lambda a, c: jnp.where(stop, a, c), st, stepped)
        st = st._replace(error=e0, violation=parts[1], stopped=stop)
        return st._replace(result=SOLVER_RESULTS.where(done, SOLVER_RESULTS.successful, st.result))

    return jax.lax.while_loop(cond, body, st)
