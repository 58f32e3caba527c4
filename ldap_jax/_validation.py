"""Input validation that works the same eagerly, under ``jax.jit`` and under ``jax.vmap``.

Three levels (as in diffrax): shapes, dtypes and settings are checked at trace time with a
``ValueError``/``TypeError`` naming the argument; values that are known at trace time (concrete,
even inside an outer ``jit`` over other arguments) are checked at once the same way, computed
under ``jax.ensure_compile_time_eval``; values that are traced are checked inside the run and
reported per trajectory as a result code (:data:`~ldap_jax.RESULTS` ``invalid_input``).
"""

from __future__ import annotations

import contextlib
import numbers
import warnings
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ._compilation_cache import as_dtype, asarray, in_trace
from ._controls import Constant, Sampled
from ._fields import converter_field as converter_field
from ._policy import AbstractPolicy
from ._results import RESULTS
from ._typing import ArrayLike

__all__ = [
    "ArrayOrSequence",
    "check_array",
    "check_positive_int",
    "check_scalar",
    "cast_floats",
    "is_concrete",
    "raise_if_concrete",
    "input_result",
    "constraint_tolerance",
    "converter_field",
    "check_positive_number",
    "nonfinite_leaves",
    "initial_violation",
]

_SUPPORTED = (np.dtype(np.float32), np.dtype(np.float64))

#: An array argument of the public API: a JAX or NumPy array, a number, or a (nested) Python
#: sequence of numbers (converted with ``jnp.asarray``; :func:`check_array` names a bad one).
ArrayOrSequence = ArrayLike | Sequence[Any]


def is_concrete(tree: Any) -> bool:
    """True when no leaf of ``tree`` is a tracer."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def check_positive_int(name: str, x: Any) -> int:
    """``x`` as a Python int >= 1, or a ``TypeError`` (not an integer: a float, a bool, a string,
    a traced value) or ``ValueError`` (< 1) naming ``name``. A known 0-d integer JAX array counts
    as its value."""
    if isinstance(x, jax.Array) and x.ndim == 0 and jnp.issubdtype(x.dtype, jnp.integer):
        if not is_concrete(x):
            raise TypeError(
                f"'{name}' must be a positive integer known when the program is traced (it sets a "
                f"loop or an array size), got a traced value {x!r}"
            )
        x = int(x)
    if isinstance(x, bool) or not isinstance(x, (int, np.integer)):
        raise TypeError(f"'{name}' must be a positive integer, got {x!r}")
    if x < 1:
        raise ValueError(f"'{name}' must be a positive integer, got {x!r}")
    return int(x)


def check_array(name: str, x: Any, shape: tuple[int, ...], context: str = "") -> Array:
    """``x`` as a float32/float64 array of ``shape`` (lists and integer arrays are converted), or
    a ``ValueError``/``TypeError`` naming ``name``."""
    if isinstance(x, (str, bytes)):
        raise TypeError(f"'{name}' must be an array of numbers, got {x!r}")
    try:
        x = asarray(x)  # a host value without an eager JAX operation
    except (TypeError, ValueError) as err:
        raise TypeError(f"'{name}' must be an array of numbers, got {x!r}") from err
    if jnp.issubdtype(x.dtype, jnp.integer) or x.dtype == jnp.bool_:
        x = as_dtype(x, jnp.result_type(float))
    if np.dtype(x.dtype) not in _SUPPORTED:
        raise ValueError(f"'{name}' must be float32 or float64, got dtype {x.dtype}")
    if x.shape != shape:
        raise ValueError(
            f"'{name}' must have shape {shape}{(' ' + context) if context else ''}, got {x.shape}"
        )
    return x


def check_scalar(name: str, x: ArrayLike) -> ArrayLike:
    """``x`` unchanged if it is a real scalar (Python number or 0-d array), else a ``TypeError``
    (not a number) or ``ValueError`` (not a scalar)."""
    if isinstance(x, (str, bytes)) or x is None:
        raise TypeError(f"'{name}' must be a real number, got {x!r}")
    try:
        ndim = jnp.ndim(x)
    except TypeError as err:
        raise TypeError(f"'{name}' must be a real number, got {x!r}") from err
    if ndim != 0:
        raise ValueError(f"'{name}' must be a scalar, got {x!r}")
    if not (
        jnp.issubdtype(jnp.result_type(x), jnp.floating) or jnp.issubdtype(jnp.result_type(x), jnp.integer)
    ):
        raise ValueError(f"'{name}' must be a real number, got {x!r}")
    return x


def check_positive_number(name: str, x: Any, *, allow_inf: bool = False) -> float:
    """``x`` as a Python float > 0 (finite unless ``allow_inf``), or a ``TypeError`` (not a real
    number: a string, a bool, an array) / ``ValueError`` (out of range) naming ``name``."""
    if isinstance(x, bool) or not isinstance(x, numbers.Real):
        raise TypeError(f"'{name}' must be a positive number, got {x!r}")
    x = float(x)
    if not (x > 0 and (allow_inf or np.isfinite(x))):
        raise ValueError(f"'{name}' must be a positive{'' if allow_inf else ' finite'} number, got {x!r}")
    return x


def nonfinite_leaves(tree: Any) -> list[str]:
    """Paths (``".amplitude"``) of the concrete floating array leaves of ``tree`` holding a NaN or
    an infinity (traced leaves are skipped)."""
    bad = []
    for path, x in jax.tree_util.tree_flatten_with_path(tree)[0]:
        if eqx.is_inexact_array(x) and is_concrete(x):
            if not bool(np.all(np.isfinite(np.asarray(x)))):
                bad.append(jax.tree_util.keystr(path) or "(value)")
    return bad


def _finite_leaves(tree: Any):
    """True when every floating array leaf of ``tree`` is finite (a traced boolean)."""
    ok = jnp.asarray(True)
    for x in jax.tree_util.tree_leaves(tree):
        if eqx.is_inexact_array(x):
            ok = ok & jnp.all(jnp.isfinite(x))
    return ok


def cast_floats(tree: Any, dtype: Any) -> Any:
    """Cast every floating array leaf of ``tree`` to ``dtype``."""
    return jax.tree_util.tree_map(
        lambda x: x.astype(dtype) if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating) else x, tree
    )


def constraint_tolerance(qdot: Array) -> Array:
    """Tolerance of the initial constraint check: ``10 eps^(3/4) (1 + max |qdot|)`` (1.8e-11 in
    float64, 6.4e-5 in float32). The round-off of a consistent ``qdot0`` is a few ``eps``; an
    earlier ``1e4 eps`` was as tight in float64 but let a car's ``qdot0`` 0.1% off its rolling
    constraint through in float32 (6.4e-3)."""
    return 10.0 * jnp.finfo(qdot.dtype).eps ** 0.75 * (1.0 + jnp.max(jnp.abs(qdot)))


def _constraint_violation(system, q0, qdot0) -> Array:
    return system.constraint_residual(q0, qdot0)


def raise_if_concrete(
    system, integrator, q0, qdot0, controls, t0, t_final, check_constraints: bool, n_steps: int | None = None
) -> None:
    """The value checks, raised now (``ValueError`` naming the argument) for every input whose
    value is known at trace time (concrete, even inside an outer ``jit`` over other arguments);
    with ``n_steps``, also a step ``(t_final - t0) / n_steps`` that is positive in the run's dtype."""
    with jax.ensure_compile_time_eval():
        if is_concrete(t0) and not np.isfinite(float(np.asarray(t0))):
            raise ValueError(f"'t0' must be finite, got {t0}")
        if t_final is not None and is_concrete(t_final):
            tf_ = float(np.asarray(t_final))
            if not np.isfinite(tf_):
                raise ValueError(f"'t_final' must be finite, got {t_final}")
            if is_concrete(t0) and not tf_ > float(np.asarray(t0)):
                raise ValueError(
                    f"'t_final' must exceed t0 (a positive step), got t_final={t_final}, t0={t0}"
                )
            if is_concrete(t0) and n_steps is not None:
                dtype = jnp.result_type(q0, qdot0)
                h = (np.asarray(t_final, dtype) - np.asarray(t0, dtype)) / dtype.type(n_steps)
                if not h > 0:
                    raise ValueError(
                        f"'t_final' - 't0' = {tf_ - float(np.asarray(t0)):.3g} over n_steps={n_steps} "
                        f"gives a step of 0 in {dtype.name}: lengthen the run or use fewer steps"
                    )
        for name, x in (("q0", q0), ("qdot0", qdot0)):
            if is_concrete(x) and not bool(np.all(np.isfinite(np.asarray(x)))):
                raise ValueError(f"'{name}' must be finite, got {np.asarray(x)}")
        bad = nonfinite_leaves(controls)
        if bad:
            raise ValueError(
                f"'controls' must be finite: {type(controls).__name__} holds NaN or infinite values in "
                f"{', '.join(bad)}"
            )
        _warn_if_samples_miss_the_run(controls, t0, t_final)

    if is_concrete((system, q0)) and _has_both_views(system):
        with jax.ensure_compile_time_eval() if in_trace() else contextlib.nullcontext():
            mismatch, scale = (float(x) for x in _views_mismatch(system, q0))
        if not mismatch <= 1e-9 * max(scale, 1.0):
            raise ValueError(
                f"'system': its constraints C(r) and its symmetry basis and connection disagree at q0: "
                f"|C(r) [e(r), -A(r); 0, I]| = {mismatch:.3e}, where it must vanish (every velocity "
                "xi = e(r) w - A(r) rdot must satisfy C(r) [xi; rdot] = 0)"
            )

    if check_constraints and is_concrete((system, q0, qdot0, controls, t0)):
        try:
            finite_c0, viol, tol = known_initial_violation(system, q0, qdot0, controls, t0)
        except jax.errors.ConcretizationTypeError:
            # a policy that closes over a traced value (a plain function capturing a gain under
            # jit or grad): its leaves look known but its output is not; checked in the run
            return
        if not finite_c0:  # a policy's output at t0 (open-loop controls' data were checked above)
            raise ValueError(
                f"'controls' must be finite: their value at t0 = {float(np.asarray(t0)):g} is not "
                "(for a policy, its output at (t0, q0, qdot0))"
            )
        if not viol <= tol:
            raise ValueError(
                f"'qdot0' violates the constraints: |omega(q0) qdot0| = {viol:.3e} > {tol:.1e}. "
                "Build it "
                f"on the constraint distribution, e.g. system.qdot_from_velocities(q0, v0, u_kin)."
            )


def _warn_if_samples_miss_the_run(controls, t0, t_final) -> None:
    """A ``UserWarning`` when known :class:`~ldap_jax.Sampled` controls span a window that misses
    part of the run ``[t0, t_final]`` by more than 1e-9 of the run's length: there they are held
    at their end values, which is rarely what was meant (samples made for another horizon)."""
    if not isinstance(controls, Sampled) or t_final is None:
        return
    leaves = (controls.t0, controls.t_final, t0, t_final)
    if not is_concrete(leaves) or any(np.ndim(x) for x in leaves):
        return
    a, b, r0, r1 = (float(np.asarray(x)) for x in leaves)
    slack = 1e-9 * abs(r1 - r0)
    if a > r0 + slack or b < r1 - slack:
        warnings.warn(
            f"the sampled controls span [{a:g}, {b:g}] s but the run spans [{r0:g}, {r1:g}] s: outside "
            "their span they are held at their end values (samples for another horizon?)",
            stacklevel=4,
        )


def _has_both_views(system) -> bool:
    """A user :class:`~ldap_jax.System` given its constraints (the full view) besides its
    connection (and symmetry basis, if any: ``c = 0`` without one): the two descriptions must
    agree."""
    return getattr(system, "constraints_fn", None) is not None


@eqx.filter_jit
def _views_mismatch(system, q0) -> tuple[Array, Array]:
    """``(max |C(r) B(r)|, max |C| max |B|)`` with ``B = [e(r), -A(r); 0, I]``, whose columns span
    the velocities the reduced description allows (``xi = e w - A rdot``): one compiled program."""
    r = q0[3:]
    c, e, a = system.body_constraints(r), system.symmetry_basis(r), system.connection(r)
    n = r.shape[0]
    basis = jnp.block([[e, -a], [jnp.zeros((n, e.shape[1]), r.dtype), jnp.eye(n, dtype=r.dtype)]])
    return jnp.max(jnp.abs(c @ basis)), jnp.max(jnp.abs(c)) * jnp.max(jnp.abs(basis))


def known_initial_violation(system, q0, qdot0, controls, t0) -> tuple[bool, float, float]:
    """:func:`initial_violation` of known (concrete) values, as Python numbers (``controls=None``:
    zero inputs).

    At the top level one compiled program. Inside an outer trace (values closed over by a jitted
    function) it is evaluated at trace time; not at the top level, where that ran every operation
    on constants as a program of its own (a first ``simulate`` of the car compiled 14 programs, 9
    of them single operations, measured)."""
    if controls is None and _at_rest(q0, qdot0):
        # zero inputs and a zero velocity: omega(q0) 0 = 0 on every system (the constraints are
        # linear in the velocity), with no program to run (20-60 ms in a new process)
        return True, 0.0, float(10.0 * np.finfo(np.asarray(q0).dtype).eps ** 0.75)
    with jax.ensure_compile_time_eval() if in_trace() else contextlib.nullcontext():
        if controls is None:  # made here: inside a trace, a constant made outside is traced
            controls = Constant(jnp.zeros(system.n_controls))
        finite, viol, tol = initial_violation(system, q0, qdot0, controls, t0)
        return bool(finite), float(viol), float(tol)


def _at_rest(q0, qdot0) -> bool:
    """True for a known finite floating ``q0`` and a known, exactly zero floating ``qdot0``."""
    if not is_concrete((q0, qdot0)):
        return False
    q0, qdot0 = np.asarray(q0), np.asarray(qdot0)
    return (
        q0.dtype.kind == qdot0.dtype.kind == "f"
        and bool(np.all(qdot0 == 0))
        and bool(np.all(np.isfinite(q0)))
    )


@eqx.filter_jit
def initial_violation(system, q0, qdot0, controls, t0) -> tuple[Array, Array, Array]:
    """``(controls at t0 finite, |omega(q0) qdot|, its tolerance)`` for the initial velocity
    ``qdot`` of ``qdot0`` made consistent with the kinematic controls at ``t0``.

    One compiled program per signature: run op by op on known values, this check made a first call
    of ``simulate`` compile 41 single-operation programs besides the rollout (now 13)."""

    t = jnp.asarray(t0, q0.dtype)
    c0 = controls(t, q0, qdot0) if isinstance(controls, AbstractPolicy) else controls(t)
    c0 = jnp.asarray(c0, q0.dtype)
    finite = jnp.all(jnp.isfinite(c0))
    qd = system.consistent_qdot(q0, qdot0.astype(q0.dtype), jnp.where(finite, c0, 0.0))
    return finite, _constraint_violation(system, q0, qd), constraint_tolerance(qd)


def input_result(
    system,
    integrator,
    q0,
    qdot0,
    t0,
    t_final,
    check_constraints: bool,
    controls: Any = None,
    n_steps: int | None = None,
) -> RESULTS:
    """The value checks on traced values, as a result code (``invalid_input`` or ``successful``):
    finite times with ``t_final > t0``, a finite initial state, finite controls (every floating
    leaf) passing their ``value_checks``, the system's parameter checks, ``alpha`` in [0, 1] (and
    ``alpha = 1/2`` for a composition, ``RDP(order=4 | 6 | 8)``) and,
    with ``check_constraints``,
    ``qdot0`` on the constraints. ``t_final=None`` skips the time check. Finite inputs whose start
    is at the system's singularity (``|singularity(q0)| < eps^(1/4)``, the snakeboard within 1.2e-4
    rad of ``|phi| = pi/2`` in float64) give ``singular`` whatever their constraint residual (which
    may not be finite there): the steps test only their ends."""
    ok = jnp.isfinite(t0)
    if t_final is not None:
        ok = ok & jnp.isfinite(t_final) & (t_final > t0)
        if n_steps is not None:  # a step that underflows to 0 in the run's dtype
            ok = ok & ((t_final - t0) / n_steps > 0)
    ok = ok & jnp.all(jnp.isfinite(q0)) & jnp.all(jnp.isfinite(qdot0)) & _finite_leaves(controls)
    for _, cond in system.parameter_checks():
        ok = ok & jnp.all(cond)
    for _, cond in getattr(controls, "value_checks", lambda: ())():
        ok = ok & jnp.all(cond)
    alpha = getattr(integrator, "alpha", None)
    if alpha is not None:
        ok = ok & (alpha >= 0) & (alpha <= 1)
        if getattr(integrator, "order", 2) > 2:  # a composition (RDP(order=4 | 6 | 8)) of symmetric steps
            ok = ok & (alpha == 0.5)
    # a start at the singularity is that (what is derived there, e.g. a constraint residual, may
    # not be finite)
    singular = ok & system.singular(q0)
    if check_constraints:
        ok = ok & (_constraint_violation(system, q0, qdot0) <= constraint_tolerance(qdot0))
    valid = RESULTS.where(ok, RESULTS.successful, RESULTS.invalid_input)
    return RESULTS.where(singular, RESULTS.singular, valid)
