"""The Newton step of a discrete optimal control problem by a Riccati recursion.

The equality-constrained quadratic program of one interior-point iteration, in stage form: free
initial parameters ``dp`` (s), states ``dx_1 .. dx_K`` (n), controls ``dv_1 .. dv_{K-1}`` (m)::

    min  dp^T W_p dp / 2 + w_p^T dp
         + sum_{j=1}^{K-1} [ z_j^T W_j z_j / 2 + w_j^T z_j ] + dx_K^T Q_K dx_K / 2 + q_K^T dx_K
    s.t. dx_1 = G dp + e_0,   dx_{j+1} = A_j dx_j + B_j dv_j + e_j,   C dx_K + c = 0,

with ``z_j = (dx_j, dv_j)`` and ``Z_j = [A_j, B_j]``. The initial parameters are what a problem
leaves free at its start: the first node's controls, and for a periodic problem the initial
reduced state. It is solved exactly in O(K) by a backward Riccati recursion and a forward pass,
in two phases:

* :func:`riccati_factor` depends on the matrices only: the gains, the value-function Hessians
  ``P_j``, the reduced Hessian of the initial parameters ``H_p = W_p + G^T P_1 G``, and how the
  terminal multiplier ``nu`` of ``C dx_K + c = 0`` enters (one extra column per constraint: the
  terminal state is affine in ``nu``, ``dx_K = a + M nu``, and ``nu`` solves
  ``(C M - delta I) nu = -(C a + c)``); it reports whether every ``H_j = R_j + B_j^T P_{j+1} B_j``
  and ``H_p`` were positive definite (the reduced Hessian is then positive definite on the
  dynamics' null space, the inertia condition of an interior-point method);
* :func:`riccati_apply` is linear in the right-hand side ``(w_p, e_0, w, e, q_K, c)``: one
  backward and one forward pass. Derivatives of a solution with respect to the right-hand side
  (the implicit function theorem of :mod:`._sensitivity`) transpose it as any linear map.

Small dense algebra in ``lax.scan`` (no LAPACK), with the stage blocks stacked so that each stage
costs a handful of matrix products: per-operation overhead, not arithmetic, dominates here.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._linalg import solve

__all__ = ["QPMatrices", "QPVector", "QPSolution", "Factor", "riccati_factor", "riccati_apply", "spd_solve"]


class QPMatrices(NamedTuple):
    """The matrices of the QP (leading axis ``K - 1`` for the stage blocks ``j = 1 .. K-1``)."""

    Wp: Float[Array, "s s"]
    G: Float[Array, "n s"]
    W: Float[Array, "K1 nm nm"]
    Z: Float[Array, "K1 n nm"]
    QK: Float[Array, "n n"]
    C: Float[Array, "p n"]


class QPVector(NamedTuple):
    """The right-hand side of the QP, in the layout of its residuals (:func:`kkt_residual`)."""

    wp: Float[Array, " s"]
    e0: Float[Array, " n"]
    w: Float[Array, "K1 nm"]
    e: Float[Array, "K1 n"]
    qK: Float[Array, " n"]
    c: Float[Array, " p"]


class QPSolution(NamedTuple):
    dp: Float[Array, " s"]
    dx: Float[Array, "K n"]  # dx_1 .. dx_K
    dv: Float[Array, "K1 m"]  # dv_1 .. dv_{K-1}
    y: Float[Array, "K n"]  # multipliers of dx_1 = ... (y_0) and dx_{j+1} = ... (y_j)
    nu: Float[Array, " p"]


class Factor(NamedTuple):
    """What :func:`riccati_factor` computes from the matrices (and the matrices themselves, for
    the residuals of :func:`riccati_apply`'s refinement)."""

    mat: QPMatrices
    K: Float[Array, "K1 m n"]  # feedback gains
    Hinv: Float[Array, "K1 m m"]  # inverses of H_j
    Hxu: Float[Array, "K1 n m"]
    P: Float[Array, "K1 n n"]  # P_{j+1}
    Knu: Float[Array, "K1 m p"]  # control response to nu
    Pnu: Float[Array, "K1 n p"]  # costate response to nu, at j + 1
    P1: Float[Array, "n n"]
    Pnu1: Float[Array, "n p"]
    Hp_inv: Float[Array, "s s"]
    Mp: Float[Array, "s p"]  # initial-parameter response to nu
    Mx: Float[Array, "K n p"]  # state response to nu, dx_1 .. dx_K
    Mv: Float[Array, "K1 m p"]  # control response to nu
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
    (closed forms for 1 x 1 and 2 x 2; Cholesky pivots and Gauss-Jordan otherwise)."""
    m = h.shape[0]
    if m == 0:
        return rhs, jnp.ones((), bool)
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
        t = t - jnp.outer(col, t[k, :]) * (jnp.arange(m) > k).astype(t.dtype)[:, None]
    return solve(h, rhs), piv_ok


def _backward_factor(mat: QPMatrices):
    n = mat.QK.shape[0]
    m = mat.W.shape[1] - n
    dtype = mat.QK.dtype

    def backward(carry, data):
        P, Pn, ok = carry
        W_j, Z_j = data
        PZ = _mm(P, Z_j)
        Gm = _mm(Z_j.T, PZ) + W_j
        H = 0.5 * (Gm[n:, n:] + Gm[n:, n:].T)
        Hinv, ok_j = spd_solve(H, jnp.eye(m, dtype=dtype))
        Hxu = Gm[:n, n:]
        K = -_mm(Hinv, Hxu.T)
        P_new = Gm[:n, :n] + _mm(Hxu, K)
        gn = _mm(Z_j.T, Pn)  # (n + m, p)
        Knu = -_mm(Hinv, gn[n:])
        Pn_new = gn[:n] + _mm(Hxu, Knu)
        return (0.5 * (P_new + P_new.T), Pn_new, ok & ok_j), (K, Hinv, Hxu, P, Knu, Pn)

    return jax.lax.scan(backward, (mat.QK, mat.C.T, jnp.ones((), bool)), (mat.W, mat.Z), reverse=True)


def riccati_factor(mat: QPMatrices, delta_c: Array) -> Factor:
    """The matrix phase of the recursion (see the module docstring)."""
    p = mat.C.shape[0]
    s = mat.G.shape[1]
    dtype = mat.QK.dtype
    (P1, Pnu1, positive), (K, Hinv, Hxu, P, Knu, Pnu) = _backward_factor(mat)
    GP = mat.G.T @ P1
    Hp = mat.Wp + GP @ mat.G
    Hp_inv, ok_p = spd_solve(0.5 * (Hp + Hp.T), jnp.eye(s, dtype=dtype))
    Mp = -Hp_inv @ (mat.G.T @ Pnu1)

    def forward(Mx, data):
        K_j, Knu_j, Z_j = data
        Mv = _mm(K_j, Mx) + Knu_j
        Mx_next = _mm(Z_j, jnp.concatenate([Mx, Mv], axis=0))
        return Mx_next, (Mx_next, Mv)

    Mx1 = mat.G @ Mp
    MK, (Mx, Mv) = jax.lax.scan(forward, Mx1, (K, Knu, mat.Z))
    eye_p = jnp.eye(p, dtype=dtype)
    CM_inv = solve(mat.C @ MK - delta_c * eye_p, eye_p) if p else jnp.zeros((0, 0), dtype)
    return Factor(
        mat=mat,
        K=K,
        Hinv=Hinv,
        Hxu=Hxu,
        P=P,
        Knu=Knu,
        Pnu=Pnu,
        P1=P1,
        Pnu1=Pnu1,
        Hp_inv=Hp_inv,
        Mp=Mp,
        Mx=jnp.concatenate([Mx1[None], Mx]),
        Mv=Mv,
        CM_inv=CM_inv,
        positive=positive & ok_p,
    )


def kkt_residual(f: Factor, rhs: QPVector, sol: QPSolution) -> QPVector:
    """The residual of the QP's optimality conditions at ``sol``, in the layout of its right-hand
    side (zero at the exact solution): stationarity of the Lagrangian
    ``dp^T W_p dp / 2 + w_p^T dp + y_0^T (G dp + e_0 - dx_1) + sum_j [z_j^T W_j z_j / 2 + w_j^T z_j
    + y_j^T (Z_j z_j + e_j - dx_{j+1})] + dx_K^T Q_K dx_K / 2 + q_K^T dx_K + nu^T (C dx_K + c)`` in
    ``dp``, ``z_j`` and ``dx_K``, and the constraints."""
    mat = f.mat
    n = mat.QK.shape[0]
    dp, dx, dv, y, nu = sol
    z = jnp.concatenate([dx[:-1], dv], axis=1)
    r_p = mat.Wp @ dp + rhs.wp + mat.G.T @ y[0]
    r_w = jnp.einsum("jab,jb->ja", mat.W, z) + rhs.w + jnp.einsum("jab,ja->jb", mat.Z, y[1:])
    r_w = r_w.at[:, :n].add(-y[:-1])
    r_e0 = mat.G @ dp + rhs.e0 - dx[0]
    r_e = jnp.einsum("jab,jb->ja", mat.Z, z) + rhs.e - dx[1:]
    r_q = mat.QK @ dx[-1] + rhs.qK - y[-1] + mat.C.T @ nu
    r_c = mat.C @ dx[-1] + rhs.c
    return QPVector(r_p, r_e0, r_w, r_e, r_q, r_c)


def riccati_apply(f: Factor, rhs: QPVector, refine: int = 0, atol: Array | float = 0.0) -> QPSolution:
    """The right-hand-side phase: linear in ``rhs``.

    ``refine``: at most this many steps of iterative refinement: while the residual of the
    solution (:func:`kkt_residual`, max norm) exceeds ``atol``, solve for it with the same factors
    and add the correction, as long as that reduces the residual (on a system too ill-conditioned
    for its factors refinement diverges; the best solution is kept). The systems of a converging
    interior-point method are ill-conditioned (the barrier's ``zeta / slack`` grows like
    ``1 / mu`` on active bounds), and their residual perturbs the next iterate's KKT error
    directly. With ``refine > 0`` the result is not reverse-differentiable (a ``while_loop``)."""
    if not refine:
        return _apply(f, rhs)
    # the first solve is the loop's first pass, from the zero solution (whose residual is
    # ``rhs``), always taken: one copy of the solve in the program instead of two

    def cond(carry):
        _, _, size, k = carry
        return (k < refine) & (size > atol)

    def body(carry):
        s, r, size, k = carry
        s_new = jax.tree_util.tree_map(jnp.add, s, _apply(f, r))
        r_new = kkt_residual(f, rhs, s_new)
        size_new = max_abs(r_new)
        # a correction that does not reduce the residual is not taken
        better = (size_new < size) | (k < 0)

        def keep(new, old):
            return jax.tree_util.tree_map(lambda x, y: jnp.where(better, x, y), new, old)

        return (
            keep(s_new, s),
            keep(r_new, r),
            jnp.where(better, size_new, size),
            jnp.where(better, k + 1, refine),
        )

    zero = jax.tree_util.tree_map(lambda x: jnp.zeros(x.shape, x.dtype), jax.eval_shape(_apply, f, rhs))
    start = (zero, rhs, jnp.asarray(jnp.inf, rhs.qK.dtype), -jnp.ones((), jnp.int32))
    return jax.lax.while_loop(cond, body, start)[0]


def max_abs(tree) -> Array:
    """The largest absolute entry of the arrays of ``tree`` (0 if all are empty)."""
    return jnp.max(jnp.stack([jnp.max(jnp.abs(x), initial=0.0) for x in jax.tree_util.tree_leaves(tree)]))


def _apply(f: Factor, rhs: QPVector) -> QPSolution:
    mat = f.mat
    n = mat.QK.shape[0]

    def backward(pv, data):
        Z_j, P_next, Hinv, Hxu, w_j, e_j = data
        pe = pv + _mv(P_next, e_j)
        gz = _mv(Z_j.T, pe) + w_j
        k = -_mv(Hinv, gz[n:])
        return gz[:n] + _mv(Hxu, k), (k, pv)

    p1, (k, p_next) = jax.lax.scan(backward, rhs.qK, (mat.Z, f.P, f.Hinv, f.Hxu, rhs.w, rhs.e), reverse=True)
    dp_a = -f.Hp_inv @ (mat.G.T @ (f.P1 @ rhs.e0 + p1) + rhs.wp)

    def forward(dx, data):
        K_j, k_j, Z_j, e_j = data
        dv = _mv(K_j, dx) + k_j
        dx_next = _mv(Z_j, jnp.concatenate([dx, dv])) + e_j
        return dx_next, (dx_next, dv)

    a1 = mat.G @ dp_a + rhs.e0
    a, (dx_a, dv_a) = jax.lax.scan(forward, a1, (f.K, k, mat.Z, rhs.e))
    # nu from the regularised (C M - delta_c I) nu = -(C a + c); one refinement step with C M
    # itself brings the linearised terminal residual from delta_c nu to O(delta_c^2): without it the
    # residual floor (~1e-9) stalls the line search of a nearly converged iterate
    r = mat.C @ a + rhs.c
    nu = -f.CM_inv @ r
    nu = nu - f.CM_inv @ (r + mat.C @ (f.Mx[-1] @ nu))
    dp = dp_a + f.Mp @ nu
    dx = jnp.concatenate([a1[None], dx_a]) + f.Mx @ nu
    dv = dv_a + f.Mv @ nu
    y0 = f.P1 @ dx[0] + p1 + f.Pnu1 @ nu
    y = jnp.einsum("jab,jb->ja", f.P, dx[1:]) + p_next + f.Pnu @ nu
    return QPSolution(dp=dp, dx=dx, dv=dv, y=jnp.concatenate([y0[None], y]), nu=nu)
