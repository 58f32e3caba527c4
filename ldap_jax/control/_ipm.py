"""A primal-dual interior-point method for discrete optimal control, jitted end to end.

The problem (built from a :class:`~ldap_jax.control.Task` by :mod:`._problem`), with the node
controls carried in an augmented state so that the dynamics ``x_{k+1} = f(x_k, u_k, u_{k+1})``
take the stage form of optimal control: ``chi_j = (x_{j-1}, u_{j-1})``, control ``v_j = u_j``,

    min   sum_{j=1}^{K} l(chi_j) + l_K(chi_K)
    s.t.  chi_{j+1} = F_j(chi_j, v_j)  (j = 0 .. K-1, chi_0 fixed),   c(chi_K) = 0,
          lo <= chi_j <= hi  (j = 1 .. K),

``K = N + 1``. Multiple shooting: every ``chi_j`` and ``v_j`` is a variable and the dynamics are
equality constraints, so the dynamics and their derivatives are evaluated for all stages at once
(``vmap``), and only the Riccati recursion of :mod:`._riccati` is sequential.

One iteration (Wachter and Biegler's IPOPT, simplified): the Newton step of the barrier problem
``min f - mu sum log(slacks)`` with the exact Hessian of the Lagrangian (second derivatives of
the integrator's step by automatic differentiation) plus the barrier's ``Sigma = zeta / slack``,
solved by the Riccati recursion; if its reduced Hessian is not positive definite, ``delta_w I``
is added and the solve repeated (inertia correction); the fraction-to-the-boundary rule keeps
the iterates strictly inside the bounds; a backtracking line search on the exact l1 merit
function ``f_mu + rho |constraints|_1`` globalises; ``mu`` decreases superlinearly
(``mu <- min(0.2 mu, mu^1.5)``) once the barrier problem is solved to ``10 mu``. It stops when the
scaled KKT error (dual infeasibility, constraint violation, complementarity) is below ``tol``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ._riccati import QP, riccati_solve

__all__ = ["SOLVER_RESULTS", "IPMOptions", "IPMState", "ipm_solve", "OCPFunctions"]


class SOLVER_RESULTS(eqx.Enumeration):
    """Why :func:`~ldap_jax.control.solve` stopped."""

    successful = ""
    max_iterations = "the iteration budget ran out before the KKT error met the tolerance"
    line_search_failed = (
        "the line search found no acceptable step (the problem may be infeasible from this guess, "
        "or badly scaled); try another initial guess"
    )
    nonfinite = "non-finite values in the iterates (an integrator failure along the trajectory?)"
    regularization_failed = "the Hessian could not be regularised to the right inertia"


class OCPFunctions(NamedTuple):
    """The problem in stage form: callables of one stage (vmapped by the solver)."""

    dynamics: Callable[[Array, Array], Array]  # (chi, v) -> next chi, for stages j >= 1
    first: Callable[[Array], Array]  # v_0 -> chi_1
    stage_cost: Callable[[Array], Array]  # chi -> scalar (stages 1..K)
    terminal_cost: Callable[[Array], Array]  # chi_K -> scalar (added to the stage cost of K)
    terminal: Callable[[Array], Array]  # chi_K -> (p,) equality residuals


class IPMOptions(NamedTuple):
    tol: float = 1e-8
    max_iterations: int = 200
    mu0: float = 0.1
    kappa_eps: float = 10.0
    tau_min: float = 0.99
    bound_push: float = 1e-2
    max_backtracks: int = 30
    rho_c: float = 1e4
    exact_hessian_tol: float = 1e-2
    filter_size: int = 64
    penalty_tol: float = float("inf")
    rho_t: float = 100.0
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
    iteration: Int[Array, ""]
    error: Float[Array, ""]
    result: SOLVER_RESULTS


def _lag_stage(fns: OCPFunctions, chi, v, y):
    return fns.stage_cost(chi) + y @ fns.dynamics(chi, v)


def _derivatives(fns: OCPFunctions, st: IPMState, kappa: Array):
    """Residuals, Jacobians and Hessian blocks of every stage."""
    chi, v, y = st.chi, st.v, st.y
    # stage 0: chi_1 = first(v_0) (linear in v_0 by construction)
    F0 = fns.first(v[0])
    B0 = jax.jacfwd(fns.first)(v[0])
    # stages 1 .. K-1: chi_{j+1} = dynamics(chi_j, v_j)
    chi_in, v_in, y_in = chi[:-1], v[1:], y[1:]
    F = jax.vmap(fns.dynamics)(chi_in, v_in)
    A, B = jax.vmap(jax.jacfwd(fns.dynamics, argnums=(0, 1)))(chi_in, v_in)
    n, m = chi.shape[1], v.shape[1]

    def hess(c, vv, yy):
        w = jnp.concatenate([c, vv])
        return jax.hessian(lambda w: _lag_stage(fns, w[:n], w[n:], yy))(w)

    H = jax.vmap(hess)(chi_in, v_in, kappa * y_in)
    g_chi = jax.vmap(jax.grad(fns.stage_cost))(chi_in)
    # terminal stage K
    chiK = chi[-1]
    term = lambda c: fns.stage_cost(c) + fns.terminal_cost(c)  # noqa: E731
    cK = fns.terminal(chiK)
    CK = jax.jacfwd(fns.terminal)(chiK)
    QK = jax.hessian(lambda c: term(c) + kappa * st.nu @ fns.terminal(c))(chiK)
    qK = jax.grad(term)(chiK)
    defects = jnp.concatenate([(F0 - chi[0])[None], F - chi[1:]])
    return dict(F0=F0, B0=B0, A=A, B=B, H=H, g=g_chi, cK=cK, CK=CK, QK=QK, qK=qK, defects=defects, n=n, m=m)


def _objective(fns, chi):
    return jnp.sum(jax.vmap(fns.stage_cost)(chi)) + fns.terminal_cost(chi[-1])


def _constraints(fns, chi, v):
    d0 = fns.first(v[0]) - chi[0]
    d = jax.vmap(fns.dynamics)(chi[:-1], v[1:]) - chi[1:]
    return jnp.concatenate([d0[None], d]), fns.terminal(chi[-1])


def _barrier(chi, lo, hi, mu):
    sl = jnp.where(jnp.isfinite(lo), chi - lo, 1.0)
    su = jnp.where(jnp.isfinite(hi), hi - chi, 1.0)
    return -mu * (jnp.sum(jnp.log(sl)) + jnp.sum(jnp.log(su)))


def _fraction_to_boundary(x, dx, lo, hi, tau):
    """Largest alpha in (0, 1] with x + alpha dx >= lo + (1 - tau)(x - lo) (and for hi)."""
    big = jnp.asarray(1.0, x.dtype)
    al = jnp.where(jnp.isfinite(lo) & (dx < 0), -tau * (x - lo) / jnp.where(dx < 0, dx, -1.0), big)
    au = jnp.where(jnp.isfinite(hi) & (dx > 0), tau * (hi - x) / jnp.where(dx > 0, dx, 1.0), big)
    return jnp.minimum(1.0, jnp.minimum(jnp.min(al), jnp.min(au)))


def _multiplier_step(z, dz, tau):
    a = jnp.where(dz < 0, -tau * z / jnp.where(dz < 0, dz, -1.0), 1.0)
    return jnp.minimum(1.0, jnp.min(a))


def _kkt_error(fns, st: IPMState, d, lo, hi, mu):
    """Scaled dual infeasibility, constraint violation and complementarity (IPOPT's E_mu)."""
    chi, y = st.chi, st.y
    # gradient of the Lagrangian w.r.t. chi_j (j = 1..K) and v_j (j = 0..K-1)
    g = jnp.concatenate([d["g"], (d["qK"])[None]])
    AT_y = jnp.concatenate([jnp.einsum("jab,ja->jb", d["A"], y[1:]), jnp.zeros((1, chi.shape[1]), chi.dtype)])
    gc = g + AT_y - y
    gc = gc.at[-1].add(d["CK"].T @ st.nu) - st.zl + st.zu
    gv = jnp.concatenate([(d["B0"].T @ y[0])[None], jnp.einsum("jab,ja->jb", d["B"], y[1:])])
    dual = jnp.maximum(jnp.max(jnp.abs(gc)), jnp.max(jnp.abs(gv)))
    primal = jnp.maximum(jnp.max(jnp.abs(d["defects"])), jnp.max(jnp.abs(d["cK"]), initial=0.0))
    sl = jnp.where(jnp.isfinite(lo), chi - lo, 0.0)
    su = jnp.where(jnp.isfinite(hi), hi - chi, 0.0)
    comp = jnp.maximum(jnp.max(jnp.abs(sl * st.zl - jnp.where(jnp.isfinite(lo), mu, 0.0))),
                       jnp.max(jnp.abs(su * st.zu - jnp.where(jnp.isfinite(hi), mu, 0.0))))
    n_mult = y.size + st.nu.size + st.zl.size
    s_d = jnp.maximum(1.0, (jnp.sum(jnp.abs(y)) + jnp.sum(jnp.abs(st.nu)) + jnp.sum(st.zl + st.zu)) / (100.0 * n_mult))
    s_c = jnp.maximum(1.0, jnp.sum(st.zl + st.zu) / (100.0 * st.zl.size))
    return jnp.maximum(jnp.maximum(dual / s_d, primal), comp / s_c), primal


def ipm_solve(
    fns: OCPFunctions, chi: Array, v: Array, lo: Array, hi: Array, options: IPMOptions
) -> IPMState:
    """Run the interior-point method from the primal guess ``(chi, v)``; ``lo``/``hi`` (n,) bound
    every ``chi_j`` (infinite entries: no bound)."""
    dtype = chi.dtype
    K, n = chi.shape
    m = v.shape[1]
    p = jax.eval_shape(fns.terminal, chi[-1]).shape[0]
    lo = jnp.broadcast_to(lo, chi.shape)
    hi = jnp.broadcast_to(hi, chi.shape)
    # push the guess strictly inside the bounds (IPOPT's bound_push)
    push = options.bound_push
    width = jnp.where(jnp.isfinite(lo) & jnp.isfinite(hi), hi - lo, jnp.inf)
    pl = jnp.minimum(push * jnp.maximum(1.0, jnp.abs(lo)), 0.5 * push * width)
    pu = jnp.minimum(push * jnp.maximum(1.0, jnp.abs(hi)), 0.5 * push * width)
    chi = jnp.where(jnp.isfinite(lo), jnp.maximum(chi, lo + pl), chi)
    chi = jnp.where(jnp.isfinite(hi), jnp.minimum(chi, hi - pu), chi)
    mu0 = jnp.asarray(options.mu0, dtype)
    zl = jnp.where(jnp.isfinite(lo), mu0 / jnp.where(jnp.isfinite(lo), chi - lo, 1.0), 0.0)
    zu = jnp.where(jnp.isfinite(hi), mu0 / jnp.where(jnp.isfinite(hi), hi - chi, 1.0), 0.0)
    zero = jnp.zeros((), dtype)
    st = IPMState(
        chi=chi,
        v=v,
        y=jnp.zeros((K, n), dtype),
        nu=jnp.zeros((p,), dtype),
        zl=zl,
        zu=zu,
        mu=mu0,
        theta_max=jnp.asarray(jnp.inf, dtype),
        filter=jnp.full((options.filter_size, 2), jnp.inf, dtype),
        delta_w=zero,
        iteration=jnp.zeros((), jnp.int32),
        error=jnp.asarray(jnp.inf, dtype),
        result=SOLVER_RESULTS.max_iterations,
    )
    tol = jnp.asarray(options.tol, dtype)
    eye_n = jnp.eye(n, dtype=dtype)

    def theta_phi(chi, v, mu):
        """Constraint violation (l1) and barrier objective at a trial point."""
        defects, cK = _constraints(fns, chi, v)
        theta = jnp.sum(jnp.abs(defects)) + jnp.sum(jnp.abs(cK))
        return theta, _objective(fns, chi) + _barrier(chi, lo, hi, mu)

    def iteration(st: IPMState, d) -> IPMState:
        mu = st.mu
        # barrier update (possibly several times) once the barrier problem is solved to kappa mu
        def mu_cond(c):
            mu_, _ = c
            e_mu, _ = _kkt_error(fns, st, d, lo, hi, mu_)
            return (e_mu <= options.kappa_eps * mu_) & (mu_ > tol / 10)

        def mu_body(c):
            mu_, k = c
            return jnp.maximum(tol / 10, jnp.minimum(0.2 * mu_, mu_**1.5)), k + 1

        mu, _ = jax.lax.while_loop(mu_cond, mu_body, (mu, jnp.zeros((), jnp.int32)))
        sl = jnp.where(jnp.isfinite(lo), st.chi - lo, 1.0)
        su = jnp.where(jnp.isfinite(hi), hi - st.chi, 1.0)
        sigma = jnp.where(jnp.isfinite(lo), st.zl / sl, 0.0) + jnp.where(jnp.isfinite(hi), st.zu / su, 0.0)
        grad_barrier = jnp.where(jnp.isfinite(lo), -mu / sl, 0.0) + jnp.where(jnp.isfinite(hi), mu / su, 0.0)
        g = jnp.concatenate([d["g"], d["qK"][None]]) + grad_barrier
        Hs = d["H"]
        Qs = Hs[:, :n, :n]
        Ss = Hs[:, n:, :n]
        Rs = Hs[:, n:, n:]
        # stage 0 has no state variable and a linear map; its rows are the first of the QP
        zq = jnp.zeros((1, n, n), dtype)

        def build(delta):
            Q = jnp.concatenate([zq, Qs + jax.vmap(jnp.diag)(sigma[:-1]) + delta * eye_n])
            S = jnp.concatenate([jnp.zeros((1, m, n), dtype), Ss])
            R = jnp.concatenate([jnp.zeros((1, m, m), dtype), Rs]) + delta * jnp.eye(m, dtype=dtype)
            q = jnp.concatenate([jnp.zeros((1, n), dtype), g[:-1]])
            A = jnp.concatenate([zq, d["A"]])
            B = jnp.concatenate([d["B0"][None], d["B"]])
            # rho_c C^T C: free in the QP (C dx_K = -c holds exactly) but makes the terminal
            # directions positively curved, so the stagewise test below is the right inertia test
            QK = d["QK"] + jnp.diag(sigma[-1]) + delta * eye_n + options.rho_c * d["CK"].T @ d["CK"]
            # far from the terminal constraint, a quadratic penalty instead of the equality
            # (the step then trades the constraint against the objective and the bounds)
            CK = jnp.where(penalty_mode, 0.0, d["CK"])
            cK = jnp.where(penalty_mode, 0.0, d["cK"])
            qK = g[-1] + jnp.where(penalty_mode, options.rho_t * d["CK"].T @ d["cK"], 0.0)
            QK = QK + jnp.where(penalty_mode, options.rho_t * d["CK"].T @ d["CK"], 0.0)
            return QP(Q=Q, S=S, R=R, q=q, r=jnp.zeros((K, m), dtype), A=A, B=B, e=d["defects"],
                      QK=QK, qK=qK, C=CK, c=cK)

        penalty_mode = jnp.max(jnp.abs(d["cK"]), initial=0.0) > options.penalty_tol
        delta_c = jnp.where(jnp.max(jnp.abs(d["cK"]), initial=0.0) >= 0, 1e-10, 0.0).astype(dtype)

        def reg_cond(c):
            delta, sol, tries = c
            return (~sol.positive | ~jnp.all(jnp.isfinite(sol.dx))) & (tries < 40)

        def reg_body(c):
            delta, _, tries = c
            delta = jnp.where(delta == 0, jnp.maximum(1e-4, st.delta_w / 3), 8.0 * delta)
            return delta, riccati_solve(build(delta), delta_c), tries + 1

        sol0 = riccati_solve(build(zero), delta_c)
        delta, sol, tries = jax.lax.while_loop(reg_cond, reg_body, (zero, sol0, jnp.zeros((), jnp.int32)))
        reg_ok = sol.positive & jnp.all(jnp.isfinite(sol.dx))
        dchi, dv = sol.dx[1:], sol.dv
        # bound multipliers: zeta + dzeta = mu / s - Sigma ds
        dzl = jnp.where(jnp.isfinite(lo), mu / sl - st.zl - st.zl / sl * dchi, 0.0)
        dzu = jnp.where(jnp.isfinite(hi), mu / su - st.zu + st.zu / su * dchi, 0.0)
        tau = jnp.maximum(options.tau_min, 1.0 - mu)
        a_max = _fraction_to_boundary(st.chi, dchi, lo, hi, tau)
        a_z = jnp.minimum(_multiplier_step(st.zl, dzl, tau), _multiplier_step(st.zu, dzu, tau))
        # line search with the acceptance test of IPOPT's filter method (without the filter's
        # memory): sufficient decrease of the violation theta or of the barrier objective phi,
        # and an Armijo decrease of phi when theta is small and the step is a descent step for phi
        theta0 = jnp.sum(jnp.abs(d["defects"])) + jnp.sum(jnp.abs(d["cK"]))
        phi0 = _objective(fns, st.chi) + _barrier(st.chi, lo, hi, mu)
        slope = jnp.sum(g * dchi)
        theta_max = jnp.where(jnp.isfinite(st.theta_max), st.theta_max, 1e4 * jnp.maximum(1.0, theta0))
        theta_min = 1e-4 * jnp.maximum(1.0, theta_max / 1e4)

        # the filter (reset when mu changes): a trial point must not be dominated by any entry
        filt = jnp.where(mu == st.mu, st.filter, jnp.inf)

        def acceptable(alpha):
            theta, phi = theta_phi(st.chi + alpha * dchi, st.v + alpha * dv, mu)
            switching = (slope < 0) & (alpha * (-slope) ** 2.3 > theta0**1.1)
            armijo = phi <= phi0 + 1e-4 * alpha * slope
            f_type = (theta0 <= theta_min) & switching
            h_ok = (theta <= (1 - 1e-5) * theta0) | (phi <= phi0 - 1e-8 * theta0)
            in_filter = jnp.any((theta >= (1 - 1e-5) * filt[:, 0]) & (phi >= filt[:, 1] - 1e-8 * filt[:, 0]))
            ok = jnp.where(f_type, armijo, h_ok) & (theta <= theta_max) & ~in_filter
            return ok & jnp.isfinite(theta) & jnp.isfinite(phi), f_type

        def ls_cond(c):
            alpha, k, ok = c
            return (~ok) & (k < options.max_backtracks)

        def ls_body(c):
            alpha, k, _ = c
            alpha = jnp.where(k == 0, alpha, 0.5 * alpha)
            return alpha, k + 1, acceptable(alpha)[0]

        alpha, _, ls_ok = jax.lax.while_loop(ls_cond, ls_body, (a_max, jnp.zeros((), jnp.int32), jnp.zeros((), bool)))
        alpha = jnp.where(ls_ok, alpha, 0.0)
        # augment the filter after a step that was not an f-type (Armijo) step
        _, f_type = acceptable(alpha)
        entry = jnp.stack([(1 - 1e-5) * theta0, phi0 - 1e-8 * theta0])
        augmented = jnp.concatenate([entry[None], filt[:-1]])
        filt = jnp.where(ls_ok & ~f_type, augmented, filt)
        new = IPMState(
            chi=st.chi + alpha * dchi,
            v=st.v + alpha * dv,
            y=st.y + alpha * (sol.y - st.y),
            nu=st.nu + alpha * (sol.nu - st.nu),
            zl=st.zl + a_z * dzl,
            zu=st.zu + a_z * dzu,
            mu=mu,
            theta_max=theta_max,
            filter=filt,
            delta_w=delta,
            iteration=st.iteration + 1,
            error=st.error,
            result=st.result,
        )
        # keep the bound multipliers within IPOPT's kappa_Sigma corridor of mu / slack
        sl_n = jnp.where(jnp.isfinite(lo), new.chi - lo, 1.0)
        su_n = jnp.where(jnp.isfinite(hi), hi - new.chi, 1.0)
        zl = jnp.where(jnp.isfinite(lo), jnp.clip(new.zl, mu / (1e10 * sl_n), 1e10 * mu / sl_n), 0.0)
        zu = jnp.where(jnp.isfinite(hi), jnp.clip(new.zu, mu / (1e10 * su_n), 1e10 * mu / su_n), 0.0)
        new = new._replace(zl=zl, zu=zu)
        finite = jnp.all(jnp.isfinite(new.chi)) & jnp.all(jnp.isfinite(new.v))
        result = SOLVER_RESULTS.where(
            ~finite,
            SOLVER_RESULTS.nonfinite,
            SOLVER_RESULTS.where(
                ~reg_ok,
                SOLVER_RESULTS.regularization_failed,
                SOLVER_RESULTS.where(~ls_ok, SOLVER_RESULTS.line_search_failed, SOLVER_RESULTS.max_iterations),
            ),
        )
        new = new._replace(result=result)
        if options.verbose:
            jax.debug.print(
                "it {i:3d} mu {mu:.1e} err {e:.2e} theta {p:.2e} delta {dl:.1e} alpha {a:.2e} amax {am:.2e} az {az:.2e} ls {ls} phi0 {phi:.6e} slope {sl:.2e} ymax {ym:.1e}",
                i=st.iteration, mu=mu, e=st.error, p=theta0, dl=delta, a=alpha, am=a_max, az=a_z, ls=ls_ok, phi=phi0, sl=slope, ym=jnp.max(jnp.abs(new.y)),
            )
        return jax.tree_util.tree_map(lambda a, b: jnp.where(finite, a, b), new, st._replace(result=result))

    def cond(st: IPMState):
        running = st.result == SOLVER_RESULTS.max_iterations
        return running & (st.iteration < options.max_iterations)

    def body(st: IPMState):
        theta, _ = theta_phi(st.chi, st.v, st.mu)
        kappa = (theta <= options.exact_hessian_tol).astype(dtype)
        d = _derivatives(fns, st, kappa)
        e0, _ = _kkt_error(fns, st, d, lo, hi, jnp.zeros((), dtype))
        done = e0 <= tol
        stepped = iteration(st, d)
        st = jax.tree_util.tree_map(lambda a, b: jnp.where(done, a, b), st, stepped)
        return st._replace(error=e0, result=SOLVER_RESULTS.where(done, SOLVER_RESULTS.successful, st.result))

    return jax.lax.while_loop(cond, body, st)

