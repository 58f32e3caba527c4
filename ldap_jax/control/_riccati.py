"""The Newton step of a discrete optimal control problem by a Riccati recursion.

The equality-constrained quadratic program of one interior-point iteration, in stage form
(``j = 0 .. K-1``, states ``dx_0 .. dx_K``, controls ``dv_0 .. dv_{K-1}``)::

    min  sum_j [ dx_j^T Q_j dx_j / 2 + dv_j^T S_j dx_j + dv_j^T R_j dv_j / 2 + q_j^T dx_j + r_j^T dv_j ]
         + dx_K^T Q_K dx_K / 2 + q_K^T dx_K
    s.t. dx_0 = 0,   dx_{j+1} = A_j dx_j + B_j dv_j + e_j,   C dx_K + c = 0,

is solved exactly in O(K) by the backward Riccati recursion and a forward pass. The terminal
equality is handled by carrying the costate's dependence on its multiplier ``nu`` through both
passes (one extra column per constraint): the terminal state is affine in ``nu``,
``dx_K = a + M nu``, and ``nu`` solves the small system ``(C M - delta I) nu = -(C a + c)``.
The recursion reports whether every ``H_j = R_j + B_j^T P_{j+1} B_j`` was positive definite (the
reduced Hessian is then positive definite on the dynamics' null space, the inertia condition of an
interior-point method); the caller regularises and retries otherwise.

Everything is small dense algebra in ``lax.scan`` (no LAPACK: :func:`ldap_jax._linalg.solve`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._linalg import solve

__all__ = ["QP", "QPSolution", "riccati_solve", "positive_definite"]


class QP(NamedTuple):
    """Stage data (leading axis ``K`` for the ``j``-indexed blocks)."""

    Q: Float[Array, "K n n"]
    S: Float[Array, "K m n"]
    R: Float[Array, "K m m"]
    q: Float[Array, "K n"]
    r: Float[Array, "K m"]
    A: Float[Array, "K n n"]
    B: Float[Array, "K n m"]
    e: Float[Array, "K n"]
    QK: Float[Array, "n n"]
    qK: Float[Array, " n"]
    C: Float[Array, "p n"]
    c: Float[Array, " p"]


class QPSolution(NamedTuple):
    dx: Float[Array, "K1 n"]  # dx_0 .. dx_K
    dv: Float[Array, "K m"]
    y: Float[Array, "K n"]  # costates y_j = P_{j+1} dx_{j+1} + p_{j+1}: the dynamics multipliers
    nu: Float[Array, " p"]
    positive: Bool[Array, ""]


def positive_definite(h: Array) -> Bool[Array, ""]:
    """True when the small symmetric matrix ``h`` is positive definite (unrolled Cholesky pivots)."""
    m = h.shape[0]
    a = h
    ok = jnp.ones((), bool)
    for k in range(m):
        piv = a[k, k]
        ok = ok & (piv > 0) & jnp.isfinite(piv)
        safe = jnp.where(piv > 0, piv, 1.0)
        col = a[:, k] / safe
        a = a - jnp.outer(col, a[k, :]) * (jnp.arange(m) > k)[:, None]
    return ok


def riccati_solve(qp: QP, delta_c: Array) -> QPSolution:
    """Solve the stage-structured KKT system of :class:`QP` (see the module docstring)."""
    n = qp.QK.shape[0]
    p = qp.C.shape[0]
    dtype = qp.QK.dtype
    # costate gradient columns: [base | one per terminal constraint]
    p_K = jnp.concatenate([qp.qK[:, None], qp.C.T], axis=1)  # (n, 1 + p)

    def backward(carry, data):
        P, pm, ok = carry
        Q, S, R, q, r, A, B, e = data
        PB = P @ B
        H = R + B.T @ PB
        H = 0.5 * (H + H.T)
        Hx = S + PB.T @ A
        pe = pm.at[:, 0].add(P @ e)
        g = jnp.concatenate([r[:, None], jnp.zeros((r.shape[0], p), dtype)], axis=1) + B.T @ pe
        ok = ok & positive_definite(H)
        sol = solve(H, jnp.concatenate([Hx, g], axis=1))
        K, k = -sol[:, :n], -sol[:, n:]
        P_new = Q + A.T @ P @ A + Hx.T @ K
        P_new = 0.5 * (P_new + P_new.T)
        pm_new = A.T @ pe + Hx.T @ k
        pm_new = pm_new.at[:, 0].add(q)
        return (P_new, pm_new, ok), (K, k, P, pm)

    data = (qp.Q, qp.S, qp.R, qp.q, qp.r, qp.A, qp.B, qp.e)
    (_, _, positive), (K, k, P_next, pm_next) = jax.lax.scan(
        backward, (qp.QK, p_K, jnp.ones((), bool)), data, reverse=True
    )

    def forward(dx, data):
        K_j, k_j, A, B, e = data
        dv = K_j @ dx + k_j
        dx_next = A @ dx + B @ dv
        dx_next = dx_next.at[:, 0].add(e)
        return dx_next, (dx_next, dv)

    dx0 = jnp.zeros((n, 1 + p), dtype)
    dxK, (dxs, dvs) = jax.lax.scan(forward, dx0, (K, k, qp.A, qp.B, qp.e))
    a, M = dxK[:, 0], dxK[:, 1:]
    if p:
        lhs = qp.C @ M - delta_c * jnp.eye(p, dtype=dtype)
        nu = solve(lhs, -(qp.C @ a + qp.c))
    else:
        nu = jnp.zeros((0,), dtype)
    coef = jnp.concatenate([jnp.ones((1,), dtype), nu])
    dx = jnp.concatenate([jnp.zeros((1, n), dtype), dxs @ coef])
    dv = dvs @ coef
    y = jnp.einsum("jab,jb->ja", P_next, dx[1:]) + pm_next @ coef
    return QPSolution(dx=dx, dv=dv, y=y, nu=nu, positive=positive)
