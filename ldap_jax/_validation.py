"""Input validation that works the same eagerly, under ``jax.jit`` and under ``jax.vmap``.

Three levels (as in diffrax): shapes, dtypes and settings are checked at trace time with a
``ValueError``/``TypeError`` naming the argument; values that are known at trace time (concrete,
even inside an outer ``jit`` over other arguments) are checked at once the same way, computed
under ``jax.ensure_compile_time_eval``; values that are traced are checked inside the run and
reported per trajectory as a result code (:data:`~ldap_jax.RESULTS` ``invalid_input``).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from ._results import RESULTS

__all__ = [
    "check_array",
    "check_positive_int",
    "check_scalar",
    "cast_floats",
    "is_concrete",
    "raise_if_concrete",
    "input_result",
    "constraint_tolerance",
]

_SUPPORTED = (np.dtype(np.float32), np.dtype(np.float64))


def is_concrete(tree: Any) -> bool:
    """True when no leaf of ``tree`` is a tracer."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def check_positive_int(name: str, x: Any) -> int:
    """``x`` as a Python int >= 1, or a ``ValueError`` naming ``name``."""
    if isinstance(x, bool) or not isinstance(x, (int, np.integer)) or x < 1:
        raise ValueError(f"'{name}' must be a positive integer, got {x!r}")
    return int(x)


def check_array(name: str, x: ArrayLike, shape: tuple[int, ...], context: str = "") -> Array:
    """``x`` as a float32/float64 array of ``shape`` (lists and integer arrays are converted), or
    a ``ValueError``/``TypeError`` naming ``name``."""
    if isinstance(x, (str, bytes)):
        raise TypeError(f"'{name}' must be an array of numbers, got {x!r}")
    try:
        x = jnp.asarray(x)
    except (TypeError, ValueError) as err:
        raise TypeError(f"'{name}' must be an array of numbers, got {x!r}") from err
    if jnp.issubdtype(x.dtype, jnp.integer) or x.dtype == jnp.bool_:
        x = x.astype(jnp.result_type(float))
    if np.dtype(x.dtype) not in _SUPPORTED:
        raise ValueError(f"'{name}' must be float32 or float64, got dtype {x.dtype}")
    if x.shape != shape:
        raise ValueError(f"'{name}' must have shape {shape}{(' ' + context) if context else ''}, got {x.shape}")
    return x


def check_scalar(name: str, x: ArrayLike) -> ArrayLike:
    """``x`` unchanged if it is a real scalar (Python number or 0-d array), else a ``ValueError``."""
    if isinstance(x, (str, bytes)) or jnp.ndim(x) != 0:
        raise ValueError(f"'{name}' must be a scalar, got {x!r}")
    if not (jnp.issubdtype(jnp.result_type(x), jnp.floating) or jnp.issubdtype(jnp.result_type(x), jnp.integer)):
        raise ValueError(f"'{name}' must be a real number, got {x!r}")
    return x


def cast_floats(tree: Any, dtype: Any) -> Any:
    """Cast every floating array leaf of ``tree`` to ``dtype``."""
    return jax.tree_util.tree_map(
        lambda x: x.astype(dtype) if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating) else x, tree
    )


def constraint_tolerance(qdot: Array) -> Array:
    """Tolerance of the initial constraint check: ``1e4 eps (1 + max |qdot|)``."""
    return 1e4 * jnp.finfo(qdot.dtype).eps * (1.0 + jnp.max(jnp.abs(qdot)))


def _constraint_violation(system, q0, qdot0) -> Array:
    return system.constraint_residual(q0, qdot0)


def raise_if_concrete(system, integrator, q0, qdot0, controls, t0, t_final, check_constraints: bool) -> None:
    """The value checks, raised now for every input whose value is known at trace time."""
    with jax.ensure_compile_time_eval():
        if t_final is not None and is_concrete((t0, t_final)):
            t0_, tf_ = float(np.asarray(t0)), float(np.asarray(t_final))
            if not np.isfinite(t0_) or not np.isfinite(tf_) or not tf_ > t0_:
                raise ValueError(f"'t_final' must be finite and exceed t0 (a positive step), got t_final={t_final}, t0={t0}")
        for name, x in (("q0", q0), ("qdot0", qdot0)):
            if is_concrete(x) and not bool(np.all(np.isfinite(np.asarray(x)))):
                raise ValueError(f"'{name}' must be finite, got {np.asarray(x)}")
        from ._policy import AbstractPolicy

        if check_constraints and is_concrete((system, q0, qdot0, controls, t0)):
            if isinstance(controls, AbstractPolicy):
                c0 = controls(jnp.asarray(t0, q0.dtype), q0, qdot0)
            else:
                c0 = controls(jnp.asarray(t0, q0.dtype))
            if is_concrete(c0) and bool(np.all(np.isfinite(np.asarray(c0)))):
                qd = system.consistent_qdot(q0, qdot0.astype(q0.dtype), jnp.asarray(c0, q0.dtype))
                viol, tol = float(_constraint_violation(system, q0, qd)), float(constraint_tolerance(qd))
                if not viol <= tol:
                    raise ValueError(
                        f"'qdot0' violates the constraints: |omega(q0) qdot0| = {viol:.3e} > {tol:.1e}. Build it "
                        f"on the constraint distribution, e.g. system.qdot_from_velocities(q0, v0, u_kin)."
                    )


def input_result(system, integrator, q0, qdot0, t0, t_final, check_constraints: bool) -> RESULTS:
    """The value checks on traced values, as a result code (``invalid_input`` or ``successful``).
    ``t_final=None`` skips the time check."""
    ok = jnp.isfinite(t0)
    if t_final is not None:
        ok = ok & jnp.isfinite(t_final) & (t_final > t0)
    ok = ok & jnp.all(jnp.isfinite(q0)) & jnp.all(jnp.isfinite(qdot0))
    for _, cond in system.parameter_checks():
        ok = ok & jnp.all(cond)
    alpha = getattr(integrator, "alpha", None)
    if alpha is not None:
        ok = ok & (alpha >= 0) & (alpha <= 1)
    if check_constraints:
        ok = ok & (_constraint_violation(system, q0, qdot0) <= constraint_tolerance(qdot0))
    return RESULTS.where(ok, RESULTS.successful, RESULTS.invalid_input)
