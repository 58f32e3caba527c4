"""Small dense linear solves in plain XLA operations (no LAPACK custom call).

Every linear system in the library is tiny: the KKT systems of the full Lagrange-d'Alembert
equations (dimension of Q plus the number of constraints, below 10), the Newton systems of the
implicit steps (3 + dim of the constrained symmetries) and the Gram matrices ``e^T e`` of the
symmetry basis. :func:`solve` eliminates them with an unrolled Gauss-Jordan sweep with partial
pivoting written in element-wise ``jax.numpy`` operations, so that

* ``jax.vmap`` over a batch of maneuvers turns it into dense vector code across the batch, rather
  than one ``dgetrf``/``dgetrs`` call per matrix;
* nothing goes through jaxlib's batched LAPACK kernel, whose parallel batch loop waits on the
  intra-op thread pool from inside a device thread: with several XLA host devices
  (``--xla_force_host_platform_device_count``, a batch sharded across the cores) each device
  thread blocks on sub-tasks that only the other, equally blocked, device thread could run, and
  the computation deadlocks (seen with jaxlib 0.10.2: ``jax::ParallelBatchMap`` under
  ``lapack_dgetrf_ffi`` on both ``tf_XLAEigen`` threads);
* forward and reverse mode differentiate through it like any other ``jax.numpy`` code.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array

from ._typing import ArrayLike

__all__ = ["solve"]


def _gauss_jordan(a: Array, b: Array) -> Array:
    """``a^{-1} b`` for one ``(n, n)`` matrix ``a`` and ``(n, k)`` right-hand sides ``b``.

    The pivots and multipliers are computed from ``a`` alone and then applied to ``b``, so the
    map ``b -> x`` is visibly linear to JAX (``lax.custom_root`` transposes it in reverse mode).
    """
    n = a.shape[-1]
    rows = jnp.arange(n)
    for k in range(n):  # n is static and small: the sweep is unrolled at trace time
        # partial pivoting: the largest |entry| of column k among rows k..n-1 (NaN wins, as it
        # should: a non-finite system gives a non-finite answer, which callers report)
        p = jnp.argmax(jnp.where(rows >= k, jnp.abs(a[:, k]), -1.0))
        swap = (rows == k).astype(a.dtype) - (rows == p).astype(a.dtype)  # e_k - e_p
        row_p = (rows == p).astype(a.dtype)
        a = a + swap[:, None] * (row_p @ a - a[k])[None, :]  # exchange rows k and p
        b = b + swap[:, None] * (row_p @ b - b[k])[None, :]
        factors = jnp.where(rows == k, 0.0, a[:, k] / a[k, k])
        a = a - factors[:, None] * a[k][None, :]  # clear column k in every other row
        b = b - factors[:, None] * b[k][None, :]
    return b / jnp.diagonal(a)[:, None]


def solve(a: ArrayLike, b: ArrayLike) -> Array:
    """Solve ``a x = b`` for small square ``a`` (Gauss-Jordan with partial pivoting).

    Same contract as ``jnp.linalg.solve`` for the shapes the library uses: ``a`` of shape
    ``(..., n, n)`` and ``b`` of shape ``(..., n)`` (one right-hand side) or ``(..., n, k)``,
    with leading batch axes broadcast. The cost is ``n^2 (n + k)`` multiply-adds, unrolled over
    ``n``: meant for ``n`` up to a few tens. A singular ``a`` gives non-finite entries (as LAPACK
    does), never an exception.

    Args:
        a: coefficient matrix, shape ``(..., n, n)``.
        b: right-hand side, shape ``(..., n)`` or ``(..., n, k)``.

    Returns:
        ``x`` with the shape of ``b`` (after broadcasting the batch axes).

    Raises:
        ValueError: if ``a`` is not square or ``b`` does not match it.

    Example:
        >>> import jax.numpy as jnp
        >>> from ldap_jax._linalg import solve
        >>> solve(jnp.array([[0.0, 2.0], [1.0, 1.0]]), jnp.array([2.0, 3.0]))
        Array([2., 1.], dtype=float32)
    """
    a = jnp.asarray(a)
    b = jnp.asarray(b)
    if a.ndim < 2 or a.shape[-1] != a.shape[-2]:
        raise ValueError(f"solve: 'a' must be square (..., n, n), got shape {a.shape}")
    n = a.shape[-1]
    dtype = jnp.result_type(a, b)
    a = a.astype(dtype)
    b = b.astype(dtype)
    vector = b.ndim == a.ndim - 1 or b.ndim == 1
    if vector:
        if b.shape[-1] != n:
            raise ValueError(f"solve: 'b' of shape {b.shape} does not match 'a' of shape {a.shape}")
        b = b[..., None]
    elif b.shape[-2] != n:
        raise ValueError(f"solve: 'b' of shape {b.shape} does not match 'a' of shape {a.shape}")
    if n == 0:
        x = jnp.zeros(jnp.broadcast_shapes(a.shape[:-2], b.shape[:-2]) + b.shape[-2:], dtype)
    else:
        batch = jnp.broadcast_shapes(a.shape[:-2], b.shape[:-2])
        a_b = jnp.broadcast_to(a, batch + a.shape[-2:]).reshape((-1, n, n))
        b_b = jnp.broadcast_to(b, batch + b.shape[-2:]).reshape((-1,) + b.shape[-2:])
        if a_b.shape[0] == 1 and not batch:
            x = _gauss_jordan(a_b[0], b_b[0])
        else:
            x = jax.vmap(_gauss_jordan)(a_b, b_b).reshape(batch + b.shape[-2:])
    return x[..., 0] if vector else x
