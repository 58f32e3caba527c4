"""High-accuracy reference solutions with diffrax (ground truth for tests and studies).

diffrax is imported when :func:`reference` is first called, not with the library (it takes about
a fifth of a second to import).
"""

from __future__ import annotations

import contextlib
import threading
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ._compilation_cache import jit, note_program, program_key
from ._controls import AbstractControls
from ._results import RESULTS
from ._simulate import check_problem
from ._typing import ArrayLike
from ._validation import (
    ArrayOrSequence,
    cast_floats,
    check_positive_int,
    check_positive_number,
    check_scalar,
    input_result,
    is_concrete,
    raise_if_concrete,
)
from .systems import AbstractSystem

__all__ = ["reference", "Solution"]


class Solution(eqx.Module):
    """A reference solution sampled at ``ts``.

    Attributes:
        t: sample times (s), (T,).
        q: configurations (m, rad), (T, d). NaN at the samples the solve did not reach.
        qdot: velocities (m/s, rad/s), (T, d). NaN likewise.
        result: a :class:`~ldap_jax.RESULTS` item: ``successful``; ``nonfinite`` (the state or
            the vector field turned non-finite, or the step size collapsed); ``singular`` (the
            system's ``singularity``, e.g. the snakeboard's ``cos(phi)``, changed sign or fell
            below ``eps^(1/4)`` in magnitude, as :func:`~ldap_jax.simulate`'s steps test it; at
            the start: then every sample is NaN, while
            :func:`~ldap_jax.simulate` keeps its node 0);
            ``max_steps_reached``; ``invalid_input`` (a traced input failed its check).
        num_steps: accepted + rejected steps taken by the adaptive solver.
    """

    t: Float[Array, " T"]
    q: Float[Array, "T d"]
    qdot: Float[Array, "T d"]
    result: RESULTS
    num_steps: Int[Array, ""]

    @property
    def failed(self):
        return self.result != RESULTS.successful


def _check_ts(ts: Any, t0: ArrayLike) -> Array:
    """``ts`` as a 1-d floating array, checked now where its values are known."""
    if isinstance(ts, (str, bytes)) or ts is None:
        raise TypeError(f"'ts' must be an array of times, got {ts!r}")
    try:
        ts = jnp.asarray(ts)
    except (TypeError, ValueError) as err:
        raise TypeError(f"'ts' must be an array of times, got {ts!r}") from err
    if not (jnp.issubdtype(ts.dtype, jnp.floating) or jnp.issubdtype(ts.dtype, jnp.integer)):
        raise TypeError(f"'ts' must be an array of real times, got dtype {ts.dtype}")
    if ts.ndim != 1 or ts.shape[0] < 1:
        raise ValueError(f"'ts' must be a non-empty 1-d array of times, got shape {ts.shape}")
    with jax.ensure_compile_time_eval():
        if is_concrete(ts):
            ts_np = np.asarray(ts, float)
            if not np.all(np.isfinite(ts_np)):
                raise ValueError(f"'ts' must be finite, got {ts_np}")
            if np.any(np.diff(ts_np) < 0):
                raise ValueError(f"'ts' must be non-decreasing, got {ts_np}")
            if is_concrete(t0):
                t0_ = float(np.asarray(t0))
                if np.isfinite(t0_) and ts_np[0] < t0_:
                    raise ValueError(f"'ts' must start at or after t0={t0_}, got {ts_np}")
    return ts


def default_tolerance(dtype: Any) -> float:
    """:func:`reference`'s default ``rtol`` and ``atol`` in ``dtype``: 1e-11 in float64, 1e-6 in
    float32 (its ``eps`` is 1.2e-7)."""
    return 1e-11 if jnp.finfo(dtype).eps < 1e-10 else 1e-6


def reference(
    system: AbstractSystem,
    q0: ArrayOrSequence,
    qdot0: ArrayOrSequence,
    controls: AbstractControls | None,
    ts: ArrayOrSequence,
    *,
    t0: ArrayLike = 0.0,
    rtol: float | None = None,
    atol: float | None = None,
    solver: Any = None,
    max_steps: int = 200_000,
    check_constraints: bool = True,
) -> Solution:
    """Solve the continuous Lagrange-d'Alembert equations with diffrax at tight tolerances.

    Integrates the minimal form ``(q, v)`` of the equations of motion (the system's
    ``velocity_dynamics``, checked against the full KKT form ``M qddot = F + omega^T lambda``
    in the tests) with Dopri8 and a PID step-size controller whose steps end on the control's
    breakpoints (:meth:`~ldap_jax.AbstractControls.breakpoints`: the samples of
    :class:`~ldap_jax.Sampled`). The solve stops at once when the state turns non-finite or the
    system's singularity is crossed (diffrax events), and after
    ``max_steps`` steps: it cannot hang. Inputs are checked as in :func:`~ldap_jax.simulate`.

    One compiled program serves every request of up to 32 samples, and above that every request
    whose number of samples rounds up to the same power of two (the samples are padded with the
    last time and sliced off again: the solver's steps do not depend on where it samples), and any
    tolerances (``rtol`` and ``atol`` are traced).

    Args:
        system, q0, qdot0, controls: as for :func:`ldap_jax.simulate` (``controls=None``: none).
        ts: non-decreasing, finite sample times (T,), all ``>= t0``; e.g. ``traj.t`` of a
            :func:`~ldap_jax.simulate` run, or just ``[t_final]``.
        t0: the time at which ``(q0, qdot0)`` is given (default 0, as for :func:`~ldap_jax.simulate`).
        rtol, atol: positive tolerances (default ``None``: 1e-11 each in float64, 1e-6 in float32,
            whose round-off 1e-11 is far below: the solve would spend ``max_steps`` and fail).
        solver: a diffrax solver (default ``diffrax.Dopri8()``).
        max_steps: cap on solver steps (accepted and rejected; default 200000).
        check_constraints: check that ``qdot0`` satisfies the constraints (default ``True``).

    Returns:
        :class:`Solution` with ``q`` and ``qdot`` at ``ts``.

    Raises:
        TypeError, ValueError: bad inputs (the message names the argument); on traced values
            the result is ``invalid_input`` instead.
    """
    controls, q0, qdot0 = check_problem(system, controls, q0, qdot0, policies=False, caller="reference")
    t0 = check_scalar("t0", t0)
    ts = _check_ts(ts, t0)
    tight = default_tolerance(jnp.result_type(q0, qdot0))
    rtol = tight if rtol is None else check_positive_number("rtol", rtol)
    atol = tight if atol is None else check_positive_number("atol", atol)
    max_steps = check_positive_int("max_steps", max_steps)
    import diffrax

    if solver is None:
        solver = diffrax.Dopri8()
    if not isinstance(solver, diffrax.AbstractSolver):
        raise TypeError(f"'solver' must be a diffrax solver (e.g. diffrax.Dopri8()) or None, got {solver!r}")
    raise_if_concrete(system, None, q0, qdot0, controls, t0, None, check_constraints)
    n = ts.shape[0]
    ts = _padded(ts)
    note_program(
        (
            "reference",
            program_key(system, q0, qdot0, controls, ts, solver),
            max_steps,
            bool(check_constraints),
        )
    )
    sol = _reference(
        system,
        q0,
        qdot0,
        controls,
        ts,
        jnp.asarray(t0),
        jnp.asarray(rtol),
        jnp.asarray(atol),
        solver,
        max_steps,
        bool(check_constraints),
    )
    return sol if n == ts.shape[0] else _first(sol, n)


_checks_lock = threading.Lock()


@contextlib.contextmanager
def _save_times_unchecked():
    """Trace ``diffeqsolve`` without its run-time checks of the save times.

    diffrax checks that ``SaveAt(ts)`` is ordered and lies in ``[t0, t1]`` with equinox's
    run-time errors, a host callback in the program; JAX keeps no program with a host callback
    in its persistent compilation cache, so every new process compiled the reference again
    (2-4 s of a notebook's warm run per model and sample count). The times :func:`_reference`
    passes always pass both checks (they are validated first, and an invalid request integrates
    from ``t0`` to ``t0``), so while this thread traces the call equinox's error mode is
    ``"nan"``: a failed check would give NaN (never a host callback). Equinox reads the mode at
    trace time; without the setting (a future equinox) the checks stay as they are.
    """
    try:
        from equinox import _errors
    except ImportError:  # pragma: no cover - a future equinox: keep the checks
        yield
        return
    if not hasattr(_errors, "EQX_ON_ERROR"):  # pragma: no cover
        yield
        return
    with _checks_lock:
        old = _errors.EQX_ON_ERROR
        _errors.EQX_ON_ERROR = "nan"
        try:
            yield
        finally:
            _errors.EQX_ON_ERROR = old


def _bucket(n: int) -> int:
    """The number of samples ``reference`` solves for when asked for ``n``: the next power of two,
    at least 32, so that requests differing only in their number of samples share a compiled
    program (up to 32 samples, one). The solver's steps do not depend on the sample times (it
    interpolates its dense output at them), so the extra samples cost nothing but the
    interpolation: a 10 s snakeboard maneuver took 1.6-1.8 ms for 2, 4, 32 or 64 samples."""
    return max(32, 1 << (n - 1).bit_length())


def _padded(ts: Array) -> Array:
    """``ts`` extended to :func:`_bucket` samples by repeating its last time."""
    pad = _bucket(ts.shape[0]) - ts.shape[0]
    if not pad:
        return ts
    if is_concrete(ts):
        ts_np = np.asarray(ts)
        return jnp.asarray(np.concatenate([ts_np, np.full(pad, ts_np[-1], ts_np.dtype)]))
    return jnp.concatenate([ts, jnp.full(pad, ts[-1], ts.dtype)])


@eqx.filter_jit
def _first(sol: Solution, n: int) -> Solution:
    """The first ``n`` samples of ``sol`` (undoing :func:`_padded`)."""
    return eqx.tree_at(lambda s: (s.t, s.q, s.qdot), sol, (sol.t[:n], sol.q[:n], sol.qdot[:n]))


@jit
def _reference(system, q0, qdot0, controls, ts, t0, rtol, atol, solver, max_steps, check_constraints):
    import diffrax

    dtype = jnp.result_type(q0, qdot0)
    system, controls = cast_floats((system, controls), dtype)
    q0, qdot0, ts, t0, rtol, atol = (jnp.asarray(x, dtype) for x in (q0, qdot0, ts, t0, rtol, atol))
    c0 = controls(t0)
    qdot0 = system.consistent_qdot(q0, qdot0, c0)
    ok_ts = jnp.all(jnp.isfinite(ts)) & jnp.all(jnp.diff(ts) >= 0) & (ts[0] >= t0)
    initial = input_result(system, None, q0, qdot0, t0, None, check_constraints, controls)
    valid = (initial == RESULTS.successful) & ok_ts & jnp.all(jnp.isfinite(c0))
    # an invalid member integrates a harmless problem (rest, a zero-length interval) so a vmapped
    # batch does not pay for it, and is reported as invalid
    q_start = jnp.where(valid, q0, jnp.zeros_like(q0))
    v_start = jnp.where(valid, system.velocities_from_qdot(q0, qdot0), 0.0)
    t_end = jnp.where(valid, ts[-1], t0)
    ts_safe = jnp.where(valid, ts, t0)

    # a kinematic coordinate's prescribed acceleration (the controls' derivative) enters the
    # dynamics where it is coupled to the others (a System's steered, inert front wheel, say)
    kinematic = len(system.kinematic_index) > 0

    def vector_field(t, y, args):
        c_dot = jnp.where(valid, controls.derivative(t), 0.0) if kinematic else None
        return system.ode(y, jnp.where(valid, controls(t), 0.0), c_dot)

    def nonfinite(t, y, args, **kwargs):
        return ~(jnp.all(jnp.isfinite(y[0])) & jnp.all(jnp.isfinite(y[1])))

    def singularity(t, y, args, **kwargs):
        return system.singularity(y[0])

    # as simulate's steps test it: a magnitude below eps^(1/4) is the singularity too (approached
    # without a sign change, the adaptive steps shrink until max_steps)
    threshold = jnp.finfo(dtype).eps ** 0.25

    def near_singularity(t, y, args, **kwargs):
        return jnp.abs(system.singularity(y[0])) < threshold

    # steps end on the control's kinks: across the kinks of sampled (piecewise-linear) controls,
    # Dopri8 at rtol = atol = 1e-11 left errors of 1e-9 to 1.2e-7 in the snakeboard's steering
    # angle on an optimised reach (depending on how XLA rounds), against 9e-14 stepping onto them
    controller = diffrax.PIDController(rtol=rtol, atol=atol)
    jumps = controls.breakpoints()
    if jumps is not None:
        controller = diffrax.ClipStepSizeController(controller, jump_ts=jumps)
    with _save_times_unchecked():
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(vector_field),
            solver,
            t0=t0,
            t1=t_end,
            dt0=None,
            y0=(q_start, v_start),
            saveat=diffrax.SaveAt(ts=ts_safe),
            stepsize_controller=controller,
            max_steps=max_steps,
            event=diffrax.Event((nonfinite, singularity, near_singularity)),
            throw=False,
        )
    q, v = sol.ys
    u_kin = jax.vmap(lambda t: system.inputs(controls(t))[1])(ts)
    qdot = jax.vmap(system.qdot_from_velocities)(q, v, u_kin)
    d_res = diffrax.RESULTS
    hit_nonfinite, crossed, near = sol.event_mask if sol.event_mask is not None else (False,) * 3
    hit_singular = crossed | near
    result = RESULTS.where(
        sol.result == d_res.successful,
        RESULTS.successful,
        RESULTS.where(
            sol.result == d_res.max_steps_reached,
            RESULTS.max_steps_reached,
            RESULTS.where(
                (sol.result == d_res.event_occurred) & hit_singular & ~hit_nonfinite,
                RESULTS.singular,
                RESULTS.nonfinite,
            ),
        ),
    )
    # a start at the singularity (valid otherwise) is reported as that, with every sample NaN
    at_start = (initial == RESULTS.singular) & ok_ts & jnp.all(jnp.isfinite(c0))
    result = RESULTS.where(valid, result, RESULTS.where(at_start, RESULTS.singular, RESULTS.invalid_input))
    # samples the solve did not reach (diffrax fills them with inf) are NaN, as in simulate
    row_ok = valid & jnp.all(jnp.isfinite(q), axis=1) & jnp.all(jnp.isfinite(qdot), axis=1)
    mask = jnp.where(row_ok, 1.0, jnp.nan).astype(dtype)[:, None]
    return Solution(t=ts, q=q * mask, qdot=qdot * mask, result=result, num_steps=sol.stats["num_steps"])
