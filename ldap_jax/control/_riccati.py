"""The Newton step of a discrete optimal control problem by a Riccati recursion.

The equality-constrained quadratic program of one interior-point iteration, in stage form
(``j = 0 .. K-1``, states ``dx_0 .. dx_K``, controls ``dv_0 .. dv_{K-1}``)::

    min  sum_j [ (dx_j, dv_j)^T W_j (dx_j, dv_j) / 2 + w_j^T (dx_j, dv_j) ] + dx_K^T Q_K dx_K / 2 + q_K^T dx_K
    s.t. dx_0 = 0,   dx_{j+1} = A_j dx_j + B_j dv_j + e_j,   C dx_K + c = 0,

with ``Z_j = [A_j, B_j]``, is solved exactly in O(K) by a backward Riccati recursion and a
forward pass, in two phases:

* :func:`riccati_factor` depends on the matrices only (``W``, ``Z``, ``Q_K``, ``C``): the gains,
  the value-function Hessians ``P_j``, and how the terminal multiplier ``nu`` of ``C dx_K + c = 0``
  enters (one extra column per constraint: the terminal state is affine in ``nu``,
  ``dx_K = a + M nu``, and ``nu`` solves ``(C M - delta I) nu = -(C a + c)``); it reports whether
  every ``H_j = R_j + B_j^T P_{j+1} B_j`` was positive definite (the reduced Hessian is then
  positive definite on the dynamics' null space, the inertia condition of an interior-point
  method);
* :func:`riccati_apply` is linear in the right-hand side ``(w, e, q_K, c)``: one backward and one
  forward pass. Derivatives of a solution with respect to the right-hand side (the implicit
  function theorem of :mod:`._solve`) transpose it as any linear map.

Small dense algebra in ``lax.scan`` (no LAPACK), with the stage blocks stacked so that each stage
costs a handful of matrix products: per-operation overhead, not arithmetic, dominates here.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._linalg import solve

__all__ = ["QP", "QPSolution", "Factor", "riccati_factor", "riccati_apply", "riccati_solve", "spd_solve"]


class QP(NamedTuple):
    """Stage data (leading axis ``K`` for the ``j``-indexed blocks). ``W_j`` is the stage Hessian
    over ``(dx_j, dv_j)``, ``w_j`` its gradient and ``Z_j = [A_j, B_j]`` the linearised dynamics."""

    W: Float[Array, "K nm nm"]
    w: Float[Array, "K nm"]
    Z: Float[Array, "K n nm"]
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


class Factor(NamedTuple):
    """What :func:`riccati_factor` computes from the matrices (and the matrices ``W``, ``Z``,
    ``QK``, ``C`` themselves, for the residuals of :func:`riccati_apply`'s refinement)."""

    W: Float[Array, "K nm nm"]
    QK: Float[Array, "n n"]
    Z: Float[Array, "K n nm"]
    K: Float[Array, "K m n"]  # feedback gains
    Hinv: Float[Array, "K m m"]  # inverses of H_j
    Hxu: Float[Array, "K n m"]
    P: Float[Array, "K n n"]  # P_{j+1}
    Knu: Float[Array, "K m p"]  # control response to nu
    Pnu: Float[Array, "K n p"]  # costate response to nu, at j + 1
    Mx: Float[Array, "K n p"]  # state response to nu, dx_{j+1}
    Mv: Float[Array, "K m p"]  # control response to nu, dv_j
    C: Float[Array, "p n"]
    CM_inv: Float[Array, "p p"]
    positive: Bool[Array, ""]


def _mm(a: Array, b: Array) -> Array:
    """``a @ b`` for small matrices as a broadcast product and a sum, which XLA fuses with the
    surrounding arithmetic: inside the recursion's sequential loop a library matrix product costs
    more in per-call overhead than in arithmetic (a stage of the factorisation 2x faster on CPU)."""
    return jnp.sum(a[:, :, None] * b[None, :, :], axis=1)


def _mv(a: Array, x: Array) -> Array:
    """``a @ x`` for a small matrix and a vector, as :func:`_mm`."""
    return jnp.sum(a * x[None, :], axis=1)


def spd_solve(h: Array, rhs: Array) -> tuple[Array, Bool[Array, ""]]:
    """``h^-1 rhs`` for a small symmetric ``h``, and whether ``h`` is positive definite
    (closed forms for 1 x 1 and 2 x 2; unrolled Cholesky pivots and Gauss-Jordan otherwise)."""
    m = h.shape[0]
    if m == 1:
        return rhs / h[0, 0], h[0, 0] > 0
    if m == 2:
        a, b, d = h[0, 0], h[0, 1], h[1, 1]
        det = a * d - b * b
        inv = jnp.stack([jnp.stack([d, -b]), jnp.stack([-b, a])]) / det
        return inv @ rhs, (a > 0) & (det > 0)
    piv_ok = jnp.ones((), bool)
    t = h
    for k in range(m):
        piv = t[k, k]
        piv_ok = piv_ok & (piv > 0)
        col = t[:, k] / jnp.where(piv > 0, piv, 1.0)
        t = t - jnp.outer(col, t[k, :]) * (jnp.arange(m) > k)[:, None]
    return solve(h, rhs), piv_ok


def riccati_factor(W: Array, Z: Array, QK: Array, C: Array, delta_c: Array) -> Factor:
    """The matrix phase of the recursion (see the module docstring)."""
    n = QK.shape[0]
    m = W.shape[1] - n
    p = C.shape[0]
    dtype = QK.dtype

    def backward(carry, data):
        P, Pn, ok = carry
        W_j, Z_j = data
        PZ = _mm(P, Z_j)
        G = _mm(Z_j.T, PZ) + W_j
        H = 0.5 * (G[n:, n:] + G[n:, n:].T)
        Hinv, ok_j = spd_solve(H, jnp.eye(m, dtype=dtype))
        Hxu = G[:n, n:]
        K = -_mm(Hinv, Hxu.T)
        P_new = G[:n, :n] + _mm(Hxu, K)
        gn = _mm(Z_j.T, Pn)  # (n + m, p)
        Knu = -_mm(Hinv, gn[n:])
        Pn_new = gn[:n] + _mm(Hxu, Knu)
        return (0.5 * (P_new + P_new.T), Pn_new, ok & ok_j), (K, Hinv, Hxu, P, Knu, Pn)

    (_, _, positive), (K, Hinv, Hxu, P, Knu, Pnu) = jax.lax.scan(
        backward, (QK, C.T, jnp.ones((), bool)), (W, Z), reverse=True
    )

    def forward(Mx, data):
        K_j, Knu_j, Z_j = data
        Mv = _mm(K_j, Mx) + Knu_j
        Mx_next = _mm(Z_j, jnp.concatenate([Mx, Mv], axis=0))
        return Mx_next, (Mx_next, Mv)

    MK, (Mx, Mv) = jax.lax.scan(forward, jnp.zeros((n, p), dtype), (K, Knu, Z))
    CM_inv = (
        solve(C @ MK - delta_c * jnp.eye(p, dtype=dtype), jnp.eye(p, dtype=dtype))
        if p
        else jnp.zeros((0, 0), dtype)
    )
    return Factor(
        W=W,
        QK=QK,
        Z=Z,
        K=K,
        Hinv=Hinv,
        Hxu=Hxu,
        P=P,
        Knu=Knu,
        Pnu=Pnu,
        Mx=Mx,
        Mv=Mv,
        C=C,
        CM_inv=CM_inv,
        positive=positive,
    )


def kkt_residual(f: Factor, w: Array, e: Array, qK: Array, c: Array, sol: QPSolution):
    """The residual of the QP's optimality conditions at ``sol``, in the shape of its right-hand
    side ``(w, e, q_K, c)`` (zero at the exact solution): stationarity of the Lagrangian
    ``sum_j [z_j^T W_j z_j / 2 + w_j^T z_j + y_j^T (Z_j z_j + e_j - dx_{j+1})] + dx_K^T Q_K dx_K / 2
    + q_K^T dx_K + nu^T (C dx_K + c)`` in ``z_j = (dx_j, dv_j)`` (``j >= 1`` for ``dx_j``, which is
    fixed at ``j = 0``) and in ``dx_K``, and the constraints."""
    n = qK.shape[0]
    dx, dv, y, nu = sol
    z = jnp.concatenate([dx[:-1], dv], axis=1)
    prev = jnp.concatenate([jnp.zeros((1, n), y.dtype), y[:-1]])
    r_w = (
        jnp.einsum("jab,jb->ja", f.W, z)
        + w
        + jnp.einsum("jab,ja->jb", f.Z, y)
        - jnp.pad(prev, ((0, 0), (0, z.shape[1] - n)))
    )
    r_w = r_w.at[0, :n].set(0.0)
    r_e = jnp.einsum("jab,jb->ja", f.Z, z) + e - dx[1:]
    r_q = f.QK @ dx[-1] + qK - y[-1] + f.C.T @ nu
    r_c = f.C @ dx[-1] + c
    return r_w, r_e, r_q, r_c


def riccati_apply(
    f: Factor, w: Array, e: Array, qK: Array, c: Array, refine: int = 0, atol: Array | float = 0.0
) -> QPSolution:
    """The right-hand-side phase: linear in ``(w, e, qK, c)``.

    ``refine``: at most this many steps of iterative refinement: while the residual of the
    solution (:func:`kkt_residual`, max norm) exceeds ``atol``, solve for it with the same factors
    and add the correction, as long as that reduces the residual (on a system too ill-conditioned
    for its factors refinement diverges; the best solution is kept). The systems of a converging
    interior-point method are ill-conditioned (the barrier's ``zeta / slack`` grows like
    ``1 / mu`` on active bounds), and their residual perturbs the next iterate's KKT error
    directly. With ``refine > 0`` the result is not reverse-differentiable (a ``while_loop``)."""
    sol = _apply(f, w, e, qK, c)
    if not refine:
        return sol
    res = kkt_residual(f, w, e, qK, c, sol)

    def cond(carry):
        _, _, size, k = carry
        return (k < refine) & (size > atol)

    def body(carry):
        s, r, size, k = carry
        s_new = jax.tree_util.tree_map(jnp.add, s, _apply(f, *r))
        r_new = kkt_residual(f, w, e, qK, c, s_new)
        size_new = _max_abs(r_new)
        better = size_new < size  # a correction that does not reduce the residual is not taken

        def keep(new, old):
            return jax.tree_util.tree_map(lambda x, y: jnp.where(better, x, y), new, old)

        return (
            keep(s_new, s),
            keep(r_new, r),
            jnp.where(better, size_new, size),
            jnp.where(better, k + 1, refine),
        )

    return jax.lax.while_loop(cond, body, (sol, res, _max_abs(res), jnp.zeros((), jnp.int32)))[0]


def _max_abs(tree) -> Array:
    """The largest absolute entry of the arrays of ``tree`` (0 if all are empty)."""
    return jnp.max(jnp.stack([jnp.max(jnp.abs(x), initial=0.0) for x in jax.tree_util.tree_leaves(tree)]))


def _apply(f: Factor, w: Array, e: Array, qK: Array, c: Array) -> QPSolution:
    n = qK.shape[0]
    dtype = qK.dtype

    def backward(pv, data):
        Z_j, P_next, Hinv, Hxu, w_j, e_j = data
        pe = pv + _mv(P_next, e_j)
        gz = _mv(Z_j.T, pe) + w_j
        k = -_mv(Hinv, gz[n:])
        return gz[:n] + _mv(Hxu, k), (k, pv)

    _, (k, p_next) = jax.lax.scan(backward, qK, (f.Z, f.P, f.Hinv, f.Hxu, w, e), reverse=True)

    def forward(dx, data):
        K_j, k_j, Z_j, e_j = data
        dv = _mv(K_j, dx) + k_j
        dx_next = _mv(Z_j, jnp.concatenate([dx, dv])) + e_j
        return dx_next, (dx_next, dv)

    a, (dx_a, dv_a) = jax.lax.scan(forward, jnp.zeros((n,), dtype), (f.K, k, f.Z, e))
    # nu from the regularised (C M - delta_c I) nu = -(C a + c); one refinement step with C M
    # itself brings the linearised terminal residual from delta_c nu to O(delta_c^2): without it the
    # residual floor (~1e-9) stalls the line search of a nearly converged iterate
    r = f.C @ a + c
    nu = -f.CM_inv @ r
    nu = nu - f.CM_inv @ (r + f.C @ (f.Mx[-1] @ nu))
    dx = jnp.concatenate([jnp.zeros((1, n), dtype), dx_a + f.Mx @ nu])
    dv = dv_a + f.Mv @ nu
    y = jnp.einsum("jab,jb->ja", f.P, dx[1:]) + p_next + f.Pnu @ nu
    return QPSolution(dx=dx, dv=dv, y=y, nu=nu)


def riccati_solve(qp: QP, delta_c: Array) -> QPSolution:
    """Factor and apply in one call."""
    f = riccati_factor(qp.W, qp.Z, qp.QK, qp.C, delta_c)
    return riccati_apply(f, qp.w, qp.e, qp.qK, qp.c)
