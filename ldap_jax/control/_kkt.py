"""The stage form of a discrete optimal control problem, its derivatives and its KKT conditions.

The problem that :mod:`._ipm` solves::

    min   sum_{j=1}^{K-1} l(chi_j, v_j) + l_K(chi_K)
    s.t.  chi_1 = F_0(p),   chi_{j+1} = F(chi_j, v_j)  (j = 1 .. K-1),   c(chi_K) = 0,
          lo <= chi_j <= hi  (j = 1 .. K),

over the initial parameters ``p`` (what the problem leaves free at its start: the first node's
controls, and for a periodic problem the initial reduced state), the states ``chi_1 .. chi_K``
and the controls ``v_1 .. v_{K-1}``. Multiple shooting: every ``chi_j`` is a variable and the
dynamics are equality constraints (defects), so the dynamics and their derivatives are evaluated
for all stages at once (``vmap``), and only the Riccati recursion is sequential.

A problem may declare its last ``n_passive`` state entries *passive*: constant copies of initial
parameters that the terminal constraints compare with (a periodic problem's start). Their
dynamics are the identity and no cost reads them, so their derivatives are not computed.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = ["OCPFunctions", "Derivatives", "derivatives", "constraints", "theta", "objective", "rollout"]


class OCPFunctions(NamedTuple):
    """The problem in stage form: callables of one stage (vmapped by the solver)."""

    first: Callable[[Array], Array]  # p -> chi_1
    dynamics: Callable[[Array, Array, Array], Array]  # (chi_j, v_j, j - 1) -> chi_{j+1}, j = 1 .. K-1
    stage_cost: Callable[[Array, Array], Array]  # (chi_j, v_j) -> scalar, j = 1 .. K-1
    terminal_cost: Callable[[Array], Array]  # chi_K -> scalar
    terminal: Callable[[Array], Array]  # chi_K -> (p,) equality residuals
    # (chi, v) -> next chi whose second derivatives stand in for the dynamics' in the Hessian of
    # the Lagrangian (default: ``dynamics`` itself)
    curvature_dynamics: Callable[[Array, Array], Array] | None = None
    # (p, v, key, size) -> (p, v) with the controls perturbed within their bounds by ``size`` (a
    # fraction of their half-width), for a restart from a point where the linearisation gives no
    # direction (see ``._ipm``); None: restarts never perturb
    perturbation: Callable[[Array, Array, Array, Array], tuple[Array, Array]] | None = None
    n_passive: int = 0


class Derivatives(NamedTuple):
    defects: Float[Array, "K n"]  # (F_0(p) - chi_1, F(chi_j, v_j) - chi_{j+1})
    G: Float[Array, "n s"]  # dF_0/dp
    Wp: Float[Array, "s s"]  # curvature y_0^T F_0''
    Z: Float[Array, "K1 n nm"]  # [A_j, B_j]
    W: Float[Array, "K1 nm nm"]  # Hessian of the stage Lagrangian (no barrier)
    g: Float[Array, "K n"]  # gradient of the objective w.r.t. chi_1 .. chi_K
    gv: Float[Array, "K1 m"]  # ... and w.r.t. v_1 .. v_{K-1}
    cK: Float[Array, " p"]
    CK: Float[Array, "p n"]
    QK: Float[Array, "n n"]  # Hessian of l_K + nu^T c (no barrier)
    f: Float[Array, ""]  # the objective


def rollout(fns: OCPFunctions, p: Array, v: Array) -> Array:
    """The states ``chi_1 .. chi_K`` of ``(p, v)`` (no defects)."""

    def one(chi, data):
        vv, k = data
        nxt = fns.dynamics(chi, vv, k)
        return nxt, nxt

    chi1 = fns.first(p)
    _, rest = jax.lax.scan(one, chi1, (v, _nodes(v)))
    return jnp.concatenate([chi1[None], rest])


def constraints(fns: OCPFunctions, p: Array, chi: Array, v: Array) -> tuple[Array, Array]:
    """The defects ``(K, n)`` and the terminal residuals ``(p,)``."""
    d0 = fns.first(p) - chi[0]
    d = jax.vmap(fns.dynamics)(chi[:-1], v, _nodes(v)) - chi[1:]
    return jnp.concatenate([d0[None], d]), fns.terminal(chi[-1])


def theta(defects: Array, cK: Array) -> Array:
    """The constraint violation of the filter, ``|defects|_1 + |c_K|_1``."""
    return jnp.sum(jnp.abs(defects)) + jnp.sum(jnp.abs(cK))


def objective(fns: OCPFunctions, chi: Array, v: Array) -> Array:
    return jnp.sum(jax.vmap(fns.stage_cost)(chi[:-1], v)) + fns.terminal_cost(chi[-1])


def _nodes(v: Array) -> Array:
    """The node index ``j - 1`` of each stage ``j = 1 .. K-1``."""
    return jnp.arange(v.shape[0])


def _active(fns: OCPFunctions, n: int) -> int:
    return n - fns.n_passive


def _jacobians(fns: OCPFunctions, chi: Array, v: Array):
    """``F(chi_j, v_j)`` and its Jacobians ``[A_j, B_j]``, the passive entries' identity blocks
    filled in without differentiating through them."""
    K1, n = chi[:-1].shape
    na = _active(fns, n)

    def active(ca, vv, passive, k):
        f = fns.dynamics(jnp.concatenate([ca, passive]), vv, k)[:na]
        return f, f

    jac = jax.jacfwd(active, argnums=(0, 1), has_aux=True)
    (A, B), F = jax.vmap(jac)(chi[:-1, :na], v, chi[:-1, na:], _nodes(v))
    if na < n:
        A = jnp.concatenate([A, jnp.zeros((K1, na, n - na), A.dtype)], axis=2)
        eye = jnp.broadcast_to(jnp.eye(n - na, n, na, dtype=A.dtype), (K1, n - na, n))
        A = jnp.concatenate([A, eye], axis=1)
        B = jnp.concatenate([B, jnp.zeros((K1, n - na, B.shape[2]), B.dtype)], axis=1)
        F = jnp.concatenate([F, chi[:-1, na:]], axis=1)
    return F, jnp.concatenate([A, B], axis=2)


def _stage_hessians(fns: OCPFunctions, chi: Array, v: Array, y: Array, curved: bool) -> Array:
    """The Hessians of the stage Lagrangians ``l(chi_j, v_j) + [y_j^T F(chi_j, v_j)]`` over
    ``(chi_j, v_j)`` (the dynamics' part when ``curved``), passive entries zero."""
    K1, n = chi[:-1].shape
    m = v.shape[1]
    na = _active(fns, n)
    dyn = fns.dynamics if fns.curvature_dynamics is None else fns.curvature_dynamics

    def one(ca, vv, passive, yy, k):
        def lag(w):
            c = jnp.concatenate([w[:na], passive])
            out = fns.stage_cost(c, w[na:])
            if curved:
                out = out + yy[:na] @ dyn(c, w[na:], k)[:na]
            return out

        return jax.hessian(lag)(jnp.concatenate([ca, vv]))

    H = jax.vmap(one)(chi[:-1, :na], v, chi[:-1, na:], y[1:], _nodes(v))
    if na == n:
        return H
    idx = jnp.concatenate([jnp.arange(na), n + jnp.arange(m)])
    return jnp.zeros((K1, n + m, n + m), H.dtype).at[:, idx[:, None], idx[None, :]].set(H)


def derivatives(
    fns: OCPFunctions, p: Array, chi: Array, v: Array, y: Array, nu: Array, exact_tol
) -> Derivatives:
    """The constraints and the derivatives of one iteration. The dynamics' curvature enters ``W``
    and ``W_p`` (and the terminal constraints' ``QK``) once the constraint violation
    ``theta = |defects|_1 + |c_K|_1``, from this same evaluation of the dynamics, is at most
    ``exact_tol``; before, the Hessian is Gauss-Newton (the objective's curvature)."""
    dtype = chi.dtype
    F, Z = _jacobians(fns, chi, v)
    # F_0's value, Jacobian and second derivatives in one pass (s is small: forward over forward)
    (H0, (G, f1)) = _second_order(jax.jacfwd, jax.jacfwd, fns.first, p)
    defects = jnp.concatenate([(f1 - chi[0])[None], F - chi[1:]])
    (gc, gv), costs = jax.vmap(_grad_and_value(fns.stage_cost))(chi[:-1], v)
    chiK = chi[-1]
    # the terminal cost and constraints, with their Jacobians and Hessians, in one pass: forward
    # over forward, like F_0 (one node, so its n^2 directions cost little at run time; a smaller
    # program for XLA to compile than forward over reverse)
    HK, (JK, vK) = _second_order(jax.jacfwd, jax.jacfwd, _terminal_values(fns), chiK)
    cK, CK = vK[1:], JK[1:]
    exact = theta(defects, cK) <= exact_tol

    W = jax.lax.cond(
        exact,
        lambda _: _stage_hessians(fns, chi, v, y, True),
        lambda _: _stage_hessians(fns, chi, v, y, False),
        None,
    )
    Wp = jnp.where(exact, jnp.einsum("i,ijk->jk", y[0], H0), 0.0)
    QK = HK[0] + exact.astype(dtype) * jnp.einsum("i,ijk->jk", nu, HK[1:])
    g = jnp.concatenate([gc, JK[0][None]])
    f = jnp.sum(costs) + vK[0]
    return Derivatives(defects=defects, G=G, Wp=Wp, Z=Z, W=W, g=g, gv=gv, cK=cK, CK=CK, QK=QK, f=f)


def _second_order(outer, inner, fun, x):
    """``(fun'', (fun', fun))`` at ``x`` by ``outer(inner(fun))`` (``jax.jacfwd``/``jax.jacrev``),
    one traced copy of ``fun`` for all three."""

    def first(z):
        out = fun(z)
        return out, out

    def second(z):
        jac, out = inner(first, has_aux=True)(z)
        return jac, (jac, out)

    return outer(second, has_aux=True)(x)


def _grad_and_value(fun):
    """``((d fun/d chi, d fun/d v), fun)`` of a stage function (one traced copy)."""

    def with_aux(c, vv):
        out = fun(c, vv)
        return out, out

    return jax.grad(with_aux, argnums=(0, 1), has_aux=True)


def _terminal_values(fns: OCPFunctions):
    """``chi_K -> (l_K, c)``: the terminal cost and constraints as one vector."""

    def values(c):
        return jnp.concatenate([fns.terminal_cost(c)[None], fns.terminal(c)])

    return values


def dual_residuals(d: Derivatives, y: Array, nu: Array, zl: Array, zu: Array) -> tuple[Array, Array, Array]:
    """The gradients of the Lagrangian (without the barrier) w.r.t. ``p``, ``chi`` and ``v``."""
    n = y.shape[1]
    A, B = d.Z[:, :, :n], d.Z[:, :, n:]
    gp = d.G.T @ y[0]
    AT_y = jnp.einsum("jab,ja->jb", A, y[1:])
    gc = d.g + jnp.concatenate([AT_y, jnp.zeros((1, n), d.g.dtype)]) - y
    gc = gc.at[-1].add(d.CK.T @ nu) - zl + zu
    gv = d.gv + jnp.einsum("jab,ja->jb", B, y[1:])
    return gp, gc, gv
