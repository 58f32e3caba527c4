"""Sensitivities of an optimum by the implicit function theorem.

At a solution of the barrier problem the KKT conditions ``G(z, lambda; theta) = 0`` hold (``z``
the primal variables ``(p, chi, v)``, ``lambda`` the equality multipliers, the bound multipliers
eliminated as ``zeta = (zeta s) / s`` with each bound's complementarity ``zeta s`` held at its value
at the returned point, so that ``Sigma = zeta / s`` below is the same in the matrix and in the
right-hand side). Their derivative with respect to the task's arrays
``theta`` (model parameters, goal, bounds, period) gives::

    [[W + Sigma, J^T], [J, 0]] (dz, dlambda) = -(d_theta grad L, d_theta c) dtheta,

the same structured system as a Newton step, solved by the same Riccati recursion with the exact
Hessian of the Lagrangian at the solution. Forward mode computes it; reverse mode transposes it
(the map from the right-hand side to the step is linear). The tangents of a solve that did not
converge are NaN: the implicit function theorem holds only at a solution.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ._ipm import SOLVER_RESULTS, IPMState
from ._kkt import constraints, derivatives, objective
from ._riccati import QPMatrices, QPVector, riccati_apply, riccati_factor

__all__ = ["optimum"]


def _setup(task):
    from ._solve import setup

    return setup(task)


@eqx.filter_custom_jvp
def optimum(task, st: IPMState):
    """The optimum ``(p, chi, v, cost)`` of a run; its derivatives with respect to the task's
    arrays come from the implicit function theorem (module docstring)."""
    _, fns, _, _, _ = _setup(task)
    return st.p, st.chi, st.v, objective(fns, st.chi, st.v)


def _barrier(lo, hi, chi):
    sl = jnp.where(jnp.isfinite(lo), chi - lo, 1.0)
    su = jnp.where(jnp.isfinite(hi), hi - chi, 1.0)
    return sl, su


@optimum.def_jvp
def _optimum_jvp(primals, tangents):
    task, st = primals
    t_task, _ = tangents
    out = optimum(task, st)
    if t_task is None:
        return out, jax.tree_util.tree_map(jnp.zeros_like, out)
    diff, static = eqx.partition(task, eqx.is_inexact_array)
    t_diff = jax.tree_util.tree_map(
        lambda x, t: None if x is None else (jnp.zeros_like(x) if t is None else t),
        diff,
        t_task,
        is_leaf=lambda x: x is None,
    )
    p, chi, v, _ = out
    # each bound's barrier weighted by its own complementarity z s at the returned point (not the
    # barrier parameter mu): then the tangent of the barrier's gradient, (z / s) d(bound), has the
    # coefficient Sigma = z / s of the matrix (_ift_step), and an active bound moves the optimum
    # with it exactly. With mu, a final iterate whose z s had drifted from mu (1e-12 and tighter
    # tolerances) moved it by mu / (z s) of that: d(cost)/d(bound) 3e-4 off at tol=1e-12.
    _, _, lo0, hi0, _ = _setup(task)
    sl0, su0 = _barrier(jnp.broadcast_to(lo0, chi.shape), jnp.broadcast_to(hi0, chi.shape), chi)
    wl, wu = jax.lax.stop_gradient((st.zl * sl0, st.zu * su0))

    def residuals(diff_):
        _, fns_, lo_, hi_, _ = _setup(eqx.combine(diff_, static))
        lo_, hi_ = jnp.broadcast_to(lo_, chi.shape), jnp.broadcast_to(hi_, chi.shape)

        def lagrangian(p_, chi_, v_):
            defects, cK = constraints(fns_, p_, chi_, v_)
            sl, su = _barrier(lo_, hi_, chi_)
            barrier = -(
                jnp.sum(jnp.where(jnp.isfinite(lo_), wl * jnp.log(sl), 0.0))
                + jnp.sum(jnp.where(jnp.isfinite(hi_), wu * jnp.log(su), 0.0))
            )
            f = objective(fns_, chi_, v_) + barrier
            return f + jnp.sum(st.y * defects) + st.nu @ cK, (defects, cK)

        grads, (defects, cK) = jax.grad(lagrangian, argnums=(0, 1, 2), has_aux=True)(p, chi, v)
        return grads, defects, cK

    _, ((r_p, r_chi, r_v), e, c) = jax.jvp(residuals, (diff,), (t_diff,))
    dp, dchi, dv = _ift_step(
        task,
        st,
        QPVector(wp=r_p, e0=e[0], w=jnp.concatenate([r_chi[:-1], r_v], axis=1), e=e[1:], qK=r_chi[-1], c=c),
    )

    def cost(chi_, v_, diff_):
        _, fns_, _, _, _ = _setup(eqx.combine(diff_, static))
        return objective(fns_, chi_, v_)

    _, dcost = jax.jvp(cost, (chi, v, diff), (dchi, dv, t_diff))
    # a failed solve: NaN tangents (every loss that reads it sees the failure)
    flag = jnp.where(st.result == SOLVER_RESULTS.successful, 1.0, jnp.nan).astype(chi.dtype)
    return out, (flag * dp, flag * dchi, flag * dv, flag * dcost)


def _ift_step(task, st: IPMState, rhs: QPVector):
    """The Riccati solve of the KKT system at the solution with the right-hand side ``rhs``."""
    _, fns, lo, hi, _ = _setup(task)
    chi = st.chi
    n = chi.shape[1]
    dtype = chi.dtype
    lo, hi = jnp.broadcast_to(lo, chi.shape), jnp.broadcast_to(hi, chi.shape)
    d = derivatives(fns, st.p, chi, st.v, st.y, st.nu, jnp.asarray(jnp.inf, dtype))
    sl, su = _barrier(lo, hi, chi)
    sigma = jnp.where(jnp.isfinite(lo), st.zl / sl, 0.0) + jnp.where(jnp.isfinite(hi), st.zu / su, 0.0)
    mat = QPMatrices(
        Wp=d.Wp,
        G=d.G,
        W=d.W.at[:, :n, :n].add(jax.vmap(jnp.diag)(sigma[:-1])),
        Z=d.Z,
        QK=d.QK + jnp.diag(sigma[-1]),
        C=d.CK,
    )
    # the matrices belong to the solution (no tangent flows through them); the map from the
    # right-hand side to the step is linear, so forward and reverse mode both go through it
    fac = jax.lax.stop_gradient(riccati_factor(mat, jnp.zeros((), dtype)))
    sol = riccati_apply(fac, rhs)
    return sol.dp, sol.dx, sol.dv
